"""Where one more recording would reveal each candidate term best (the paper's conclusion asks where
to place sensors).

At the baseline's mode x0 one batched call runs the screening's members (screen.members: x0, each
baseline parameter nudged, each candidate's switch stepped) and keeps their maps. With F the Fisher
information of the recorded observations (their whitened finite-difference Jacobian J over the
baseline parameters theta and the candidate's switch s, the likelihood's own covariance), a new gauge
at cell c that records the peak flow thickness and the peak speed there with errors sigma_h, sigma_v
adds g_c^T g_c (g_c: its whitened sensitivities, 2 x (p + 1)). The switch's information after theta
re-tunes is the Schur complement

    I_s(c) = F_ss - F_st F_tt^-1 F_ts,     F = J^T J + g_c^T g_c,

and the smallest switch the data would reveal at 2 ln BF = T is sqrt(T / I_s(c)) (local.detectable_switch
for the recorded data alone). Cells are ranked by it. Linearised at x0 over the screening's steps: a
guide to where a sensor pays, not a guarantee.

``discriminate`` asks the same of two candidates A and B that the evidence does not separate ("A or B"):
the switch of A whose effect B's switch cannot mimic, with theta and B's switch both re-tuned (the Schur
complement over theta and s_B), and the same for B against A: where one more gauge tells them apart.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from .screen import members


@dataclass
class Design:
    """For each candidate: ``now`` the smallest detectable switch with the recorded data, ``maps``
    (ny, nx) the same with one more gauge at each cell (inf where the data carry no information),
    ``best`` the top cells [{x, y, row, col, switch}]; ``sigma_h`` (m), ``sigma_v`` (m/s) the new gauge's
    errors, ``threshold`` the 2 ln BF level."""

    now: dict
    maps: dict
    best: dict
    sigma_h: float
    sigma_v: float
    threshold: float

    def to_json(self) -> dict:
        fin = lambda v: None if not math.isfinite(v) else float(v)
        return {"threshold_two_ln_bf": self.threshold, "new_gauge_sigma": {"h": self.sigma_h, "speed": self.sigma_v},
                "candidates": {c: {"detectable_now": fin(self.now[c]),
                                   "best_new_gauges": [{**b, "switch": fin(b["switch"])} for b in self.best[c]]}
                               for c in self.now}}


def _schur(F: np.ndarray) -> np.ndarray:
    """(..., q, q) Fisher matrices, the switch last -> (...,) its information after the others re-tune."""
    Ftt, Fts, Fss = F[..., :-1, :-1], F[..., :-1, -1:], F[..., -1, -1]
    sol = np.linalg.solve(Ftt + 1e-12 * np.eye(Ftt.shape[-1]) * np.trace(Ftt, axis1=-2, axis2=-1)[..., None, None],
                          Fts)
    return np.maximum(Fss - (Fts * sol).sum(axis=(-2, -1)), 0.0)


def _detectable(info: np.ndarray, threshold: float) -> np.ndarray:
    with np.errstate(divide="ignore"):
        return np.where(info > 0, np.sqrt(threshold / np.where(info > 0, info, 1.0)), np.inf)


def _sensitivities(evaluator, x0: np.ndarray, candidates, sigma_h: float, sigma_v: float, step_fraction: float):
    """(dW (n - 1, k) whitened sensitivities of the recorded data, gh and gv (n - 1, ny, nx) of a new gauge's
    peak depth and speed, failed (n,)) of the screening's members at x0: rows the baseline parameters, then
    ``candidates``' switches."""
    if not (sigma_h > 0 and sigma_v > 0):
        raise ValueError(f"the new gauge's errors must be > 0, got sigma_h = {sigma_h!r}, sigma_v = {sigma_v!r}")
    names = list(evaluator.prior.names)
    p = len(names)
    values, steps = members(evaluator, x0, candidates, step_fraction)
    preds, failed, hmax, vmax = [], [], [], []
    for res in evaluator.simulate_values(values):
        y, f, _ = evaluator.predict(res)
        preds.append(y.numpy())
        failed.append(f.numpy())
        hmax.append(res.h_max.double().cpu().numpy())
        vmax.append(res.v_max.double().cpu().numpy())
    preds, failed = np.concatenate(preds), np.concatenate(failed)
    hmax, vmax = np.concatenate(hmax), np.concatenate(vmax)
    if failed[: 1 + p].any():
        raise RuntimeError("a run of the design's baseline members failed at x0 = " + str(np.round(x0, 6).tolist()))
    W = evaluator.likelihood.whiten(torch.as_tensor(preds)).numpy()    # (n, k) whitened predictions
    st = np.array([steps[n] for n in names] + [steps[c] for c in candidates])   # member m + 1's step
    dW = (W[1:] - W[0]) / st[:, None]                                   # (n - 1, k)
    gh = (hmax[1:] - hmax[0]) / st[:, None, None] / sigma_h             # (n - 1, ny, nx)
    gv = (vmax[1:] - vmax[0]) / st[:, None, None] / sigma_v
    return dW, gh, gv, failed


