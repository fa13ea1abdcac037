"""Profile of a refit along its switch: does the posterior follow the whole ridge?

A nested candidate's switch often trades off against the baseline's (mu, xi): a yield stress tau_y
that stops the flow earlier can be partly replaced by a larger mu, a rate-dependent mu_i by another
xi. The posterior is then a long curved ridge in (mu, xi, switch), and a refit of 24-36 runs plus a
local emulator can put a narrow posterior on one stretch of it. On the harness's control recordings
(no grid error) the yield-stress refits' 90 % intervals of tau_y were [2.02, 2.39], [4.58, 5.00],
[3.83, 4.17] around a truth of 3: each on the ridge, none covering the others. Importance-sampling
verification cannot see mass its proposal never visits.

The profile z*(s) = max over the baseline parameters of z(mu, xi, s) (z = ln L + ln prior, the
solver's) is measured on a ladder of switch values around the refit's posterior: each value starts
from the posterior's linear trend of (mu, xi) against the switch (the conditional mean of its
draws) and a batched local search on the solver (polish.local_search with the switch held) climbs
to the ridge. Where the profile stays high at the ladder's end the ladder is extended (the ridge
goes on). The runs then join the refit's local emulator (pipeline.profile_refit), so its proposal
covers the ridge that the profile found.
"""
from __future__ import annotations

import numpy as np
import torch

from .polish import local_search


