"""The smallest switch of each candidate the recordings reveal: predicted by the screening, measured on the solver.

A candidate at switch s adds to the baseline's predictions an effect that re-tuning mu, xi partly mimics.
What they cannot mimic, whitened by the likelihood's covariance (L L^T, the grid's error included),
sets the evidence the recordings can hold for the term:

    nc(s) = min_theta |L^-1 (y(theta, 0) - y(x0, s))|^2

the 2 ln likelihood ratio of noise-free data made by the candidate's model at the baseline's mode x0
and switch s, against the baseline refitted to them (the noncentrality of the fit's 2 ln LR under noise).

* Predicted (the screening's step): nc(s) = (a s)^2, a = |P L^-1 J_c| with J_c the effect per unit
  switch and P the projection off the baseline's sensitivities. A term that mu, xi mimic far from x0
  (mu(I)) or one whose effect grows faster than linearly (a threshold: yield stress, entrainment) is
  mispredicted by factors of 2 or more.
* Measured (:func:`baseline_gap`): nc on the solver, the baseline fitted by trust-region least squares
  in its prior box with Broyden's Jacobian (:func:`broyden_mode`, one member a step), all candidates in
  lockstep: first at the predicted four-in-five switch, then (PASSES measurements at most, until the
  switch moves by less than 5 %) at the one the measurements so far give, nc(s) being the power law
  through the last two (:func:`lr_at`).

With a uniform prior of width W on the switch and the baseline profiled out, a switch s gives

    2 ln BF ~ nc(s) - 2 ln(a W / sqrt(2 pi))        (Laplace; the second term is the Occam factor)

so the decision threshold bf_min is reached where nc(s) = t^2, t = sqrt(bf_min + max(occam, 0)) (an Occam
term below 0, a prior narrower than the likelihood, is taken as 0), and with noise the fit's whitened
size is sqrt(nc) + z (z ~ N(0, 1)): in a share POWER of the noise draws where nc(s) = (t + Phi^-1(POWER))^2.
A candidate whose switch for t^2 lies beyond its prior range cannot be named from these data on this grid
whatever its strength; below it, a smaller true switch goes unseen.
"""
from __future__ import annotations

import math

import numpy as np
from scipy import optimize, stats
from scipy.linalg import solve_triangular

from ..physics import default_value
from .candidates import CANDIDATES
from .evaluator import stack_values
from .lockstep import Lockstep
from .screen import ScreenResult

POWER = 0.8    # the share of noise draws in which a term at ``switch_power`` reaches bf_min
PASSES = 3     # most measurements of nc per candidate (each at the four-in-five switch the last ones give)
EXPONENT_RANGE = (0.5, 8.0)
"""The power law's exponent is kept in this range (2: an effect linear in the switch)."""


def switch_threshold(a: float, prior: tuple, bf_min: float) -> dict:
    """{per_unit: a, switch: s_det, within_prior, switch_power} for nc(s) = (a s)^2 (module doc):
    s_det = t / a and s_power = (t + Phi^-1(POWER)) / a."""
    if a <= 0:
        return {"per_unit": 0.0, "switch": math.inf, "within_prior": False, "switch_power": math.inf}
    t = _t(a, prior, bf_min)
    return {"per_unit": a, "switch": t / a, "within_prior": bool(t / a <= prior[1]),
            "switch_power": (t + float(stats.norm.ppf(POWER))) / a}


def _t(a: float, prior: tuple, bf_min: float) -> float:
    """sqrt(bf_min + the Occam term, if positive) for a whitened effect ``a`` per unit switch."""
    occam = 2.0 * math.log(a * (prior[1] - prior[0]) / math.sqrt(2.0 * math.pi))
    return math.sqrt(bf_min + max(occam, 0.0))


def lr_at(det: dict, s: float) -> float:
    """The noise-free 2 ln LR nc(s) (module doc) at switch ``s`` from a :func:`detectable_switch` entry: the
    power law through the last two of its ``measured`` points (the one nearer s in log switch as reference),
    else (a s)^2."""
    pts = (det.get("measured") or [])[-2:]
    if not pts:
        return float(det["per_unit"] * s) ** 2
    s_ref, nc_ref = min(pts, key=lambda p: abs(math.log(p[0] / s)))
    return float(nc_ref * (s / s_ref) ** det["exponent"])


def _exponent(pts: list) -> float:
    """The power law's exponent through the last two measured (switch, nc) points, 2 with one (a linear effect)."""
    if len(pts) < 2 or min(p[1] for p in pts[-2:]) <= 0 or pts[-1][0] == pts[-2][0]:
        return 2.0
    k = math.log(pts[-1][1] / pts[-2][1]) / math.log(pts[-1][0] / pts[-2][0])
    return float(np.clip(k, *EXPONENT_RANGE))


