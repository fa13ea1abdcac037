"""Which observation design lets the harness' data detect every library term? ``python -m
experiments.hidden_physics.design_check [--terrain resolved] [--designs "none;1200;1000,1300"]
[--seeds 100,101,102] [--bf-min 12.1] [--out FILE]``

Curvature's detectable switch (torchslide.diagnose.screen.detectable_switch) lies beyond its prior in
12 of 14 saved harness cases (detectability.py): no strength of it can be named from a deposit map,
two gauges and the final volume on the 40 m grid. Choosing the observations so that every term is
detectable is experimental design, and it needs no hidden-term result: for each design (extra gauges
g3, g4, ... at the given x on the thalweg, h and speed like g1, g2) and each NULL recording seed, the
pilot model error and a baseline calibration as the diagnosis makes them (harness budgets), the
screening at the baseline's mode, and every candidate's detectable switch at ``--bf-min`` (default:
the resolved terrain's null-calibrated threshold). Rows go to ``--out`` (default
results/design_check_<terrain>.json); the results page reads them.
"""
from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path

import numpy as np

from torchslide.diagnose import Budgets
from torchslide.diagnose.pipeline import grid_model_error
from torchslide.diagnose.predictive import posterior_mode
from torchslide.diagnose.refit import calibrate_evaluator
from torchslide.diagnose.screen import detectable_switch, screen

from . import scenarios
from .harness import HARNESS_BUDGETS, LIBRARY
from .scenarios import TERRAINS, make_evaluator, make_recording

HERE = Path(__file__).parent


def design_row(terrain: str, xs: list[float], seed: int, bf_min: float) -> dict:
    """Detectable switches of the library on the null recording ``seed`` with extra gauges at ``xs``."""
    bud = Budgets(**HARNESS_BUDGETS, seed=seed)
    with scenarios.terrain_variant(terrain), scenarios.extra_gauges(xs):
        ev = make_evaluator(make_recording("null", seed))
        with tempfile.TemporaryDirectory() as wd:
            ev_me, _ = grid_model_error(ev, bud, wd, log=lambda m: None)
        cal = calibrate_evaluator(ev_me, bud.baseline_n_initial, bud.baseline_n_total, batch_size=bud.batch_size,
                                  seed=seed, mcmc_steps=bud.mcmc_steps, grid_size=bud.baseline_grid_size)
        x0 = posterior_mode(cal)
        scr = screen(ev_me, x0, LIBRARY)
    det = detectable_switch(scr, ev_me, bf_min)
    return {"terrain": terrain, "extra_gauges": list(xs), "seed": seed, "bf_min": bf_min,
            "x0": {n: float(v) for n, v in zip(ev.prior.names, x0)},
            "detectable": {c: (None if v is None else {"switch": float(v["switch"]) if np.isfinite(v["switch"]) else None,
                                                       "within_prior": bool(v["within_prior"])})
                           for c, v in det.items()}}


def main(argv=None) -> int:
    a = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    a.add_argument("--terrain", default="resolved", choices=sorted(TERRAINS))
    a.add_argument("--designs", default="none;1200;1000,1300",
                   help="';'-separated designs, each 'none' or comma-separated x (m) of extra gauges")
    a.add_argument("--seeds", default="100,101,102", help="null recording seeds")
    a.add_argument("--bf-min", type=float, default=12.1)
    a.add_argument("--out", default=None)
    args = a.parse_args(argv)
    designs = [[] if d.strip() == "none" else [float(x) for x in d.split(",")] for d in args.designs.split(";") if d]
    rows = []
    for xs in designs:
        for s in [int(x) for x in args.seeds.split(",") if x]:
            rows.append(design_row(args.terrain, xs, s, args.bf_min))
            print(args.terrain, xs, s, {c: v and v["switch"] and round(v["switch"], 4) for c, v in
                                        rows[-1]["detectable"].items()}, flush=True)
    out = Path(args.out or HERE / "results" / f"design_check_{args.terrain}.json")
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(rows, indent=1))
    print("wrote", out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
