"""Checks of a calibrated model made with *solver runs*, not the emulator alone.

The emulator's evidence log Z_hat = log integral exp(g_hat) is only as good as g_hat: with 20-40 runs
in 3-D a GP can overshoot a peak or put it in the wrong corner, and 2 ln BF then swings by hundreds.
Posterior-predictive runs are made anyway (draws x_s from q = exp(g_hat) / Z_hat), so at every draw
the true z_s = ln L + ln prior is known and

    Z = integral exp(z) = Z_hat  E_q[exp(z - g_hat)]   ~=   Z_hat * mean_s exp(z_s - g_hat(x_s))

(importance sampling with the emulator's posterior as the proposal; for a grid posterior, p <= 2, the
proposal is the piecewise-constant grid density the draws come from): the *verified* evidence. Where
the emulator is good the weights w_s = z_s - g_hat(x_s) are nearly equal; where it is bad they are
spread out and their effective sample size (ESS) is small; the bootstrap standard error of the
log-mean-exp is reported with it. A region of high z the emulator missed is missed here too, so a
verified evidence errs low (conservative for a candidate refit).

Also here:

* ``waic``: out-of-sample predictive score elpd_WAIC = sum_i (log mean_s p(d_i | y_s) - var_s log p(d_i | y_s)),
  per datum, with the evaluator's effective sigmas.
* ``savage_dickey``: 2 ln BF (candidate vs baseline) = 2 ln(prior density / posterior density) of the
  switch at 0; posterior density at 0 from a boundary-corrected (reflected) KDE of the refit's MCMC
  samples with a bandwidth adapted to the posterior width: a bounded cross-check of the sign of the
  evidence Bayes factor.
* ``hdi_interval``: 90 % highest-density interval of a switch from its samples with the same KDE
  (it may include a prior bound, where an equal-tailed interval never does).
* ``rescore``: the located mismatches of the baseline re-scored with another model's predictive draws
  at the same cells / time windows / observables (does a candidate remove the located structure?).
"""
from __future__ import annotations

import math

import numpy as np
import torch

from .localise import aligned_running_score, arrival_shift, standardised


def logmeanexp(a: np.ndarray) -> float:
    a = np.asarray(a, float)
    m = float(np.max(a))
    return m + math.log(float(np.mean(np.exp(a - m))))


def proposal_log_density(cal, x: np.ndarray) -> np.ndarray:
    """(n,) the unnormalised log density, in z units (ln L + ln prior), of the proposal that
    posterior_samples(cal) draws from, at points ``x`` (n, p): for a grid posterior, ln of the
    piecewise-constant grid density of the nearest cell + log evidence; else the emulator's mean. The importance log weight of a solver run at x is z(x) minus this."""
    x = np.atleast_2d(np.asarray(x, float))
    if getattr(cal, "samples", None) is None and cal.posterior_grid is not None:
        dens = np.asarray(cal.posterior_grid, float)
        idx = tuple(np.clip(np.rint((x[:, d] - ax[0]) / (ax[1] - ax[0])).astype(int), 0, len(ax) - 1)
                    if len(ax) > 1 else np.zeros(len(x), int) for d, ax in enumerate(cal.grid_axes))
        return np.log(np.maximum(dens[idx], 1e-300)) + float(cal.log_evidence)
    return cal.emulator.mean(torch.as_tensor(x)).detach().numpy()


def verified_evidence(evaluator, cal, x: np.ndarray, draws: np.ndarray, n_boot: int = 200, seed: int = 0) -> dict:
    """Verified log evidence of ``cal`` from solver runs ``draws`` (M, k) at posterior draws ``x`` (M, p)."""
    x = np.asarray(x, float)
    draws = np.asarray(draws, float)
    out = {"log_evidence_emulator": float(cal.log_evidence), "n_draws": int(len(x))}
    if len(x) == 0 or (cal.emulator is None and cal.posterior_grid is None):
        out.update(log_evidence=float(cal.log_evidence), verified=False, ess=0.0, ess_fraction=0.0, se=float("inf"),
                   sd_log_weight=float("inf"), max_z=float("nan"))
        return out
    z = (evaluator.likelihood.log_likelihood(torch.as_tensor(draws)) +
         evaluator.prior.log_prob(torch.as_tensor(x))).numpy()
    lw = z - proposal_log_density(cal, x)
    ok = np.isfinite(lw)
    lw = lw[ok]
    if lw.size == 0:
        out.update(log_evidence=-math.inf, verified=False, ess=0.0, ess_fraction=0.0, se=float("inf"),
                   sd_log_weight=float("inf"), max_z=float("nan"))
        return out
    lme = logmeanexp(lw)
    w = np.exp(lw - lw.max())
    ess = float(w.sum() ** 2 / (w**2).sum())
    rng = np.random.default_rng(seed)
    boots = [logmeanexp(lw[rng.integers(0, lw.size, lw.size)]) for _ in range(n_boot)]
    out.update(log_evidence=float(cal.log_evidence + lme), verified=True, log_correction=float(lme), ess=ess,
               ess_fraction=ess / lw.size, se=float(np.std(boots)), sd_log_weight=float(np.std(lw)),
               max_z=float(np.max(z[ok])))
    return out


