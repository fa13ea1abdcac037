"""``torchslide sweep CONFIG.toml --out DIR [--n 20] [--calibration CAL_DIR] [--resume]``: brute force.

Runs the solver at every node of an n x ... x n grid (cell centres) over the calibrate config's prior box,
in batched calls of ``[calibration] max_batch`` members, and evaluates z = ln L + ln prior there: the
reference posterior an emulator-based calibration should reproduce (the paper's check, section 4). With
``--calibration`` (p <= 2) it says how far that calibration's posterior is from the reference: TV
(Eq. 17) between the two on the sweep's grid, the calibration's density interpolated bilinearly onto it.

Writes::

    DIR/sweep.csv        one line per node: parameters, predicted observables, z, failed, reason
    DIR/sweep.npz        axes (axis_0, ...), z and the normalised density on the grid (n, ..., n)
    DIR/sweep.json       n, runs, failed, solver seconds, log evidence, mean / sd / MAP / 90 % HDR per
                         parameter, and tv_to_calibration when --calibration is given
    DIR/posterior.png    the reference posterior (figures.plot_posterior_any; p <= 2)

The runs are checkpointed after every solver call (DIR/sweep_checkpoint.npz): ``--resume`` continues an
interrupted sweep without repeating a finished run. Exit code 0; 1 when some nodes failed (they count as
zero density and are listed in sweep.csv); 2 on bad input.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from ..config import ConfigError
from . import add_executor_arguments, executor_for

HELP = "brute-force reference posterior on a grid over the prior box (optionally against a calibration)"

MAX_RUNS = 100_000  # more nodes than this is a mistake in --n, not a sweep


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("config", help="calibrate config (simulate config + [prior], [[observations]])")
    p.add_argument("--out", "-o", required=True, metavar="DIR", help="output folder")
    p.add_argument("--n", type=int, default=20, help="grid nodes per calibrated parameter (default 20)")
    p.add_argument("--calibration", default=None, metavar="CAL_DIR",
                   help="a `torchslide calibrate` output folder to compare with (TV distance, p <= 2)")
    p.add_argument("--resume", action="store_true", help="continue an interrupted sweep in --out")
    p.add_argument("--quiet", "-q", action="store_true", help="no progress bar")
    add_executor_arguments(p)


def interpolate_density(axes_from, density: np.ndarray, axes_to) -> np.ndarray:
    """A grid density on ``axes_from`` evaluated bilinearly (multilinearly) at the nodes of ``axes_to``,
    extrapolated flat beyond the outer cell centres, clipped at 0 and renormalised on the new grid."""
    from scipy.interpolate import RegularGridInterpolator

    from ..posterior import cell_volume, grid_points

    pts = [np.clip(a, f[0], f[-1]) for a, f in zip(axes_to, axes_from)]
    f = RegularGridInterpolator(tuple(axes_from), np.asarray(density, dtype=np.float64))
    q = np.clip(f(grid_points(pts).numpy()), 0.0, None).reshape([len(a) for a in axes_to])
    return q / (q.sum() * cell_volume(axes_to))


def _open_checkpoint(ckpt: Path):
    """np.load of the sweep's checkpoint; FileStateError naming it when it is corrupt or truncated."""
    import zipfile

    from ..files import FileStateError

    try:
        c = np.load(ckpt)
        for key in ("x", "z", "failed", "preds", "reasons", "done"):
            c[key]
        return c
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile) as e:
        raise FileStateError(f"sweep checkpoint {ckpt} is corrupt or truncated ({type(e).__name__}); delete it "
                             "to start the sweep again") from None


def _write_csv(path: Path, names, obs_names, x, preds, z, failed, reasons) -> None:
    from ..files import atomic_path

    with atomic_path(path) as tmp, open(tmp, "w") as f:
        f.write(",".join(list(names) + list(obs_names) + ["z", "failed", "reason"]) + "\n")
        for xi, pi, zi, fi, ri in zip(x, preds, z, failed, reasons):
            f.write(",".join([f"{v:.10g}" for v in list(xi) + list(pi)] + [f"{zi:.10g}", str(int(fi)),
                                                                          str(ri).replace(",", ";")]) + "\n")


def run(args: argparse.Namespace) -> int:
    from ..output_folder import run_locked

    return run_locked(args.out, _run, args)


def _sweep_runs(ev, x, z, failed, preds, reasons, done: int, ckpt: Path, bar) -> None:
    """Evaluate the nodes x[done:] into z, failed, preds, reasons (in place), one checkpoint per step of
    max_batch members per worker (each step: one chunk per worker of the evaluator's executor)."""
    import torch

    from ..files import atomic_path

    n_runs = len(x)
    step = ev.max_batch * (ev.executor.workers if ev.executor is not None else 1)
    for s in range(done, n_runs, step):
        e = min(s + step, n_runs)
        res, p = ev.evaluate(torch.as_tensor(x[s:e]))
        z[s:e], failed[s:e], preds[s:e] = res.z.numpy(), res.failed.numpy(), p.numpy()
        reasons[s:e] = res.reasons
        with atomic_path(ckpt) as tmp:
            np.savez(tmp, x=x, z=z, failed=failed, preds=preds, reasons=np.array(reasons), done=e)
        if bar is not None:
            bar.update(e - s)


