"""Which terms could the harness' data name at all? ``python -m experiments.hidden_physics.detectability
[--cases narrow:null_s0,resolved:curvature_s0,...] [--out FILE]``

The diagnosis now reports, for every screened candidate, the smallest switch value whose own effect
would reach the evidence threshold (torchslide.diagnose.screen.detectable_switch: linearised at the
baseline's mode, whitened by the likelihood's covariance with the grid's error). The harness cases on
the results page ran before it; this recomputes it for saved cases: the case's recording and
evaluator, the grid's model error from the same pilot calibration (pipeline.grid_model_error, the
case's seed), the screening at the saved baseline mode (it reproduces the saved screening scores) and
the case's bf_min. Rows go to ``--out`` (default results/detectability.json); the results page reads them.
"""
from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path

import numpy as np

from torchslide.diagnose import Budgets
from torchslide.diagnose.pipeline import grid_model_error
from torchslide.diagnose.screen import detectable_switch, screen

from . import scenarios
from .harness import HARNESS_BUDGETS, LIBRARY
from .scenarios import SCENARIOS, SWITCH, make_evaluator, make_recording

HERE = Path(__file__).parent
RESULTS = {"narrow": HERE / "results" / "harness", "resolved": HERE / "results" / "resolved" / "results"}
DEFAULT_CASES = ",".join(f"{t}:{sc}_s0" for t in ("narrow", "resolved") for sc in SCENARIOS)


def detectability_case(terrain: str, case: str, results=None) -> dict:
    """The detectable switches of every library candidate for one saved case (module doc)."""
    sc, s = case.rsplit("_s", 1)
    seed = int(s)
    D = json.loads((Path(results or RESULTS[terrain]) / f"{case}.json").read_text())["diagnosis"]
    with scenarios.terrain_variant(terrain):
        ev = make_evaluator(make_recording(sc, seed))
    with tempfile.TemporaryDirectory() as wd:
        ev_me, _ = grid_model_error(ev, Budgets(**HARNESS_BUDGETS, seed=seed), wd, log=lambda m: None)
    x0 = np.array([D["screening"]["x0"][n] for n in ev.prior.names])
    scr = screen(ev_me, x0, LIBRARY)
    det = detectable_switch(scr, ev_me, D["thresholds"]["bf_min"])
    term = SCENARIOS[sc][0]
    saved = {c: v["score"] for c, v in D["screening"]["candidates"].items()}
    return {"terrain": terrain, "case": case, "true_term": term,
            "truth": None if term not in SWITCH else SCENARIOS[sc][1][SWITCH[term]],
            "found": D["missing_physics"], "bf_min": D["thresholds"]["bf_min"],
            "screening_reproduced": bool(all(abs(scr.scores[c] - saved[c]) <= 1e-6 * max(1.0, saved[c]) for c in saved)),
            "detectable": {c: (None if v is None else {k: (None if not np.isfinite(x) else float(x)) if k != "within_prior"
                                                         else bool(x) for k, x in v.items()}) for c, v in det.items()}}


def main(argv=None) -> int:
    a = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    a.add_argument("--cases", default=DEFAULT_CASES, help="comma-separated terrain:case")
    a.add_argument("--out", default=str(HERE / "results" / "detectability.json"))
    args = a.parse_args(argv)
    rows = []
    for spec in [c for c in args.cases.split(",") if c]:
        t, case = spec.split(":")
        if t not in RESULTS:
            raise SystemExit(f"--cases: unknown terrain {t!r} in {spec!r} (known: {sorted(RESULTS)})")
        rows.append(detectability_case(t, case))
        print(t, case, {c: v and round(v["switch"], 4) if v and v["switch"] is not None else None
                        for c, v in rows[-1]["detectable"].items()}, flush=True)
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(rows, indent=1))
    print("wrote", args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
