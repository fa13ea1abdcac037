"""Table 1 (simulation at the truth + synthetic observed data) and the Table 2 log-posteriors."""
from __future__ import annotations

import numpy as np
import torch

from torchslide.bayes import EvaluationResult, GaussianLikelihood, Prior

from .config import CASES, DATA, OBSERVABLES, BondoConfig


def synthetic_data(simulated: dict, noise_seed: int) -> dict:
    """Observed data d = y_true + eps, eps ~ N(0, (f y_true)^2), sigma = f y_true (fixed seed).

    Returns data id -> {"observable", "fraction", "simulated", "sigma", "observed"}.
    Each data id gets its own deterministic stream (seed, row index), so adding rows never changes others.
    """
    out = {}
    for i, (did, obs, frac) in enumerate(DATA):
        y = float(simulated[obs])
        rng = np.random.default_rng([int(noise_seed), i])
        sigma = frac * abs(y)
        out[did] = {"observable": obs, "fraction": frac, "simulated": y, "sigma": sigma,
                    "observed": float(y + sigma * rng.standard_normal())}
    return out


def table1(sim, cfg: BondoConfig) -> dict:
    """Simulate the truth (cached) and build Table 1."""
    x = np.array([[cfg.truth[n] for n in cfg.names]])
    y, failed, reasons = sim.get(x)
    if failed[0]:
        raise RuntimeError(f"the truth run failed: {reasons[0]}")
    simulated = dict(zip(OBSERVABLES, map(float, y[0])))
    return {"simulated": simulated, "data": synthetic_data(simulated, cfg.noise_seed)}


class CaseLogPosterior:
    """z = ln L(x | d_case) + ln pi(x) from the cached simulator (Eq. 6-7, 10), for one Table 2 case."""

    def __init__(self, case: int, sim, data: dict, cfg: BondoConfig):
        self.case = case
        self.sim = sim
        self.ids = CASES[case][1]
        cols = list(OBSERVABLES)
        self.columns = [cols.index(data[i]["observable"]) for i in self.ids]
        self.likelihood = GaussianLikelihood([data[i]["observed"] for i in self.ids],
                                             sigma=[data[i]["sigma"] for i in self.ids])
        self.prior = Prior.uniform(cfg.bounds_array(), cfg.names)

    def from_observables(self, x, y) -> torch.Tensor:
        """z for points x (n, 2) with all observables y (n, k) (nan where failed)."""
        yy = torch.as_tensor(np.asarray(y)[:, self.columns], dtype=torch.float64)
        return self.likelihood.log_likelihood(yy) + self.prior.log_prob(torch.as_tensor(x, dtype=torch.float64))

    def __call__(self, x) -> EvaluationResult:
        x = np.asarray(torch.as_tensor(x, dtype=torch.float64).reshape(-1, 2))
        y, failed, reasons = self.sim.get(x)
        z = self.from_observables(x, y)
        bad = failed | ~np.isfinite(z.numpy())
        reasons = [r if (b and r) else ("non-finite z" if b else "") for r, b in zip(reasons, bad)]
        z = torch.where(torch.as_tensor(bad), torch.full_like(z, float("nan")), z)
        return EvaluationResult(z, torch.as_tensor(bad), reasons)
