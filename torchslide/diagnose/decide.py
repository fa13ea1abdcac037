"""The verdict: "missing_physics" | "no_missing_physics" | "unexplained".

Rules (thresholds in :class:`Thresholds`, defaults set from null harness runs, see
experiments/hidden_physics/README.md):

1. A candidate is *supported* when 2 ln BF against the baseline >= ``bf_min`` and its refit reduces
   the misfit.
2. The best supported candidate is named ("missing_physics") only when, after its refit, no located
   mismatch remains above ``located_min`` (adequacy); its lead over the runner-up (2 ln BF) is
   reported, and ``ambiguous`` is set when it is below ``margin_min``.
3. Otherwise, when the baseline left located mismatches above ``located_min``: "unexplained"
   (located, but no library term explains it: never a forced label).
4. Otherwise "no_missing_physics".
"""
from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np


@dataclass
class Thresholds:
    bf_min: float = 6.0         # 2 ln BF vs the baseline to support a candidate
    margin_min: float = 6.0     # 2 ln BF over the runner-up for an unambiguous name
    located_min: float = 8.0    # |standardised residual| of a located mismatch that counts (null runs: up to ~6.6)
    z_threshold: float = 3.0    # per-value / cluster / window detection level (localisation)

    def to_json(self) -> dict:
        return asdict(self)


def significant(located: list, th: Thresholds) -> list:
    return [l for l in located if abs(l["standardised_residual"]) >= th.located_min]


def decide(candidates: list, located_before: list, located_after: dict, misfit_before: float,
           misfit_after: dict, th: Thresholds) -> dict:
    """candidates: [{name, log_bayes_factor}], located_after: name -> located list after its refit,
    misfit_after: name -> misfit of its refit. Returns {verdict, missing_physics, ambiguous, reason, ...}."""
    scored = sorted([c for c in candidates if c.get("log_bayes_factor") is not None
                     and np.isfinite(c["log_bayes_factor"])], key=lambda c: -c["log_bayes_factor"])
    sig_before = significant(located_before, th)
    out = {"verdict": None, "missing_physics": None, "ambiguous": False, "runner_up": None,
           "two_ln_bf": None, "two_ln_bf_over_runner_up": None, "reason": ""}
    best = scored[0] if scored else None
    if best is not None:
        tl = 2 * best["log_bayes_factor"]
        out["two_ln_bf"] = tl
        if len(scored) > 1:
            out["runner_up"] = scored[1]["name"]
            out["two_ln_bf_over_runner_up"] = 2 * (best["log_bayes_factor"] - max(scored[1]["log_bayes_factor"], 0.0))
        else:
            out["two_ln_bf_over_runner_up"] = tl
        improves = misfit_after.get(best["name"], np.inf) < misfit_before
        if tl >= th.bf_min and improves:
            left = significant(located_after.get(best["name"], []), th)
            if not left:
                out.update(verdict="missing_physics", missing_physics=best["name"],
                           ambiguous=out["two_ln_bf_over_runner_up"] < th.margin_min,
                           reason=f"{best['name']}: 2 ln BF = {tl:.1f} >= {th.bf_min}, no located mismatch left")
                return out
            out.update(verdict="unexplained",
                       reason=f"{best['name']} is supported (2 ln BF = {tl:.1f}) but leaves {len(left)} located "
                              f"mismatch(es) above {th.located_min}: not named")
            return out
    why = (f"no candidate reaches 2 ln BF >= {th.bf_min}" if best is None or out["two_ln_bf"] < th.bf_min else
           f"{best['name']} reaches 2 ln BF = {out['two_ln_bf']:.1f} but does not reduce the misfit")
    if sig_before:
        out.update(verdict="unexplained",
                   reason=f"{len(sig_before)} located mismatch(es) above {th.located_min}; {why}")
    else:
        out.update(verdict="no_missing_physics", reason=f"no located mismatch above {th.located_min}; {why}")
    return out
