"""Measure the detectable switches of saved harness cases again with the current code.

``python -m experiments.hidden_physics.redetect DIR [--scenarios a,b]`` takes every case file
``<scenario>_s<seed>[_x<strength>].json`` in DIR, makes its recordings again (scenario, seed, strength and
the harness settings it was run with), repeats the diagnosis' baseline stages up to the screening
(torchslide.diagnose.pipeline.baseline_screening: minutes a case, not the whole diagnosis) and replaces the
screening's ``detectable_switch`` entries in the case file (atomically). The verdicts are not touched: the
detectable switches only say which strengths a case is scored against (summary.detectability). A case whose
baseline mode is not the saved one (other code for the stages before the screening) is left as it was.
``--from-measured``: no solver runs; the switches are derived again from the [switch, nc] points the entries
measured (torchslide.diagnose.power.measured_threshold), after a change in how they are read.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path

import numpy as np

from torchslide.diagnose import Budgets, Thresholds
from torchslide.diagnose.candidates import CANDIDATES
from torchslide.diagnose.pipeline import baseline_screening
from torchslide.diagnose.power import measured_threshold

from .harness import HARNESS_BUDGETS
from .scenarios import make_evaluator, make_recording, noise_sigmas, terrain_variant
from .summary import write_json

X0_RTOL = 1e-6
"""Largest relative difference of the baseline's mode from the saved one for a case to be updated."""


def redetect(path, log=print) -> bool:
    """Measure the detectable switches of the case file ``path`` again (module doc); whether it was updated."""
    path = Path(path)
    case = json.loads(path.read_text())
    j = case["diagnosis"]
    saved = (j.get("screening") or {}).get("candidates") or {}
    with terrain_variant(case.get("terrain", "narrow")):
        rec = make_recording(case["scenario"], case["seed"], cellsize=case["cellsize"], strength=case["strength"],
                             fine_factor=case.get("fine_factor", 2))
        if case.get("sigmas") == "noise":
            rec = dataclasses.replace(rec, observations=noise_sigmas(rec.observations))
        ev = make_evaluator(rec, cellsize=case["cellsize"], fine_terrain=case.get("fine_terrain", False))
        bud = Budgets(**{**HARNESS_BUDGETS, **(case.get("budgets") or {}), "seed": case["seed"],
                         "detectability": "measured"})
        scr = baseline_screening(ev, [c for c in saved if c in CANDIDATES], bud, Thresholds(**j["thresholds"]),
                                 log=lambda s: None)
    x0, x_saved = np.array(list(scr.x0.values())), np.array([j["screening"]["x0"][n] for n in scr.x0])
    if not np.allclose(x0, x_saved, rtol=X0_RTOL, atol=0.0):
        log(f"{path.name}: baseline mode {x0.tolist()} is not the saved {x_saved.tolist()}; left as it was")
        return False
    for c, d in scr.detectable.items():
        saved[c]["detectable_switch"] = d
    write_json(path, case)
    return True


def rethreshold(path) -> bool:
    """The detectable switches of the case file ``path`` derived again from their measured points (module doc);
    whether it had any."""
    path = Path(path)
    case = json.loads(path.read_text())
    j = case["diagnosis"]
    done = False
    for c, v in ((j.get("screening") or {}).get("candidates") or {}).items():
        d = v.get("detectable_switch") or {}
        if d.get("measured") and c in CANDIDATES:
            v["detectable_switch"] = measured_threshold([tuple(p) for p in d["measured"]], CANDIDATES[c].prior,
                                                        j["thresholds"]["bf_min"], d["per_unit_linear"])
            done = True
    if done:
        write_json(path, case)
    return done


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description="measure the detectable switches of saved harness cases again")
    p.add_argument("folder", help="folder of the case files")
    p.add_argument("--scenarios", default=None, help="comma-separated scenarios (default: all)")
    p.add_argument("--from-measured", action="store_true",
                   help="derive the switches again from the points measured, without solver runs")
    a = p.parse_args(argv)
    want = None if a.scenarios is None else set(a.scenarios.split(","))
    files = sorted(f for f in Path(a.folder).glob("*_s*.json")
                   if want is None or json.loads(f.read_text()).get("scenario") in want)
    if not files:
        p.error(f"{a.folder}: no case files" + ("" if want is None else f" of {sorted(want)}"))
    done = 0
    for f in files:
        ok = rethreshold(f) if a.from_measured else redetect(f)
        done += ok
        print(f"{f.name}: {'updated' if ok else 'left'}", flush=True)
    print(f"{done} of {len(files)} case files updated")
    return 0 if done == len(files) else 1


if __name__ == "__main__":
    raise SystemExit(main())
