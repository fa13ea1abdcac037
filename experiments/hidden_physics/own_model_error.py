"""Would a candidate-specific model error separate the terms? ``python -m experiments.hidden_physics.own_model_error
[--case yield_stress_s1] [--results DIR] [--candidates yield_stress,mu_i,earth_pressure] [--out FILE]``
(the case is re-made on the terrain variant it was run on, scenarios.TERRAINS)

The diagnosis puts one approximation error of the grid into every likelihood: the pilot baseline's
(torchslide.diagnose.model_error, drawn at the switch = 0). A term whose effect depends strongly on
the grid (yield stress on a 40 m grid) could be misjudged by it. The alternative, each candidate's
likelihood with the error drawn at *its own* posterior, is measured here on a saved harness case:

* the pilot error exactly as the pipeline makes it (grid_model_error, the case's seed);
* per candidate, 12 parameter sets drawn from a normal with the saved refit's posterior mean and
  sd = (90 % interval width) / 3.3 (the report keeps no samples), clipped to the prior box, run on
  the inversion grid and on cells half as large (model_error.approximation_error): its own error;
* the largest ln posterior a Nelder-Mead search (``--evals`` solver runs, from the refit's mean)
  reaches under each of the two errors.

If the own error raised the true term's best ln posterior more than the others', it would help to
tell them apart; if it raises all of them (or the wrong ones more), it would not. Rows are written to
--out (default results/own_model_error.json, results/own_model_error_<terrain>.json for a case on another
terrain variant).
"""
from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path

import numpy as np
import torch
from scipy.optimize import minimize

from torchslide.diagnose import Budgets
from torchslide.diagnose.model_error import approximation_error
from torchslide.diagnose.pipeline import grid_model_error
from torchslide.diagnose.refit import candidate_evaluator

from .harness import HARNESS_BUDGETS
from .scenarios import make_evaluator, make_recording, terrain_variant

HERE = Path(__file__).parent


def best_log_posterior(ev, x0: np.ndarray, scale: np.ndarray, evals: int) -> tuple[float, np.ndarray]:
    """(largest ln posterior found, its point) by Nelder-Mead on the solver from ``x0`` (p,), in
    coordinates divided by ``scale`` (p,), points clipped to the prior box."""
    b = np.asarray(ev.prior.bounds, float)

    def f(u):
        r = ev(torch.as_tensor(np.clip(u * scale, b[0], b[1])[None]))
        return 1e9 if bool(r.failed[0]) else -float(r.z[0])

    o = minimize(f, x0 / scale, method="Nelder-Mead", options=dict(maxfev=evals))
    return -float(o.fun), np.clip(o.x * scale, b[0], b[1])


def main(argv=None) -> int:
    p = argparse.ArgumentParser()
    p.add_argument("--case", default="yield_stress_s1", help="<scenario>_s<seed> of a saved strength-1 harness case")
    p.add_argument("--results", default=str(HERE / "results" / "harness"))
    p.add_argument("--candidates", default="yield_stress,mu_i,earth_pressure")
    p.add_argument("--evals", type=int, default=80)
    p.add_argument("--out", default=None, help="default results/own_model_error.json for a case on the narrow "
                   "terrain, results/own_model_error_<terrain>.json otherwise (the results page reads both)")
    a = p.parse_args(argv)
    case = json.loads((Path(a.results) / f"{a.case}.json").read_text())
    terrain = case.get("terrain", "narrow")
    with terrain_variant(terrain):  # the terrain the case was run on
        rows = _rows(a, case)
    out = Path(a.out) if a.out else HERE / "results" / (
        "own_model_error.json" if terrain == "narrow" else f"own_model_error_{terrain}.json")
    old = json.loads(out.read_text()) if out.exists() else []
    old = [r for r in old if not (r["case"] == a.case and r["candidate"] in {x["candidate"] for x in rows})]
    out.write_text(json.dumps(old + rows, indent=1))
    return 0


def _rows(a, case) -> list[dict]:
    sc, seed = case["scenario"], int(case["seed"])
    rec = make_recording(sc, seed, cellsize=case["cellsize"])
    ev = make_evaluator(rec, cellsize=case["cellsize"])
    bud = Budgets(**{**HARNESS_BUDGETS, "seed": seed})
    with tempfile.TemporaryDirectory() as wd:
        ev_pilot, _ = grid_model_error(ev, bud, wd, log=lambda s: None)
    rng = np.random.default_rng(seed)
    rows = []
    for c in a.candidates.split(","):
        cd = next(x for x in case["diagnosis"]["candidates"] if x["name"] == c)
        names = list(cd["parameters"])
        mean = np.array([cd["parameters"][n]["mean"] for n in names])
        sd = np.array([np.diff(cd["parameters"][n]["hdr90"])[0] / 3.3 for n in names])
        ev_c = candidate_evaluator(ev, c)
        b = np.asarray(ev_c.prior.bounds, float)
        x = np.clip(mean + sd * rng.standard_normal((12, len(mean))), b[0], b[1])
        me_own = approximation_error(ev_c, x)
        row = {"case": a.case, "terrain": case.get("terrain", "narrow"), "truth": rec.truth, "candidate": c,
               "names": names}
        for tag, e in (("pilot", candidate_evaluator(ev_pilot, c)), ("own", ev_c.with_model_error(me_own))):
            z, xb = best_log_posterior(e, mean, np.maximum(sd, 1e-6), a.evals)
            row[f"best_z_{tag}"], row[f"best_x_{tag}"] = z, xb.tolist()
        row["gain"] = row["best_z_own"] - row["best_z_pilot"]
        print(f"{c:15s} best ln posterior: pilot error {row['best_z_pilot']:.1f}, own error {row['best_z_own']:.1f} "
              f"(gain {row['gain']:+.1f})", flush=True)
        rows.append(row)
    return rows


if __name__ == "__main__":
    raise SystemExit(main())