def switch_for(pts: list, k: float, target: float) -> float:
    """The switch where the power law nc(s) = nc_ref (s / s_ref)^k reaches ``target``, the one of the last two
    measured points with nc nearer the target (in log) as reference; inf where neither nc is above 0."""
    pos = [p for p in pts[-2:] if p[1] > 0]
    if not pos:
        return math.inf
    s_ref, nc_ref = min(pos, key=lambda p: abs(math.log(p[1] / target)))
    return float(s_ref * (target / nc_ref) ** (1.0 / k))


def measured_threshold(pts: list, prior: tuple, bf_min: float, a_linear: float) -> dict:
    """switch_threshold's entry from the measured (switch, nc) points, in the order measured: the switches for
    t^2 and (t + Phi^-1(POWER))^2 of the power law through the last two (the newest, nearest the target; an
    earlier refit that stopped short of its minimum drops out), the Occam term at the last one's effective
    per-unit effect; ``per_unit`` is sqrt(nc) / s at the four-in-five switch, ``per_unit_linear`` the
    screening's a."""
    k = _exponent(pts)
    pos = [p for p in pts[-2:] if p[1] > 0]
    if not pos:
        return {**switch_threshold(0.0, prior, bf_min), "per_unit_linear": a_linear, "exponent": k,
                "measured": [list(p) for p in pts]}
    s_ref, nc_ref = pos[-1]
    t = _t(math.sqrt(nc_ref) / s_ref, prior, bf_min)
    s_det = switch_for(pts, k, t * t)
    s_pow = switch_for(pts, k, (t + float(stats.norm.ppf(POWER))) ** 2)
    return {"per_unit": (t + float(stats.norm.ppf(POWER))) / s_pow, "switch": s_det,
            "within_prior": bool(s_det <= prior[1]), "switch_power": s_pow, "per_unit_linear": a_linear,
            "exponent": k, "measured": [list(p) for p in pts]}


def _whitener(evaluator):
    """v (k,) or (k, n) raw residuals -> whitened by the likelihood's Cholesky factor (or its sigmas)."""
    chol = getattr(evaluator.likelihood, "chol", None)
    if chol is None:
        sig = np.asarray(evaluator.sigma, dtype=np.float64)
        return lambda v: v / sig.reshape((-1,) + (1,) * (np.ndim(v) - 1))
    L = chol.detach().cpu().numpy()
    return lambda v: solve_triangular(L, v, lower=True)


def broyden_mode(residuals, x_start: np.ndarray, J0: np.ndarray, bounds: np.ndarray, max_nfev: int = 12,
                 restarts: int = 2, ftol: float = 1e-3, rel_step: float = 1e-2) -> tuple:
    """(x (p,), r(x) (k,), the Jacobian's estimate there (k, p)): the minimum of |r(x)|^2 in the box by scipy's
    trust-region reflective least squares, the Jacobian ``J0`` (k, p; per unit of each parameter) updated by
    Broyden's rank-one rule from every pair of residuals evaluated (one solver member a step); where it stops,
    the Jacobian is taken again by forward differences (``rel_step`` of each range, p members) and it goes on
    from there, up to ``restarts`` times while that lowers |r|^2 by more than ``ftol`` of itself.
    ``residuals``: X (n, p) -> r (n, k); a failed member raises RuntimeError."""
    b = np.asarray(bounds, dtype=np.float64)
    scale = b[1] - b[0]

    def run(U: np.ndarray) -> np.ndarray:
        R = np.asarray(residuals(b[0] + np.atleast_2d(U) * scale), dtype=np.float64)
        if not np.all(np.isfinite(R)):
            raise RuntimeError("a member of the baseline's refit failed")
        return R

    st = {"u": None, "r": None, "J": np.asarray(J0, dtype=np.float64) * scale}

    def fun(u: np.ndarray) -> np.ndarray:
        r = run(u)[0]
        if st["u"] is not None:
            du = u - st["u"]
            nrm = float(du @ du)
            if nrm > 0:
                st["J"] = st["J"] + np.outer((r - st["r"]) - st["J"] @ du, du) / nrm
        st["u"], st["r"] = u.copy(), r
        return r

    u = np.clip((np.asarray(x_start, dtype=np.float64) - b[0]) / scale, 0.0, 1.0)
    best = None
    for attempt in range(restarts + 1):
        res = optimize.least_squares(fun, u, jac=lambda _: st["J"], bounds=(0.0, 1.0), method="trf", ftol=ftol,
                                     xtol=1e-4, gtol=1e-10, max_nfev=max_nfev, x_scale="jac")
        f = float(res.fun @ res.fun)
        if best is not None and f > best[0] * (1.0 - ftol):
            best = min(best, (f, res.x, res.fun), key=lambda t: t[0])
            break
        best = (f, res.x, res.fun)
        if attempt == restarts:
            break
        u = res.x
        h = np.where(u + rel_step <= 1.0, rel_step, -rel_step)
        R = run(np.vstack([u, u + np.diag(h)]))
        st["u"], st["r"], st["J"] = u.copy(), R[0], (R[1:] - R[0]).T / h
    return b[0] + best[1] * scale, best[2], st["J"] / scale


