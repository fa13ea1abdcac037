"""python -m experiments.sweep [--n 30] [--cellsize 40] [--t-end 300] [--chunk 100] [--quick]

Runs (or resumes) the brute-force n x n sweep of the Bondo-like case over the prior box and stores all
observables per run under experiments/bondo/_work/ (saved after every chunk; rerun to resume).
"""
from __future__ import annotations

import argparse
import json
import sys


def main(argv=None) -> int:
    from experiments.bondo.config import BondoConfig

    from .core import run_sweep

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="the quick configuration (6 x 6, 100 m cells)")
    ap.add_argument("--n", type=int, default=None, help="nodes per axis (default: config sweep_n)")
    ap.add_argument("--cellsize", type=float, default=None)
    ap.add_argument("--t-end", type=float, default=None)
    ap.add_argument("--chunk", type=int, default=None, help="runs per solver call (default: config max_batch)")
    ap.add_argument("--work-dir", default=None)
    ap.add_argument("--dtype", choices=["float32", "float64"], default=None, help="solver precision")
    ap.add_argument("--kernel", choices=["fused", "eager", "compiled"], default=None,
                    help="solver step (default: fused)")
    ap.add_argument("--device", default=None, help="solver device, e.g. cuda (default: cpu)")
    a = ap.parse_args(argv)
    cfg = BondoConfig.quick(a.work_dir) if a.quick else BondoConfig()
    kw = {}
    if a.cellsize is not None:
        kw["cellsize"] = a.cellsize
    if a.t_end is not None:
        kw["t_end"] = a.t_end
    if a.work_dir is not None and not a.quick:
        kw["work_dir"] = a.work_dir
    if a.dtype is not None:
        kw["dtype"] = a.dtype
    kw.update({k: v for k, v in {"kernel": a.kernel, "device": a.device}.items()
               if v is not None})
    cfg = cfg.with_(**kw)
    res = run_sweep(cfg, a.n, chunk=a.chunk)
    print(json.dumps({"path": res.path, "n": [len(x) for x in res.axes], "failed": res.n_failed,
                      "solver_seconds": res.seconds}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
