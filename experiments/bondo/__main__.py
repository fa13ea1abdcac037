"""python -m experiments.bondo [--case N ...] [--quick] [--cellsize M] [--no-sweep] [--no-report]

Runs the Bondo-like study (Table 1, the Table 2 cases by Bayesian active learning in lockstep, the
LHS-only comparison, the brute-force sweep reference), writes results under experiments/bondo/_work/
and regenerates the figures and README.md (full configuration only; --quick writes its page under
its work directory). Rerun the same command to resume after an interruption.
"""
from __future__ import annotations

import argparse
import sys


def main(argv=None) -> int:
    from .config import CASES, HERE, BondoConfig
    from .report import write_readme
    from .study import run_study

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--case", type=int, action="append", choices=sorted(CASES), help="case number (repeatable)")
    ap.add_argument("--quick", action="store_true", help="small configuration of the whole pipeline")
    ap.add_argument("--cellsize", type=float, default=None, help="terrain cell size, m")
    ap.add_argument("--t-end", type=float, default=None, help="simulated time, s")
    ap.add_argument("--n-initial", type=int, default=None)
    ap.add_argument("--n-adaptive", type=int, default=None)
    ap.add_argument("--batch-size", type=int, default=None, help="q points per case per iteration")
    ap.add_argument("--sweep-n", type=int, default=None)
    ap.add_argument("--work-dir", default=None)
    ap.add_argument("--name", default=None, help="run name (results go to <work-dir>/<name>_<tag>)")
    ap.add_argument("--no-sweep", action="store_true", help="skip the brute-force reference")
    ap.add_argument("--no-report", action="store_true", help="do not regenerate figures / README")
    ap.add_argument("--no-tensorboard", action="store_true")
    ap.add_argument("--dtype", choices=["float32", "float64"], default=None, help="solver precision")
    ap.add_argument("--kernel", choices=["fused", "eager", "compiled"], default=None,
                    help="solver step (default: fused)")
    ap.add_argument("--device", default=None, help="solver device, e.g. cuda (default: cpu)")
    ap.add_argument("--max-batch", type=int, default=None, help="most solver members per call (default: 25)")
    ap.add_argument("--workers", type=int, default=None,
                    help="processes for the cases' GP fits and acquisitions (default: 1, this process)")
    a = ap.parse_args(argv)
    cfg = BondoConfig.quick(a.work_dir) if a.quick else BondoConfig()
    kw = {k: v for k, v in {"cellsize": a.cellsize, "t_end": a.t_end, "n_initial": a.n_initial,
                            "n_adaptive": a.n_adaptive, "batch_size": a.batch_size, "sweep_n": a.sweep_n,
                            "name": a.name}.items() if v is not None}
    if a.case:
        kw["cases"] = tuple(sorted(set(a.case)))
        if a.name is None and not a.quick and set(a.case) != set(CASES):
            # a subset gets its own run directory (the full run's results are never overwritten);
            # it reuses the full run's simulations through a read-only cache
            kw["name"] = "cases_" + "_".join(map(str, kw["cases"]))
    if a.work_dir is not None and not a.quick:
        kw["work_dir"] = a.work_dir
    if a.dtype is not None:
        kw["dtype"] = a.dtype
    kw.update({k: v for k, v in {"kernel": a.kernel, "device": a.device, "max_batch": a.max_batch,
                                 "workers": a.workers}.items()
               if v is not None})
    if a.no_tensorboard:
        kw["tensorboard"] = False
    if a.n_adaptive is not None and "snapshots" not in kw:
        kw["snapshots"] = tuple(s for s in cfg.snapshots if s < a.n_adaptive) + (a.n_adaptive,)
    cfg = cfg.with_(**kw)
    run_study(cfg, with_sweep=not a.no_sweep)
    if not a.no_report:
        if cfg.name == "full" and a.work_dir is None:
            readme, figs = HERE / "README.md", HERE / "figures"
        else:
            readme, figs = cfg.run_dir / "README.md", cfg.run_dir / "figures"
        print(write_readme(cfg.run_dir, readme, figs))
    return 0


if __name__ == "__main__":
    sys.exit(main())
