"""What ending a run early costs: observables of the Bondo-like case under each stop rule.

    python -m bench.stop_rule --out bench/results/stop_rule.json

Runs five parameter sets (mu, xi) on the Bondo-like terrain (``--cellsize``, t_end 300 s, float32, the
fused step (``--kernel``), cropped) once with stopping off (every member runs to t_end) and once per rule
of RULES: the default (the footprint rule: no cell newly reached for 10 s while the kinetic energy is below
1 % of its peak, or the kinetic energy below 1e-4 of its peak), the kinetic-energy rule alone at 1e-4, and
com1DFA's default (kinetic energy below 1 % of its peak). It reports per member the end time, the steps,
the wall time of the call and the relative change of every observable of the case study
(experiments/bondo: impact area, deposit area and volume, v_max and deposit height at the points) against
the run to t_end. A stop rule is a free speed-up only if these changes stay well below the data noise
(10 % in the case study).
"""
from __future__ import annotations

import argparse
import json
import os
import time

import numpy as np
import torch

from experiments.bondo.config import OBSERVABLES
from experiments.bondo.simulator import observables
from torchslide.physics import Params
from torchslide.solver import SolverConfig, simulate
from torchslide.terrain.synthetic import bondo_like

RULES = {"off": dict(stop_ke_fraction=0.0, stop_quiet_time=0.0),
         "default": {},
         "ke_1e-4": dict(stop_quiet_time=0.0),
         "ke_1e-2 (com1DFA)": dict(stop_ke_fraction=1e-2, stop_quiet_time=0.0)}
MEMBERS = [(0.15, 1000.0), (0.23, 1000.0), (0.30, 1000.0), (0.23, 300.0), (0.23, 3000.0)]


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="bench/results/stop_rule.json")
    ap.add_argument("--cellsize", type=float, default=20.0)
    ap.add_argument("--t-end", type=float, default=300.0)
    ap.add_argument("--dtype", default="float32", choices=["float32", "float64"])
    ap.add_argument("--kernel", default="fused", choices=["fused", "eager", "compiled"], help="SolverConfig.kernel")
    a = ap.parse_args(argv)
    case = bondo_like(a.cellsize)
    dtype = torch.float32 if a.dtype == "float32" else torch.float64
    p = Params.make(mu=[m for m, _ in MEMBERS], xi=[x for _, x in MEMBERS])
    names = list(OBSERVABLES)
    runs = {}
    for rule, kw in RULES.items():
        cfg = SolverConfig(kernel=a.kernel, crop=True, **kw)
        t0 = time.perf_counter()
        r = simulate(case.dem, case.release, p, t_end=a.t_end, config=cfg, dtype=dtype)
        runs[rule] = {"wall_s": time.perf_counter() - t0, "t_final_s": r.t_final.tolist(),
                      "steps": r.steps.tolist(), "obs": observables(r, case.points)}
        print(f"{rule}: t_final {[round(t) for t in r.t_final.tolist()]} steps {r.steps.tolist()}", flush=True)
    ref = runs["off"]["obs"]
    out = {"terrain": "bondo_like", "cellsize_m": a.cellsize, "t_end_s": a.t_end, "dtype": a.dtype,
           "kernel": a.kernel, "members": [{"mu": m, "xi": x} for m, x in MEMBERS],
           "load_average": os.getloadavg()[0], "note": "wall_s of the first row includes compiling or loading the step",
           "rows": []}
    for rule, run in runs.items():
        rel = (run["obs"] - ref) / np.where(np.abs(ref) > 0, np.abs(ref), 1.0)
        out["rows"].append({
            "rule": rule, "solver_config": RULES[rule], "wall_s": run["wall_s"], "t_final_s": run["t_final_s"],
            "steps": run["steps"], "step_fraction_of_full": float(np.sum(run["steps"]) / np.sum(runs["off"]["steps"])),
            "max_abs_rel_change": {n: float(np.abs(rel[:, j]).max()) for j, n in enumerate(names)},
            "rel_change": {n: rel[:, j].tolist() for j, n in enumerate(names)}})
    os.makedirs(os.path.dirname(a.out) or ".", exist_ok=True)
    with open(a.out, "w") as fh:
        json.dump(out, fh, indent=2)
    for row in out["rows"][1:]:
        worst = ", ".join(f"{k} {v:.3f}" for k, v in row["max_abs_rel_change"].items())
        print(f"{row['rule']}: steps {row['step_fraction_of_full']:.2f} of full; "
              f"max |rel change| {worst}")
    print("wrote", a.out)


if __name__ == "__main__":
    main()