def ridge_trend(draws: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """Linear trend of the other parameters against the switch (the last column) in posterior draws
    ``draws`` (n, p): (mean (p,), slope (p - 1,), switch sd), so that the conditional mean at switch
    s is mean[:-1] + slope * (s - mean[-1]) (Gaussian conditioning on the draws' covariance)."""
    d = np.asarray(draws, float)
    m = d.mean(0)
    C = np.cov(d.T) if len(d) > 1 else np.zeros((d.shape[1], d.shape[1]))
    var_s = float(C[-1, -1])
    slope = C[:-1, -1] / var_s if var_s > 0 else np.zeros(d.shape[1] - 1)
    return m, slope, float(np.sqrt(max(var_s, 0.0)))


def sampling_log_density(cal, x: np.ndarray) -> np.ndarray:
    """(n,) log density, up to a constant, of the distribution that posterior_samples(cal) draws from,
    at ``x`` (n, p): a grid posterior's own density (verify.proposal_log_density); for MCMC samples a
    Gaussian fitted to them (the emulator's mean would assume the chains represent it, which is what
    the profile tests). Differences of z minus this between points are importance log weights."""
    from .verify import proposal_log_density

    if getattr(cal, "samples", None) is None:
        return proposal_log_density(cal, x)
    smp = np.asarray(cal.samples, float)
    m = smp.mean(0)
    C = np.cov(smp.T) + 1e-12 * np.diag(np.maximum(np.ptp(smp, 0), 1e-6) ** 2)
    d = np.atleast_2d(np.asarray(x, float)) - m
    L = np.linalg.cholesky(C)
    u = np.linalg.solve(L, d.T)
    return -0.5 * np.sum(u * u, axis=0) - np.sum(np.log(np.diag(L)))


def switch_ladder(interval, prior, n_values: int = 5, min_half: float = 0.1) -> np.ndarray:
    """(n_values,) switch values centred on the 90 % ``interval`` [a, b] of the refit, spanning
    (a + b) / 2 +- max(1.5 (b - a), ``min_half`` x prior width), shifted inwards where it would cross a
    bound of the ``prior`` range (lo, hi) (so it keeps its span), clipped to it and deduplicated."""
    a, b = float(interval[0]), float(interval[1])
    lo, hi = float(prior[0]), float(prior[1])
    half = min(max(1.5 * (b - a), min_half * (hi - lo)), 0.5 * (hi - lo))
    c = min(max(0.5 * (a + b), lo + half), hi - half)
    v = np.clip(np.linspace(c - half, c + half, n_values), lo, hi)
    return np.unique(v)


def _profile_at(ev_c, S: np.ndarray, starts: np.ndarray, bounds, n_iter: int, pop: int, step, seed: int):
    """Run ``starts`` (n, p) (switch = S) and a local search from each with the switch held; returns
    (all runs x (m, p), z (m,), best z per value (n,), best x per value (n, p))."""
    b = np.asarray(bounds, float)
    x0 = np.clip(np.column_stack([starts[:, :-1], S]), b[0], b[1])
    r = ev_c(torch.as_tensor(x0))
    z0 = np.where(r.failed.detach().cpu().numpy(), -np.inf, r.z.detach().cpu().numpy().astype(float))
    X, Z = [x0], [z0]
    hold = np.zeros(b.shape[1], bool)
    hold[-1] = True
    if n_iter > 0 and np.isfinite(z0).any():
        ls = local_search(ev_c, x0, z0, b, n_iter=n_iter, pop=pop, n_starts=None, step0=step, seed=seed, hold=hold)
        X.append(ls["x"])
        Z.append(ls["z"])
    X, Z = np.vstack(X), np.concatenate(Z)
    best_z, best_x = np.full(len(S), -np.inf), x0.copy()
    for k, s in enumerate(S):
        on = np.isclose(X[:, -1], s, rtol=0, atol=1e-9 * (b[1, -1] - b[0, -1]))
        if on.any() and np.isfinite(Z[on]).any():
            j = np.flatnonzero(on)[int(np.argmax(np.where(np.isfinite(Z[on]), Z[on], -np.inf)))]
            best_z[k], best_x[k] = Z[j], X[j]
    return X, Z, best_z, best_x


def switch_profile(ev_c, draws: np.ndarray, interval, bounds, n_values: int = 5, n_iter: int = 2, pop: int = 6,
                   extend: int = 2, drop: float = 2.0, min_half: float = 0.1, seed: int = 0) -> dict:
    """Profile z*(s) of a refit along its switch (the last parameter; see the module doc).

    ``ev_c``: the candidate's evaluator ((n, p) points -> .z, .failed). ``draws`` (n, p): posterior
    draws of the refit (their trend sets each value's start). ``interval``: the switch's 90 %
    interval. ``bounds`` (2, p): the prior box. A ladder of ``n_values`` (switch_ladder), each run at
    the trend's (mu, xi) and searched for ``n_iter`` iterations of ``pop`` moves with the switch held
    (initial steps: twice the draws' sd per axis, in [0.01, 0.1] of the box); then, up to ``extend``
    times per side, one more value a ladder step beyond an end whose profile is within ``drop`` of the
    profile's maximum (and not at the prior bound), started from the line through the two outermost
    optima. Last, an inner value whose profile lies more than ``drop`` below the line between its
    neighbours' (its start was off the ridge) is searched again from both neighbours' optima.
    Returns {switch (K,) sorted, z (K,) profile, x (K, p) where, runs_x (m, p), runs_z (m,), repaired
    (the values searched again)}."""
    b = np.asarray(bounds, float)
    lo, hi = b[0, -1], b[1, -1]
    m, slope, _ = ridge_trend(draws)
    S = switch_ladder(interval, (lo, hi), n_values, min_half)
    h = float(np.min(np.diff(S))) if len(S) > 1 else min_half * (hi - lo)
    starts = np.column_stack([m[:-1][None, :] + np.outer(S - m[-1], slope), S])
    w = b[1] - b[0]
    step = np.clip(2 * np.asarray(draws, float).std(0) / w, 0.01, 0.1)
    X, Z, pz, px = _profile_at(ev_c, S, starts, b, n_iter, pop, step, seed)
    allX, allZ = [X], [Z]
    for it in range(extend):
        new_s, new_start = [], []
        top = np.max(pz)
        order = np.argsort(S)
        for side in (0, -1):
            k = order[side]
            k2 = order[1] if side == 0 else order[-2]
            if len(S) < 2 or pz[k] < top - drop:
                continue
            s_new = S[k] + (-h if side == 0 else h)
            if not lo <= s_new <= hi:
                s_new = lo if side == 0 else hi
            if np.isclose(s_new, S[k]):
                continue
            # the line through the two outermost optima, extrapolated to s_new
            ds = S[k] - S[k2]
            g = (px[k, :-1] - px[k2, :-1]) / ds if ds != 0 else np.zeros(b.shape[1] - 1)
            new_s.append(s_new)
            new_start.append(np.append(px[k, :-1] + g * (s_new - S[k]), s_new))
        if not new_s:
            break
        Sn = np.asarray(new_s)
        Xn, Zn, pzn, pxn = _profile_at(ev_c, Sn, np.vstack(new_start), b, n_iter, pop, step, seed + 1 + it)
        allX.append(Xn)
        allZ.append(Zn)
        S, pz, px = np.concatenate([S, Sn]), np.concatenate([pz, pzn]), np.vstack([px, pxn])
    o = np.argsort(S)
    S, pz, px = S[o], pz[o], px[o]
    # repair: an inner value whose search stayed below the line between its neighbours' profile by more
    # than ``drop`` started off the ridge; search again from both neighbours' optima (switch set to it)
    dips = [k for k in range(1, len(S) - 1)
            if pz[k] < pz[k - 1] + (pz[k + 1] - pz[k - 1]) * (S[k] - S[k - 1]) / (S[k + 1] - S[k - 1]) - drop]
    if dips:
        Sr = np.repeat(S[dips], 2)
        st = np.vstack([np.append(px[k + j, :-1], S[k]) for k in dips for j in (-1, 1)])
        Xr, Zr, pzr, pxr = _profile_at(ev_c, Sr, st, b, n_iter, pop, step, seed + 101)
        allX.append(Xr)
        allZ.append(Zr)
        for i, k in enumerate(np.repeat(dips, 2)):
            if pzr[i] > pz[k]:
                pz[k], px[k] = pzr[i], pxr[i]
    return {"switch": S, "z": pz, "x": px, "runs_x": np.vstack(allX), "runs_z": np.concatenate(allZ),
            "repaired": [float(S[k]) for k in dips]}
