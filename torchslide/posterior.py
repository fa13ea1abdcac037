"""Posterior estimation from a (emulated) log-unnormalised posterior: grid approximation (Eq. 8/15),
total-variation distance (Eq. 17), summaries (mean, sd, MAP, marginals, 90 % HDR), log evidence,
and MCMC for p > 2 (adaptive random-walk Metropolis, several chains, R-hat and ESS).

Grid convention: the box is split into G cells per axis and the grid points are the cell *centres*
``low + (i + 0.5) h``, h = (high - low) / G. A grid density ``density`` is normalised such that
``density.sum() * cell_volume == 1`` (midpoint quadrature of Eq. 15).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable, Sequence

import numpy as np
import torch


# --------------------------------------------------------------------------------------------------
# Grid
# --------------------------------------------------------------------------------------------------
def grid_axes(bounds, grid_size: int | Sequence[int] = 100) -> list[np.ndarray]:
    """Cell-centre axes of a regular grid over the box. bounds: (2, p). Returns p arrays (G_i,)."""
    b = np.asarray(torch.as_tensor(bounds, dtype=torch.float64))
    p = b.shape[1]
    sizes = [grid_size] * p if np.isscalar(grid_size) else list(grid_size)
    return [b[0, i] + (np.arange(n) + 0.5) * (b[1, i] - b[0, i]) / n for i, n in enumerate(sizes)]


def grid_points(axes: Sequence[np.ndarray]) -> torch.Tensor:
    """All grid points, (prod G_i, p) float64, 'ij' order (reshape to (G_1, ..., G_p))."""
    mesh = np.meshgrid(*axes, indexing="ij")
    return torch.from_numpy(np.stack([m.reshape(-1) for m in mesh], axis=-1)).to(torch.float64)


def cell_volume(axes: Sequence[np.ndarray]) -> float:
    return float(np.prod([a[1] - a[0] if len(a) > 1 else 1.0 for a in axes]))


def log_grid_values(fn: Callable[[torch.Tensor], torch.Tensor], axes, batch: int = 20000) -> np.ndarray:
    """Evaluate a log density fn((n, p)) -> (n,) on the grid in batches; returns array (G_1, ..., G_p)."""
    pts = grid_points(axes)
    out = [torch.as_tensor(fn(pts[i:i + batch])).detach().reshape(-1) for i in range(0, len(pts), batch)]
    return torch.cat(out).double().numpy().reshape([len(a) for a in axes])


def normalise_log_grid(log_values: np.ndarray, axes) -> tuple[np.ndarray, float]:
    """Grid posterior (Eq. 8/15) from log values, with logsumexp normalisation.

    Returns (density, log_evidence): density such that sum * cell_volume = 1 and
    log_evidence = log of the integral of exp(log_values) over the box (midpoint quadrature).
    Non-finite log values count as zero density.
    """
    lv = np.where(np.isfinite(log_values), log_values, -np.inf)
    m = np.max(lv)
    if not np.isfinite(m):
        raise ValueError("all log values are -inf / non-finite: no posterior mass on the grid")
    dv = cell_volume(axes)
    lse = m + math.log(np.exp(lv - m).sum())
    log_z = lse + math.log(dv)
    return np.exp(lv - log_z), float(log_z)


def tv_distance(p: np.ndarray, q: np.ndarray, cell_vol: float) -> float:
    """TV(p, q) = 0.5 * integral |p - q| dx (Eq. 17) for two grid densities on the same grid."""
    return 0.5 * float(np.abs(np.asarray(p) - np.asarray(q)).sum()) * cell_vol


# --------------------------------------------------------------------------------------------------
# Summaries
# --------------------------------------------------------------------------------------------------
def hdr_mask(density: np.ndarray, level: float = 0.9) -> np.ndarray:
    """Highest-density region: smallest set of cells holding `level` of the mass. Bool, grid shape."""
    flat = density.reshape(-1)
    order = np.argsort(flat)[::-1]
    cum = np.cumsum(flat[order]) / flat.sum()
    k = int(np.searchsorted(cum, level) + 1)
    mask = np.zeros(flat.shape, dtype=bool)
    mask[order[:k]] = True
    return mask.reshape(density.shape)


@dataclass
class PosteriorSummary:
    """Per-parameter summaries. Lists are indexed like `names`.

    hdr90: per parameter (low, high) = the extent of the 90 % highest-density region along that axis
    (grid), or the equal-tailed 90 % interval (MCMC samples).
    """

    names: list
    mean: list
    sd: list
    map: list
    hdr90: list
    log_evidence: float | None = None
    extra: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        return {
            "names": list(self.names),
            "mean": dict(zip(self.names, map(float, self.mean))),
            "sd": dict(zip(self.names, map(float, self.sd))),
            "map": dict(zip(self.names, map(float, self.map))),
            "hdr90": {n: [float(lo), float(hi)] for n, (lo, hi) in zip(self.names, self.hdr90)},
            "log_evidence": None if self.log_evidence is None else float(self.log_evidence),
            **self.extra,
        }


def marginals(density: np.ndarray, axes) -> list[np.ndarray]:
    """1-D marginal densities (each integrates to 1 along its axis)."""
    p = density.ndim
    out = []
    for i in range(p):
        other = tuple(j for j in range(p) if j != i)
        dv_other = float(np.prod([axes[j][1] - axes[j][0] for j in other])) if other else 1.0
        out.append(density.sum(axis=other) * dv_other if other else density.copy())
    return out


def summarise_grid(density: np.ndarray, axes, names: Sequence[str] | None = None,
                   log_evidence: float | None = None, level: float = 0.9) -> PosteriorSummary:
    """Mean, sd, MAP, 90 % HDR extent per parameter from a normalised grid density."""
    names = list(names) if names is not None else [f"x{i}" for i in range(density.ndim)]
    margs = marginals(density, axes)
    mean, sd = [], []
    for a, m in zip(axes, margs):
        w = m * (a[1] - a[0])
        mu = float((w * a).sum())
        mean.append(mu)
        sd.append(float(math.sqrt(max((w * (a - mu) ** 2).sum(), 0.0))))
    idx = np.unravel_index(int(np.argmax(density)), density.shape)
    map_ = [float(axes[i][j]) for i, j in enumerate(idx)]
    mask = hdr_mask(density, level)
    hdr = []
    for i, a in enumerate(axes):
        other = tuple(j for j in range(density.ndim) if j != i)
        on = mask.any(axis=other) if other else mask
        sel = a[on]
        h = (a[1] - a[0]) / 2
        hdr.append((float(sel.min() - h), float(sel.max() + h)))
    return PosteriorSummary(names, mean, sd, map_, hdr, log_evidence)


@dataclass
class GridPosterior:
    """A normalised grid posterior. density: (G_1, ..., G_p), sum * cell_volume = 1."""

    axes: list
    density: np.ndarray
    log_evidence: float
    log_values: np.ndarray

    @property
    def cell_volume(self) -> float:
        return cell_volume(self.axes)

    def tv(self, other: "GridPosterior") -> float:
        return tv_distance(self.density, other.density, self.cell_volume)

    def summary(self, names=None) -> PosteriorSummary:
        return summarise_grid(self.density, self.axes, names, self.log_evidence)

    def hdr_mask(self, level: float = 0.9) -> np.ndarray:
        return hdr_mask(self.density, level)


def grid_posterior(log_fn: Callable[[torch.Tensor], torch.Tensor], bounds, grid_size=100,
                   batch: int = 20000) -> GridPosterior:
    """Grid approximation of exp(log_fn) / integral (Eq. 8 / Eq. 15) over the box."""
    axes = grid_axes(bounds, grid_size)
    lv = log_grid_values(log_fn, axes, batch)
    dens, lz = normalise_log_grid(lv, axes)
    return GridPosterior(axes, dens, lz, lv)


# --------------------------------------------------------------------------------------------------
# MCMC (p > 2): adaptive random-walk Metropolis, vectorised over chains.
# --------------------------------------------------------------------------------------------------
def split_rhat(chains: np.ndarray) -> np.ndarray:
    """Split R-hat (Gelman et al. 2013) per parameter. chains: (C, N, p) -> (p,)."""
    c, n, p = chains.shape
    h = n // 2
    s = np.concatenate([chains[:, :h], chains[:, h:2 * h]], axis=0)  # (2C, h, p)
    w = s.var(axis=1, ddof=1).mean(axis=0)
    b = h * s.mean(axis=1).var(axis=0, ddof=1)
    var = (h - 1) / h * w + b / h
    return np.sqrt(var / np.maximum(w, 1e-300))


def ess(chains: np.ndarray) -> np.ndarray:
    """Effective sample size per parameter (multi-chain, Geyer initial positive sequence). (C, N, p) -> (p,)."""
    c, n, p = chains.shape
    out = np.empty(p)
    for j in range(p):
        x = chains[:, :, j] - chains[:, :, j].mean(axis=1, keepdims=True)
        f = np.fft.rfft(x, n=2 * n, axis=1)
        ac = np.fft.irfft(f * np.conj(f), axis=1)[:, :n] / n  # autocovariance per chain
        w = ac[:, 0].mean()
        mean_c = chains[:, :, j].mean(axis=1)
        var_plus = w * (n - 1) / n + (mean_c.var(ddof=1) if c > 1 else 0.0)
        rho = 1.0 - (w - ac.mean(axis=0)) / max(var_plus, 1e-300)
        rho[0] = 1.0
        s, t = 0.0, 0
        while t + 1 < n:
            pair = rho[t] + rho[t + 1]
            if pair < 0:
                break
            s += pair
            t += 2
        tau = max(-1.0 + 2.0 * s, 1e-12)
        out[j] = c * n / tau
    return out


@dataclass
class MCMCResult:
    samples: np.ndarray  # (C * N, p) post burn-in, thinned
    chains: np.ndarray  # (C, N, p)
    log_values: np.ndarray  # (C, N)
    acceptance: float
    rhat: np.ndarray
    ess: np.ndarray

    def summary(self, names=None, log_evidence=None) -> PosteriorSummary:
        s = self.samples
        names = list(names) if names is not None else [f"x{i}" for i in range(s.shape[1])]
        i = np.unravel_index(int(np.argmax(self.log_values)), self.log_values.shape)
        lo, hi = np.quantile(s, 0.05, axis=0), np.quantile(s, 0.95, axis=0)
        return PosteriorSummary(names, s.mean(0).tolist(), s.std(0, ddof=1).tolist(),
                                self.chains[i].tolist(), list(zip(lo.tolist(), hi.tolist())), log_evidence,
                                extra={"rhat": self.rhat.tolist(), "ess": self.ess.tolist(),
                                       "acceptance": float(self.acceptance)})


def adaptive_metropolis(log_fn: Callable[[torch.Tensor], torch.Tensor], bounds, n_chains: int = 8,
                        n_steps: int = 4000, burn_in: int | None = None, seed: int = 0,
                        x0: np.ndarray | None = None, thin: int = 1) -> MCMCResult:
    """Adaptive random-walk Metropolis (Haario et al. 2001), all chains in one batched log_fn call per step.

    The proposal covariance is (2.38^2 / p) * Cov(past samples of all chains) + eps I, adapted during
    burn-in only (so the kept samples come from a fixed Markov kernel). Points outside the box are
    rejected (the prior is zero there).
    """
    b = torch.as_tensor(bounds, dtype=torch.float64).numpy()
    p = b.shape[1]
    rng = np.random.default_rng(seed)
    lo, hi = b[0], b[1]
    width = hi - lo
    burn_in = n_steps // 2 if burn_in is None else burn_in

    def f(x):
        return torch.as_tensor(log_fn(torch.from_numpy(x))).detach().double().numpy().reshape(-1)

    if x0 is None:
        cand = lo + rng.random((max(64 * n_chains, 512), p)) * width
        lv = f(cand)
        x = cand[np.argsort(-np.nan_to_num(lv, nan=-np.inf))[:n_chains]]
    else:
        x = np.asarray(x0, dtype=np.float64).reshape(n_chains, p)
    lx = f(x)
    cov = np.diag((0.05 * width) ** 2)
    scale = 2.38**2 / p
    hist, kept, kept_lv = [], [], []
    acc_n, acc_tot = 0, 0
    for t in range(n_steps):
        L = np.linalg.cholesky(cov + 1e-12 * np.diag(width**2))
        prop = x + rng.standard_normal((n_chains, p)) @ L.T
        inside = np.all((prop >= lo) & (prop <= hi), axis=1)
        lp = np.full(n_chains, -np.inf)
        if inside.any():
            lp[inside] = f(prop[inside])
        lp = np.nan_to_num(lp, nan=-np.inf)
        accept = np.log(rng.random(n_chains)) < lp - lx
        x = np.where(accept[:, None], prop, x)
        lx = np.where(accept, lp, lx)
        if t < burn_in:
            hist.append(x.copy())
            if t >= 100 and t % 50 == 0:
                h = np.concatenate(hist[len(hist) // 2:], axis=0)
                cov = scale * np.cov(h.T).reshape(p, p) + 1e-10 * np.diag(width**2)
        else:
            acc_n += int(accept.sum())
            acc_tot += n_chains
            if (t - burn_in) % thin == 0:
                kept.append(x.copy())
                kept_lv.append(lx.copy())
    chains = np.stack(kept, axis=1)  # (C, N, p)
    lvs = np.stack(kept_lv, axis=1)
    return MCMCResult(chains.reshape(-1, p), chains, lvs, acc_n / max(acc_tot, 1), split_rhat(chains), ess(chains))


def log_evidence_importance(log_fn: Callable[[torch.Tensor], torch.Tensor], bounds, samples: np.ndarray,
                            n: int = 20000, seed: int = 0, defensive: float = 0.1) -> float:
    """log integral of exp(log_fn) over the box by importance sampling (for p > 2).

    Proposal: (1 - defensive) N(mean, 1.5^2 Cov) of posterior samples + defensive * Uniform(box).
    """
    b = torch.as_tensor(bounds, dtype=torch.float64).numpy()
    lo, hi = b[0], b[1]
    p = b.shape[1]
    rng = np.random.default_rng(seed)
    mu = samples.mean(0)
    cov = 2.25 * np.cov(samples.T).reshape(p, p) + 1e-12 * np.diag((hi - lo) ** 2)
    L = np.linalg.cholesky(cov)
    n_u = int(round(defensive * n))
    xg = mu + rng.standard_normal((n - n_u, p)) @ L.T
    xu = lo + rng.random((n_u, p)) * (hi - lo)
    x = np.concatenate([xg, xu])
    inside = np.all((x >= lo) & (x <= hi), axis=1)
    d = np.linalg.solve(L, (x - mu).T)
    lg = -0.5 * (d**2).sum(0) - 0.5 * p * math.log(2 * math.pi) - np.log(np.diag(L)).sum()
    lu = -np.log(hi - lo).sum()
    lq = np.logaddexp(math.log(1 - defensive) + lg, math.log(defensive) + lu)
    lv = np.full(n, -np.inf)
    xin = x[inside]
    vals = []
    for i in range(0, len(xin), 20000):
        vals.append(torch.as_tensor(log_fn(torch.from_numpy(xin[i:i + 20000]))).detach().double().numpy().reshape(-1))
    lv[inside] = np.concatenate(vals) if vals else []
    w = np.nan_to_num(lv, nan=-np.inf) - lq
    m = w.max()
    return float(m + math.log(np.exp(w - m).mean()))
