"""Which term do cells half as large prefer? ``python -m experiments.hidden_physics.finer_grid_points
[--cases resolved_20m:yield_stress_s0,...] [--candidates yield_stress,mu_i] [--out FILE]``

On the resolved terrain at 20 m cells the diagnosis named mu(I) for yield stress in two seeds, with
2 ln BF 59 against 34-43 (results page, "The resolved terrain on 20 m cells"). Is that the 20 m
solver's own error, or would the recordings prefer mu(I) on any grid? For each saved case
(``run:case``, run one of finer_grid_profile.RESULTS' keys) the log-likelihood ln L with the
measurement errors alone (no grid model error: the finer grid is what that error stands for) is
evaluated on the case's inversion grid and on cells half as large over the same DEM
(finer_grid_profile.finer_grid_evaluator, model_error.fine_run) at:

* ``truth``: the true term at its true switch and TRUE_BASE's mu, xi (in-library scenarios only);
* each candidate's best run in the saved refit (report ``best_x``), under that candidate's model.

Points, not searches: a candidate's best run on the inversion grid is not its best on the finer
grid, so its finer-grid ln L is a lower bound of what it reaches there (finer_grid_profile.py
searches along the switch, locally). ln L, not ln L + ln prior, so that candidates with different
switch priors compare. Rows go to ``--out`` (default results/finer_grid_points.json); the results
page reads them. About 10 s per point on 10 m cells on one core (resolved terrain).
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch

from torchslide.diagnose.refit import candidate_evaluator
from torchslide.physics import CANDIDATES

from . import scenarios
from .finer_grid_profile import RESULTS, finer_grid_evaluator
from .scenarios import SWITCH, TRUE_BASE, make_evaluator, make_recording

HERE = Path(__file__).parent
DEFAULT_CASES = ",".join(f"resolved_20m:{sc}_s{s}" for sc in ("yield_stress", "mu_i", "null") for s in range(5))


def _log_lik(evc, X: np.ndarray) -> list[float]:
    """ln L = z - ln prior at the rows of X (n, 3); nan where a run failed."""
    x = torch.as_tensor(X, dtype=torch.float64)
    r = evc(x)
    ll = r.z - evc.prior.log_prob(x)
    ll[r.failed] = float("nan")
    return ll.tolist()


def points_case(run: str, case: str, candidates=("yield_stress", "mu_i"), results=None) -> dict:
    """One saved case's row: {run, terrain, cellsize, case, scenario, truth, points: [{label,
    candidate, x, log_lik: {inversion_grid, finer_grid}}], wall_s} (module doc)."""
    for c in candidates:
        if c not in CANDIDATES:
            raise SystemExit(f"--candidates: unknown candidate {c!r}; known: {sorted(CANDIDATES)}")
    t0 = time.perf_counter()
    D = json.loads((Path(results or RESULTS[run]) / f"{case}.json").read_text())
    sc, seed = D["scenario"], int(D["seed"])
    terrain, cellsize = D.get("terrain", "narrow"), float(D.get("cellsize", 40.0))
    with scenarios.terrain_variant(terrain):
        rec = make_recording(sc, seed, cellsize=cellsize, fine_factor=D.get("fine_factor", 2))
        ev = make_evaluator(rec, cellsize=cellsize)
        pts = []
        if sc in SWITCH:
            pts.append(("truth", sc, [TRUE_BASE["mu"], TRUE_BASE["xi"], D["truth"][SWITCH[sc]]]))
        refits = {c["name"]: c for c in D["diagnosis"]["candidates"]}
        pts += [("best run", c, list(refits[c]["best_x"])) for c in candidates if c in refits]
        rows = []
        for label, cand, x in pts:
            evc = candidate_evaluator(ev, cand)
            X = np.array([x], float)
            rows.append({"label": label, "candidate": cand, "x": x,
                         "log_lik": {"inversion_grid": _log_lik(evc, X)[0],
                                     "finer_grid": _log_lik(finer_grid_evaluator(evc), X)[0]}})
            print(run, case, label, cand, {k: round(v, 1) for k, v in rows[-1]["log_lik"].items()}, flush=True)
    return {"run": run, "terrain": terrain, "cellsize": cellsize, "case": case, "scenario": sc,
            "truth": D["truth"], "points": rows, "wall_s": time.perf_counter() - t0}


def main(argv=None) -> int:
    a = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    a.add_argument("--cases", default=DEFAULT_CASES, help="comma-separated run:case")
    a.add_argument("--candidates", default="yield_stress,mu_i", help="comma-separated candidate names")
    a.add_argument("--out", default=str(HERE / "results" / "finer_grid_points.json"))
    args = a.parse_args(argv)
    cands = [c for c in args.candidates.split(",") if c]
    raw = [spec for spec in args.cases.split(",") if spec]
    specs = [spec.partition(":")[::2] for spec in raw]
    for spec, (run, case) in zip(raw, specs):      # every spec checked before any run
        if run not in RESULTS or not case:
            raise SystemExit(f"--cases: {spec!r} is not run:case with run in {sorted(RESULTS)}")
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    rows = []
    for run, case in specs:
        rows.append(points_case(run, case, cands))
        out.write_text(json.dumps(rows, indent=1))      # after every case: an interrupted run keeps the rest
    print("wrote", out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
