"""Subset consistency: do the observations agree on the baseline's parameters? (docs/diagnosis.md)

A structural error often shows as observation groups that want different parameters: one (mu, xi)
cannot match the gauges' peak speed and the deposit's run-out together (rate-dependent friction), or
the deposit map and the final volume disagree (entrainment). Calibrating every group separately costs
a calibration each; here the test is linearised at a baseline point x0 (p parameters), with the
whitened Jacobian A (k, p) of the observables and the whitened residual r (k,) at x0 (both from
screen.screen: one batch of p + 1 runs). For each observation (block b) against all the others:

    T_b = min_d |r - A d|^2 - min_d |r_b - A_b d|^2 - min_d |r_rest - A_rest d|^2   (>= 0)

the chi-square a common parameter shift costs over separate shifts for b and the rest. With a
consistent linear-Gaussian model T_b ~ chi2(df), df = rank(A_b) + rank(A_rest) - rank(A) (the
split-sample or parameter-consistency test of least squares). A block is flagged when its p-value is
below ``alpha`` / (number of blocks) (Bonferroni). The parameters each side wants (x0 + d) are
reported where that side determines all p of them.

It is a diagnostic of *where*, not part of the verdict: its null distribution is only as good as the
linearisation and the error model (the whitening is by the effective sigmas: with the grid's
approximation error in the evaluator, its variance is in them, its correlations between values are
not), and it was not calibrated on null data as the decision's thresholds were. On the 40 m harness
the grid's own error made an observation disagree in 9 of 10 null cases.
"""
from __future__ import annotations

import numpy as np
from scipy.stats import chi2


def _fit(A: np.ndarray, r: np.ndarray, tol: float = 1e-9) -> tuple[float, np.ndarray, int]:
    """(min |r - A d|^2, argmin d (minimum norm), rank of A) of a whitened least-squares problem."""
    if A.size == 0 or len(r) == 0:
        return float(r @ r), np.zeros(A.shape[1]), 0
    d, _, rank, _ = np.linalg.lstsq(A, r, rcond=tol)
    res = r - A @ d
    return float(res @ res), d, int(rank)


def subset_consistency(blocks, A: np.ndarray, r: np.ndarray, names, x0, alpha: float = 0.01) -> list[dict]:
    """Per block (objects with ``name`` and ``slice`` into the k values): its consistency with the rest.

    ``A``: (k, p) whitened Jacobian d y / d x at ``x0`` ((p,) values of ``names``); ``r``: (k,)
    whitened residual (d - y(x0)) / sigma. Returns one dict per block: block, k (its values),
    statistic T_b, df, p_value, conflict (p_value < alpha / n_blocks), wants / rest_wants ({name:
    x0 + d} when that side has rank p, else None), sorted by p-value (smallest first)."""
    A = np.asarray(A, float)
    r = np.asarray(r, float)
    x0 = np.asarray(x0, float)
    if A.ndim != 2 or A.shape[0] != len(r) or A.shape[1] != len(names) or len(x0) != len(names):
        raise ValueError(f"subset_consistency: A {A.shape}, r {r.shape}, x0 {x0.shape} and names {list(names)} "
                         "do not match")
    p = A.shape[1]
    chi_all, _, rank_all = _fit(A, r)
    n_blocks = max(1, len(blocks))
    out = []
    for b in blocks:
        m = np.zeros(len(r), bool)
        m[b.slice] = True
        chi_b, d_b, rank_b = _fit(A[m], r[m])
        chi_o, d_o, rank_o = _fit(A[~m], r[~m])
        df = rank_b + rank_o - rank_all
        T = max(0.0, chi_all - chi_b - chi_o)
        pv = float(chi2.sf(T, df)) if df > 0 else 1.0
        wants = lambda d, rk: ({n: float(v) for n, v in zip(names, x0 + d)} if rk == p else None)
        out.append({"block": b.name, "k": int(m.sum()), "statistic": T, "df": int(df), "p_value": pv,
                    "conflict": bool(df > 0 and pv < alpha / n_blocks), "wants": wants(d_b, rank_b),
                    "rest_wants": wants(d_o, rank_o)})
    return sorted(out, key=lambda e: e["p_value"])