def _answer(dW, gh, gv, rows: list, threshold: float, top: int, dem) -> tuple:
    """(detectable now, map with one more gauge per cell, best cells) of the switch in ``rows``' last place,
    the others (the nuisance: theta, or theta and a rival's switch) re-tuned."""
    J = dW[rows].T                                                      # (k, q)
    F0 = J.T @ J
    G = np.moveaxis(np.stack([gh[rows], gv[rows]], axis=0), (2, 3), (0, 1))   # (ny, nx, 2, q)
    F = F0 + np.einsum("yxaq,yxar->yxqr", G, G)
    m = _detectable(_schur(F), threshold)
    flat = np.argsort(m, axis=None)[:top]
    best = [{"row": int(r), "col": int(k), "x": dem.cell_centre(int(r), int(k))[0],
             "y": dem.cell_centre(int(r), int(k))[1], "switch": float(m[r, k])}
            for r, k in zip(*np.unravel_index(flat, m.shape))]
    return float(_detectable(_schur(F0), threshold)), m, best


def design(evaluator, x0: np.ndarray, candidates, sigma_h: float = 0.5, sigma_v: float = 2.0,
           threshold: float = 6.0, top: int = 5, step_fraction: float = 0.3) -> Design:
    """The design of the module doc at the baseline point x0 (p,) for ``candidates``."""
    p = len(evaluator.prior.names)
    dW, gh, gv, failed = _sensitivities(evaluator, x0, candidates, sigma_h, sigma_v, step_fraction)
    now, maps, best = {}, {}, {}
    for i, c in enumerate(candidates):
        if failed[1 + p + i]:
            now[c], maps[c], best[c] = math.inf, np.full(gh.shape[1:], np.inf), []
            continue
        now[c], maps[c], best[c] = _answer(dW, gh, gv, list(range(p)) + [p + i], threshold, top, evaluator.dem)
    return Design(now=now, maps=maps, best=best, sigma_h=float(sigma_h), sigma_v=float(sigma_v),
                  threshold=float(threshold))


def discriminate(evaluator, x0: np.ndarray, a: str, b: str, sigma_h: float = 0.5, sigma_v: float = 2.0,
                 threshold: float = 6.0, top: int = 5, step_fraction: float = 0.3) -> Design:
    """Where one more gauge separates candidates ``a`` and ``b`` (module doc): a Design whose entries
    "a|b" and "b|a" give the smallest switch of the first that the second (with theta) cannot mimic."""
    if a == b:
        raise ValueError(f"discriminate needs two different candidates, got {a!r} twice")
    p = len(evaluator.prior.names)
    dW, gh, gv, failed = _sensitivities(evaluator, x0, [a, b], sigma_h, sigma_v, step_fraction)
    now, maps, best = {}, {}, {}
    for s_, o_, (name, other) in ((p, p + 1, (a, b)), (p + 1, p, (b, a))):
        key = f"{name}|{other}"
        if failed[1 + p] or failed[2 + p]:
            now[key], maps[key], best[key] = math.inf, np.full(gh.shape[1:], np.inf), []
            continue
        now[key], maps[key], best[key] = _answer(dW, gh, gv, list(range(p)) + [o_, s_], threshold, top,
                                                 evaluator.dem)
    return Design(now=now, maps=maps, best=best, sigma_h=float(sigma_h), sigma_v=float(sigma_v),
                  threshold=float(threshold))
