"""Priors, Gaussian likelihood (Eq. 6-7) and the log-unnormalised posterior z = g(x) (Eq. 10).

Everything is in log space end to end: the likelihood is computed as a log density (never exp then
log). Points are (n, p) tensors; log densities are (n,) tensors.

The evaluator protocol used by the active-learning loop lives here too: an evaluator maps a batch
(n, p) of parameter points to an :class:`EvaluationResult` holding z (n,), a failed mask (n,) and a
reason per failed run. Failed or non-finite runs are *flagged*, never turned into numbers.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable, Protocol, Sequence

import torch

_LOG_2PI = math.log(2.0 * math.pi)


def _as2d(x: torch.Tensor) -> torch.Tensor:
    x = torch.as_tensor(x)
    return x.unsqueeze(0) if x.dim() == 1 else x


# --------------------------------------------------------------------------------------------------
# 1-D priors: each has bounds (low, high) and log_prob on (n,) values.
# --------------------------------------------------------------------------------------------------
class Prior1D:
    """A prior on one parameter restricted to [low, high]. ``log_prob`` returns -inf outside."""

    low: float
    high: float

    def _check(self, name: str = "parameter") -> None:
        if not (math.isfinite(self.low) and math.isfinite(self.high)):
            raise ValueError(f"{name}: bounds must be finite, got low={self.low}, high={self.high}")
        if self.low >= self.high:
            raise ValueError(f"{name}: low must be < high, got low={self.low}, high={self.high}")

    def _inside(self, v: torch.Tensor) -> torch.Tensor:
        return (v >= self.low) & (v <= self.high)

    def _log_density(self, v: torch.Tensor) -> torch.Tensor:  # pragma: no cover - abstract
        raise NotImplementedError

    def log_prob(self, v: torch.Tensor) -> torch.Tensor:
        """Normalised log density on [low, high] (truncated), -inf outside. v: (n,)."""
        v = torch.as_tensor(v, dtype=torch.float64) if not torch.is_tensor(v) else v
        lp = self._log_density(v)
        return torch.where(self._inside(v), lp, torch.full_like(lp, -math.inf))


@dataclass
class Uniform(Prior1D):
    """Uniform on [low, high]: log p = -log(high - low)."""

    low: float
    high: float

    def __post_init__(self):
        self._check()

    def _log_density(self, v):
        return torch.full_like(v, -math.log(self.high - self.low))


def _log_normal_cdf_diff(a: float, b: float) -> float:
    """log(Phi(b) - Phi(a)) for standard normal Phi, stable in the tails."""
    from scipy.special import log_ndtr

    la, lb = float(log_ndtr(a)), float(log_ndtr(b))
    if lb <= la:
        return -math.inf
    return lb + math.log1p(-math.exp(la - lb))


@dataclass
class TruncatedNormal(Prior1D):
    """Normal(loc, scale) truncated to [low, high]."""

    loc: float
    scale: float
    low: float
    high: float

    def __post_init__(self):
        self._check()
        if self.scale <= 0:
            raise ValueError(f"TruncatedNormal: scale must be > 0, got {self.scale}")
        self._log_z = _log_normal_cdf_diff((self.low - self.loc) / self.scale,
                                           (self.high - self.loc) / self.scale)

    def _log_density(self, v):
        u = (v - self.loc) / self.scale
        return -0.5 * u**2 - 0.5 * _LOG_2PI - math.log(self.scale) - self._log_z


@dataclass
class LogNormal(Prior1D):
    """LogNormal(mu, sigma) (of ln v) truncated to [low, high], low > 0."""

    mu: float
    sigma: float
    low: float
    high: float

    def __post_init__(self):
        self._check()
        if self.low <= 0 or self.sigma <= 0:
            raise ValueError(f"LogNormal: need low > 0 and sigma > 0, got low={self.low}, sigma={self.sigma}")
        self._log_z = _log_normal_cdf_diff((math.log(self.low) - self.mu) / self.sigma,
                                           (math.log(self.high) - self.mu) / self.sigma)

    def _log_density(self, v):
        lv = torch.log(v.clamp_min(1e-300))
        u = (lv - self.mu) / self.sigma
        return -0.5 * u**2 - 0.5 * _LOG_2PI - math.log(self.sigma) - lv - self._log_z


@dataclass
class Gamma(Prior1D):
    """Gamma(concentration, rate) truncated to [low, high], low >= 0."""

    concentration: float
    rate: float
    low: float
    high: float

    def __post_init__(self):
        self._check()
        if self.low < 0 or self.concentration <= 0 or self.rate <= 0:
            raise ValueError("Gamma: need low >= 0, concentration > 0, rate > 0")
        from scipy.stats import gamma

        d = gamma(self.concentration, scale=1.0 / self.rate)
        mass = d.cdf(self.high) - d.cdf(self.low)
        self._log_z = math.log(mass) if mass > 0 else -math.inf

    def _log_density(self, v):
        a, b = self.concentration, self.rate
        return (a * math.log(b) - math.lgamma(a) + (a - 1) * torch.log(v.clamp_min(1e-300)) - b * v
                - self._log_z)


# --------------------------------------------------------------------------------------------------
# Joint prior over named parameters (independent components).
# --------------------------------------------------------------------------------------------------
class Prior:
    """Independent prior over named parameters, e.g. ``Prior({"mu": Uniform(0.02, 0.3), ...})``.

    Args:
        components: mapping name -> Prior1D, or name -> (low, high) for a uniform prior.

    Raises:
        ValueError: bad bounds (low >= high or non-finite), naming the parameter and values.
    """

    def __init__(self, components: dict):
        if not components:
            raise ValueError("Prior needs at least one parameter")
        self.components: dict[str, Prior1D] = {}
        for name, c in components.items():
            if isinstance(c, Prior1D):
                c._check(name)
            else:
                low, high = (float(v) for v in c)
                if not (math.isfinite(low) and math.isfinite(high)) or low >= high:
                    raise ValueError(f"parameter {name!r}: need finite low < high, got low={low}, high={high}")
                c = Uniform(low, high)
            self.components[name] = c

    @classmethod
    def uniform(cls, bounds, names: Sequence[str] | None = None) -> "Prior":
        """Uniform box prior from bounds (2, p) or a list of (low, high) pairs."""
        b = check_bounds(bounds, names)
        names = list(names) if names is not None else [f"x{i}" for i in range(b.shape[1])]
        return cls({n: (float(b[0, i]), float(b[1, i])) for i, n in enumerate(names)})

    @property
    def names(self) -> list[str]:
        return list(self.components)

    @property
    def dim(self) -> int:
        return len(self.components)

    @property
    def bounds(self) -> torch.Tensor:
        """(2, p) float64 tensor [lows; highs]."""
        return torch.tensor([[c.low for c in self.components.values()],
                             [c.high for c in self.components.values()]], dtype=torch.float64)

    def log_prob(self, x: torch.Tensor) -> torch.Tensor:
        """Sum of component log densities. x: (n, p) -> (n,); -inf outside the box."""
        x = _as2d(x)
        if x.shape[-1] != self.dim:
            raise ValueError(f"expected {self.dim} parameters {self.names}, got shape {tuple(x.shape)}")
        return sum(c.log_prob(x[:, i]) for i, c in enumerate(self.components.values()))


def check_bounds(bounds, names: Sequence[str] | None = None) -> torch.Tensor:
    """Validate bounds given as (2, p) [lows; highs] (BoTorch's convention, also for p = 2), as p pairs
    (low, high) when p != 2, or as a dict {name: (low, high)}; return (2, p) float64.

    Raises ValueError naming the parameter when low >= high or a bound is not finite.
    """
    if isinstance(bounds, dict):
        bounds = [[float(v[0]) for v in bounds.values()], [float(v[1]) for v in bounds.values()]]
    b = torch.as_tensor(bounds, dtype=torch.float64)
    if b.dim() != 2:
        raise ValueError(f"bounds must be (2, p) or (p, 2), got shape {tuple(b.shape)}")
    if b.shape[0] != 2 and b.shape[1] == 2:
        b = b.T
    elif b.shape[0] != 2:
        raise ValueError(f"bounds must be (2, p) or (p, 2), got shape {tuple(b.shape)}")
    p = b.shape[1]
    if names is not None and len(names) != p:
        raise ValueError(f"{len(names)} names for {p} parameters")
    for i in range(p):
        lo, hi = float(b[0, i]), float(b[1, i])
        n = names[i] if names is not None else f"x{i}"
        if not (math.isfinite(lo) and math.isfinite(hi)):
            raise ValueError(f"parameter {n!r}: bounds must be finite, got low={lo}, high={hi}")
        if lo >= hi:
            hint = ""
            if b.shape == (2, 2) and bool((b.T[0] < b.T[1]).all()):
                hint = (" (a 2 x 2 bounds array is read as [lows; highs]; for (low, high) pairs pass a dict "
                        "{name: (low, high)} or the transpose)")
            raise ValueError(f"parameter {n!r}: low must be < high, got low={lo}, high={hi}{hint}")
    return b.contiguous()


# --------------------------------------------------------------------------------------------------
# Likelihood (Eq. 6-7)
# --------------------------------------------------------------------------------------------------
class GaussianLikelihood:
    """ln L(x|d) for d = y(x) + eps, eps ~ N(0, Sigma) (Eq. 6), Sigma diagonal (Eq. 7) or full.

    Args:
        observed: (k,) observed data d.
        sigma: (k,) residual standard deviations (diagonal Sigma, Eq. 7), or None.
        covariance: (k, k) full covariance, or None. Exactly one of sigma/covariance.

    ``log_likelihood(simulated)`` takes simulated outputs (n, k) and returns (n,) log densities,
    computed directly as -0.5 r^T Sigma^-1 r - 0.5 log det(2 pi Sigma) (Cholesky for full Sigma).
    """

    def __init__(self, observed, sigma=None, covariance=None):
        self.observed = torch.as_tensor(observed, dtype=torch.float64).reshape(-1)
        k = self.observed.numel()
        if (sigma is None) == (covariance is None):
            raise ValueError("give exactly one of sigma (diagonal) or covariance (full)")
        if sigma is not None:
            s = torch.as_tensor(sigma, dtype=torch.float64).reshape(-1).expand(k).clone()
            if not torch.all(s > 0):
                raise ValueError(f"sigma must be > 0, got {s.tolist()}")
            self.sigma, self.chol = s, None
            self._log_norm = -0.5 * k * _LOG_2PI - torch.log(s).sum()
        else:
            c = torch.as_tensor(covariance, dtype=torch.float64)
            if c.shape != (k, k):
                raise ValueError(f"covariance must be ({k}, {k}), got {tuple(c.shape)}")
            L, info = torch.linalg.cholesky_ex(c)
            if info != 0:
                raise ValueError("covariance is not positive definite")
            self.sigma, self.chol = None, L
            self._log_norm = -0.5 * k * _LOG_2PI - torch.log(torch.diagonal(L)).sum()

    @property
    def log_norm(self) -> float:
        """-0.5 log det(2 pi Sigma): ln L = log_norm - |whiten(y)|^2 / 2."""
        return float(self._log_norm)

    def whiten(self, simulated: torch.Tensor) -> torch.Tensor:
        """simulated: (n, k) model outputs -> (n, k) whitened residuals L^-1 (y - d), Sigma = L L^T."""
        y = _as2d(torch.as_tensor(simulated, dtype=torch.float64))
        r = y - self.observed.to(y)
        if self.chol is None:
            return r / self.sigma.to(y)
        return torch.linalg.solve_triangular(self.chol.to(y), r.T, upper=False).T

    def residuals(self, simulated: torch.Tensor) -> torch.Tensor:
        """The least-squares form of ln L = log_norm - |r|^2 / 2: the whitened residuals (n, k)."""
        return self.whiten(simulated)

    def log_likelihood(self, simulated: torch.Tensor) -> torch.Tensor:
        """simulated: (n, k) model outputs -> (n,) ln L (Eq. 6). Non-finite outputs give nan."""
        w = self.whiten(simulated)
        return self._log_norm.to(w) - 0.5 * (w**2).sum(-1)

    __call__ = log_likelihood


def log_posterior(x: torch.Tensor, loglik: Callable[[torch.Tensor], torch.Tensor], prior: Prior) -> torch.Tensor:
    """z = g(x) = ln L(x|d) + ln pi(x) (Eq. 10). x: (n, p) -> (n,)."""
    x = _as2d(x)
    return loglik(x) + prior.log_prob(x)


# --------------------------------------------------------------------------------------------------
# Evaluator protocol
# --------------------------------------------------------------------------------------------------
@dataclass
class EvaluationResult:
    """What an evaluator returns for a batch of n points.

    Attributes:
        z: (n,) float64 log-unnormalised posterior values; entries of failed runs are nan.
        failed: (n,) bool, True where the run failed or z was not finite.
        reasons: list of n strings ('' for successful runs).
    """

    z: torch.Tensor
    failed: torch.Tensor
    reasons: list = field(default_factory=list)

    def __post_init__(self):
        self.z = torch.as_tensor(self.z, dtype=torch.float64).reshape(-1)
        n = self.z.numel()
        self.failed = torch.as_tensor(self.failed, dtype=torch.bool).reshape(-1)
        if self.failed.numel() != n:
            raise ValueError(f"failed mask has {self.failed.numel()} entries for {n} values")
        if not self.reasons:
            self.reasons = [""] * n
        self.reasons = list(self.reasons)
        # Flag anything non-finite that was not already flagged; never keep a silent number.
        nonfinite = ~torch.isfinite(self.z) & ~self.failed
        for i in torch.nonzero(nonfinite).flatten().tolist():
            self.reasons[i] = f"non-finite z ({float(self.z[i])})"
        self.failed = self.failed | nonfinite
        self.z = torch.where(self.failed, torch.full_like(self.z, math.nan), self.z)


class Evaluator(Protocol):
    """Maps parameter points (n, p) (in parameter units) to an EvaluationResult."""

    def __call__(self, x: torch.Tensor) -> EvaluationResult: ...


class FunctionEvaluator:
    """Wrap a user log-posterior ``f(x: (n, p)) -> (n,)`` or ``-> (z, failed_mask)`` as an Evaluator.

    Exceptions raised by ``f`` are *not* swallowed (an interrupted evaluation must stop the loop so
    that it can be resumed); per-point failures are reported through the failed mask or non-finite z.
    """

    def __init__(self, fn: Callable):
        self.fn = fn

    def __call__(self, x: torch.Tensor) -> EvaluationResult:
        out = self.fn(x)
        if isinstance(out, EvaluationResult):
            return out
        if isinstance(out, tuple):
            if len(out) == 3:
                z, failed, reasons = out
            else:
                z, failed = out
                reasons = None
            failed = torch.as_tensor(failed, dtype=torch.bool).reshape(-1)
            if reasons is None:
                reasons = ["failed run (reported by evaluator)" if f else "" for f in failed.tolist()]
            return EvaluationResult(z=torch.as_tensor(z, dtype=torch.float64), failed=failed, reasons=list(reasons))
        z = torch.as_tensor(out, dtype=torch.float64).reshape(-1)
        return EvaluationResult(z=z, failed=torch.zeros(z.numel(), dtype=torch.bool))
