"""Mode check of a refit: a batched local search on the solver itself, from the refit's best runs.

A refit's active learning (24 runs in 3-D in the harness) can put its posterior on the wrong side of
a narrow ridge: on an entrainment recording the refit's 90 % interval of kappa was [0.00094, 0.00100],
z = -1451 at its posterior mean, while the solver gives z = -1364 at kappa = 0.0014 (truth 0.0015). Importance-sampling
verification cannot see such missing mass (its draws come from the proposal), so the pipeline checks
the mode directly: a (1+lambda) evolution strategy in the unit cube of the candidate's prior box,
several starts in one batched solver call per iteration. A search that beats the refit's best run,
or the best of its posterior draws, by more than a margin means the refit missed its mode
(pipeline.refit_candidate); its runs then join the local emulator of verify.refine_refit, so the
refined posterior is built where the mass is.
"""
from __future__ import annotations

import numpy as np
import torch


def _best_starts(X: np.ndarray, Z: np.ndarray, n: int, min_dist: float) -> list[int]:
    """Indices of up to ``n`` best runs, pairwise at least ``min_dist`` apart (unit-cube distance)."""
    order = np.argsort(-Z)
    picked: list[int] = []
    for i in order:
        if all(np.linalg.norm(X[i] - X[j]) >= min_dist for j in picked):
            picked.append(int(i))
        if len(picked) == n:
            break
    return picked


def local_search(ev_c, X: np.ndarray, Z: np.ndarray, bounds, n_iter: int = 4, pop: int = 8, n_starts: int | None = 2,
                 step0=None, seed: int = 0, hold=None, max_iter: int = 0, tol: float = 1.0, window: int = 4) -> dict:
    """Batched (1+lambda) local search of z = ln L + ln prior (the solver's, not the emulator's).

    ``ev_c``: the candidate's evaluator (callable on (n, p) points, returns .z, .failed).
    ``X`` (n, p), ``Z`` (n,): runs already made (physical units; failed ones as non-finite z).
    ``bounds`` (2, p): the prior box. ``step0``: (p,) initial step per axis in unit-cube units
    (default 0.05); each start keeps its own step, x1.5 after an improving iteration, x0.5 after one
    that did not improve. Each iteration: ``pop`` Gaussian moves per start, the first of them the
    start's last improving move repeated (a ridge is followed rather than re-found), all starts in
    one call of ``ev_c``. ``n_starts``: the best runs (pairwise >= 0.05 apart in the unit cube) the
    search starts from; None: every finite run of ``X`` is a start. ``hold``: (p,) bool, axes kept at
    each start's value (a search in the others: a profile, see profile.py). ``max_iter`` > ``n_iter``: the
    search goes on after ``n_iter`` iterations while it still climbs, i.e. while the best z of all starts rose by
    more than ``tol`` over the last ``window`` iterations, up to ``max_iter`` iterations in all (a narrow
    curved ridge is followed to its top instead of being left halfway). The window spans stalls: on a ridge the search often
    fails 2-3 iterations in a row (its steps halve) before it climbs on.
    Returns {x (m, p), z (m,), best_x, best_z, start_z, improvement, iters, trace}, with improvement =
    best_z - max(Z) (> 0: the search found a better point than every earlier run), iters the iterations
    made and trace (iters,) the best z of all starts after each.
    """
    b = np.asarray(bounds, float)
    lo, w = b[0], b[1] - b[0]
    ok = np.isfinite(Z)
    X, Z = np.asarray(X, float)[ok], np.asarray(Z, float)[ok]
    if not len(X):
        return {"x": np.zeros((0, b.shape[1])), "z": np.zeros(0), "best_x": None, "best_z": -np.inf,
                "start_z": -np.inf, "improvement": 0.0, "iters": 0, "trace": []}
    U = (X - lo) / w
    rng = np.random.default_rng(seed)
    p = b.shape[1]
    step = np.full(p, 0.05) if step0 is None else np.clip(np.asarray(step0, float), 1e-4, 0.25)
    starts = list(range(len(U))) if n_starts is None else _best_starts(U, Z, n_starts, min_dist=0.05)
    free = np.ones(p) if hold is None else (~np.asarray(hold, bool)).astype(float)
    cur_u = [U[i].copy() for i in starts]
    cur_z = [float(Z[i]) for i in starts]
    steps = [step.copy() for _ in starts]
    moves = [np.zeros(p) for _ in starts]
    start_z = float(Z.max())
    xs, zs, trace = [], [], []
    n_max = max(int(n_iter), int(max_iter or 0))
    for it in range(n_max):
        if it >= n_iter and trace[-1] - (trace[-1 - window] if len(trace) > window else start_z) <= tol:
            break
        cand = []
        for k in range(len(cur_u)):
            d = rng.standard_normal((pop, p)) * steps[k] * free
            if np.any(moves[k]):
                d[0] = moves[k]
            cand.append(np.clip(cur_u[k] + d, 0.0, 1.0))
        C = np.vstack(cand)
        r = ev_c(torch.as_tensor(lo + C * w))
        z = r.z.detach().cpu().numpy().astype(float)
        z[np.asarray(r.failed.detach().cpu().numpy(), bool)] = -np.inf
        xs.append(lo + C * w)
        zs.append(z)
        for k in range(len(cur_u)):
            zk = z[k * pop:(k + 1) * pop]
            j = int(np.argmax(zk))
            if zk[j] > cur_z[k]:
                moves[k] = C[k * pop + j] - cur_u[k]
                cur_u[k], cur_z[k] = C[k * pop + j].copy(), float(zk[j])
                steps[k] = np.minimum(steps[k] * 1.5, 0.25)
            else:
                moves[k] = np.zeros(p)
                steps[k] = np.maximum(steps[k] * 0.5, 1e-4)
        trace.append(max(start_z, max(cur_z)))
    if not xs:         # no iteration asked for (mode_search_iters = 0): no run, the best given one
        i = int(np.argmax(Z))
        return {"x": np.zeros((0, p)), "z": np.zeros(0), "best_x": X[i], "best_z": start_z, "start_z": start_z,
                "improvement": 0.0, "iters": 0, "trace": []}
    xa, za = np.vstack(xs), np.concatenate(zs)
    i = int(np.argmax(za))
    return {"x": xa, "z": za, "best_x": xa[i], "best_z": float(za[i]), "start_z": start_z,
            "improvement": float(za[i] - start_z), "iters": len(trace), "trace": [float(t) for t in trace]}
