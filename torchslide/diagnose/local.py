"""Local Gaussian inference on the solver: the posterior mode, the Laplace evidence, detectability.

Rich data (gauge series, deposit maps) give log-likelihoods in the thousands and posteriors far
narrower than the prior box; there the posterior is found by a local optimiser on the solver itself
and described by its Gaussian (Laplace) approximation, where a GP emulator over the whole box cannot
resolve the peak.

With whitened residuals r(x) = L^-1 (y(x) - d) (k,), Sigma = L L^T the likelihood's covariance, and
ln L(x) = c - |r(x)|^2 / 2 (c the Gaussian normaliser):

* ``jacobian``: J = dr/dx (k, p) by central differences, its 2p points in one batched solver call
  (one-sided where a step would leave the prior box).
* ``fit``: the mode of ln L + ln prior in the box by scipy.optimize.least_squares (trust-region
  reflective, bounds kept): one run per trial point, J from ``jacobian`` only where a step is accepted
  (most trial points near the mode are rejected: the trust region shrinks there until the step is below
  xtol).
* ``laplace_log_evidence``: ln Z = ln L(x*) + ln pi(x*) + (p/2) ln 2 pi - (1/2) ln det A
  + ln P_box, A = J^T J the Gauss-Newton precision and P_box the probability that N(x*, A^-1) gives to
  the prior box; for a mode on the box's edge (e.g. a candidate's switch at 0) the Gaussian is centred
  where the quadratic model of ln L peaks, beyond the edge, and only its part inside the box counts.
  Exact for a linear model with a uniform prior.
* ``profile_log_integral``: ln of the integral over a switch's range of exp(-D(s) / 2), D the profile
  likelihood's 2 ln drop from the mode measured at a few points: the switch's factor of the evidence
  where the profile is not the Laplace Gaussian (``profile_evidence_shift``).
* ``detectability``: for a candidate's switch s with nuisance parameters theta (mu, xi), the Fisher
  information of s after theta is re-tuned is the Schur complement
  I_s = J_s^T J_s - J_s^T J_t (J_t^T J_t)^-1 J_t^T J_s, so a switch s moves 2 ln of the likelihood ratio
  by s^2 I_s (exactly, for a linear model): the smallest detectable switch at a threshold T of
  2 ln BF is sqrt(T / I_s).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import numpy as np
from scipy import optimize, stats

Residuals = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]
"""X (n, p) -> (whitened residuals (n, k), failed (n,) bool): one batched call."""


@dataclass
class LocalFit:
    """The mode of a posterior and its Laplace approximation (physical units of the parameters).

    x: (p,) mode; log_like: ln L there (with the normaliser); jacobian: (k, p) dr/dx there;
    precision: (p, p) J^T J; covariance: its inverse; centre: (p,) the Gaussian's centre (x, or beyond
    the box where the mode sits on an active bound); log_evidence: the Laplace ln Z (module doc);
    n_runs: solver members used; converged: the optimiser's own test passed; message: its status.
    """

    x: np.ndarray
    log_like: float
    jacobian: np.ndarray
    precision: np.ndarray
    covariance: np.ndarray
    centre: np.ndarray
    log_evidence: float
    n_runs: int
    converged: bool
    message: str

    @property
    def sd(self) -> np.ndarray:
        return np.sqrt(np.diag(self.covariance))

    def interval(self, level: float = 0.9) -> np.ndarray:
        """(2, p) central ``level`` interval of each parameter under the Gaussian approximation."""
        q = stats.norm.ppf(0.5 + level / 2)
        return np.stack([self.x - q * self.sd, self.x + q * self.sd])

    def draws(self, n: int, bounds: np.ndarray, seed: int = 0) -> np.ndarray:
        """(n, p) draws of the Laplace Gaussian N(centre, covariance) truncated to the box (rejection in
        batches; a box that holds almost none of the Gaussian gives its draws clipped to the box)."""
        lo, hi = np.asarray(bounds, dtype=np.float64)
        rng = np.random.default_rng(seed)
        out = np.empty((0, self.x.size))
        for _ in range(20):
            d = rng.multivariate_normal(self.centre, self.covariance, size=max(64, 8 * n))
            out = np.vstack([out, d[np.all((d >= lo) & (d <= hi), axis=1)]])
            if len(out) >= n:
                return out[:n]
        d = rng.multivariate_normal(self.centre, self.covariance, size=n - len(out))
        return np.vstack([out, np.clip(d, lo, hi)])


def steps(bounds: np.ndarray, rel: float = 1e-3) -> np.ndarray:
    """(p,) finite-difference steps: ``rel`` of each prior range."""
    b = np.asarray(bounds, dtype=np.float64)
    return rel * (b[1] - b[0])


def residual(residuals: Residuals, x: np.ndarray) -> np.ndarray:
    """r(x) (k,) from one run at x (p,); a failed run raises RuntimeError."""
    x = np.asarray(x, dtype=np.float64)
    R, failed = residuals(x[None])
    if np.any(failed):
        raise RuntimeError(f"the run failed at x = {x.tolist()}")
    return R[0]


def jacobian(residuals: Residuals, x: np.ndarray, bounds: np.ndarray, h: np.ndarray) -> np.ndarray:
    """J (k, p) at x (p,) by central differences in one batched call of 2p points (x + h_i, x - h_i); a step
    that would leave the box is taken one-sided (forward or backward, still of size h)."""
    x = np.asarray(x, dtype=np.float64)
    p = x.size
    lo, hi = np.asarray(bounds, dtype=np.float64)
    plus, minus = np.minimum(x + h, hi), np.maximum(x - h, lo)
    X = np.repeat(x[None], 2 * p, axis=0)
    for i in range(p):
        X[2 * i, i] = plus[i]
        X[2 * i + 1, i] = minus[i]
    R, failed = residuals(X)
    if np.any(failed):
        raise RuntimeError(f"{int(np.sum(failed))} of the {2 * p} finite-difference runs failed at x = {x.tolist()}")
    return np.stack([(R[2 * i] - R[2 * i + 1]) / (plus[i] - minus[i]) for i in range(p)], axis=1)


def box_log_probability(x: np.ndarray, covariance: np.ndarray, bounds: np.ndarray) -> float:
    """ln P(lo <= X <= hi) for X ~ N(x, covariance) (scipy's multivariate normal CDF, in standardised
    coordinates so that parameters of very different scales keep a well-conditioned correlation; exact in 1-D)."""
    lo, hi = np.asarray(bounds, dtype=np.float64)
    x = np.asarray(x, dtype=np.float64)
    sd = np.sqrt(np.diag(covariance))
    a, b = (lo - x) / sd, (hi - x) / sd
    if x.size == 1:
        return float(np.log(stats.norm.cdf(b[0]) - stats.norm.cdf(a[0])))
    corr = covariance / np.outer(sd, sd)
    mvn = stats.multivariate_normal(mean=np.zeros(x.size), cov=0.5 * (corr + corr.T), allow_singular=False)
    return float(np.log(mvn.cdf(b, lower_limit=a)))


def laplace_log_evidence(log_like: float, log_prior: float, precision: np.ndarray, x: np.ndarray,
                         bounds: np.ndarray) -> float:
    """The Laplace ln Z of the module docstring (uniform prior density ``exp(log_prior)`` on ``bounds``)."""
    p = precision.shape[0]
    sign, logdet = np.linalg.slogdet(precision)
    if sign <= 0:
        raise np.linalg.LinAlgError("the precision J^T J is not positive definite: a parameter the data do not inform")
    cov = np.linalg.inv(precision)
    cov = 0.5 * (cov + cov.T)
    return float(log_like + log_prior + 0.5 * p * math.log(2 * math.pi) - 0.5 * logdet
                 + box_log_probability(x, cov, bounds))


def fit(residuals: Residuals, x0: np.ndarray, bounds: np.ndarray, log_norm: float, log_prior: float,
        rel_step: float = 3e-3, max_iter: int = 30, ftol: float = 1e-6, xtol: float = 1e-6) -> LocalFit:
    """The mode in the prior box by trust-region least squares on the solver, and its Laplace fit.

    ``residuals``: batched whitened residuals (Residuals); ``log_norm``: the likelihood's normaliser c
    (ln L = c - |r|^2 / 2); ``log_prior``: ln pi, constant in the box (uniform prior). ``rel_step``:
    finite-difference step as a share of each prior range; a solver's outputs are smooth in the
    parameters only above its time-step noise (a small chute case stalled at 1e-3 and converged in 16
    evaluations at 3e-3); ``max_iter``: most trial points (runs of the residuals); ``ftol``:
    stop when |r|^2 / 2 falls by less than this share of itself (1e-6 of a misfit of thousands is a
    thousandth of a nat); ``xtol``: ... or the step is below this share of the prior range."""
    b = np.asarray(bounds, dtype=np.float64)
    h = steps(b, rel_step)
    scale = b[1] - b[0]
    n_runs = 0
    seen: dict = {}         # trial point (unit box) -> [r, J or None]

    def at(u: np.ndarray, with_jacobian: bool) -> list:
        nonlocal n_runs
        key = tuple(np.round(u, 15))
        if key not in seen:
            seen[key] = [residual(residuals, b[0] + u * scale), None]
            n_runs += 1
        if with_jacobian and seen[key][1] is None:
            seen[key][1] = jacobian(residuals, b[0] + u * scale, b, h)
            n_runs += 2 * u.size
        return seen[key]

    u0 = np.clip((np.asarray(x0, dtype=np.float64) - b[0]) / scale, 0.0, 1.0)
    res = optimize.least_squares(lambda u: at(u, False)[0], u0, jac=lambda u: at(u, True)[1] * scale,
                                 bounds=(0.0, 1.0), method="trf", xtol=xtol, ftol=ftol, gtol=1e-10,
                                 max_nfev=max_iter, x_scale="jac")
    x = b[0] + res.x * scale
    r, J = at(res.x, True)
    A = J.T @ J
    log_like = float(log_norm - 0.5 * r @ r)
    cov = np.linalg.inv(A)
    cov = 0.5 * (cov + cov.T)
    # on an active bound the gradient J^T r is not 0: the Gaussian's centre lies beyond the bound, at
    # x - A^-1 J^T r, where the quadratic model of ln L is higher by (J^T r)^T A^-1 (J^T r) / 2; only the
    # components on a bound (pushing outwards) count: inside, the gradient left is the optimiser's tolerance
    g = J.T @ r
    g = np.where(((res.x <= 1e-9) & (g > 0)) | ((res.x >= 1 - 1e-9) & (g < 0)), g, 0.0)
    step = np.linalg.solve(A, g)
    log_z = laplace_log_evidence(log_like + 0.5 * float(g @ step), log_prior, A, x - step, b)
    return LocalFit(x=x, log_like=log_like, jacobian=J, precision=A, covariance=cov, centre=x - step, log_evidence=log_z,
                    n_runs=n_runs, converged=bool(res.success), message=str(res.message))


def switch_information(J: np.ndarray, switch: int) -> float:
    """Fisher information of parameter ``switch`` after the others are re-tuned: the Schur complement
    of J^T J (module doc)."""
    J = np.asarray(J, dtype=np.float64)
    s = J[:, switch]
    T = np.delete(J, switch, axis=1)
    if T.shape[1] == 0:
        return float(s @ s)
    coef, *_ = np.linalg.lstsq(T, s, rcond=None)
    resid = s - T @ coef
    return float(resid @ resid)


def detectable_switch(J: np.ndarray, switch: int, threshold: float = 6.0) -> float:
    """The smallest switch value whose effect the data can reveal at 2 ln BF = ``threshold``:
    sqrt(threshold / I_s) (inf when the data carry no information on it)."""
    info = switch_information(J, switch)
    return math.sqrt(threshold / info) if info > 0 else math.inf


def profile_log_integral(points, mode: float, bounds, n: int = 4001) -> float:
    """ln of the integral over ``bounds`` (lo, hi) of exp(-D(s) / 2), the profile likelihood of a switch s
    relative to its ``mode``: D (the 2 ln drop from the mode; a negative one, a point within the fit's
    tolerance above it, taken as 0) known at ``points`` [(s, D)]; sqrt(D) is interpolated linearly in s
    between the points of each side of the mode (a running maximum outwards: the drop cannot fall again),
    continued past the outermost one along the secant from the mode (a Gaussian tail as wide as that point
    says), on ``n`` points (trapezoid rule). Exact for a quadratic profile, even one of different widths on
    the two sides."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    lo, hi = float(bounds[0]), float(bounds[1])
    m = float(mode)
    s = np.linspace(lo, hi, n)
    r = np.zeros_like(s)
    for side in (-1.0, 1.0):
        q = pts[(pts[:, 0] - m) * side > 0]
        q = q[np.argsort(np.abs(q[:, 0] - m))]
        dist = np.concatenate([[0.0], np.abs(q[:, 0] - m)])
        root = np.maximum.accumulate(np.concatenate([[0.0], np.sqrt(np.maximum(q[:, 1], 0.0))]))
        on = (s - m) * side >= 0
        d = np.abs(s[on] - m)
        tail = root[-1] / dist[-1] * d if dist[-1] > 0 else np.zeros_like(d)
        r[on] = np.where(d <= dist[-1], np.interp(d, dist, root), tail)
    return float(np.log(np.trapezoid(np.exp(-0.5 * r * r), s)))


def profile_evidence_shift(points, centre: float, sd: float, bounds) -> float:
    """ln Z_profile - ln Z_Laplace of a switch whose profile likelihood is measured at ``points`` [(s, D)]
    (``profile_log_integral``, about the mode ``centre``): the Laplace evidence integrates the profile as the
    Gaussian of the switch's marginal (``centre``, ``sd``: 1 / sd^2 is its Schur complement, det A = det A_bb
    / sd^2) over ``bounds``; the measured profile replaces that factor, the nuisance parameters' Gaussian
    kept (their precision taken as constant along the profile). 0 for a quadratic profile of that width."""
    lo, hi = float(bounds[0]), float(bounds[1])
    gauss = math.log(math.sqrt(2.0 * math.pi) * sd
                     * max(stats.norm.cdf((hi - centre) / sd) - stats.norm.cdf((lo - centre) / sd), 1e-300))
    return profile_log_integral(points, centre, bounds) - gauss
