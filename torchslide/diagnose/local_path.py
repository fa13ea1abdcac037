"""The diagnosis's local path: every model fitted on the solver and described by its Laplace approximation.

Rich data (gauge series, deposit maps) give posteriors far narrower than the prior box. There the
baseline and each candidate model are fitted by trust-region least squares on the solver
(local.fit) and their evidence is the Laplace integral at the mode (local.laplace_log_evidence):

1. ``fit_model``: a maximin-LHS batch over the box ranks start points (one batched call), local.fit
   runs from the best ``starts`` and the highest mode is kept;
2. ``choose_path``: the fraction of the prior box that the baseline's 90 % Laplace ellipsoid fills;
   below ``max_fraction`` the local path is used (a GP over the box cannot resolve such a peak with
   tens of runs), else the emulator path (the paper's case: broad posteriors, sparse data);
3. ``laplace_result``: the fit as a CalibrationResult (Laplace draws truncated to the box as its
   samples), so the localisation, WAIC, re-scoring and report of the pipeline apply unchanged;
4. ``fit_candidate``: the enlarged model (baseline + switch) from the baseline's mode, with the
   switch started at the screening's linearised optimum, and from global starts (``candidate_lhs``
   maximin-LHS points over the switch's whole range and the baseline's mode +- ``candidate_box`` of each
   range, in the same batch; the ``candidate_starts`` best that beat the first start); its 2 ln BF against the baseline, the
   likelihood ratio lambda = 2 (ln L_c - ln L_0) with its boundary-corrected reference (the switch's
   null value 0 is the bound of its range, so under the null lambda ~ chi2_0 / 2 + chi2_1 / 2, Self &
   Liang 1987: p = P(chi2_1 > lambda) / 2), the Savage-Dickey ratio of the Laplace marginal at 0, and
   the profile of ln L at the ends of the switch's 90 % interval for the ``profile_top`` candidates
   with the largest 2 ln BF (``profile_ends``: mu, xi re-fitted with the switch held; a Gaussian gives
   2 ln drops of chi2_1(0.9) = 2.71 there, a very different drop says the Laplace shape does not hold,
   and a negative one that the fit is not at its mode: the fit restarts from that profile point
   (``refit_from``), and a candidate whose profile still beats its fit is unreliable).

Fits that can run side by side (the starts of one model, the candidates, the profile ends) run in
lockstep (lockstep.Lockstep, ``merged_residuals``): one solver call per round for all of them.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np
import torch
from scipy import special, stats

from ..active import maximin_lhs
from ..calibration import CalibrationResult
from ..evaluator import RunRecord
from .candidates import CANDIDATES
from .evaluator import stack_values
from .local import LocalFit, fit, profile_evidence_shift
from .lockstep import Lockstep
from .refit import candidate_evaluator
from .verify import hdi_interval


@dataclass
class Problem:
    """An evaluator's likelihood as whitened residuals: ln L(x) = log_norm - |r(x)|^2 / 2.

    names: the free parameters; bounds: (2, p) their prior box; lockstep: the Lockstep whose rounds
    run this problem's points together with other fits' (None: each request is its own solver call)."""

    evaluator: object
    names: list
    bounds: np.ndarray
    log_norm: float
    n_runs: int = 0     # solver members run so far, by every fit of this problem (failed ones included)
    lockstep: Lockstep | None = None

    def values(self, X: np.ndarray) -> dict:
        """Params values of the points X (n, p): the free parameters' columns over the evaluator's fixed ones."""
        return {**self.evaluator.fixed, **{n: X[:, i] for i, n in enumerate(self.names)}}

    def residuals(self, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """X (n, p) -> (whitened residuals (n, k), failed (n,)); one batched solver call per max_batch."""
        X = np.atleast_2d(np.asarray(X, dtype=np.float64))
        if self.lockstep is not None:
            return self.lockstep.ask((self, X))
        return merged_residuals([(self, X)])[0]

    def log_prior(self, x: np.ndarray) -> float:
        return float(self.evaluator.prior.log_prob(torch.as_tensor(np.atleast_2d(x), dtype=torch.float64))[0])


def merged_residuals(requests: list) -> list:
    """[(Problem, X (n_i, p_i))] -> [(residuals (n_i, k), failed (n_i,))], all points in one batch of the
    first problem's evaluator, each request's predictions whitened by its own likelihood (a candidate
    may carry its own grid error). The problems must share the terrain and observations (models of one
    diagnosis: they differ in which parameters are free and which are fixed, and in the grid's error)."""
    runner = requests[0][0].evaluator
    for prob, _ in requests[1:]:
        e = prob.evaluator
        if e.dem is not runner.dem or e.observations is not runner.observations:
            raise ValueError("problems of one batch must share the terrain and the observations")
        if getattr(e, "finer_grid", False) != getattr(runner, "finer_grid", False):
            raise ValueError("problems of one batch must run on the same grid (finer_grid)")
    for prob, X in requests:
        prob.n_runs += len(X)
    preds, failed = runner.run_values(stack_values([(len(X), prob.values(X)) for prob, X in requests]))
    cuts = np.cumsum([len(X) for _, X in requests])[:-1]
    out = []
    for (prob, X), p, f in zip(requests, np.split(np.asarray(preds), cuts), np.split(np.asarray(failed), cuts)):
        # one row at a time: numpy's reductions over a batch sum in another order than over one row, and a
        # point's residuals must not depend on its batch (a fit's trial point runs alone, its Jacobian apart)
        lik = prob.evaluator.likelihood
        r = np.concatenate([lik.residuals(torch.as_tensor(p[i:i + 1])).numpy() for i in range(len(p))]) \
            if len(p) else np.empty((0, prob.evaluator.k))
        bad = f | ~np.all(np.isfinite(r), axis=1)
        z = prob.log_norm - 0.5 * np.sum(np.where(bad[:, None], 0.0, r) ** 2, axis=1)
        prob.evaluator.records += [RunRecord(x.copy(), pi.copy(), float(zi + prob.log_prior(x)) if not b else math.nan,
                                             bool(b), "failed run" if b else "")
                                   for x, pi, zi, b in zip(X, p, z, bad)]   # what the fits ran (tradeoff, the cache)
        out.append((np.where(bad[:, None], np.inf, r), bad))
    return out


def problem(evaluator, lockstep: Lockstep | None = None) -> Problem:
    return Problem(evaluator, list(evaluator.prior.names), evaluator.prior.bounds.numpy().astype(np.float64),
                   evaluator.likelihood.log_norm, lockstep=lockstep)


def _with_prior(f: LocalFit, prob: Problem) -> LocalFit:
    """local.fit takes ln pi = 0; the prior density at the mode is added here (a prior that is flat over
    the posterior's width, the case this path is for)."""
    f.log_evidence += prob.log_prior(f.x)
    return f


def fit_model(evaluator, n_lhs: int = 16, starts: int = 2, extra_starts=None, seed: int = 0,
              rel_step: float = 3e-3, max_iter: int = 30, log=print, lockstep: Lockstep | None = None,
              box: tuple | None = None, only_better: bool = False) -> tuple[LocalFit, int]:
    """(best LocalFit, solver members used) of ``evaluator``'s model: ``n_lhs`` maximin-LHS points in one
    batch (over ``box`` (lo (p,), hi (p,)), default the prior box), local.fit from the ``starts`` best of them
    and from every ``extra_starts`` (m, p) point; ``only_better``: from those LHS points only that fit the
    data better than every extra start (evaluated in the same batch). The fits from several starts run in
    lockstep (one solver call per round for all of them); inside a ``lockstep`` of the caller's they run one
    after another, each round shared with the caller's other fits."""
    prob = problem(evaluator, lockstep)
    lo, hi = prob.bounds if box is None else (np.asarray(box[0], float), np.asarray(box[1], float))
    pts = lo + maximin_lhs(n_lhs, len(prob.names), seed) * (hi - lo) if n_lhs > 0 else np.empty((0, len(lo)))
    extra = [] if extra_starts is None else [np.asarray(x, dtype=np.float64) for x in np.atleast_2d(extra_starts)]
    x0 = []
    if len(pts):
        R, _ = prob.residuals(np.concatenate([pts] + ([np.stack(extra)] if only_better and extra else [])))
        ss = np.sum(R * R, axis=1)
        bar = ss[len(pts):].min() if only_better and extra else np.inf
        order = [i for i in np.argsort(ss[:len(pts)]) if ss[i] < bar]
        x0 = [pts[i] for i in order[:starts]]
    x0 = extra + list(x0)

    def one(x):
        return _with_prior(fit(prob.residuals, x, prob.bounds, prob.log_norm, 0.0, rel_step=rel_step,
                               max_iter=max_iter), prob)

    if lockstep is None and len(x0) > 1:
        prob.lockstep = Lockstep(merged_residuals)
        fits = prob.lockstep.map(one, x0)
        prob.lockstep = None
    else:
        fits = []
        for x in x0:
            try:
                fits.append(one(x))
            except (RuntimeError, np.linalg.LinAlgError) as e:
                fits.append(e)
    best = None
    for x, f in zip(x0, fits):
        if isinstance(f, (RuntimeError, np.linalg.LinAlgError)):
            log(f"[diagnose] local fit from {np.round(x, 4).tolist()} failed: {f}")
            continue
        if isinstance(f, BaseException):
            raise f
        if best is None or f.log_like + prob.log_prior(f.x) > best.log_like + prob.log_prior(best.x):
            best = f
    if best is None:
        raise RuntimeError(f"every local fit of {prob.names} failed")
    return best, prob.n_runs


def box_fraction(covariance: np.ndarray, bounds: np.ndarray, level: float = 0.9) -> float:
    """Share of the prior box's volume filled by the ``level`` ellipsoid of a Gaussian of ``covariance``
    (p, p) (capped at 1)."""
    b = np.asarray(bounds, dtype=np.float64)
    covariance = np.atleast_2d(covariance)
    p = covariance.shape[0]
    r2 = stats.chi2.ppf(level, p)
    log_ball = 0.5 * p * math.log(math.pi) - special.gammaln(0.5 * p + 1)
    log_v = log_ball + 0.5 * p * math.log(r2) + 0.5 * np.linalg.slogdet(covariance)[1]
    return float(min(1.0, math.exp(log_v - np.sum(np.log(b[1] - b[0])))))


def choose_path(f: LocalFit, bounds: np.ndarray, max_fraction: float) -> tuple[str, str]:
    """("local" | "emulator", why) from the baseline's Laplace fit (module doc, item 2)."""
    frac = box_fraction(f.covariance, bounds)
    if frac < max_fraction:
        return "local", (f"the baseline posterior's 90 % region fills {frac:.2g} of the prior box (< {max_fraction:g}): "
                         f"fitted on the solver with the Laplace evidence")
    return "emulator", (f"the baseline posterior's 90 % region fills {frac:.2g} of the prior box (>= {max_fraction:g}): "
                        f"GP emulator over the box")


def laplace_result(f: LocalFit, names: list, bounds: np.ndarray, n_draws: int = 2000, seed: int = 0) -> CalibrationResult:
    """The fit as a CalibrationResult: mode, Laplace draws (truncated to the box) as samples, Laplace ln Z."""
    b = np.asarray(bounds, dtype=np.float64)
    s = f.draws(n_draws, b, seed=seed)
    summary = {"names": list(names), "mean": {n: float(s[:, i].mean()) for i, n in enumerate(names)},
               "sd": {n: float(s[:, i].std()) for i, n in enumerate(names)},
               "map": {n: float(f.x[i]) for i, n in enumerate(names)},
               "hdr90": {n: [float(v) for v in hdi_interval(s[:, i], b[0, i], b[1, i])] for i, n in enumerate(names)}}
    return CalibrationResult(names=list(names), bounds=b, x=f.x[None].copy(),
                             z=np.array([f.log_like]), failed=np.zeros(1, bool), reasons=[""], n_initial=0,
                             grid_axes=None, posterior_grid=None, log_evidence=float(f.log_evidence), tv_history=[],
                             summary=summary, samples=s, stopped_reason="laplace (local fit on the solver)")


def lr_pvalue(lam: float) -> float:
    """Boundary-corrected p-value of the likelihood ratio for one switch at its bound 0 (module doc)."""
    return 1.0 if lam <= 0 else float(0.5 * stats.chi2.sf(lam, 1))


def savage_dickey(f: LocalFit, i: int, prior_range) -> float:
    """2 ln BF_10 = 2 ln(prior density at 0 / posterior density at 0), the posterior marginal of
    parameter ``i`` being the Laplace Gaussian's, truncated to the prior range."""
    lo, hi = float(prior_range[0]), float(prior_range[1])
    m, s = float(f.centre[i]), float(math.sqrt(f.covariance[i, i]))
    log_mass = math.log(max(stats.norm.cdf((hi - m) / s) - stats.norm.cdf((lo - m) / s), 1e-300))
    log_post0 = stats.norm.logpdf((lo - m) / s) - math.log(s) - log_mass
    return float(2 * (-math.log(hi - lo) - log_post0))


@dataclass
class CandidateFit:
    """A candidate's local fit: its evaluator and LocalFit, the likelihood ratio against the baseline
    and its boundary-corrected p-value, Savage-Dickey, members used."""

    name: str
    evaluator: object
    fit: LocalFit
    two_ln_bf: float
    lr: float
    lr_pvalue: float
    two_ln_bf_savage_dickey: float
    n_runs: int


def fit_candidate(evaluator, c: str, base: LocalFit, start: dict | None, bud, log=print,
                  lockstep: Lockstep | None = None) -> CandidateFit:
    """The enlarged model of candidate ``c`` fitted from the screening's linearised optimum ``start``
    {name: value} (module doc, item 4); None (the residual points away from the term): from the
    baseline's mode with the switch at 5 % of its range."""
    cd = CANDIDATES[c]
    ev_c = candidate_evaluator(evaluator, c)
    names = list(ev_c.prior.names)
    b = ev_c.prior.bounds.numpy().astype(np.float64)
    x_small = np.append(base.x, cd.prior[0] + 0.05 * (cd.prior[1] - cd.prior[0]))
    starts = [x_small] if start is None else [np.clip([start[n] for n in names], b[0], b[1])]
    fc, n = fit_model(ev_c, n_lhs=bud.candidate_lhs, starts=bud.candidate_starts, seed=bud.seed + 1,
                      extra_starts=np.array(starts), rel_step=bud.local_rel_step, max_iter=bud.local_max_iter,
                      log=log, lockstep=lockstep, box=global_box(base.x, b, bud.candidate_box), only_better=True)
    return candidate_fit(c, ev_c, fc, base, n)


def global_box(x0: np.ndarray, bounds: np.ndarray, fraction: float) -> tuple[np.ndarray, np.ndarray]:
    """The box of a candidate's global starts: each baseline parameter within ``fraction`` of its prior
    range around the baseline's mode x0 (p,), the switch (the last of ``bounds`` (2, p + 1)) over its whole
    prior range: where re-tuned baseline parameters and any strength of the term may meet."""
    w = fraction * (bounds[1, :-1] - bounds[0, :-1])
    lo = np.append(np.maximum(x0 - w, bounds[0, :-1]), bounds[0, -1])
    hi = np.append(np.minimum(x0 + w, bounds[1, :-1]), bounds[1, -1])
    return lo, hi


def candidate_fit(c: str, ev_c, fc: LocalFit, base: LocalFit, n: int) -> CandidateFit:
    """The CandidateFit of candidate ``c``'s local fit ``fc`` (its evaluator ``ev_c``) against the baseline's."""
    cd = CANDIDATES[c]
    names = list(ev_c.prior.names)
    lam = 2 * (fc.log_like - base.log_like)
    return CandidateFit(c, ev_c, fc, 2 * (fc.log_evidence - base.log_evidence), lam, lr_pvalue(lam),
                        savage_dickey(fc, names.index(cd.param), cd.prior), n)


def profile_interval(cf: CandidateFit) -> list[float]:
    """The ends of the switch's 90 % interval: the HDI of the Laplace draws on the switch's prior range."""
    fc = cf.fit
    names = list(cf.evaluator.prior.names)
    bounds = cf.evaluator.prior.bounds.numpy().astype(np.float64)
    i = names.index(CANDIDATES[cf.name].param)
    return [float(v) for v in hdi_interval(fc.draws(2000, bounds, seed=1)[:, i], bounds[0, i], bounds[1, i])]


def profile_drop(evaluator, cf: CandidateFit, value: float, bud, log=print,
                 lockstep: Lockstep | None = None) -> tuple[float, int, np.ndarray]:
    """(2 ln drop of the profile likelihood from the mode with the switch held at ``value``, members used,
    the profile's point in the candidate's parameters): ln L re-maximised over the baseline parameters
    (module doc, item 4)."""
    cd, fc = CANDIDATES[cf.name], cf.fit
    names = list(cf.evaluator.prior.names)
    bounds = cf.evaluator.prior.bounds.numpy().astype(np.float64)
    i = names.index(cd.param)
    if abs(value - fc.x[i]) <= 1e-12 * (bounds[1, i] - bounds[0, i]):
        return 0.0, 0, fc.x.copy()
    # the candidate's own likelihood (its grid error, its grid) over the baseline's parameters
    ev_s = cf.evaluator.with_prior(evaluator.prior, fixed={**dict(cd.fixed), cd.param: float(value)})
    fs, n = fit_model(ev_s, n_lhs=0, extra_starts=np.delete(fc.x, i)[None], rel_step=bud.local_rel_step,
                      max_iter=bud.local_max_iter, log=log, lockstep=lockstep)
    return float(2 * (fc.log_like - fs.log_like)), n, np.insert(fs.x, i, float(value))


def grouped_residuals(requests: list) -> list:
    """merged_residuals of each group of ``requests`` that can share a batch (the same terrain, observations
    and grid: the models of one diagnosis on its inversion grid, or on its finer one), answers in the
    requests' order: a round of a Lockstep over fits on both grids is one solver call per grid."""
    groups: dict = {}
    for i, (prob, _) in enumerate(requests):
        e = prob.evaluator
        groups.setdefault((id(e.dem), id(e.observations), bool(getattr(e, "finer_grid", False))), []).append(i)
    out: list = [None] * len(requests)
    for idx in groups.values():
        for i, a in zip(idx, merged_residuals([requests[i] for i in idx])):
            out[i] = a
    return out


def _profile_side(evaluator, cf: CandidateFit, v_end: float, d_end: float, bound: float, bud, steps: int, log,
                  lockstep: Lockstep | None = None) -> tuple[list, int]:
    """([(switch value, 2 ln drop)] from the mode outward, members used) of one side of the 90 % profile
    interval (profile_interval90): from the Laplace end ``v_end`` (drop ``d_end``) towards the prior's
    ``bound``, stepped until the drop reaches chi2_1(0.9)."""
    level = float(stats.chi2.ppf(0.9, 1))
    i = list(cf.evaluator.prior.names).index(CANDIDATES[cf.name].param)
    lo, hi = cf.evaluator.prior.bounds.numpy().astype(np.float64)[:, i]
    m = float(cf.fit.x[i])
    pts, runs = [(m, 0.0), (float(v_end), float(d_end))], 0
    for k in range(steps + 1):
        v, d = pts[-1]
        if d >= level or abs(v - bound) <= 1e-12 * (hi - lo) or v == m:
            break
        grow = min(max(1.1 * math.sqrt(level / max(d, 0.25 * level)), 1.25), 3.0)
        v_new = float(bound if k == steps else np.clip(m + (v - m) * grow, lo, hi))
        d_new, n, _ = profile_drop(evaluator, cf, v_new, bud, log, lockstep=lockstep)
        runs += n
        pts.append((v_new, d_new))
    return pts, runs


def _crossing(pts: list, level: float) -> tuple[float, bool]:
    """(where the side's drop reaches ``level``, interpolated linearly in sqrt(drop) between the last point
    below it and the first at or above it; True) or (its last point, False: open there)."""
    hit = next((k for k in range(1, len(pts)) if pts[k][1] >= level), None)
    if hit is None:
        return pts[-1][0], False
    (v0, d0), (v1, d1) = pts[hit - 1], pts[hit]
    s0, s1 = math.sqrt(max(d0, 0.0)), math.sqrt(d1)
    return (v0 + (math.sqrt(level) - s0) / (s1 - s0) * (v1 - v0) if s1 > s0 else v1), True


def profile_intervals90(evaluator, jobs: list, bud, steps: int = 2, log=print) -> list[tuple[dict, int]]:
    """[({"interval": [lo, hi], "closed": [bool, bool], "level", "points"}, members used)] of each (CandidateFit,
    profile_ends record) in ``jobs``: the 90 % profile-likelihood interval of the candidate's switch, where
    the profile's 2 ln drop from the mode reaches chi2_1(0.9) = 2.71. From the ends of the Laplace interval
    and their drops: a side whose drop is below 2.71 is stepped outward (the distance scaled by
    sqrt(2.71 / drop), at most 3 times, within the prior range) up to ``steps`` times, then, still below it,
    probed at the prior's bound; the crossing is interpolated in sqrt(drop) (_crossing). A side that never
    reaches it is open ("closed" False) at the prior's bound. Every side of every job runs in lockstep (one
    solver call per round and grid, grouped_residuals): the same points as one side after the other."""
    level = float(stats.chi2.ppf(0.9, 1))
    sides = []
    for cf, prof in jobs:
        i = list(cf.evaluator.prior.names).index(CANDIDATES[cf.name].param)
        bounds = cf.evaluator.prior.bounds.numpy().astype(np.float64)[:, i]
        sides += list(zip([cf] * 2, prof["interval90"], prof["two_ln_drop"], bounds))
    ls = Lockstep(grouped_residuals)
    done = ls.map(lambda j: _profile_side(evaluator, *j, bud, steps, log, lockstep=ls), sides)
    for d in done:
        if isinstance(d, BaseException):
            raise d
    out = []
    for k, (cf, _) in enumerate(jobs):
        i = list(cf.evaluator.prior.names).index(CANDIDATES[cf.name].param)
        (lo_pts, n_lo), (hi_pts, n_hi) = done[2 * k], done[2 * k + 1]
        ends = [_crossing(lo_pts, level), _crossing(hi_pts, level)]
        seen = [[float(cf.fit.x[i]), 0.0]] + [[float(v), float(d)] for v, d in lo_pts[1:] + hi_pts[1:]]
        out.append(({"interval": [e[0] for e in ends], "closed": [e[1] for e in ends], "level": level,
                     "points": sorted(seen)}, n_lo + n_hi))
    return out


def profile_interval90(evaluator, cf: CandidateFit, prof: dict, bud, steps: int = 2, log=print) -> tuple[dict, int]:
    """profile_intervals90 of one candidate ``cf`` with its profile_ends record ``prof``."""
    return profile_intervals90(evaluator, [(cf, prof)], bud, steps, log)[0]


def profile_two_ln_bf(cf: CandidateFit, p90: dict) -> float:
    """2 ln BF of candidate ``cf`` with its switch's factor taken from the measured profile likelihood
    (local.profile_evidence_shift): the points of ``p90`` (profile_interval90) and, at the switch's null
    value, the likelihood ratio 2 ln LR (the baseline is the profile there). The Laplace Gaussian of a
    switch is set by finite differences at the mode; where the likelihood is not quadratic in the switch
    (mu(I): sharper at its mode than the drop to 0 says) it misstates the Occam factor, which the profile
    measures. A mode on a bound of the switch's range keeps the Laplace value (its Gaussian is centred
    beyond the bound there)."""
    cd = CANDIDATES[cf.name]
    i = list(cf.evaluator.prior.names).index(cd.param)
    lo, hi = cf.evaluator.prior.bounds.numpy().astype(np.float64)[:, i]
    if not lo + 1e-9 * (hi - lo) < cf.fit.x[i] < hi - 1e-9 * (hi - lo):
        return cf.two_ln_bf
    pts = [tuple(p) for p in p90["points"]]
    if cf.lr > 0 and all(v > lo for v, _ in pts):
        pts.append((float(lo), float(cf.lr)))
    shift = profile_evidence_shift(pts, float(cf.fit.centre[i]), math.sqrt(float(cf.fit.covariance[i, i])), (lo, hi))
    return float(cf.two_ln_bf + 2.0 * shift)


def fit_candidates(evaluator, cands: list, base: LocalFit, starts: dict, bud, log=print) -> dict:
    """{candidate: CandidateFit, or the exception that ended its fit}: ``fit_candidate`` of every
    candidate in ``cands`` (``starts``: the screening's linearised optima), all in lockstep (one solver
    call per round for all of them)."""
    ls = Lockstep(merged_residuals)
    out = ls.map(lambda c: fit_candidate(evaluator, c, base, starts.get(c), bud, log, lockstep=ls), cands)
    log(f"[diagnose] {len(cands)} candidate fits in {ls.rounds} batched rounds")
    return dict(zip(cands, out))


def profile_ends(evaluator, fits: list, bud, log=print) -> list[tuple[dict, int]]:
    """[(profile record, members used)] of each CandidateFit in ``fits``: the 2 ln drop of the profile
    likelihood at both ends of its switch's 90 % interval (``profile_drop``; a Gaussian gives
    chi2_1(0.9) = 2.71 at both), every end's fit in lockstep."""
    ends = [profile_interval(cf) for cf in fits]
    jobs = [(cf, v) for cf, e in zip(fits, ends) for v in e]
    ls = Lockstep(merged_residuals)
    out = ls.map(lambda j: profile_drop(evaluator, j[0], j[1], bud, log, lockstep=ls), jobs)
    for o in out:
        if isinstance(o, BaseException):
            raise o
    gauss = float(stats.chi2.ppf(0.9, 1))
    res = []
    for k, e in enumerate(ends):
        pair = out[2 * k: 2 * k + 2]
        j = int(np.argmin([d for d, _, _ in pair]))
        res.append(({"interval90": e, "two_ln_drop": [d for d, _, _ in pair], "gaussian": gauss,
                     "lowest_point": pair[j][2].tolist()}, sum(n for _, n, _ in pair)))
    return res


def refit_from(evaluator, cf: CandidateFit, x: np.ndarray, base: LocalFit, bud, log=print) -> CandidateFit:
    """Candidate ``cf`` fitted again from ``x`` (a profile point that beats its fit: the fit was not at its
    mode); the better of the two fits is kept."""
    fc, n = fit_model(cf.evaluator, n_lhs=0, extra_starts=np.asarray(x, float)[None], rel_step=bud.local_rel_step,
                      max_iter=bud.local_max_iter, log=log)
    if fc.log_like <= cf.fit.log_like:
        return cf
    return candidate_fit(cf.name, cf.evaluator, fc, base, cf.n_runs + n)


def refit_with_error(cf: CandidateFit, model_error, base: LocalFit, bud, log=print) -> CandidateFit:
    """Candidate ``cf`` fitted again from its mode with ``model_error`` (model_error.ModelError) in its
    likelihood: the grid's error where the candidate fits (pipeline._candidate_grid_error)."""
    ev = cf.evaluator.with_model_error(model_error)
    fc, n = fit_model(ev, n_lhs=0, extra_starts=cf.fit.x[None], rel_step=bud.local_rel_step,
                      max_iter=bud.local_max_iter, log=log)
    return candidate_fit(cf.name, ev, fc, base, cf.n_runs + n)


INFERENCE = ("auto", "local", "emulator")
"""How a posterior is described: the GP emulator over the box, the local fit on the solver, or the
local fit when the emulator's posterior is too sharp for it (``local_calibration``)."""


def local_calibration(evaluator, cal: CalibrationResult, inference: str = "auto", max_fraction: float = 0.05,
                      rel_step: float = 3e-3, max_iter: int = 30, seed: int = 0,
                      log=print) -> tuple[CalibrationResult, dict]:
    """A calibration described on the solver when its posterior is too sharp for the emulator.

    ``inference`` "auto": when the 90 % region of the emulator's posterior (a Gaussian of its draws'
    covariance) fills less than ``max_fraction`` of the prior box, the mode is fitted on the solver from
    the emulator's MAP (fit_model) and the posterior is its Laplace approximation (``laplace_result``;
    the calibration's runs, tv history and emulator are kept with it); "local": always; "emulator": never.
    Returns (result, {"path", "why", "box_fraction", "log_evidence_emulator", "n_runs"}); a local fit
    that fails (e.g. fewer data values than parameters) leaves the emulator's result, saying why."""
    from ..predict import posterior_samples

    if inference not in INFERENCE:
        raise ValueError(f"inference must be one of {INFERENCE}, got {inference!r}")
    b = np.asarray(cal.bounds, dtype=np.float64)
    draws = posterior_samples(cal, 2000, seed=seed)
    frac = box_fraction(np.cov(draws.T) + np.diag((1e-9 * (b[1] - b[0])) ** 2), b)
    info = {"path": "emulator", "box_fraction": frac, "log_evidence_emulator": float(cal.log_evidence), "n_runs": 0}
    if inference == "emulator" or (inference == "auto" and frac >= max_fraction):
        info["why"] = ("inference = \"emulator\"" if inference == "emulator" else
                       f"the emulator's 90 % region fills {frac:.2g} of the prior box (>= {max_fraction:g})")
        return cal, info
    start = np.array([cal.summary["map"][n] for n in cal.names])
    try:
        f, n = fit_model(evaluator, n_lhs=0, extra_starts=start[None], rel_step=rel_step, max_iter=max_iter, log=log)
    except (RuntimeError, np.linalg.LinAlgError) as e:
        info["why"] = f"the local fit on the solver failed ({e}): the emulator's posterior is kept"
        return cal, info
    lap = laplace_result(f, list(cal.names), b, seed=seed)
    res = dataclasses.replace(lap, x=cal.x, z=cal.z, failed=cal.failed, reasons=cal.reasons, n_initial=cal.n_initial,
                              tv_history=cal.tv_history, emulator=cal.emulator, timings=cal.timings)
    info.update(path="local", n_runs=n, converged=bool(f.converged), log_evidence=float(f.log_evidence),
                why=("inference = \"local\"" if inference == "local" else
                     f"the emulator's 90 % region fills {frac:.2g} of the prior box (< {max_fraction:g}): "
                     f"the mode fitted on the solver, Laplace posterior"))
    log(f"[calibrate] local fit on the solver ({n} runs): " +
        ", ".join(f"{k} {v:.4g} +- {s:.2g}" for k, v, s in zip(cal.names, f.x, f.sd)))
    return res, info
