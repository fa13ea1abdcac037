"""Cheap screening of candidate terms with ONE batched solver call.

At the baseline posterior mode x0 the batch holds: x0; x0 with each baseline parameter nudged
(mu by +5 %, xi by +20 %, others by +5 % of their prior width); x0 with each candidate switch set
to ``step_fraction`` of its prior upper bound (and the candidate's fixed values, e.g. phi_int).
Finite differences give the sensitivities J_b (baseline) and J_c (candidates) of every observable.
Everything is whitened by the effective sigmas. With A = [J_b] and P = I - A A^+ the projection onto
what re-tuning the baseline parameters cannot mimic, each candidate gets

    s_c = P J_c,     score_c = max(0, s_c . r)^2 / |s_c|^2     (r = whitened residual at x0)

the chi-square reduction a small positive switch buys after the baseline parameters re-tune (a
one-sided score test; 0 when the residual points the other way). ``mimic`` = 1 - |s_c|^2 / |J_c|^2
is the fraction of the candidate's signature that mu, xi can reproduce. ``jacobian`` (A) and
``residual`` (r) are kept for the subset-consistency test (consistency.py); with no candidates the
call is just that: p + 1 runs.

``linear_opt``: the linearised optimum of every candidate, the joint least-squares solution of
r = A db + J_c beta (beta > 0; None otherwise) as a point {name: value} of the candidate's model
(x0 + db, switch beta). The local path's candidate fits start from it (local_path.fit_candidate).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from .candidates import CANDIDATES
from .evaluator import stack_values


@dataclass
class ScreenResult:
    x0: dict
    scores: dict
    mimic: dict
    norms: dict
    effects: dict = field(default_factory=dict)
    ranking: list = field(default_factory=list)
    linear_opt: dict = field(default_factory=dict)
    n_members: int = 0
    steps: dict = field(default_factory=dict)   # the switch step of every candidate's member
    detectable: dict = field(default_factory=dict)  # power.detectable_switch() (set by the pipeline)
    failed: list = field(default_factory=list)
    jacobian: np.ndarray | None = None   # (k, p) whitened d y / d x of the baseline parameters at x0
    residual: np.ndarray | None = None   # (k,) whitened residual (d - y(x0)) / sigma
    y0: np.ndarray | None = None         # (k,) prediction at x0, raw units

    def to_json(self) -> dict:
        return {"x0": self.x0, "ranking": self.ranking,
                "candidates": {c: {"score": self.scores[c], "mimic": self.mimic[c], "signature_norm": self.norms[c],
                                   **({"detectable_switch": self.detectable[c]} if c in self.detectable else {})}
                               for c in self.scores}, "linear_opt": self.linear_opt, "n_members": self.n_members,
                "failed": self.failed}


def members(evaluator, x0: np.ndarray, candidates, step_fraction: float = 0.3) -> tuple[dict, dict]:
    """The screening batch at x0 (module doc): ({param: (n,) values}, {param or candidate: its step});
    member 0 is x0, then one per baseline parameter, then one per candidate."""
    names = list(evaluator.prior.names)
    bounds = evaluator.prior.bounds.numpy()
    base = {n: float(v) for n, v in zip(names, x0)}
    batch = [dict(base)]
    steps = {}
    for i, n in enumerate(names):
        m = dict(base)
        if n == "mu":
            h = 0.05 * base[n]
        elif n == "xi":
            h = 0.2 * base[n]
        else:
            h = 0.05 * (bounds[1, i] - bounds[0, i])
        if m[n] + h > bounds[1, i]:
            h = -h
        m[n] += h
        steps[n] = h
        batch.append(m)
    for c in candidates:
        cd = CANDIDATES[c]
        m = dict(base)
        h = step_fraction * cd.prior[1]
        m[cd.param] = h
        steps[c] = h
        for k, v in cd.fixed:
            m[k] = v
        batch.append(m)
    return stack_values([(1, {**evaluator.fixed, **m}) for m in batch]), steps


def screen(evaluator, x0: np.ndarray, candidates, step_fraction: float = 0.3) -> ScreenResult:
    """Rank ``candidates`` (names of physics.CANDIDATES) at x0 (baseline prior point) with one batch."""
    names = list(evaluator.prior.names)
    bounds = evaluator.prior.bounds.numpy()
    base = {n: float(v) for n, v in zip(names, x0)}
    values, steps = members(evaluator, x0, candidates, step_fraction)
    preds, failed = evaluator.run_values(values)
    w = 1.0 / evaluator.sigma
    y0 = preds[0]
    r = (evaluator.data - y0) * w
    J = {}
    for j, n in enumerate(names):
        J[n] = (preds[1 + j] - y0) * w / steps[n]
    A = np.stack([J[n] for n in names], axis=1) if names else np.zeros((len(r), 0))
    Ap = np.linalg.pinv(A)
    scores, mimic, norms, effects, lin = {}, {}, {}, {}, {}
    for i, c in enumerate(candidates):
        row = 1 + len(names) + i
        if failed[row] or failed[0]:
            scores[c], mimic[c], norms[c], lin[c] = 0.0, float("nan"), 0.0, None
            continue
        Jc = (preds[row] - y0) * w / steps[c]
        s = Jc - A @ (Ap @ Jc)
        ss = float(s @ s)
        jj = float(Jc @ Jc)
        sr = float(s @ r)
        scores[c] = (sr * sr / ss) if (ss > 0 and sr > 0) else 0.0
        mimic[c] = 1.0 - ss / jj if jj > 0 else float("nan")
        norms[c] = math.sqrt(ss) * steps[c]  # whitened size of the unmimickable effect of the step
        effects[c] = preds[row] - y0
        lin[c] = _linear_opt(A, Jc, r, names, base, bounds, CANDIDATES[c])
    ranking = sorted(candidates, key=lambda c: -scores[c])
    return ScreenResult(x0=base, scores=scores, mimic=mimic, norms=norms, effects=effects, ranking=ranking,
                        linear_opt=lin, n_members=len(preds), steps={c: steps[c] for c in candidates},
                        failed=[int(i) for i in np.nonzero(failed)[0]],
                        jacobian=None if failed[: 1 + len(names)].any() else A, residual=r,
                        y0=None if failed[0] else y0)


def _linear_opt(A: np.ndarray, Jc: np.ndarray, r: np.ndarray, names, base: dict, bounds: np.ndarray, cd):
    """Linearised optimum {name: value} of the baseline + candidate model (least squares of
    r = A db + Jc beta, whitened, (k,) each), the baseline parameters clipped to their prior box and
    beta to the switch's; None when the best beta is not positive."""
    sol, *_ = np.linalg.lstsq(np.column_stack([A, Jc]), r, rcond=None)
    beta = float(sol[-1])
    if not (np.isfinite(beta) and beta > 0):
        return None
    out = {n: float(np.clip(base[n] + sol[j], bounds[0, j], bounds[1, j])) for j, n in enumerate(names)}
    out[cd.param] = float(min(beta, cd.prior[1]))
    return out
