"""Where do model and data disagree? Standardised residuals, predictive p-values, map clusters, gauge windows.

Definitions (d data, y posterior-predictive draws, sigma the per-value measurement sd, f the
correlation factor of the block, see torchslide.observe_series):

* element standardised residual  z_i = (d_i - E y_i) / sqrt(Var y_i + sigma_i^2)
* scalar observable: its z, and the two-sided predictive p-value 2 min(F, 1 - F), F the fraction of
  replicated data y + sigma eps (eps ~ N(0, 1)) below d.
* vector block: Z_block = (sum z_i^2 - m) / sqrt(2 m f) (a chi-square turned to a normal score; the
  factor f widens the spread for correlated errors).
* vector block, with the likelihood's own covariance (``block_fit``): chi2_b = r^T (Sigma_bb + C_bb)^-1 r,
  r = d_b - E y_b, Sigma the likelihood's full covariance (measurement errors with their correlation,
  plus the grid's approximation error when the evaluator has one), C the draws' covariance; under the
  model chi2_b ~ chi-square(m_b), reported as its upper-tail p-value and the normal score
  Z_fit = Phi^-1(1 - p) (Z_fit << 0: the data fit better than the covariance says, i.e. it is too
  wide). Unlike the per-value z (diagonal variances), it does not count the grid's correlated error
  as many independent mismatches. Reported per block; not a located item.
* map clusters: Getis-Ord Gi* of the z map with a square window of radius r cells (r >= the error
  correlation length), permutation p-values (z values shuffled over the mapped cells, n_perm
  permutations, the |Gi*| of all cells and permutations pooled into one null distribution), Benjamini-Hochberg FDR at level q; significant cells of one sign that touch form a
  cluster, reported as a bounding box [xmin, ymin, xmax, ymax] in map coordinates with the cluster
  score sum z / sqrt(n_cells f).
* gauge series: first the arrival-time shift tau (s) that best aligns E y with d (grid search over
  lags, the series shifted by linear interpolation); then time windows where the running mean of the
  aligned z over w samples, times sqrt(w / f), exceeds z_threshold.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage, special, stats

from ..observe_series import SeriesObservation, interp_series


def standardised(evaluator, mean: np.ndarray, var: np.ndarray) -> np.ndarray:
    return (evaluator.data - mean) / np.sqrt(var + evaluator.sigma_raw**2)


def predictive_pvalues(evaluator, draws: np.ndarray, seed: int = 0) -> np.ndarray:
    """(k,) two-sided predictive p-values of every value (draws + measurement noise)."""
    rng = np.random.default_rng(seed)
    rep = draws + rng.standard_normal(draws.shape) * evaluator.sigma_raw
    F = ((rep < evaluator.data).sum(0) + 0.5 * (rep == evaluator.data).sum(0)) / rep.shape[0]
    n = rep.shape[0]
    F = np.clip(F, 0.5 / n, 1 - 0.5 / n)
    return 2 * np.minimum(F, 1 - F)


def benjamini_hochberg(p: np.ndarray, q: float = 0.05) -> np.ndarray:
    """Bool mask of discoveries at FDR level q."""
    p = np.asarray(p)
    n = p.size
    if n == 0:
        return np.zeros(0, bool)
    order = np.argsort(p)
    thr = q * np.arange(1, n + 1) / n
    ok = p[order] <= thr
    out = np.zeros(n, bool)
    if ok.any():
        kmax = np.nonzero(ok)[0].max()
        out[order[:kmax + 1]] = True
    return out


def getis_ord(zmap: np.ndarray, mask: np.ndarray, radius: int = 1) -> np.ndarray:
    """Gi* statistic per mapped cell (binary square window of radius ``radius`` incl. the cell itself)."""
    x = np.where(mask, zmap, 0.0)
    n = mask.sum()
    ker = np.ones((2 * radius + 1, 2 * radius + 1))
    S1 = ndimage.convolve(x, ker, mode="constant")
    W = ndimage.convolve(mask.astype(float), ker, mode="constant")
    xbar = x[mask].mean()
    s = math.sqrt(max((x[mask] ** 2).mean() - xbar**2, 1e-300))
    den = s * np.sqrt(np.maximum(n * W - W**2, 1e-12) / max(n - 1, 1))
    g = (S1 - xbar * W) / den
    return np.where(mask, g, 0.0)


@dataclass
class Cluster:
    bbox: list
    n_cells: int
    score: float
    sign: int
    mean_z: float
    cells: list = field(default_factory=list, repr=False)  # flat grid indices (not in the JSON)

    def to_json(self) -> dict:
        return {k: v for k, v in self.__dict__.items() if k != "cells"}


def map_clusters(zmap: np.ndarray, mask: np.ndarray, dem, radius: int = 1, n_perm: int = 199, q: float = 0.05,
                 f: float = 1.0, min_cells: int = 2, seed: int = 0) -> tuple[list[Cluster], np.ndarray]:
    """Gi* hot/cold spots with permutation p-values and BH FDR -> clusters (see module doc), p-value map."""
    rng = np.random.default_rng(seed)
    g = getis_ord(zmap, mask, radius)
    vals = zmap[mask]
    gm = np.abs(g[mask])
    perm = np.zeros_like(zmap)
    pooled = []
    for _ in range(n_perm):
        perm[mask] = rng.permutation(vals)
        pooled.append(np.abs(getis_ord(perm, mask, radius)[mask]))
    pooled = np.sort(np.concatenate(pooled)) if pooled else np.zeros(0)
    # pooled permutation null (all cells, all permutations): resolution 1 / (n_perm * n_cells)
    exceed = pooled.size - np.searchsorted(pooled, gm, side="left")
    p = (1 + exceed) / (pooled.size + 1)
    sig = np.zeros(mask.shape, bool)
    sig[mask] = benjamini_hochberg(p, q)
    pmap = np.full(mask.shape, np.nan)
    pmap[mask] = p
    out = []
    cs = dem.cellsize
    for sign in (1, -1):
        lab, n = ndimage.label(sig & (np.sign(g) == sign))
        for c in range(1, n + 1):
            cells = lab == c
            nc = int(cells.sum())
            if nc < min_cells:
                continue
            ii, jj = np.nonzero(cells)
            bbox = [dem.xll + jj.min() * cs, dem.yll + ii.min() * cs, dem.xll + (jj.max() + 1) * cs,
                    dem.yll + (ii.max() + 1) * cs]
            zc = zmap[cells]
            score = float(zc.sum() / math.sqrt(nc * max(f, 1.0)))
            out.append(Cluster([float(b) for b in bbox], nc, score, sign, float(zc.mean()),
                               np.flatnonzero(cells.ravel()).tolist()))
    out.sort(key=lambda c: -abs(c.score))
    return out, pmap


def arrival_shift(t: np.ndarray, d: np.ndarray, y: np.ndarray, max_shift: float | None = None) -> float:
    """Shift tau (s) minimising sum (d(t) - y(t - tau))^2 over a grid of lags (y sampled at t)."""
    t = np.asarray(t, float)
    dt = float(np.median(np.diff(t)))
    max_shift = max_shift if max_shift is not None else 0.25 * (t[-1] - t[0])
    lags = np.arange(-max_shift, max_shift + 1e-9, dt / 2)
    best, tau = np.inf, 0.0
    for L in lags:
        ys = np.interp(t - L, t, y)
        e = float(np.sum((d - ys) ** 2))
        if e < best - 1e-12:
            best, tau = e, float(L)
    return tau


def aligned_running_score(t, d, mean, var, sigma, w: int, f: float):
    """Gauge-series statistic of the localisation: the arrival shift tau aligning the predictive mean
    with the data, the aligned standardised residuals za, and their running mean over ``w`` samples
    times sqrt(w / f) (the window score). Returns (tau, za, run)."""
    t = np.asarray(t, float)
    tau = arrival_shift(t, d, mean)
    ys = np.interp(t - tau, t, mean)
    vs = np.interp(t - tau, t, var)
    za = (d - ys) / np.sqrt(vs + np.asarray(sigma, float) ** 2)
    run = np.convolve(za, np.ones(w) / w, mode="same") * math.sqrt(w / f)
    return tau, za, run


@dataclass
class Localisation:
    """Per-value z, per-block summaries, and the list of located mismatches."""

    z: np.ndarray
    pvalues: np.ndarray
    blocks: dict = field(default_factory=dict)
    located: list = field(default_factory=list)
    maps: dict = field(default_factory=dict)

    @property
    def n_located(self) -> int:
        return len(self.located)

    def public(self) -> list:
        """``located`` without the private index keys (for JSON)."""
        return [{k: v for k, v in l.items() if not k.startswith("_")} for l in self.located]

    def max_abs(self) -> float:
        return max([abs(l["standardised_residual"]) for l in self.located], default=0.0)


def likelihood_covariance(evaluator) -> np.ndarray:
    """(k, k) covariance of the evaluator's Gaussian likelihood (raw units): L L^T of its Cholesky factor,
    else diag(sigma^2) of the evaluator's effective sigmas (an evaluator without a full covariance)."""
    lik = getattr(evaluator, "likelihood", None)
    if getattr(lik, "chol", None) is not None:
        L = lik.chol.detach().cpu().numpy()
        return L @ L.T
    return np.diag(np.asarray(evaluator.sigma, float) ** 2)


