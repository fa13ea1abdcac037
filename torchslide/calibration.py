"""Entry point: ``calibrate(log_posterior, bounds, ...) -> CalibrationResult``.

Runs Algorithm 1 (torchslide.active) on a user log-unnormalised posterior z = g(x) and estimates the
posterior from the final GP emulator: grid approximation (Eq. 15) for p <= 2, adaptive Metropolis on
the emulator mean for p > 2. This module does not import the solver.

Grid convention: ``grid_axes`` are cell centres; ``posterior_grid`` is a density normalised such that
``posterior_grid.sum() * cell_volume == 1`` with ``cell_volume = prod(axis[1] - axis[0])``.
"""
from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from .active import ActiveConfig, ActiveLearner
from .bayes import check_bounds
from .files import atomic_path, write_text_atomic
from .posterior import PosteriorSummary, adaptive_metropolis, log_evidence_importance


@dataclass
class CalibrationResult:
    """Result of :func:`calibrate`.

    Attributes:
        names: parameter names.
        bounds: (2, p) box.
        x: (n, p) all evaluated points in run order; the first ``n_initial`` are the LHS design.
        z: (n,) log-unnormalised posterior values (nan where failed).
        failed: (n,) bool; ``reasons`` the failure reason per run ('' if fine).
        grid_axes: list of p cell-centre axes (p <= 2), else None.
        posterior_grid: density on the grid (sum * cell_volume = 1), or None for p > 2.
        log_evidence: log of the integral of exp(g_hat) over the box.
        tv_history: list of (n_runs, TV(p_i, p_{i-lag})).
        summary: dict with mean, sd, map, hdr90 per parameter (see PosteriorSummary.to_dict).
        samples: (N, p) MCMC samples on the emulator for p > 2, else None.
        emulator: the final LogPosteriorEmulator.
    """

    names: list
    bounds: np.ndarray
    x: np.ndarray
    z: np.ndarray
    failed: np.ndarray
    reasons: list
    n_initial: int
    grid_axes: list | None
    posterior_grid: np.ndarray | None
    log_evidence: float
    tv_history: list
    summary: dict
    samples: np.ndarray | None = None
    stopped_reason: str = ""
    timings: dict = field(default_factory=dict)
    emulator: object = None
    inference: dict = field(default_factory=lambda: {"path": "emulator", "why": "a log-posterior function"})
    discrepancy_factors: dict = field(default_factory=dict)

    @property
    def n_runs(self) -> int:
        return int(self.x.shape[0])

    def to_json(self) -> dict:
        """JSON-ready dict: mean, sd, map, hdr90, log_evidence, runs and diagnostics."""
        runs = [{"x": dict(zip(self.names, map(float, xi))),
                 "z": None if not np.isfinite(zi) else float(zi),
                 "failed": bool(fi), "reason": ri, "initial": i < self.n_initial}
                for i, (xi, zi, fi, ri) in enumerate(zip(self.x, self.z, self.failed, self.reasons))]
        out = dict(self.summary)
        out.update({"log_evidence": float(self.log_evidence), "n_runs": self.n_runs,
                    "n_initial": self.n_initial, "n_failed": int(np.sum(self.failed)),
                    "stopped_reason": self.stopped_reason,
                    "bounds": {n: [float(self.bounds[0, i]), float(self.bounds[1, i])] for i, n in enumerate(self.names)},
                    "tv_history": [[int(n), float(t)] for n, t in self.tv_history],
                    "timings": self.timings, "inference": self.inference,
                    "discrepancy_factors": self.discrepancy_factors, "runs": runs})
        return out

    def save(self, directory: str | os.PathLike) -> Path:
        """Write posterior.json and posterior.npz (x, z, failed, grid axes, density, samples)."""
        d = Path(directory)
        d.mkdir(parents=True, exist_ok=True)
        write_text_atomic(d / "posterior.json", json.dumps(self.to_json(), indent=2))
        arrays = {"x": self.x, "z": self.z, "failed": self.failed, "bounds": self.bounds,
                  "tv_history": np.asarray(self.tv_history, dtype=float).reshape(-1, 2)}
        if self.posterior_grid is not None:
            arrays["posterior_grid"] = self.posterior_grid
            for i, a in enumerate(self.grid_axes):
                arrays[f"axis_{i}"] = a
        if self.samples is not None:
            arrays["samples"] = self.samples
        with atomic_path(d / "posterior.npz") as tmp:
            np.savez_compressed(tmp, **arrays)
        return d


    @classmethod
    def load(cls, directory: str | os.PathLike) -> "CalibrationResult":
        """Read what :meth:`save` wrote (posterior.json and posterior.npz; the emulator is not saved).

        Raises FileNotFoundError naming the missing file, ValueError naming a corrupt file or when the two
        files disagree."""
        d = Path(directory)
        for f in ("posterior.json", "posterior.npz"):
            if not (d / f).is_file():
                raise FileNotFoundError(f"{d}: no {f} (is this the --out folder of a finished `torchslide "
                                        f"calibrate`?)")
        try:
            info = json.loads((d / "posterior.json").read_text())
        except ValueError as e:
            raise ValueError(f"{d / 'posterior.json'} is not valid JSON ({e})") from None
        try:
            with np.load(d / "posterior.npz") as a:
                arrays = {k: a[k] for k in a.files}
        except Exception as e:  # noqa: BLE001 - numpy raises several kinds for a truncated file
            raise ValueError(f"{d / 'posterior.npz'} is corrupt or truncated ({type(e).__name__})") from None
        names = list(info["names"])
        if arrays["x"].ndim != 2 or arrays["x"].shape[1] != len(names):
            raise ValueError(f"{d}: posterior.npz holds runs of {arrays['x'].shape[-1]} parameters, posterior.json "
                             f"names {names}")
        axes = [arrays[f"axis_{i}"] for i in range(len(names))] if "posterior_grid" in arrays else None
        summary = {k: info[k] for k in ("names", "mean", "sd", "map", "hdr90", "log_evidence") if k in info}
        return cls(names=names, bounds=arrays["bounds"], x=arrays["x"], z=arrays["z"], failed=arrays["failed"],
                   reasons=[r.get("reason", "") for r in info.get("runs", [])] or [""] * len(arrays["x"]),
                   n_initial=int(info.get("n_initial", 0)), grid_axes=axes,
                   posterior_grid=arrays.get("posterior_grid"), log_evidence=float(info["log_evidence"]),
                   tv_history=[tuple(r) for r in arrays["tv_history"].tolist()], summary=summary,
                   samples=arrays.get("samples"), stopped_reason=info.get("stopped_reason", ""),
                   timings=info.get("timings", {}), inference=info.get("inference", {}),
                   discrepancy_factors=info.get("discrepancy_factors", {}))


