"""A cached batched simulator: parameter points -> ALL Table-1 observables per point.

Each point (mu, xi) is keyed by its exact float64 bytes; a point is simulated once, whatever case
asks for it. The cache is persisted to an .npz file after every solver call (atomic replace), so an
interrupted study or sweep resumes without repeating finished runs. Failed runs are stored with
their reason and give nan observables (never a silent number).

Solver workaround: gauges at L1-L3 are always passed (the current solver mis-handles runs with
zero gauges; see the experiments report).
"""
from __future__ import annotations

import json
import os
import time
from pathlib import Path

import numpy as np
import torch

from torchslide import observe as ob
from torchslide.physics import Params
from torchslide.terrain.synthetic import bondo_like

from .config import OBSERVABLES, BondoConfig


def observables(result, points: dict) -> np.ndarray:
    """(B, k) observables of a batched SimulationResult, columns in OBSERVABLES order."""
    cols = {
        "impact_area": ob.impact_area(result),
        "deposit_area": ob.deposit_area(result),
        "deposit_volume": ob.deposit_volume(result),
    }
    for k in ("L1", "L2", "L3"):
        x, y = points[k]
        cols[f"vmax_{k}"] = ob.max_velocity(result, x, y)
        cols[f"hdep_{k}"] = ob.deposit_height(result, x, y)
    return np.stack([cols[n].detach().double().cpu().numpy() for n in OBSERVABLES], axis=1)


def _key(x) -> bytes:
    return np.ascontiguousarray(np.asarray(x, dtype=np.float64)).tobytes()