def chi2_score(chi2: float, m: int) -> tuple[float, float]:
    """(Z, p) of a chi-square statistic with m degrees of freedom: p its upper-tail probability and
    Z = Phi^-1(F(chi2)) its normal score (0 at the median, < 0 below), from the log of whichever tail is
    accurate; beyond scipy's range of log sf, the Wilson-Hilferty approximation."""
    logp = float(stats.chi2.logsf(chi2, m))
    z = -special.ndtri_exp(logp) if logp < math.log(0.5) else special.ndtri_exp(float(stats.chi2.logcdf(chi2, m)))
    if not math.isfinite(z):
        z = ((chi2 / m) ** (1 / 3) - (1 - 2 / (9 * m))) / math.sqrt(2 / (9 * m))
    return float(z), float(math.exp(logp))


def block_fit(resid: np.ndarray, cov: np.ndarray, draws: np.ndarray | None = None) -> dict:
    """Whitened fit of one block: resid (m,) = d_b - E y_b, cov (m, m) the likelihood's covariance of
    the block, draws (M, m) the posterior-predictive draws (their covariance is added; None: not).
    Returns {chi2, m, p_value, Z_fit}: chi2 = r^T (cov + C)^-1 r against chi-square(m), (Z_fit, p_value)
    = chi2_score(chi2, m) (Z_fit < 0: a fit better than the covariance expects)."""
    r = np.asarray(resid, float)
    m = r.size
    c = np.asarray(cov, float).reshape(m, m)
    if draws is not None and len(draws) > 1:
        c = c + np.cov(np.asarray(draws, float).reshape(len(draws), m), rowvar=False).reshape(m, m)
    w = np.linalg.solve(np.linalg.cholesky(c), r)
    chi2 = float(w @ w)
    z, p = chi2_score(chi2, m)
    return {"chi2": chi2, "m": int(m), "p_value": p, "Z_fit": z}