def _run(args: argparse.Namespace) -> int:
    import torch

    from ..figures import plot_posterior_any
    from ..files import atomic_path, write_text_atomic
    from ..posterior import cell_volume, grid_axes, grid_points, normalise_log_grid, summarise_grid, tv_distance
    from ..calibration_config import load_calibration, load_calibration_config, make_evaluator

    if args.n < 2:
        raise ConfigError(f"--n must be >= 2 nodes per parameter, got {args.n}")
    cfg = load_calibration_config(args.config)
    ev = make_evaluator(cfg)
    ev.solver_progress = not args.quiet
    names, bounds = list(ev.prior.names), np.asarray(ev.prior.bounds, dtype=np.float64)
    n_runs = args.n ** len(names)
    if n_runs > MAX_RUNS:
        raise ConfigError(f"--n {args.n} over {len(names)} parameters is {n_runs} runs (at most {MAX_RUNS})")
    cal = None
    if args.calibration is not None:
        cal = load_calibration(args.calibration, ev.prior)
        if cal.posterior_grid is None:
            raise ConfigError(f"--calibration {args.calibration} has no grid posterior ({len(names)} parameters: "
                              f"the TV comparison needs p <= 2)")
        ev.set_discrepancy_factors(cal.discrepancy_factors)     # the calibration's likelihood
    out = Path(args.out)
    ckpt = out / "sweep_checkpoint.npz"
    if ckpt.exists() and not args.resume:
        raise ConfigError(f"{out} holds an earlier sweep (sweep_checkpoint.npz): pass --resume to continue it "
                          f"or choose another --out")
    axes = grid_axes(bounds, args.n)
    x = grid_points(axes).numpy()
    k = ev.k
    z, failed = np.full(n_runs, np.nan), np.zeros(n_runs, dtype=bool)
    preds, reasons, done = np.full((n_runs, k), np.nan), [""] * n_runs, 0
    if ckpt.exists():
        with _open_checkpoint(ckpt) as c:
            if c["x"].shape != x.shape or not np.allclose(c["x"], x):
                raise ConfigError(f"{ckpt}: the saved sweep has other nodes (another --n or prior box); "
                                  f"choose another --out")
            done = int(c["done"])
            z[:done], failed[:done], preds[:done] = c["z"][:done], c["failed"][:done], c["preds"][:done]
            reasons[:done] = [str(r) for r in c["reasons"][:done]]
    from ..output_folder import prepare_work_folder

    prepare_work_folder(out)
    bar = None
    if not args.quiet:
        from tqdm.auto import tqdm

        bar = tqdm(total=n_runs, initial=done, desc="sweep", unit="run")
    try:
        with executor_for(args, cfg, ev):
            _sweep_runs(ev, x, z, failed, preds, reasons, done, ckpt, bar)
    finally:
        if bar is not None:
            bar.close()

    if cal is None and ev.discrepancy == "learnt" and (~failed).any():
        # the discrepancy's correlation learnt at the best node (as a calibration learns it at its pilot's best
        # run), every node's z scored again from its predictions
        ev.learn_discrepancy_from(preds[int(np.nanargmax(np.where(failed, np.nan, z)))])
        ok = ~failed
        z[ok] = (ev.likelihood.log_likelihood(torch.as_tensor(preds[ok]))
                 + ev.prior.log_prob(torch.as_tensor(x[ok]))).numpy()
    zg = np.where(failed, -np.inf, z).reshape([len(a) for a in axes])
    try:
        density, log_z = normalise_log_grid(zg, axes)
    except ValueError:
        raise ConfigError(f"every one of the {n_runs} sweep runs failed; first: {reasons[0]}") from None
    summ = summarise_grid(density, axes, names).to_dict()
    info = {"n": args.n, "n_runs": n_runs, "n_failed": int(failed.sum()), "solver_seconds": ev.solver_seconds,
            "discrepancy": ev.discrepancy, "discrepancy_factors": ev.discrepancy_factors or {},
            "log_evidence": log_z, **{key: summ[key] for key in ("mean", "sd", "map", "hdr90")},
            "conventions": cfg.conventions()}
    if cal is not None:
        q = interpolate_density(cal.grid_axes, cal.posterior_grid, axes)
        info["tv_to_calibration"] = tv_distance(q, density, cell_volume(axes))
        info["calibration"] = {"path": str(args.calibration), "n_runs": cal.n_runs,
                               "log_evidence": float(cal.log_evidence)}
    _write_csv(out / "sweep.csv", names, ev.observation_names, x, preds, z, failed, reasons)
    with atomic_path(out / "sweep.npz") as tmp:
        np.savez_compressed(tmp, z=zg, density=density, **{f"axis_{i}": a for i, a in enumerate(axes)})
    write_text_atomic(out / "sweep.json", json.dumps(info, indent=2))
    # the figure marks failed nodes only (every node is a run: drawing them all would hide the density)
    ref = SimpleNamespace(names=names, bounds=bounds, x=x[failed], failed=np.ones(int(failed.sum()), dtype=bool),
                          n_initial=n_runs, grid_axes=axes, posterior_grid=density, samples=None)
    if len(names) <= 2:
        plot_posterior_any(ref, out / "posterior.png", title=f"brute-force reference, ${args.n}^{len(names)}$ runs")
    if not args.quiet:
        for nm in names:
            print(f"{nm}: mean {summ['mean'][nm]:.4g}  sd {summ['sd'][nm]:.3g}  MAP {summ['map'][nm]:.4g}  "
                  f"90% HDR [{summ['hdr90'][nm][0]:.4g}, {summ['hdr90'][nm][1]:.4g}]")
        tv = f"; TV to the calibration {info['tv_to_calibration']:.3f}" if cal is not None else ""
        print(f"log evidence {log_z:.3f}; {n_runs} runs{tv}; results in {out}")
    if failed.any():
        print(f"torchslide: warning: {int(failed.sum())} of {n_runs} sweep runs failed and count as zero density "
              f"(sweep.csv); first: {reasons[int(np.argmax(failed))]}", file=sys.stderr)
    return 1 if failed.any() else 0