def pointwise_loglik(evaluator, draws: np.ndarray) -> np.ndarray:
    """(M, k) log N(d_i | y_si, sigma_eff_i)."""
    s = evaluator.sigma
    r = (evaluator.data[None, :] - np.asarray(draws, float)) / s
    return -0.5 * r * r - np.log(s * math.sqrt(2 * math.pi))


def waic(evaluator, draws: np.ndarray) -> dict:
    """elpd_WAIC, lppd and p_waic of predictive draws (M, k) (M >= 2)."""
    ll = pointwise_loglik(evaluator, draws)
    m = ll.max(0)
    lppd = float(np.sum(m + np.log(np.mean(np.exp(ll - m), axis=0))))
    p = float(np.sum(ll.var(0, ddof=1))) if len(ll) > 1 else 0.0
    return {"elpd": lppd - p, "lppd": lppd, "p_waic": p}


def _reflected_kde(s: np.ndarray, lo: float, hi: float, grid: np.ndarray, bw: float | None = None):
    """Gaussian KDE of samples ``s`` on [lo, hi] with reflection at both bounds (boundary-corrected:
    mass piled up at a bound gives a finite density *at* the bound). Bandwidth: Silverman's rule on
    the samples (floored at 0.1 % of the range). Returns (density on ``grid``, bandwidth)."""
    s = np.asarray(s, float)
    n = s.size
    if bw is None:
        sd = float(np.std(s, ddof=1)) if n > 1 else 0.0
        iqr = float(np.subtract(*np.percentile(s, [75, 25]))) / 1.349 if n > 1 else 0.0
        spread = min(sd, iqr) if iqr > 0 else sd
        bw = 0.9 * spread * n ** (-0.2)
    bw = max(float(bw), 1e-3 * (hi - lo))
    dens = np.zeros(len(grid))
    for c in (s, 2 * lo - s, 2 * hi - s):
        u = (grid[:, None] - c[None, :]) / bw
        dens += np.exp(-0.5 * u * u).sum(1)
    return dens / (n * bw * math.sqrt(2 * math.pi)), bw


def hdi_interval(samples, lo: float, hi: float, level: float = 0.9, n_grid: int = 801) -> list:
    """Extent [a, b] of the ``level`` highest-density region of one parameter from its posterior
    samples, with the boundary-corrected KDE on the prior range [lo, hi]: unlike an equal-tailed
    interval it contains a bound when the posterior piles up against it."""
    s = np.asarray(samples, float)
    s = s[np.isfinite(s)]
    if s.size < 2:
        return [float("nan"), float("nan")]
    grid = np.linspace(lo, hi, n_grid)
    dens, _ = _reflected_kde(np.clip(s, lo, hi), lo, hi, grid)
    w = dens / dens.sum()
    order = np.argsort(-w)
    k = int(np.searchsorted(np.cumsum(w[order]), level)) + 1
    sel = grid[order[:k]]
    return [float(sel.min()), float(sel.max())]


def hdi_from_grid(density: np.ndarray, axes, i: int, level: float = 0.9) -> list:
    """The same extent from a grid posterior's marginal along axis ``i`` (cell edges)."""
    from ..posterior import marginals

    a = np.asarray(axes[i], float)
    m = marginals(np.asarray(density, float), axes)[i]
    w = m / m.sum()
    order = np.argsort(-w)
    k = int(np.searchsorted(np.cumsum(w[order]), level)) + 1
    sel = a[order[:k]]
    h = (a[1] - a[0]) / 2 if len(a) > 1 else 0.0
    return [float(sel.min() - h), float(sel.max() + h)]