def calibrate(log_posterior: Callable, bounds, n_initial: int = 40, n_total: int = 120, batch_size: int = 1,
              seed: int = 0, grid_size: int = 100, acquisition: str = "entropy",
              checkpoint: str | os.PathLike | None = None, log_dir: str | os.PathLike | None = None,
              tv_threshold: float | None = None, names: Sequence[str] | None = None, progress: bool = True,
              clip_range: float | None = 1000.0, tv_lag: int = 10, tv_patience: int = 3,
              num_restarts: int = 8, raw_samples: int = 256, mcmc_steps: int = 4000,
              mcmc_chains: int = 8, inference: str = "auto", local_max_fraction: float = 0.05,
              log=None) -> CalibrationResult:
    """Calibrate parameters in a box by Bayesian active learning (Algorithm 1).

    Args:
        log_posterior: maps an (n, p) float64 tensor of parameter points to z (n,), or to (z, failed_mask),
            or to a torchslide.bayes.EvaluationResult. One call gets a whole batch. A
            torchslide.evaluator.LandslideEvaluator (the solver's) also learns its discrepancy's correlation
            from the initial design first (``learn_discrepancy``) and can be fitted on the solver
            (``inference``).
        bounds: (2, p) [lows; highs], or {name: (low, high)} (which also names the parameters).
        n_initial: b0, maximin-LHS initial runs. n_total: total run budget.
        batch_size: q points per iteration (kriging believer).
        seed: seeds the LHS and every iteration (resume reproduces the uninterrupted run).
        grid_size: points per axis of the estimation grid (p <= 2).
        acquisition: "entropy" (Eq. 16) or "expvar" (BAPE).
        checkpoint: file to write after every batch and resume from if it exists.
        log_dir: TensorBoard log dir (optional).
        tv_threshold: stop when TV(p_i, p_{i-tv_lag}) < threshold for tv_patience iterations.
        clip_range: GP training values are capped at max(z) - clip_range (None: off).
        inference: for a LandslideEvaluator, "auto" (the mode fitted on the solver and its Laplace posterior
            when the emulator's 90 % region fills less than ``local_max_fraction`` of the box), "local"
            (always) or "emulator" (never); torchslide.diagnose.local_path.local_calibration. Other
            log-posteriors take the emulator's posterior. The result's ``inference`` says which and why.
        log: a callable(str) for the local fit's messages (None: silent).
    """
    if isinstance(bounds, dict):
        names = list(bounds) if names is None else names
    if names is None and isinstance(getattr(log_posterior, "names", None), list):
        names = list(log_posterior.names)      # a LandslideEvaluator's calibrated parameters
    b = check_bounds(bounds, names)
    p = b.shape[1]
    names = list(names) if names is not None else [f"x{i}" for i in range(p)]
    cfg = ActiveConfig(n_initial=n_initial, n_total=n_total, batch_size=batch_size, seed=seed,
                       grid_size=grid_size, acquisition=acquisition, tv_threshold=tv_threshold, tv_lag=tv_lag,
                       tv_patience=tv_patience, clip_range=clip_range, num_restarts=num_restarts,
                       raw_samples=raw_samples)
    solver = hasattr(log_posterior, "learn_discrepancy")
    factors = {}
    if solver and log_posterior.discrepancy_factors is None:   # (a diagnosis' candidates keep the baseline's)
        from .active import initial_design

        factors = log_posterior.learn_discrepancy(initial_design(b, n_initial, seed).numpy())
    elif solver:
        factors = dict(log_posterior.discrepancy_factors)
    learner = ActiveLearner(log_posterior, b, cfg, checkpoint=checkpoint, log_dir=log_dir, progress=progress,
                            names=names)
    s = learner.run()
    em = learner.emulator
    samples = None
    if p <= 2:
        post = learner.posterior
        axes, dens, log_z = post.axes, post.density, post.log_evidence
        summ: PosteriorSummary = post.summary(names)
    else:
        mc = adaptive_metropolis(em.mean, b, n_chains=mcmc_chains, n_steps=mcmc_steps, seed=seed)
        samples = mc.samples
        log_z = log_evidence_importance(em.mean, b, samples, seed=seed)
        summ = mc.summary(names, log_z)
        axes, dens = None, None
    timings = {"fit_s_median": float(np.median(s.fit_seconds)) if s.fit_seconds else None,
               "acquisition_s_median": float(np.median(s.acq_seconds)) if s.acq_seconds else None}
    res = CalibrationResult(names=names, bounds=b.numpy(), x=s.x.numpy(), z=s.z.numpy(), failed=s.failed.numpy(),
                            reasons=list(s.reasons), n_initial=int(s.is_initial.sum()), grid_axes=axes,
                            posterior_grid=dens, log_evidence=float(log_z), tv_history=list(s.tv_history),
                            summary=summ.to_dict(), samples=samples, stopped_reason=s.stopped_reason,
                            timings=timings, emulator=em, discrepancy_factors=factors)
    if not solver:
        return res
    from .diagnose.local_path import local_calibration   # the local fit on the solver (its residuals)

    res, info = local_calibration(log_posterior, res, inference, local_max_fraction, seed=seed,
                                  log=log or (lambda m: None))
    if info["path"] == "local":     # the mode's run joins the records: the best run is the mode's
        log_posterior.evaluate(np.array([[res.summary["map"][n] for n in names]]))
    res.inference, res.discrepancy_factors = info, factors
    return res
