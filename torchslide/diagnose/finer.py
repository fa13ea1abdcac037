"""The finer-grid check: which of two supported candidates fits better on cells half as large?

On the harness' resolved terrain, inverted on 20 m cells, yield stress (tau_y) and rate-dependent
friction (mu_i) both gain strong evidence from a yield-stress recording; in 2 of 5 seeds mu_i came
out 16-25 ahead in 2 ln BF and was named. Both terms act where the flow slows down and stops, and
that is where the grid's own error is largest: the likelihood's model error (model_error) widens the
errors there, but it cannot say which term the grid's error looks like. Profiled on cells half as
large over the same inputs, the order flipped in both seeds (yield stress ahead by 9.2 and 10.4 in
ln; experiments/hidden_physics/finer_grid_profile.py).

The check, for a pair of candidates (decide.finer_pair: the two largest Bayes factors among those
that pass the evidence check, when one of them could be named): for each, the profile
z*(s) = max over (mu, xi) of ln L + ln prior along its switch s (profile.switch_profile: a ladder of
5 values over its refit's 90 % interval, a local search on the solver at each), with every run on
the finer grid (model_error.fine_run, seen on the inversion grid) and the likelihood of the
measurement errors alone (the finer runs are what the grid's model error stands for). The
comparison is max_s z*_A - max_s z*_B: a profile-likelihood ratio of two models with the same
number of parameters (the prior density of each switch's uniform prior is in z). decide() takes the
pair's order and its separation (2 x the ratio, against margin_min) from it instead of from the Bayes
factors; every other check stays the candidates' own.

Cost: 2 x (starts + n_values x (n_iter x pop + 1)) finer-grid runs, about 8 times an inversion-grid
run each in 2-D (4 times the cells, twice the steps): 6-14 min per candidate on one core for a
20 m inversion grid of the resolved terrain. So it is off by default (Budgets.finer_check).
"""
from __future__ import annotations

import dataclasses
import time

import numpy as np

from .model_error import fine_run
from .profile import switch_profile

N_STARTS = 32       # profile start points drawn around the refit (profile_starts)
MIN_HALF = 0.02     # the ladder's least half-width, fraction of the prior range (it follows the refit's interval)


def finer_grid_evaluator(ev, factor: int = 2):
    """A copy of the DiagnosisEvaluator ``ev`` (same prior, likelihood and observations) whose runs are
    on cells ``factor`` times smaller over the same inputs (model_error.fine_run)."""
    if int(factor) != factor or factor < 2:
        raise ValueError(f"finer-grid factor must be an integer >= 2, got {factor!r}")
    base = type(ev)

    class FinerGrid(base):
        def simulate(self, x):
            return fine_run(self, x, int(factor))

    kw = {f.name: getattr(ev, f.name) for f in dataclasses.fields(ev) if f.init and f.name not in ("records", "solver_seconds")}
    return FinerGrid(**kw)


def profile_starts(parameters: dict, names, bounds: np.ndarray, n: int = N_STARTS, seed: int = 0) -> np.ndarray:
    """(n, p) start points around a refit known by its reported ``parameters`` ({name: {mean, hdr90}},
    as in report.json, so the check can be rerun from a saved report): normal draws with the posterior
    mean and sd = (90 % interval width) / 3.3, clipped to ``bounds`` (2, p); ``names`` (p,) in the
    evaluator's order, the switch last."""
    missing = [k for k in names if k not in parameters or "mean" not in parameters[k] or "hdr90" not in parameters[k]]
    if missing:
        raise ValueError(f"refit parameters lack mean / hdr90 for {missing}")
    m = np.array([parameters[k]["mean"] for k in names], float)
    sd = np.array([(parameters[k]["hdr90"][1] - parameters[k]["hdr90"][0]) / 3.3 for k in names], float)
    b = np.asarray(bounds, float)
    return np.clip(m + sd * np.random.default_rng(seed).standard_normal((n, len(names))), b[0], b[1])


def finer_profile(ev_c, parameters: dict, factor: int = 2, seed: int = 0, n_values: int = 5, n_iter: int = 2,
                  pop: int = 6) -> dict:
    """Profile of one candidate along its switch on cells ``factor`` times smaller (module doc).
    ``ev_c``: the candidate's evaluator (its prior: baseline parameters + switch last) with the
    likelihood it should be compared in (the pipeline passes the measurement errors alone);
    ``parameters``: its refit's {name: {mean, hdr90}}. Returns {switch (n_values,), z (n_values,),
    best (switch at the maximum), z_max, runs, wall_s}."""
    names = list(ev_c.prior.names)
    b = ev_c.prior.bounds.numpy()
    draws = profile_starts(parameters, names, b, seed=seed)
    fine = finer_grid_evaluator(ev_c, factor)
    t0 = time.perf_counter()
    r = switch_profile(fine, draws, parameters[names[-1]]["hdr90"], b, n_values=n_values, n_iter=n_iter, pop=pop,
                       min_half=MIN_HALF, seed=seed)
    z = np.asarray(r["z"], float)
    if not np.isfinite(z).any():
        raise RuntimeError(f"finer-grid profile of {names[-1]}: every run failed")
    k = int(np.nanargmax(np.where(np.isfinite(z), z, -np.inf)))
    return {"switch": np.asarray(r["switch"], float).tolist(), "z": z.tolist(), "best": float(r["switch"][k]),
            "z_max": float(z[k]), "runs": len(fine.records), "wall_s": time.perf_counter() - t0}


def compare(z_max: dict, pair) -> dict:
    """The check's result for ``pair`` (A, B) from {name: max profile z}: {pair, z_max, leader,
    two_ln_ratio (2 (z*_leader - z*_other) >= 0)}."""
    a, b = pair
    d = 2.0 * (float(z_max[a]) - float(z_max[b]))
    return {"pair": [a, b], "z_max": {a: float(z_max[a]), b: float(z_max[b])},
            "leader": a if d >= 0 else b, "two_ln_ratio": abs(d)}
