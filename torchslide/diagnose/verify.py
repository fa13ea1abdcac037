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
* ``zoom_proposal`` / ``refine_baseline``: the baseline (p = 2) posterior is narrow (~1 % of the box);
  its verification draws come from a grid posterior of the emulator on a zoomed box around the
  posterior mass (cells much narrower than the posterior), and the baseline emulator is refitted with
  the verification runs until the zoomed posterior stops changing (TV between rounds) and the verified
  evidence is trustworthy.
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
    piecewise-constant grid density of the nearest cell + log evidence (beyond the zoomed grid: its
    edge cell, which lies ~25 below the peak, so a point there weighs heavily only where z is high);
    else the emulator's mean. The importance log weight of a solver run at x is z(x) minus this."""
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
        if ax[0] - 0.5 * bw > lo + 1e-9 * width:
            # zoomed grid (refine_refit) that stops short of switch = 0: the mass there is below the
            # zoom's cut (exp(-25) of the peak), i.e. at the floor
            dens0, mass = floor, 0.0
        else:
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
    scores, the largest |score| after, and the fraction of sum(score^2) removed (``explained``)."""
    items = [l for l in located if "_idx" in l]
    if not items:
        return {"items": [], "max_after": 0.0, "max_before": 0.0, "explained": None}
    mb, vb = _moments(draws_before)
    ma, va = _moments(draws_after)
    rows = [{"what": l["what"], "before": located_statistic(evaluator, mb, vb, l),
             "after": located_statistic(evaluator, ma, va, l)} for l in items]
    sb = sum(r["before"] ** 2 for r in rows)
    sa = sum(r["after"] ** 2 for r in rows)
    return {"items": rows, "max_after": max(abs(r["after"]) for r in rows),
            "max_before": max(abs(r["before"]) for r in rows), "explained": (1 - sa / sb) if sb > 0 else None}


def slice_proposal(cal_c, base_bounds, grid_size: int = 160):
    """The beta = 0 slice of a candidate refit's emulator as a (zoomed) grid posterior over the
    baseline parameters (the candidate's switch is its last parameter): a second proposal for the
    *baseline* evidence. The refit explores (mu, xi) with more runs than the baseline calibration, so
    where the baseline calibration missed the narrow peak, this slice may find it; both proposals are
    verified with baseline solver runs and the larger verified evidence is kept."""
    def log_fn(X):
        X = torch.as_tensor(X, dtype=torch.float64)
        return cal_c.emulator.mean(torch.cat([X, torch.zeros(len(X), 1, dtype=X.dtype)], dim=1))

    return zoom_proposal(log_fn, np.asarray(base_bounds, float), coarse=grid_size)


def _bounds_of(cal_or_bounds):
    return np.asarray(getattr(cal_or_bounds, "bounds", cal_or_bounds), float)


def zoom_proposal(log_fn, bounds, coarse: int = 160, fine: int = 120, drop: float = 25.0):
    """Grid posterior of ``log_fn`` ((n, p) tensor -> (n,)) on a zoomed box: a coarse grid over
    ``bounds`` finds the cells within ``drop`` log units of the maximum; the box around them (padded by
    one coarse cell) gets a ``fine`` grid. Returns a namespace usable by posterior_samples and
    verified_evidence (samples=None, posterior_grid, grid_axes, bounds, log_evidence, emulator=None);
    the mass outside the zoomed box (< exp(-drop) relative) is neglected."""
    from types import SimpleNamespace

    from ..posterior import grid_axes, log_grid_values, normalise_log_grid

    b = np.asarray(bounds, float)
    ax0 = grid_axes(b, coarse)
    lv = log_grid_values(log_fn, ax0)
    keep = np.isfinite(lv) & (lv >= np.nanmax(lv) - drop)
    zb = b.copy()
    for d, a in enumerate(ax0):
        other = tuple(j for j in range(lv.ndim) if j != d)
        on = np.where(keep.any(axis=other) if other else keep)[0]
        h = a[1] - a[0]
        zb[0, d] = max(b[0, d], a[on.min()] - 1.5 * h)
        zb[1, d] = min(b[1, d], a[on.max()] + 1.5 * h)
    axes = grid_axes(zb, fine)
    dens, logz = normalise_log_grid(log_grid_values(log_fn, axes), axes)
    return SimpleNamespace(samples=None, posterior_grid=dens, grid_axes=axes, bounds=zb, log_evidence=logz,
                           emulator=None, log_fn=log_fn)


def _tv_on(prop_new, log_fn_old) -> float:
    """TV between the new zoomed posterior and the old log density normalised on the new grid."""
    from ..posterior import cell_volume, log_grid_values, normalise_log_grid, tv_distance

    old, _ = normalise_log_grid(log_grid_values(log_fn_old, prop_new.grid_axes), prop_new.grid_axes)
    return tv_distance(prop_new.posterior_grid, old, cell_volume(prop_new.grid_axes))


def _local_proposal(X, Z, bounds, local_range: float = 100.0, min_points: int = 8, coarse: int = 160,
                    fine: int = 120):
    """Zoomed grid proposal of a GP fitted to the runs with z >= max z - local_range on their bounding
    box (padded by 15 % of its width per side, clipped to ``bounds``); all runs / the whole box when
    fewer than ``min_points`` are local."""
    from ..emulator import LogPosteriorEmulator

    b = np.asarray(bounds, float)
    sel = Z >= Z.max() - local_range
    if int(sel.sum()) < min_points:
        em = LogPosteriorEmulator(torch.as_tensor(b)).fit(torch.as_tensor(X), torch.as_tensor(Z))
        return zoom_proposal(em.mean, b, coarse=coarse, fine=fine)
    lo, hi = X[sel].min(0), X[sel].max(0)
    pad = 0.15 * np.maximum(hi - lo, 1e-3 * (b[1] - b[0]))
    lb = np.vstack([np.maximum(b[0], lo - pad), np.minimum(b[1], hi + pad)])
    em = LogPosteriorEmulator(torch.as_tensor(lb)).fit(torch.as_tensor(X[sel]), torch.as_tensor(Z[sel]))
    return zoom_proposal(em.mean, lb, coarse=coarse, fine=fine)


def refine_baseline(evaluator, cal, M: int, seed: int = 0, max_rounds: int = 3, tv_tol: float = 0.15,
                    ess_fraction: float = 0.3, se_max: float = 1.0, agree: float = 1.0, local_range: float = 100.0,
                    log=print, coarse: int = 160, fine: int = 120, label: str = "baseline"):
    """Make the baseline's verified evidence reliable (see the module doc). Each round: draw M from the
    zoomed grid posterior of the current emulator, run the solver there, verify. Stop when the verified
    evidence is trustworthy (ESS >= ``ess_fraction`` M, bootstrap se <= ``se_max``) and stable: round 0,
    or the zoomed posterior moved by TV < ``tv_tol`` since the previous round, or the verified log Z
    agrees with the previous round's within ``agree`` + 2 se. Otherwise refit an emulator *locally*
    (every run so far with z >= max z - ``local_range``, on their bounding box: a global GP over a
    box 100x wider than the posterior cannot resolve its curvature) and repeat. Every round's estimate is a valid importance-sampling estimate of the same
    log Z, so when ``max_rounds`` is reached the round with the largest ESS is kept. The verification
    dict's ``converged`` says whether the last round was trustworthy *and* stable (False: the estimate
    was still moving when the rounds ran out). Returns (proposal, predictive, verification dict, history)."""
    from .predictive import posterior_predictive, posterior_samples

    b = _bounds_of(cal)
    ok = ~np.asarray(cal.failed, bool) & np.isfinite(cal.z)
    X, Z = np.asarray(cal.x, float)[ok], np.asarray(cal.z, float)[ok]
    prop = zoom_proposal(cal.emulator.mean, b, coarse=coarse, fine=fine)
    tv = None
    hist, rounds = [], []
    prev = None
    for r in range(max_rounds + 1):
        x = posterior_samples(prop, M, seed=seed + 11 * r)
        pred = posterior_predictive(evaluator, x)
        ver = verified_evidence(evaluator, prop, pred.x, pred.draws, seed=seed)
        trusted = bool(ver.get("verified") and ver["ess_fraction"] >= ess_fraction and ver["se"] <= se_max)
        hist.append({"round": r, "n_runs": int(len(X) + len(pred.x)), "log_evidence": ver["log_evidence"],
                     "log_evidence_grid": prop.log_evidence, "ess": ver["ess"], "se": ver["se"], "tv": tv,
                     "trusted": trusted, "zoom_box": prop.bounds.tolist()})
        rounds.append((prop, pred, ver))
        log(f"[diagnose] {label} round {r}: log Z {ver['log_evidence']:.2f} (grid {prop.log_evidence:.2f}), "
            f"ESS {ver['ess']:.1f}/{ver['n_draws']}, se {ver['se']:.2f}, TV {tv if tv is None else round(tv, 3)}")
        stable = r == 0 or (tv is not None and tv < tv_tol) or (
            prev is not None and prev.get("verified") and
            abs(ver["log_evidence"] - prev["log_evidence"]) <= agree + 2 * math.hypot(ver["se"], prev["se"]))
        hist[-1]["stable"] = bool(stable)
        if (trusted and stable) or r == max_rounds or len(pred.x) == 0:
            break
        prev = ver
        z = solver_z(evaluator, pred)
        good = np.isfinite(z)
        X, Z = np.vstack([X, pred.x[good]]), np.concatenate([Z, z[good]])
        new = _local_proposal(X, Z, b, local_range, coarse=coarse, fine=fine)
        tv = _tv_on(new, prop.log_fn)
        prop = new
    converged = bool(hist[-1]["trusted"] and hist[-1]["stable"])
    if not hist[-1]["trusted"]:
        k = int(np.argmax([h["ess"] if np.isfinite(h["se"]) else -1 for h in hist]))
        prop, pred, ver = rounds[k]
        hist[k]["kept"] = True
    else:
        hist[-1]["kept"] = True
    n_total = int(len(X) + len(rounds[-1][1].x))
    prop.runs = (X, Z)  # the calibration's runs + the verification runs of every round but the last
    return prop, pred, dict(ver, rounds=hist, n_runs_total=n_total, converged=converged), hist


def needs_bound_probe(cal_c, near: float = 0.2, gap: float = 0.05, relevant: float = 10.0) -> bool:
    """True when the refit's MCMC posterior leans against the switch's (last parameter's) upper bound
    where no posterior-relevant run was made: the 95 % quantile of the switch draws is within ``near``
    x prior width of the bound, and none of the runs with z >= max z - ``relevant`` has the switch
    within ``gap`` x width of it (a run at the bound far from the posterior's mu, xi says nothing
    about the posterior there). The emulator's value at such a bound is an extrapolation."""
    draws = getattr(cal_c, "samples", None)
    if draws is None or not len(draws) or cal_c.emulator is None:
        return False
    b = _bounds_of(cal_c)
    lo, hi = b[0, -1], b[1, -1]
    ok = ~np.asarray(cal_c.failed, bool) & np.isfinite(cal_c.z)
    X, Z = np.asarray(cal_c.x, float)[ok], np.asarray(cal_c.z, float)[ok]
    if not len(X):
        return False
    rel = X[Z >= Z.max() - relevant]
    return bool(np.quantile(np.asarray(draws, float)[:, -1], 0.95) > hi - near * (hi - lo)
                and rel[:, -1].max() < hi - gap * (hi - lo))


def solver_z(evaluator, pred) -> np.ndarray:
    """(M,) z = ln L + ln prior of posterior-predictive runs ``pred`` (a Predictive): the solver's value
    of the log unnormalised posterior at its draws."""
    if not len(pred.x):
        return np.zeros(0)
    return (evaluator.likelihood.log_likelihood(torch.as_tensor(pred.draws)) +
            evaluator.prior.log_prob(torch.as_tensor(pred.x))).numpy()


def refine_refit(ev_c, cal_c, M: int, seed: int = 0, max_rounds: int = 2, grid: tuple = (48, 40), log=print,
                 n_probe: int = 4, near: float = 0.2, gap: float = 0.05, relevant: float = 10.0, extra=None, **kw):
    """The refit's (p = 3) posterior refined like the baseline's (refine_baseline): the emulator's MCMC
    posterior can be confidently wrong where the active learning left no runs, e.g. against a prior
    bound of the switch (a 24-run GP in 3-D under-predicted z by ~7 at switch = 1 on an earth-pressure
    recording and its 90 % interval excluded the truth). Here the proposal is a zoomed *grid*
    posterior of the emulator (``grid`` = (coarse, fine) points per axis), its M draws are run,
    verified, and the emulator is refitted locally with those runs until the verified evidence is
    trustworthy and stable. Bound probe: when the MCMC posterior's 95 % quantile of the switch (the
    last parameter) is within ``near`` x prior width of its upper bound and no posterior-relevant run
    lies within ``gap`` x width of it, ``n_probe`` runs are made first at posterior draws with the switch set to the bound
    and the emulator is refitted locally with them (the GP's value at an unsampled bound is an
    extrapolation; needs_bound_probe). ``extra`` = (x (n, p), z (n,)): solver runs already made (the
    pipeline passes the first verification's draws of a refit whose verified evidence was not
    trustworthy); with probes or ``extra`` the first proposal is already the local GP's.
    The pipeline calls this where the refit leans against an unsampled bound, or where its first
    verified evidence is not trustworthy (instead of continuing the global active learning).
    Returns (result, predictive, verification dict): ``result`` is a
    CalibrationResult-like namespace (grid posterior on the zoomed box, the summary / HDIs from it,
    every run in x / z, the original global emulator kept for the beta = 0 slice check)."""
    start = cal_c
    b = _bounds_of(cal_c)
    lo, hi = b[0, -1], b[1, -1]
    ok = ~np.asarray(cal_c.failed, bool) & np.isfinite(cal_c.z)
    X0, Z0 = np.asarray(cal_c.x, float)[ok], np.asarray(cal_c.z, float)[ok]
    draws = np.asarray(cal_c.samples, float) if getattr(cal_c, "samples", None) is not None else None
    probes = 0
    n_extra = 0
    if extra is not None and len(extra[0]):
        xe, ze = np.asarray(extra[0], float), np.asarray(extra[1], float)
        good = np.isfinite(ze)
        n_extra = int(good.sum())
        X0, Z0 = np.vstack([X0, xe[good]]), np.concatenate([Z0, ze[good]])
    if n_probe > 0 and needs_bound_probe(cal_c, near=near, gap=gap, relevant=relevant):
        # the posterior leans against the switch's upper bound where no run was made: the GP's value
        # there is an extrapolation. Probe the face: posterior draws with the switch set to the bound.
        rng = np.random.default_rng(seed + 7)
        xp = draws[rng.choice(len(draws), size=n_probe, replace=False)].copy()
        xp[:, -1] = hi
        from .predictive import posterior_predictive
        pp = posterior_predictive(ev_c, xp)
        zp = solver_z(ev_c, pp)
        good = np.isfinite(zp)
        probes = int(good.sum())
        if probes:
            X0, Z0 = np.vstack([X0, pp.x[good]]), np.concatenate([Z0, zp[good]])
        log(f"[diagnose] refit: posterior against the unsampled upper bound of {cal_c.names[-1]}: "
            f"{probes} probe run(s) there, emulator refitted")
    if probes or n_extra:
        start = runs_start(X0, Z0, b, coarse=grid[0], fine=grid[1])
    prop, pred, ver, hist = refine_baseline(ev_c, start, M, seed=seed, max_rounds=max_rounds, log=log,
                                            coarse=grid[0], fine=grid[1], label="refit", **kw)
    hist[0]["bound_probes"] = probes
    hist[0]["extra_runs"] = n_extra
    X, Z = prop.runs
    # the kept round's draws are runs too (the last round's draws were not added to X in the loop)
    z_last = solver_z(ev_c, pred)
    new = ~np.any(np.all(np.isclose(pred.x[:, None, :], X[None, :, :]), axis=2), axis=1) if len(pred.x) else []
    if len(pred.x):
        X, Z = np.vstack([X, pred.x[new]]), np.concatenate([Z, z_last[new]])
    res = grid_result(prop, cal_c.names, cal_c.bounds, emulator=cal_c.emulator, x=X, z=Z,
                      failed=np.zeros(len(X), bool), n_runs=int(len(X)),
                      log_evidence_global_emulator=float(cal_c.log_evidence), refine_history=hist)
    return res, pred, ver


def runs_start(X, Z, bounds, coarse: int = 160, fine: int = 120):
    """A CalibrationResult-like start for refine_baseline built from solver runs alone: X (n, p), Z (n,)
    (finite), the local GP of _local_proposal as its emulator mean."""
    from types import SimpleNamespace

    b = np.asarray(bounds, float)
    p0 = _local_proposal(X, Z, b, coarse=coarse, fine=fine)
    return SimpleNamespace(x=X, z=Z, failed=np.zeros(len(X), bool), bounds=b, emulator=SimpleNamespace(mean=p0.log_fn))


def grid_result(prop, names, bounds, **extra):
    """A CalibrationResult-like namespace of a zoomed grid proposal ``prop`` (zoom_proposal): its grid
    posterior, the summary (mean, MAP, 90 % HDR per parameter) and log evidence, over the prior ``bounds``
    (2, p) of the parameters ``names``; ``extra`` attributes are added (runs, emulator, history)."""
    from types import SimpleNamespace

    from ..posterior import summarise_grid

    summ = summarise_grid(prop.posterior_grid, prop.grid_axes, list(names), prop.log_evidence).to_dict()
    fields = dict(names=list(names), bounds=np.asarray(bounds, float), samples=None, posterior_grid=prop.posterior_grid,
                  grid_axes=prop.grid_axes, zoom_bounds=prop.bounds, log_evidence=float(prop.log_evidence), summary=summ)
    fields.update(extra)
    return SimpleNamespace(**fields)