def localise(evaluator, draws: np.ndarray, z_threshold: float = 3.0, block_threshold: float = 3.0,
             q: float = 0.05, n_perm: int = 199, seed: int = 0) -> Localisation:
    """Locate the mismatch of the posterior-predictive draws (M, k) with the evaluator's data."""
    mean = draws.mean(0)
    var = draws.var(0, ddof=1) if len(draws) > 1 else np.zeros_like(mean)
    z = standardised(evaluator, mean, var)
    pv = predictive_pvalues(evaluator, draws, seed)
    L = Localisation(z=z, pvalues=pv)
    dem = evaluator.dem
    cov = likelihood_covariance(evaluator)
    for b in evaluator.blocks:
        zb = z[b.slice]
        o = b.obs
        if not b.is_vector:
            info = {"kind": b.kind, "z": float(zb[0]), "p_value": float(pv[b.start]), "data": float(evaluator.data[b.start]),
                    "pred_mean": float(mean[b.start]), "pred_sd": float(math.sqrt(var[b.start]))}
            L.blocks[b.name] = info
            if abs(zb[0]) >= z_threshold:
                L.located.append({"what": f"{b.kind} {b.name}", "where": b.name, "standardised_residual": float(zb[0]),
                                  "p_value": float(pv[b.start]), "_idx": [b.start], "_f": 1.0, "_stat": "sum"})
            continue
        m, f = o.m, o.factor()
        Zb = float((np.sum(zb**2) - m) / math.sqrt(2 * m * f))
        info = {"kind": b.kind, "Z_block": Zb, "rms_z": float(np.sqrt(np.mean(zb**2))), "m": m, "n_eff": o.n_eff}
        fit = block_fit(evaluator.data[b.slice] - mean[b.slice], cov[b.slice, b.slice],
                        draws[:, b.slice] if len(draws) > 1 else None)
        info.update({"chi2_fit": fit["chi2"], "p_fit": fit["p_value"], "Z_fit": fit["Z_fit"]})
        if o.is_map:
            zmap = o.to_grid(zb)
            mask = np.isfinite(zmap)
            radius = max(1, int(math.ceil((o.corr_length or 0.0) / dem.cellsize)))
            clusters, pmap = map_clusters(np.nan_to_num(zmap), mask, dem, radius=radius, n_perm=n_perm, q=q, f=f,
                                          seed=seed)
            clusters = [c for c in clusters if abs(c.score) >= z_threshold]
            info["clusters"] = [c.to_json() for c in clusters]
            pos = np.full(int(np.prod(o.grid_shape)), -1)
            pos[np.asarray(o.cell_index)] = np.arange(m)
            L.maps[b.name] = {"z": zmap, "p": pmap, "data": o.to_grid(evaluator.data[b.slice]),
                              "pred": o.to_grid(mean[b.slice])}
            for c in clusters:
                L.located.append({"what": f"{b.kind} {b.name} {'excess' if c.sign > 0 else 'deficit'} cluster",
                                  "where": c.bbox, "standardised_residual": c.score, "n_cells": c.n_cells,
                                  "_idx": (b.start + pos[np.asarray(c.cells)]).tolist(), "_f": f, "_stat": "sum"})
        else:
            t = np.asarray(o.times, float)
            d = evaluator.data[b.slice]
            dt = float(np.median(np.diff(t)))
            w = max(3, int(round(2 * (o.corr_length or 0.0) / dt)) + 1)
            tau, za, run = aligned_running_score(t, d, mean[b.slice], var[b.slice], o.sigma_vector(), w, f)
            sig = np.abs(run) >= z_threshold
            windows = []
            lab, n = ndimage.label(sig)
            for c in range(1, n + 1):
                idx = np.nonzero(lab == c)[0]
                i0, i1 = max(idx[0] - w // 2, 0), min(idx[-1] + w // 2, len(t) - 1)
                k = idx[np.argmax(np.abs(run[idx]))]
                windows.append({"t0": float(t[i0]), "t1": float(t[i1]), "score": float(run[k])})
            windows.sort(key=lambda c: -abs(c["score"]))
            # the shift itself: misfit reduction from aligning, as a score
            gain = float(np.sum(zb**2) - np.sum(za**2))
            shift_score = math.copysign(math.sqrt(max(gain, 0.0) / f), tau) if tau else 0.0
            info.update({"arrival_shift_s": tau, "shift_score": shift_score, "windows": windows,
                         "Z_block_aligned": float((np.sum(za**2) - m) / math.sqrt(2 * m * f))})
            # "recorded": what the user gave; "offset": the grid's mean error the likelihood adds to the
            # prediction (data = recorded - offset; zero without a model error)
            rec = np.asarray(getattr(evaluator, "data_recorded", evaluator.data), float)[b.slice]
            L.maps[b.name] = {"t": t, "data": d, "recorded": rec, "offset": rec - d, "pred": mean[b.slice],
                              "pred_sd": np.sqrt(var[b.slice]), "z": za}
            if abs(shift_score) >= z_threshold:
                L.located.append({"what": f"arrival-time shift {tau:+.3g} s ({b.name})",
                                  "where": {"gauge": o.gauge, "quantity": o.quantity, "t0": float(t[0]), "t1": float(t[-1])},
                                  "standardised_residual": shift_score,
                                  "_idx": list(range(b.start, b.stop)), "_f": f, "_stat": "shift",
                                  "_t": t.tolist()})
            for wdw in windows:
                L.located.append({"what": f"gauge series {b.name} {'above' if wdw['score'] > 0 else 'below'} prediction",
                                  "where": {"gauge": o.gauge, "quantity": o.quantity, "t0": wdw["t0"], "t1": wdw["t1"]},
                                  "standardised_residual": wdw["score"],
                                  "_idx": [b.start + i for i in range(len(t)) if wdw["t0"] <= t[i] <= wdw["t1"]],
                                  "_f": f, "_stat": "window", "_block": [b.start, b.stop], "_t": t.tolist(),
                                  "_w": w, "_window": [wdw["t0"], wdw["t1"]]})
        if abs(Zb) >= block_threshold and Zb > 0:
            info["flagged"] = True
        L.blocks[b.name] = info
    L.located.sort(key=lambda l: -abs(l["standardised_residual"]))
    return L
