"""Acquisition functions on a GP of the log-unnormalised posterior z = g(x), and batch selection.

Both are BoTorch ``AnalyticAcquisitionFunction`` s. ``m`` and ``k`` are the GP posterior mean and
variance of g in the model's *output* space (z units: the ``Standardize`` outcome transform is undone
by ``model.posterior``), so that exp(g_hat) is the emulated unnormalised posterior.

* LogNormalEntropy (Eq. 16; Wang & Li 2018): H(x) = m(x) + 0.5 ln(2 pi e k(x)), the entropy of the
  log-normal exp(g_hat(x)).
* ExpVariance (BAPE; Kandasamy et al. 2017): Var[exp(g_hat)] = exp(2m + k)(exp(k) - 1), returned as
  its log, 2m + k + log(expm1(k)), for stability (same maximiser).
"""
from __future__ import annotations

import math
import warnings

import torch
from botorch.acquisition.analytic import AnalyticAcquisitionFunction
from botorch.models.model import Model
from botorch.optim import optimize_acqf
from botorch.utils.transforms import t_batch_mode_transform

_LOG_2PIE = math.log(2.0 * math.pi * math.e)


class _MeanVarAcquisition(AnalyticAcquisitionFunction):
    def __init__(self, model: Model, min_var: float = 1e-12, **kwargs):
        super().__init__(model=model, **kwargs)
        self.min_var = min_var

    def _mean_var(self, X: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        post = self.model.posterior(X=X, posterior_transform=self.posterior_transform)
        mean = post.mean.squeeze(-2).squeeze(-1)
        var = post.variance.squeeze(-2).squeeze(-1).clamp_min(self.min_var)
        return mean, var


class LogNormalEntropy(_MeanVarAcquisition):
    """H(x) = m(x) + 0.5 ln(2 pi e k(x)) (Eq. 16). Input X: (b, 1, d) -> (b,)."""

    @t_batch_mode_transform(expected_q=1)
    def forward(self, X: torch.Tensor) -> torch.Tensor:
        m, k = self._mean_var(X)
        return m + 0.5 * (_LOG_2PIE + torch.log(k))


class ExpVariance(_MeanVarAcquisition):
    """log Var[exp(g_hat(x))] = 2m + k + log(exp(k) - 1) (BAPE, in log form). X: (b, 1, d) -> (b,)."""

    @t_batch_mode_transform(expected_q=1)
    def forward(self, X: torch.Tensor) -> torch.Tensor:
        m, k = self._mean_var(X)
        return 2.0 * m + k + torch.log(torch.expm1(k))


ACQUISITIONS = {"entropy": LogNormalEntropy, "expvar": ExpVariance, "bape": ExpVariance}


def make_acquisition(name: str, model: Model) -> AnalyticAcquisitionFunction:
    try:
        return ACQUISITIONS[name.lower()](model)
    except KeyError:
        raise ValueError(f"unknown acquisition {name!r}; choose from {sorted(ACQUISITIONS)}") from None


def select_batch(model: Model, q: int = 1, acquisition: str = "entropy", num_restarts: int = 8,
                 raw_samples: int = 256, seed: int | None = None,
                 dim: int | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Pick q points in the unit cube maximising the acquisition, with a kriging believer for q > 1.

    After each pick x_j the model is conditioned on its own mean prediction
    (``model.condition_on_observations(x_j, m(x_j))``): the variance collapses at x_j and near it,
    so the next maximiser is a different point, and the whole batch can be run in one solver call.

    Reproducible for a given ``seed`` when torch runs on one intra-op thread (multi-threaded
    reductions change the last bits, which sends L-BFGS to other local optima): the caller sets it.

    Returns:
        (X, values): X (q, d) in the unit cube; values (q,) the acquisition maximum of each pick
        (under the model conditioned on the earlier picks).
    """
    d = dim if dim is not None else model.train_inputs[0].shape[-1]
    dtype = model.train_inputs[0].dtype
    bounds = torch.stack([torch.zeros(d, dtype=dtype), torch.ones(d, dtype=dtype)])
    picks, vals = [], []
    cur = model
    for j in range(q):
        acq = make_acquisition(acquisition, cur)
        opts = {"seed": None if seed is None else int(seed) * 1000 + j, "maxiter": 200}
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # L-BFGS-B 'ABNORMAL' line-search exits on flat regions
            x, v = optimize_acqf(acq, bounds=bounds, q=1, num_restarts=num_restarts, raw_samples=raw_samples,
                                 options=opts, retry_on_optimization_warning=False)
        x = x.detach().reshape(1, d)
        picks.append(x)
        vals.append(v.detach().reshape(()))
        if j + 1 < q:
            with torch.no_grad():
                y = cur.posterior(x).mean.detach().reshape(1, 1)
            cur = cur.condition_on_observations(X=x, Y=y)
    X = torch.cat(picks, 0)
    return X, torch.stack(vals)
