"""The model's own error: a discrepancy whose size is learnt from the data with the parameters.

Every real recording differs from the model in ways no parameter absorbs (the grid, the DEM, the
rheology). Following Kennedy & O'Hagan (2001, J. R. Stat. Soc. B 63, 425-464) the data are

    d = y(x) + delta + e,    e ~ N(0, Sigma) (the stated errors),    delta_i ~ N(0, lambda_g w_i sigma_i^2)    (D1)

with one discrepancy per observation g (a scalar, a map or a gauge series): its size lambda_g >= 0 a
multiple of the stated errors', spread over the observation's values by the weights w_i = m_i^2 /
mean_g(m^2), m_i = (|d_i| + |y_i(x)|) / 2 (the model errs where there is flow, recorded or simulated, and
not where neither has any: a deposit map's empty cells, a gauge before the front), and correlated as the
stated errors are (a map with ``corr_length`` keeps its effective count n_g = m / f, torchslide.observe_series;
``correlation_factor`` learns a longer reach from a pilot run's residual). A scalar observation has w = 1.

lambda_g is integrated out under the prior p(lambda) = (1 + lambda)^-2 (uniform in v = 1 / (1 + lambda) on
(0, 1]: a discrepancy as large as the stated error as likely as not), so that with s_i the squared
standardised residuals and c_g = n_g / m_g

    ln L(x) = ln N(d | y(x), Sigma) + sum_g ln I_g,
    I_g = int_0^1 exp(-1/2 sum_(i in g) [c_g ln(1 + lambda w_i) + s_i / (1 + lambda w_i) - s_i]) dv        (D2)

by Gauss-Legendre quadrature over ln v (``NODES``). Where the model fits (s about 1) the integral costs
almost nothing (a single datum's interval widens by 29 %, a map's of n_g = 50 by 2 %); where it does not, the
misfit grows only logarithmically: a datum the model cannot meet together with the others no longer
outweighs them by its count, and every interval widens by the misfit it leaves. For a scalar (D2) is the
closed form (2 / S)^a gamma(a, S / 2) e^(S / 2) with a = 3/2 (the lower incomplete gamma function).

For least squares (the local path: ln L = log_norm - |r|^2 / 2), ``residuals`` gives each residual scaled
by sqrt(E[1 / (1 + lambda w_i)]) (the posterior mean over lambda given the run) and one more entry per
observation, sqrt(Q_g - sum of its scaled squares) with Q_g = -2 ln I_g + S_g, so that |r|^2 / 2 is -ln L
+ log_norm and the Gauss-Newton precision at the mode is the Hessian of -ln L there (w held).

Shapes: n runs, k data values, G observations (groups), T quadrature nodes.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from scipy import special

MODELS = ("learnt", "none")
"""``[calibration] discrepancy``: "learnt" (this module) or "none" (the stated errors only)."""


def _nodes(pieces: int = 24, order: int = 16) -> tuple[np.ndarray, np.ndarray]:
    """(v, ln of the quadrature weights of int_0^1 dv) by Gauss-Legendre in ln v on ``pieces`` equal pieces of
    [ln 1e-9, 0] (dv = v d ln v): exact to 1e-10 for a scalar and fine enough for a map's sharper posterior
    of lambda (node spacing 0.05 in ln lambda)."""
    x, wq = np.polynomial.legendre.leggauss(order)
    edges = np.linspace(math.log(1e-9), 0.0, pieces + 1)
    t = np.concatenate([(b - a) / 2 * x + (a + b) / 2 for a, b in zip(edges[:-1], edges[1:])])
    w = np.concatenate([(b - a) / 2 * wq for a, b in zip(edges[:-1], edges[1:])])
    return np.exp(t), np.log(w) + t


NODES, _LOG_W = _nodes()
"""The quadrature's nodes v = 1 / (1 + lambda) and the logs of their weights."""
LAMBDA = 1.0 / NODES - 1.0


@dataclass
class Group:
    """One observation's slice of the data vector: its name, its columns (indices into the data vector), its
    effective number of independent values n (sum of 1 / f over its values at the stated errors'
    correlation) and ``factor`` >= 1, how many times farther its residual is correlated (the F learnt from a
    pilot run over the stated f, ``correlation_factor``): its misfit and count are divided by it."""

    name: str
    columns: np.ndarray
    n_eff: float
    factor: float = 1.0


