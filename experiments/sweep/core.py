"""Brute-force sweep: run the solver on an n x n node grid over the prior box (edges included),
store ALL observables per run (experiments.bondo.simulator.CachedSimulator; saved after every chunk,
so an interrupted sweep resumes where it stopped), and build any case's reference posterior.

Reference posterior of a case: the observables (not the posterior) are interpolated bilinearly from
the sweep nodes to the cell centres of the posterior grid (e.g. 100 x 100), the case's Gaussian
log-likelihood + log-prior is evaluated there and normalised on the grid (Eq. 8). When the sweep
grid already equals the posterior grid nothing is interpolated. Cells next to a failed sweep run
get zero density (nan observables propagate) and are counted in ``n_failed``.
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.interpolate import RegularGridInterpolator

from torchslide.posterior import grid_axes, grid_points, normalise_log_grid


def sweep_axes(bounds: np.ndarray, n: int) -> list[np.ndarray]:
    """n nodes per axis from low to high inclusive. bounds: (2, p)."""
    b = np.asarray(bounds, dtype=np.float64)
    return [np.linspace(b[0, i], b[1, i], n) for i in range(b.shape[1])]


@dataclass
class SweepResult:
    """axes: p node axes; y: (n_1, ..., n_p, k) observables (nan where failed); failed: (n_1, ..., n_p)."""

    axes: list
    y: np.ndarray
    failed: np.ndarray
    names: list
    seconds: float
    path: str | None = None

    @property
    def n_failed(self) -> int:
        return int(self.failed.sum())


def sweep_path(cfg, n: int) -> Path:
    return Path(cfg.work_dir) / f"sweep_{cfg.tag}_{n}x{n}.npz"


def run_sweep(cfg, n: int | None = None, path=None, chunk: int | None = None, progress: bool = True) -> SweepResult:
    """Run (or resume) the n x n sweep for the study config ``cfg`` (experiments.bondo.config.BondoConfig)."""
    from experiments.bondo.simulator import CachedSimulator

    n = int(n or cfg.sweep_n)
    path = Path(path) if path is not None else sweep_path(cfg, n)
    if chunk is not None:
        cfg = cfg.with_(max_batch=int(chunk))
    sim = CachedSimulator(cfg, path)
    axes = sweep_axes(cfg.bounds_array(), n)
    pts = grid_points(axes).numpy()
    missing = [p for p in pts if p not in sim]
    t0 = time.perf_counter()
    bar = None
    if progress and missing:
        from tqdm.auto import tqdm

        bar = tqdm(total=len(pts), initial=len(pts) - len(missing), desc=f"sweep {n}x{n}", unit="run")
    sim.run(np.asarray(missing).reshape(-1, 2), progress=(bar.update if bar is not None else None))
    if bar is not None:
        bar.close()
    y, failed, _ = sim.get(pts)
    shape = [len(a) for a in axes]
    return SweepResult(axes=axes, y=y.reshape(*shape, -1), failed=failed.reshape(shape), names=list(sim.names),
                       seconds=sim.solver_seconds if missing else time.perf_counter() - t0, path=str(path))


def interpolate_observables(sweep: SweepResult, grid: list[np.ndarray]) -> np.ndarray:
    """Observables at the grid's points ((prod G, k), 'ij' order), bilinear between sweep nodes."""
    pts = grid_points(grid).numpy()
    same = all(len(a) == len(g) and np.allclose(a, g) for a, g in zip(sweep.axes, grid))
    k = sweep.y.shape[-1]
    if same:
        return sweep.y.reshape(-1, k)
    out = np.empty((pts.shape[0], k))
    for j in range(k):
        f = RegularGridInterpolator(sweep.axes, sweep.y[..., j], method="linear", bounds_error=False, fill_value=None)
        out[:, j] = f(pts)
    return out


def reference_posterior(sweep: SweepResult, log_posterior, bounds, grid_size: int = 100):
    """Brute-force reference posterior of a case on the grid_size^p grid.

    log_posterior: an object with ``from_observables(x (n, p), y (n, k)) -> z (n,)`` (e.g.
    experiments.bondo.data.CaseLogPosterior). Returns (axes, density, log_evidence).
    """
    axes = grid_axes(bounds, grid_size)
    y = interpolate_observables(sweep, axes)
    pts = grid_points(axes).numpy()
    z = np.asarray(log_posterior.from_observables(pts, y), dtype=np.float64).reshape([len(a) for a in axes])
    dens, lz = normalise_log_grid(z, axes)
    return axes, dens, lz