def savage_dickey(cal, param: str, prior_range) -> dict:
    """2 ln BF_10 (switch on vs off) = 2 ln(prior density at 0 / posterior density at 0) (the switch's
    lower bound is 0). Posterior density at the bound: the boundary-corrected (reflected) KDE of the
    MCMC samples, bandwidth adapted to the posterior width (Silverman); grid posteriors: the marginal
    density in the first cell. The density is floored at 1 / (2 N h) (half a sample within one
    bandwidth), so the statistic stays bounded: it is a cross-check of the sign of the evidence."""
    lo, hi = float(prior_range[0]), float(prior_range[1])
    width = hi - lo
    i = list(cal.names).index(param)
    if getattr(cal, "samples", None) is not None and len(cal.samples):
        s = np.clip(np.asarray(cal.samples, float)[:, i], lo, hi)
        N = float(len(s))
        d0, bw = _reflected_kde(s, lo, hi, np.array([lo]))
        floor = 0.5 / (N * bw)
        dens0 = max(float(d0[0]), floor)
        mass = float(np.mean(s < lo + bw))
    else:  # grid posterior: marginal density in the first cell
        from ..posterior import marginals

        ax = np.asarray(cal.grid_axes[i], float)
        m = marginals(np.asarray(cal.posterior_grid, float), cal.grid_axes)[i]
        bw = float(ax[1] - ax[0]) if len(ax) > 1 else width
        floor = 1e-6 / width
        dens0 = max(float(m[0]), floor)
        mass = float(m[0] * bw)
    two_ln = 2 * (math.log(1.0 / width) - math.log(dens0))
    return {"two_ln_bf": two_ln, "posterior_density_at_0": dens0, "prior_density": 1.0 / width,
            "bandwidth": bw, "at_floor": bool(dens0 <= floor), "posterior_mass_near_zero": mass}


def located_statistic(evaluator, mean: np.ndarray, var: np.ndarray, item: dict) -> float:
    """The score of one located mismatch recomputed from predictive moments with the statistic that
    located it (see localise: '_idx', '_f', '_stat'): 'sum' = sum z / sqrt(n f) over the item's values
    (scalar, map cluster); 'window' = a gauge time window: the largest |running-mean score| of the
    arrival-aligned series inside the window [t0, t1] (localise.aligned_running_score, alignment
    re-estimated for the new predictive mean), signed; 'shift' = the arrival-time shift score (misfit
    reduction from re-aligning the series)."""
    idx = np.asarray(item["_idx"], int)
    f = max(float(item.get("_f", 1.0)), 1.0)
    if item.get("_stat") == "window":
        b0, b1 = item["_block"]
        sl = slice(int(b0), int(b1))
        t = np.asarray(item["_t"], float)
        _, _, run = aligned_running_score(t, evaluator.data[sl], mean[sl], var[sl], evaluator.sigma_raw[sl],
                                          int(item["_w"]), float(item.get("_f", 1.0)))
        t0, t1 = item["_window"]
        inside = (t >= t0) & (t <= t1)
        if not inside.any():
            return 0.0
        r = run[inside]
        return float(r[np.argmax(np.abs(r))])
    z = standardised(evaluator, mean, var)[idx]
    n = idx.size
    if item.get("_stat") == "shift":
        t = np.asarray(item["_t"], float)
        d, y, v, s = evaluator.data[idx], mean[idx], var[idx], evaluator.sigma_raw[idx]
        tau = arrival_shift(t, d, y)
        if not tau:
            return 0.0
        za = (d - np.interp(t - tau, t, y)) / np.sqrt(np.interp(t - tau, t, v) + s**2)
        gain = float(np.sum(z**2) - np.sum(za**2))
        return math.copysign(math.sqrt(max(gain, 0.0) / f), tau)
    return float(np.sum(z) / math.sqrt(n * f))


def _moments(draws) -> tuple[np.ndarray, np.ndarray]:
    d = np.asarray(draws, float)
    return d.mean(0), (d.var(0, ddof=1) if len(d) > 1 else np.zeros(d.shape[1]))


def rescore(evaluator, located: list, draws_before: np.ndarray, draws_after: np.ndarray) -> dict:
    """Located mismatches re-scored before / after (same places, same statistic). Returns per-item
    scores, the largest |score| after, and the fraction of sum(score^2) removed over every item
    (``explained_all``; the verdict weighs the share over the significant items, decide.explained_share)."""
    items = [l for l in located if "_idx" in l]
    if not items:
        return {"items": [], "max_after": 0.0, "max_before": 0.0, "explained_all": None}
    mb, vb = _moments(draws_before)
    ma, va = _moments(draws_after)
    rows = [{"what": l["what"], "before": located_statistic(evaluator, mb, vb, l),
             "after": located_statistic(evaluator, ma, va, l)} for l in items]
    sb = sum(r["before"] ** 2 for r in rows)
    sa = sum(r["after"] ** 2 for r in rows)
    return {"items": rows, "max_after": max(abs(r["after"]) for r in rows),
            "max_before": max(abs(r["before"]) for r in rows), "explained_all": (1 - sa / sb) if sb > 0 else None}