class CachedSimulator:
    """Run the solver for batches of points and store every observable per point.

    Args:
        cfg: study config (cell size, t_end, dtype, max_batch).
        path: .npz cache file (created on first save); None keeps the cache in memory.
    """

    def __init__(self, cfg: BondoConfig, path: str | os.PathLike | None = None, extra=()):
        self.cfg = cfg
        self.case = bondo_like(cfg.cellsize)
        self.path = Path(path) if path is not None else None
        self.names = list(OBSERVABLES)
        self._x: list[np.ndarray] = []
        self._y: list[np.ndarray] = []
        self._failed: list[bool] = []
        self._reason: list[str] = []
        self._index: dict[bytes, int] = {}
        self.solver_seconds = 0.0
        self.last_result = None
        self.n_solver_calls = 0
        self.n_simulated = 0
        if self.path is not None and self.path.exists():
            self._load(self.path, own=True)
        for p in extra:  # read-only caches of other runs with the same simulator setup
            if p is not None and Path(p).exists() and Path(p) != self.path:
                try:
                    self._load(Path(p), own=False)
                except ValueError:
                    pass

    # ------------------------------------------------------------------ persistence
    def _load(self, path: Path, own: bool = True) -> None:
        d = np.load(path, allow_pickle=False)
        meta = json.loads(str(d["meta"]))
        if meta.get("tag") != self.cfg.tag or meta.get("names") != self.names:
            raise ValueError(f"cache {path} was made with {meta}, not tag {self.cfg.tag}")
        for x, y, f, r in zip(d["x"], d["y"], d["failed"], json.loads(str(d["reasons"]))):
            self._add(x, y, bool(f), r)
        if own:
            self.solver_seconds = float(meta.get("solver_seconds", 0.0))

    def save(self) -> None:
        if self.path is None:
            return
        self.path.parent.mkdir(parents=True, exist_ok=True)
        tmp = self.path.with_name(self.path.stem + f".tmp{os.getpid()}.npz")
        meta = {"tag": self.cfg.tag, "names": self.names, "solver_seconds": self.solver_seconds,
                "cellsize": self.cfg.cellsize, "t_end": self.cfg.t_end}
        np.savez(tmp, x=np.asarray(self._x).reshape(-1, 2), y=np.asarray(self._y).reshape(-1, len(self.names)),
                 failed=np.asarray(self._failed, dtype=bool), reasons=json.dumps(self._reason),
                 meta=json.dumps(meta))
        os.replace(tmp, self.path)

    def _add(self, x, y, failed: bool, reason: str) -> None:
        k = _key(x)
        if k in self._index:
            return
        self._index[k] = len(self._x)
        self._x.append(np.asarray(x, dtype=np.float64).copy())
        self._y.append(np.asarray(y, dtype=np.float64).copy())
        self._failed.append(bool(failed))
        self._reason.append(str(reason))

    def __len__(self) -> int:
        return len(self._x)

    def __contains__(self, x) -> bool:
        return _key(x) in self._index

    # ------------------------------------------------------------------ running
    def simulate_batch(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray, list[str]]:
        """One solver call for (B, 2) points; returns observables (B, k), failed (B,), reasons."""
        from torchslide.solver import SolverConfig, simulate

        x = np.asarray(x, dtype=np.float64).reshape(-1, 2)
        c = self.case
        dtype = torch.float64 if self.cfg.dtype == "float64" else torch.float32
        params = Params.make(mu=x[:, 0], xi=x[:, 1], dtype=dtype)
        gauges = [(k, float(px), float(py)) for k, (px, py) in c.points.items()]
        t0 = time.perf_counter()
        res = simulate(c.dem, c.release, params, t_end=self.cfg.t_end, gauges=gauges, dtype=dtype,
                       device=self.cfg.device, config=SolverConfig(kernel=self.cfg.kernel, stop_quiet_time=self.cfg.stop_quiet_time))
        self.solver_seconds += time.perf_counter() - t0
        self.last_result = res
        self.n_solver_calls += 1
        self.n_simulated += x.shape[0]
        y = observables(res, c.points)
        failed = np.zeros(x.shape[0], dtype=bool) if res.failed is None else res.failed.cpu().numpy().astype(bool)
        reasons = []
        for b in range(x.shape[0]):
            r = (res.failure_reason[b] or "") if res.failure_reason else ""
            if failed[b] and not r:
                r = "solver reported failure"
            if not failed[b] and not np.isfinite(y[b]).all():
                failed[b], r = True, "non-finite observable"
            reasons.append(r)
        y[failed] = np.nan
        return y, failed, reasons

    def run(self, x, progress=None) -> None:
        """Make sure every (n, 2) point is in the cache (missing ones in chunks of max_batch; save after each)."""
        x = np.asarray(x, dtype=np.float64).reshape(-1, 2)
        todo, seen = [], set()
        for xi in x:
            k = _key(xi)
            if k not in self._index and k not in seen:
                seen.add(k)
                todo.append(xi)
        # members of one call share one cropped window (torchslide.solver.crop): sorted by mu, a call
        # holds similar run-outs, so a long low-friction run does not widen the window of short ones
        todo = sorted(todo, key=lambda p: (p[0], p[1]))
        for s in range(0, len(todo), self.cfg.max_batch):
            xb = np.asarray(todo[s:s + self.cfg.max_batch])
            y, f, r = self.simulate_batch(xb)
            for i in range(len(xb)):
                self._add(xb[i], y[i], f[i], r[i])
            self.save()
            if progress is not None:
                progress(len(xb))

    def get(self, x) -> tuple[np.ndarray, np.ndarray, list[str]]:
        """Observables (n, k), failed (n,), reasons for points already in the cache (runs missing ones)."""
        x = np.asarray(x, dtype=np.float64).reshape(-1, 2)
        self.run(x)
        idx = [self._index[_key(xi)] for xi in x]
        return (np.asarray([self._y[i] for i in idx]).reshape(-1, len(self.names)),
                np.asarray([self._failed[i] for i in idx], dtype=bool), [self._reason[i] for i in idx])

    def all(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        return (np.asarray(self._x).reshape(-1, 2), np.asarray(self._y).reshape(-1, len(self.names)),
                np.asarray(self._failed, dtype=bool))