class DiscrepancyLikelihood:
    """ln L(x | d) of the module doc over a Gaussian likelihood of the stated errors.

    Args:
        gaussian: a torchslide.bayes.GaussianLikelihood (diagonal sigma_eff or full covariance).
        groups: the Groups covering the data vector (each column in one group).

    Offers what the Gaussian does (``whiten``: the stated errors' whitening, ``sigma``, ``chol``,
    ``log_norm``, ``observed``) and ``log_likelihood``, ``residuals`` (least-squares form),
    ``sample_variance_factors`` and ``describe``.
    """

    def __init__(self, gaussian, groups: list[Group]):
        self.gaussian = gaussian
        self.groups = list(groups)
        k = int(gaussian.observed.numel())
        seen = np.concatenate([g.columns for g in self.groups]) if self.groups else np.array([], int)
        if sorted(seen.tolist()) != list(range(k)):
            raise ValueError(f"discrepancy groups must cover each of the {k} data values once")
        self.factor = np.array([g.factor for g in self.groups], dtype=np.float64)
        if not np.all(self.factor >= 1.0):
            raise ValueError(f"discrepancy factors must be >= 1, got {self.factor.tolist()}")
        self.n_eff = np.array([g.n_eff for g in self.groups], dtype=np.float64) / self.factor
        self._data = np.abs(gaussian.observed.detach().cpu().numpy().astype(np.float64))

    # the Gaussian's attributes, for the code that reads the stated errors
    observed = property(lambda self: self.gaussian.observed)
    sigma = property(lambda self: self.gaussian.sigma)
    chol = property(lambda self: self.gaussian.chol)
    log_norm = property(lambda self: self.gaussian.log_norm)

    @property
    def names(self) -> list[str]:
        return [g.name for g in self.groups]

    def whiten(self, simulated) -> torch.Tensor:
        """(n, k) residuals whitened by the stated errors (the Gaussian's)."""
        return self.gaussian.whiten(simulated)

    def _terms(self, simulated):
        """(s (n, k): squared whitened residuals over each group's factor, [per group: (w (n, m) weights,
        E (n, T) log posterior of lambda over the nodes, unnormalised, ln I (n,))]); rows with a value that is
        not finite have ln I = nan."""
        y = np.atleast_2d(torch.as_tensor(simulated).detach().cpu().numpy().astype(np.float64))
        s = self.whiten(torch.as_tensor(y)).detach().cpu().numpy() ** 2
        out = []
        for g, F, n in zip(self.groups, self.factor, self.n_eff):
            cols = g.columns
            s[:, cols] /= F
            m2 = (0.5 * (self._data[cols] + np.abs(y[:, cols]))) ** 2
            mean = m2.mean(axis=1, keepdims=True)
            w = np.where(mean > 0, m2 / np.where(mean > 0, mean, 1.0), 1.0)
            bad = ~np.isfinite(s[:, cols]).all(axis=1) | ~np.isfinite(w).all(axis=1)
            sg, w = np.where(np.isfinite(s[:, cols]), s[:, cols], 0.0), np.where(np.isfinite(w), w, 1.0)
            c = n / cols.size
            E = np.empty((sg.shape[0], LAMBDA.size))
            for j, lam in enumerate(LAMBDA):
                q = 1.0 + lam * w
                E[:, j] = -0.5 * np.sum(c * np.log(q) + sg / q - sg, axis=1)
            E += _LOG_W
            out.append((w, E, np.where(bad, np.nan, special.logsumexp(E, axis=1))))
        return s, out

    def log_likelihood(self, simulated) -> torch.Tensor:
        """(n, k) predictions -> (n,) ln L (D2); nan where a prediction is not finite."""
        s, terms = self._terms(simulated)
        ll = self.log_norm - 0.5 * np.sum(s, axis=1) + sum(t[2] for t in terms)
        return torch.as_tensor(ll, dtype=torch.float64)

    __call__ = log_likelihood

    def residuals(self, simulated) -> torch.Tensor:
        """(n, k + G) the least-squares form: ln L = log_norm - |r|^2 / 2 (module doc)."""
        s, terms = self._terms(simulated)
        r = np.atleast_2d(self.whiten(torch.as_tensor(simulated)).detach().cpu().numpy())
        scaled = np.array(r, dtype=np.float64, copy=True)
        extra = np.empty((r.shape[0], len(self.groups)))
        for j, (g, F, (w, E, log_I)) in enumerate(zip(self.groups, self.factor, terms)):
            post = np.exp(E - special.logsumexp(E, axis=1, keepdims=True))       # (n, T)
            shrink = np.zeros_like(w)                                           # E[1 / (1 + lambda w)]
            for t, lam in enumerate(LAMBDA):
                shrink += post[:, t, None] / (1.0 + lam * w)
            scaled[:, g.columns] = r[:, g.columns] * np.sqrt(shrink / F)
            Q = -2.0 * log_I + np.sum(s[:, g.columns], axis=1)
            extra[:, j] = np.sqrt(np.maximum(Q - np.sum(scaled[:, g.columns] ** 2, axis=1), 0.0))
        return torch.as_tensor(np.concatenate([scaled, extra], axis=1), dtype=torch.float64)

    def _posterior_lambda(self, simulated) -> list:
        """Per group, ((n, T) the posterior of lambda over the nodes given each run, its weights w (n, m))."""
        _, terms = self._terms(simulated)
        return [(np.exp(E - special.logsumexp(E, axis=1, keepdims=True)), w) for w, E, _ in terms]

    def sample_variance_factors(self, simulated, rng: np.random.Generator) -> np.ndarray:
        """(n, k) one draw per run of 1 + lambda_g w_i: the factor on each stated variance that a new
        recording's error has when the model's own error is counted, lambda_g drawn from its posterior given
        the run (the run's own misfit)."""
        out = np.ones(np.shape(np.atleast_2d(simulated)))
        for g, (post, w) in zip(self.groups, self._posterior_lambda(simulated)):
            u = rng.uniform(size=(post.shape[0], 1))
            j = np.minimum((np.cumsum(post, axis=1) < u).sum(axis=1), LAMBDA.size - 1)
            out[:, g.columns] = 1.0 + LAMBDA[j][:, None] * w
        return out

    def describe(self, simulated) -> list[dict]:
        """Per observation, for one prediction vector (k,): its values and effective count, the correlation
        factor, the misfit per value (mean squared standardised residual) and the posterior mean of the
        discrepancy's sd over the stated one, sqrt(E[lambda]) (rms over its values, whose weights average 1)."""
        sim = np.atleast_2d(simulated)
        s, _ = self._terms(sim)
        out = []
        for g, F, n, (post, _) in zip(self.groups, self.factor, self.n_eff, self._posterior_lambda(sim)):
            out.append({"observation": g.name, "n_values": int(g.columns.size), "n_eff": float(n),
                        "correlation_factor": float(F), "misfit_per_value": float(np.sum(s[0, g.columns]) / n),
                        "discrepancy_sd_over_sigma": math.sqrt(float(post[0] @ LAMBDA))})
        return out


