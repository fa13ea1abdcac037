"""Posterior-predictive runs: M posterior samples -> batched solver calls -> moments of every observable."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch


def posterior_samples(cal, M: int, seed: int = 0) -> np.ndarray:
    """(M, p) draws from a CalibrationResult: its MCMC samples (p > 2) or its grid density (p <= 2),
    jittered uniformly within the grid cell."""
    rng = np.random.default_rng(seed)
    if cal.samples is not None and len(cal.samples):
        idx = rng.choice(len(cal.samples), size=M, replace=len(cal.samples) < M)
        return np.asarray(cal.samples)[idx]
    dens = np.asarray(cal.posterior_grid, dtype=np.float64)
    p = dens.ravel() / dens.sum()
    flat = rng.choice(p.size, size=M, p=p)
    ii = np.unravel_index(flat, dens.shape)
    out = np.empty((M, len(cal.grid_axes)))
    for d, ax in enumerate(cal.grid_axes):
        h = (ax[1] - ax[0]) if len(ax) > 1 else 0.0
        out[:, d] = ax[ii[d]] + rng.uniform(-0.5, 0.5, size=M) * h
        out[:, d] = np.clip(out[:, d], cal.bounds[0, d], cal.bounds[1, d])
    return out


def posterior_mode(cal) -> np.ndarray:
    """(p,) MAP of a CalibrationResult (summary 'map')."""
    return np.array([cal.summary["map"][n] for n in cal.names], dtype=np.float64)


@dataclass
class Predictive:
    """Posterior-predictive moments of the flat observable vector (k,).

    draws: (M_ok, k) predictions of the successful members; x: (M_ok, p) their parameters.
    """

    x: np.ndarray
    draws: np.ndarray
    n_failed: int

    @property
    def mean(self) -> np.ndarray:
        return self.draws.mean(axis=0)

    @property
    def var(self) -> np.ndarray:
        return self.draws.var(axis=0, ddof=1) if len(self.draws) > 1 else np.zeros(self.draws.shape[1])


def posterior_predictive(evaluator, samples: np.ndarray) -> Predictive:
    """Run the solver on all samples (in chunks of evaluator.max_batch members, one call per chunk)."""
    x = torch.as_tensor(np.asarray(samples, dtype=np.float64))
    res, preds = evaluator.evaluate(x)
    ok = ~res.failed.numpy()
    return Predictive(x=np.asarray(samples)[ok], draws=preds.numpy()[ok], n_failed=int((~ok).sum()))
