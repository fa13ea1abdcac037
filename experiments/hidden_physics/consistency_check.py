"""Subset consistency (torchslide/diagnose/consistency.py) on saved harness cases.

The diagnosis now reports, per observation, whether it wants other baseline parameters than the
rest. The harness cases on the results page were run before it existed; this script recomputes it
for them without re-running the diagnosis: the recording and the evaluator are rebuilt from the
case's scenario and seed, the grid's approximation error is drawn as the diagnosis draws it
(pipeline.grid_model_error, the harness budgets and seed: the same pilot calibration), and the
linearisation (screen.screen with no candidates: p + 1 runs) is made at the point the pipeline uses:
the screening's x0 when the baseline stayed the calibration's, else the mode check's best run (the
pipeline takes the refined baseline's best posterior-predictive run, which the case file does not keep).

    python -m experiments.hidden_physics.consistency_check --results experiments/hidden_physics/results/harness \
        --out experiments/hidden_physics/results/consistency.json

Cases already in --out are skipped (resumable). Strength-1 cases only; each case's own terrain
variant and cell size (case["terrain"], case["cellsize"]).
"""
from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path

from torchslide.diagnose import Budgets
from torchslide.diagnose.consistency import subset_consistency
from torchslide.diagnose.pipeline import grid_model_error
from torchslide.diagnose.screen import screen

from .harness import HARNESS_BUDGETS
from .scenarios import make_evaluator, make_recording, terrain_variant


def linearisation_point(case: dict) -> tuple[list, str]:
    """(baseline point, where from) at which the pipeline linearises the consistency test for ``case``."""
    d = case["diagnosis"]
    mc = d["decision"].get("baseline_mode_check") or {}
    if mc.get("adopted") and mc.get("best_x") is not None:
        return list(mc["best_x"]), "mode check's best run"
    x0 = d["screening"]["x0"]
    return [x0[n] for n in ("mu", "xi")], "screening x0"


def check_case(case: dict, log=lambda s: None) -> dict:
    """The subset-consistency rows of one saved harness case (see the module doc)."""
    with terrain_variant(case.get("terrain", "narrow")):
        rec = make_recording(case["scenario"], case["seed"], cellsize=case["cellsize"], strength=case["strength"],
                             fine_factor=case.get("fine_factor", 2))
        ev = make_evaluator(rec, cellsize=case["cellsize"])
        bud = Budgets(**{**HARNESS_BUDGETS, "seed": case["seed"]})
        with tempfile.TemporaryDirectory(prefix="consistency_") as tmp:
            ev_me, _ = grid_model_error(ev, bud, tmp, log=log)
        x, where = linearisation_point(case)
        scr = screen(ev_me, x, [])
    if scr.jacobian is None:
        return {"point": x, "point_from": where, "rows": None, "failed": True}
    names = list(ev_me.prior.names)
    return {"point": x, "point_from": where,
            "rows": subset_consistency(ev_me.blocks, scr.jacobian, scr.residual, names, x)}


def main(argv=None) -> int:
    p = argparse.ArgumentParser()
    p.add_argument("--results", default=str(Path(__file__).parent / "results" / "harness"))
    p.add_argument("--out", default=str(Path(__file__).parent / "results" / "consistency.json"))
    p.add_argument("--cases", default="", help="comma-separated case tags (default: all strength-1 cases)")
    a = p.parse_args(argv)
    out = Path(a.out)
    done = json.loads(out.read_text()) if out.exists() else {}
    want = {t for t in a.cases.split(",") if t}
    for f in sorted(Path(a.results).glob("*.json")):
        case = json.loads(f.read_text())
        tag = f.stem
        if "diagnosis" not in case:          # e.g. a null-calibration folder's thresholds.json
            continue
        if case["strength"] != 1.0 or tag in done or (want and tag not in want):
            continue
        r = check_case(case)
        r.update(scenario=case["scenario"], seed=case["seed"], truth=case["truth"].get("term"))
        done[tag] = r
        flagged = [e["block"] for e in (r["rows"] or []) if e["conflict"]]
        print(f"{tag}: {', '.join(flagged) or 'none flagged'}", flush=True)
        out.write_text(json.dumps(done, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