def groups_of_blocks(blocks, n_eff_of, factors: dict | None = None) -> list[Group]:
    """One group per observation block of an evaluator: a scalar observation is one value, a map or gauge
    series its values with ``n_eff_of(block)`` effective ones and its learnt ``factors[name]`` (1 if none)."""
    factors = factors or {}
    return [Group(b.name, np.arange(b.start, b.stop), float(n_eff_of(b)) if b.is_vector else 1.0,
                  float(factors.get(b.name, 1.0))) for b in blocks]


def radial_correlation(field, max_lag: int = 6) -> np.ndarray:
    """(max_lag,) the empirical autocorrelation of a residual at distances 1 .. max_lag (cells, or samples
    of a series): mean(r_i r_j) / mean(r_i^2) over the pairs of values both present whose distance rounds
    to d, uncentred (a discrepancy's mean is part of it), by FFT. ``field``: (m,) a series, or (ny, nx) a
    map with NaN off its mapped cells. NaN where no pair is that far apart."""
    a = np.asarray(field, dtype=np.float64)
    a = a[None, :] if a.ndim == 1 else a
    ok = np.isfinite(a)
    r = np.where(ok, a, 0.0)
    shape = (2 * a.shape[0], 2 * a.shape[1])
    fr, fm = np.fft.rfft2(r, shape), np.fft.rfft2(ok.astype(np.float64), shape)
    R = np.fft.irfft2(fr * np.conj(fr), shape)            # sum of r_i r_(i+l) at every lag l
    N = np.round(np.fft.irfft2(fm * np.conj(fm), shape))  # pairs at that lag
    if N[0, 0] < 1 or R[0, 0] <= 0:
        return np.full(max_lag, np.nan)
    dist = np.hypot(np.fft.fftfreq(shape[0], 1.0 / shape[0])[:, None], np.fft.fftfreq(shape[1], 1.0 / shape[1])[None, :])
    out = np.full(max_lag, np.nan)
    for d in range(1, max_lag + 1):
        ring = (np.abs(dist - d) < 0.5) & (N > 0)
        if ring.any():
            out[d - 1] = (R[ring].sum() / N[ring].sum()) / (R[0, 0] / N[0, 0])
    return out


def correlation_factor(field, max_lag: int = 6) -> float:
    """F: how many values of a residual carry the information of one independent value, from an
    exponential correlation exp(-d / L) fitted to its empirical autocorrelation (``radial_correlation``;
    ln rho(d) = -d / L by least squares through the origin over the distances before the first rho <= 0.05):
    F = 2 pi L^2 on a map (L in cells), 2 L for a series (L in samples), as
    torchslide.observe_series.effective_factor has it for a stated corr_length; capped to [1, values]."""
    a = np.asarray(field, dtype=np.float64)
    m = int(np.isfinite(a).sum())
    rho = radial_correlation(a, max_lag)
    use = np.isfinite(rho) & (rho > 0.05)
    k = int(np.argmin(use)) if not use.all() else use.size
    if k == 0:
        return 1.0
    d = np.arange(1, k + 1, dtype=np.float64)
    inv_L = -float(d @ np.log(rho[:k])) / float(d @ d)
    if inv_L <= 0:
        return float(max(m, 1))
    L = 1.0 / inv_L
    F = 2.0 * math.pi * L * L if a.ndim == 2 else 2.0 * L
    return float(np.clip(F, 1.0, max(m, 1)))