def baseline_gap(evaluator, x0: dict, at: dict, starts: dict, jacobians: dict, max_nfev: int = 12) -> dict:
    """{candidate: (nc(at[c]), the refitted baseline (p,), the whitened Jacobian there (k, p))} (module doc):
    one batch of the candidates' predictions at (x0, switch at[c]), then the baseline fitted to each of them
    (:func:`broyden_mode` from ``starts[c]`` with ``jacobians[c]``), all in lockstep (one solver call of one
    member per candidate a round, p at a restart); candidates whose prediction or fit failed are left out."""
    names = list(evaluator.prior.names)
    bounds = evaluator.prior.bounds.numpy().astype(np.float64)
    whiten = _whitener(evaluator)
    cands = list(at)
    parts = [(1, {**evaluator.fixed, **x0, CANDIDATES[c].param: at[c], **dict(CANDIDATES[c].fixed)}) for c in cands]
    preds, failed = evaluator.run_values(stack_values(parts))
    target = {c: preds[i] for i, c in enumerate(cands) if not failed[i]}
    off = {CANDIDATES[c].param: default_value(CANDIDATES[c].param) for c in cands}

    def evaluate(requests: list) -> list:
        y, bad = evaluator.run_values(stack_values(
            [(len(X), {**evaluator.fixed, **off, **{n: X[:, j] for j, n in enumerate(names)}}) for _, X in requests]))
        out, i = [], 0
        for c, X in requests:
            r = whiten((np.asarray(y[i:i + len(X)]) - target[c]).T).T
            out.append(np.where(np.asarray(bad[i:i + len(X)])[:, None], np.inf, r))
            i += len(X)
        return out

    ls = Lockstep(evaluate)

    def one(c):
        x, r, J = broyden_mode(lambda X: ls.ask((c, X)), starts[c], jacobians[c], bounds, max_nfev=max_nfev)
        return float(r @ r), x, J

    got = ls.map(one, list(target))
    return {c: v for c, v in zip(target, got) if not isinstance(v, BaseException)}


def detectable_switch(scr: ScreenResult, evaluator, bf_min: float, measure: bool = True) -> dict:
    """{candidate: {per_unit, switch, within_prior, switch_power[, per_unit_linear, exponent, measured]}}: the
    smallest switch these data reveal at bf_min (``switch``: in half the noise draws; ``switch_power``: in a
    share POWER), predicted from the screening and, with ``measure``, measured on the solver (module doc;
    ``measured``: the [switch, nc] points, ``exponent``: the power law's; each pass's fits start from the last
    refit's move of the baseline, scaled to the new switch). Failed members give None."""
    if scr.jacobian is None:
        return {c: None for c in scr.scores}
    whiten = _whitener(evaluator)
    Jb = whiten(scr.jacobian * np.asarray(evaluator.sigma)[:, None])
    Jbp = np.linalg.pinv(Jb)
    out, jcs = {}, {}
    for c in scr.scores:
        eff = scr.effects.get(c)
        if eff is None or c not in scr.steps:
            out[c] = None
            continue
        jcs[c] = whiten(np.asarray(eff) / scr.steps[c])
        a = float(np.linalg.norm(jcs[c] - Jb @ (Jbp @ jcs[c])))
        out[c] = switch_threshold(a, CANDIDATES[c].prior, bf_min)
    live = [c for c, d in out.items() if d and d["per_unit"] > 0]
    if not measure or not live or scr.y0 is None:
        return out
    names = list(evaluator.prior.names)
    lo, hi = evaluator.prior.bounds.numpy()
    x0 = np.array([scr.x0[n] for n in names])
    pts = {c: [] for c in live}
    at = {c: min(out[c]["switch_power"], CANDIDATES[c].prior[1]) for c in live}
    retune = {c: -(Jbp @ jcs[c]) for c in live}     # the baseline's move per unit switch (linear, then as refitted)
    jac = {c: Jb for c in live}
    for _ in range(PASSES):
        starts = {c: np.clip(x0 + retune[c] * s, lo, hi) for c, s in at.items()}
        for c, (nc, x, J) in baseline_gap(evaluator, scr.x0, at, starts, jac).items():
            pts[c].append((at[c], nc))
            retune[c], jac[c] = (x - x0) / at[c], J
        nxt = {}
        for c in at:
            if pts[c] and pts[c][-1][0] == at[c] and pts[c][-1][1] > 0:
                s = min(measured_threshold(pts[c], CANDIDATES[c].prior, bf_min, 0.0)["switch_power"],
                        CANDIDATES[c].prior[1])
                if abs(math.log(s / at[c])) > 0.05:
                    nxt[c] = s
        at = nxt
        if not at:
            break
    for c in live:
        if pts[c]:
            out[c] = measured_threshold(pts[c], CANDIDATES[c].prior, bf_min, out[c]["per_unit"])
    return out
