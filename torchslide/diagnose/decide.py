"""The verdict: "missing_physics" (one term, or "A or B") | "no_missing_physics" | "unexplained".

Every refitted candidate gets these checks (the statistics come from torchslide.diagnose.verify and
are computed from *solver runs* at posterior draws, not from the emulator alone):

* ``reliable``: its verified evidence rests on an importance-sampling ESS >= ``ess_min`` draws (and
  so does the baseline's); on the local path (local_path.py) both local fits converged;
* ``likelihood_ratio`` (local path only): the boundary-corrected p-value of 2 ln(L_c / L_0) is at
  most ``lr_alpha``;
* ``evidence``: the lower bound 2 ln BF - 2 * 2 se (verified evidences, bootstrap standard errors of
  both) >= ``bf_min``;
* ``savage_dickey``: the Savage-Dickey 2 ln BF at switch = 0 is > 0 (same sign as the evidence);
* ``predictive``: out-of-sample check, 2 (elpd_WAIC(candidate) - elpd_WAIC(baseline)) >= ``waic_min``;
* ``misfit``: the misfit of its posterior-predictive mean is below the baseline's;
* ``within_range`` (candidates with an open range, e.g. release_volume): the switch's 90 % interval
  stays below the end of its range (a fit at the end: the data want more than the range allows);
* ``explains``: the baseline's significant located mismatches (|score| >= ``located_min``), re-scored at
  the same places with the candidate's predictive draws, lose >= ``explain_min`` of their sum of squared
  scores, and no located mismatch stays above ``located_min`` (none significant: passes; a mismatch at
  the noise's level is not one a term must remove).

Rules:

0. Candidates that fail ``within_range`` (a fit at the end of a budget range: the data want more of the
   term than its range allows, so it does not explain them as that term) are set aside (``set_aside``)
   while another candidate remains; the rules below apply to the others. One set aside with more
   evidence than the candidate rule 1 would name stays an alternative to it ("A or B": the data do not
   tell a term beyond its range from one within).
1. The candidate with the largest verified 2 ln BF is named ("missing_physics") when it passes all
   checks and nothing else competes with it:
   * no other candidate that also passes ``evidence`` is within ``margin_min`` of its 2 ln BF (the
     blind test's "2 ln BF >= 6 over the runner-up"; a close runner-up that fails another check, e.g. its
     Savage-Dickey sign, still means the evidence does not separate the two), and
   * no other candidate that passes ``explains`` explains a fraction of the located mismatch larger by
     ``explain_margin`` or more (the evidence and the located structure must point at the same term).
   Otherwise "missing_physics" with ``missing_physics`` = "A or B" (``alternatives`` [A, B, ...],
   ``ambiguous`` = True, the competitors listed): never a guess between terms that the data do not
   separate, and never a single name (the pipeline adds ``separate``: the observations where the
   alternatives' refits differ most, the data that would tell them apart).
   A candidate that fails only ``explains`` but removes at least ``explain_partial_min`` of the located
   structure is named the same way with ``partial`` = True: ``explained_share`` says how much it removes,
   ``remainder`` lists the located mismatches it leaves above ``located_min`` (what, where, score before
   and after), reported as unexplained (a recording that differs from the model in more than one way).
2. Otherwise, when that candidate passes ``evidence`` and the baseline leaves a mismatch (a located one
   with |score| >= ``located_min`` or a fit flag): "unexplained" (located / supported, but no library term
   passes every check: never a forced label). An evidence gain that fails a check where the baseline
   leaves no mismatch is what discretisation alone produces on null data: "no_missing_physics".
3. Otherwise: "unexplained" when a located mismatch has |score| >= ``located_min``, else
   "no_missing_physics".

Fit flags (``fit_max``, off by default): an observable whose Z_fit under the calibrated baseline (its
posterior-predictive residual whitened with the likelihood's full covariance,
torchslide.diagnose.localise.block_fit; taken before the refits can refine the baseline, so that it is
the statistic the levels are set on) exceeds ``fit_max`` (one level for every observable, or a dict
{observable: level}) is a mismatch at the level of the whole observable. It counts like a significant located mismatch in
rules 2 and 3: it turns "no_missing_physics" into "unexplained", and never names a term. The levels
must be set on null data of the same design (torchslide.diagnose.null sets them per observable from
null runs: each observable's Z_fit differs on null data, e.g. -36 for a
deposit map whose sigma is wide and +3 for a gauge series the grid misses).

``bf_min``, ``waic_min`` and ``located_min`` are set on null data (no hidden term; see
torchslide.diagnose.null, ``torchslide diagnose --null-runs N``); ``margin_min`` = 6 is
Kass & Raftery's "strong" level; ``explain_min`` and ``ess_min`` are fixed a priori.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np


@dataclass
class Thresholds:
    bf_min: float = 6.0         # lower bound of verified 2 ln BF vs the baseline to support a candidate
    margin_min: float = 6.0     # 2 ln BF over the runner-up for an unambiguous name
    located_min: float = 8.0    # |score| of a located mismatch that counts as significant
    waic_min: float = 6.0       # 2 (elpd_WAIC candidate - baseline) for the out-of-sample check
    explain_min: float = 0.5    # fraction of the located structure (sum of squared scores) a named term must remove
    explain_partial_min: float = 0.25  # a term that passes every other check and removes this fraction is named
                                       # with the rest of the located mismatch reported as unexplained
    explain_margin: float = 0.1  # how much more of the located structure another candidate must remove to contest
                                 # the best-supported term's name ("A or B"; 0.99 against 0.98 does not)
    ess_min: float = 2.0        # importance-sampling ESS (draws) for a verified evidence to count
    z_threshold: float = 3.0    # per-value / cluster / window detection level (localisation)
    fit_max: float | dict | None = None  # Z_fit of an observable above which its fit is a mismatch (None: off)
    lr_alpha: float = 0.01      # local path: largest boundary-corrected p-value of the likelihood ratio

    def to_json(self) -> dict:
        return asdict(self)


def _significant_items(c: dict, th: Thresholds) -> list:
    """The re-scored located mismatches of candidate ``c`` that were significant before (|score| >= located_min)."""
    return [i for i in (c.get("located_rescored") or {}).get("items") or () if abs(i["before"]) >= th.located_min]


def _explained(c: dict, th: Thresholds) -> float:
    """The share of the significant located mismatches' sum of squared scores that ``c`` removes (1 - after /
    before); 1 when none was significant; -inf when ``c`` has no re-scored mismatches (it never contests)."""
    rs = c.get("located_rescored") or {}
    if not rs.get("items"):
        return float("-inf")
    items = _significant_items(c, th)
    if not items:
        return 1.0
    before = sum(i["before"] ** 2 for i in items)
    return 1.0 - sum(i["after"] ** 2 for i in items) / before


def remainder(c: dict, located_before: list, th: Thresholds) -> list:
    """The located mismatches candidate ``c`` leaves at |score| >= located_min: [{what, where, before, after}]."""
    where = {l.get("what"): l.get("where") for l in located_before}
    return [{"what": i.get("what"), "where": where.get(i.get("what")), "before": float(i["before"]),
             "after": float(i["after"])}
            for i in (c.get("located_rescored") or {}).get("items", []) if abs(i["after"]) >= th.located_min]


def _describe(r: dict) -> str:
    return f"{r['what']} (score {r['before']:.1f} -> {r['after']:.1f})"


def significant(located: list, th: Thresholds) -> list:
    return [l for l in located if abs(l["standardised_residual"]) >= th.located_min]


def fit_flags(fit_z: dict | None, th: Thresholds) -> list:
    """[{observable, Z_fit, fit_max}] for the observables whose baseline Z_fit exceeds ``th.fit_max``.
    fit_z: {observable: Z_fit} (None values, and observables without a level, are not checked)."""
    if th.fit_max is None or not fit_z:
        return []
    out = []
    for name, z in fit_z.items():
        lim = th.fit_max.get(name) if isinstance(th.fit_max, dict) else th.fit_max
        if lim is not None and z is not None and np.isfinite(z) and z > lim:
            out.append({"observable": name, "Z_fit": float(z), "fit_max": float(lim)})
    return out


def checks(c: dict, baseline: dict, misfit_before: float, th: Thresholds) -> dict:
    """Pass/fail of every check for one refitted candidate ``c`` (see the module doc)."""
    if "reliable" in c:
        out = {"reliable": bool(c["reliable"] and baseline.get("reliable", False))}
    else:
        ess_b = baseline.get("ess", 0.0) or 0.0
        out = {"reliable": bool((c.get("ess") or 0.0) >= th.ess_min and ess_b >= th.ess_min)}
    if "lr_pvalue" in c:
        out["likelihood_ratio"] = bool(c["lr_pvalue"] is not None and c["lr_pvalue"] <= th.lr_alpha)
    lb = c.get("two_ln_bf_lower")
    out["evidence"] = bool(lb is not None and np.isfinite(lb) and lb >= th.bf_min)
    sd = c.get("two_ln_bf_savage_dickey")
    out["savage_dickey"] = bool(sd is not None and sd > 0)
    dw = c.get("delta_waic")
    out["predictive"] = bool(dw is not None and np.isfinite(dw) and dw >= th.waic_min)
    ma = c.get("misfit_after")
    out["misfit"] = bool(ma is not None and ma < misfit_before)
    if "at_range_end" in c:
        out["within_range"] = not c["at_range_end"]
    rs = c.get("located_rescored") or {}
    out["explains"] = (not rs.get("items")
                       or bool(_explained(c, th) >= th.explain_min and rs["max_after"] < th.located_min))
    return out


def decide(candidates: list, located_before: list, baseline: dict, misfit_before: float, th: Thresholds,
           fit_z: dict | None = None) -> dict:
    """candidates: refitted candidates with the verify statistics (see pipeline); baseline: the baseline's
    verified-evidence dict; fit_z: {observable: the baseline's Z_fit} for the fit flags (``th.fit_max``).
    Returns {verdict, missing_physics, ambiguous, reason, checks, fit_flags, explained_shares (per candidate
    with re-scored mismatches: the share of the significant ones it removes), ...}."""
    scored = sorted([c for c in candidates if c.get("log_bayes_factor") is not None
                     and np.isfinite(c["log_bayes_factor"])], key=lambda c: -c["log_bayes_factor"])
    sig_before = significant(located_before, th)
    flags = fit_flags(fit_z, th)
    out = {"verdict": None, "missing_physics": None, "ambiguous": False, "runner_up": None,
           "two_ln_bf": None, "two_ln_bf_over_runner_up": None, "reason": "", "checks": {}, "fit_flags": flags}
    flagged = "; ".join(f"{f['observable']} fits at Z_fit {f['Z_fit']:.1f} > {f['fit_max']:.1f}" for f in flags)
    for c in scored:
        out["checks"][c["name"]] = checks(c, baseline, misfit_before, th)
    shares = {c["name"]: _explained(c, th) for c in scored}
    out["explained_shares"] = {n: v for n, v in shares.items() if np.isfinite(v)}
    # a fit at the end of a budget range explains the data only beyond the term's range: set aside (rule 0)
    ends = [c["name"] for c in scored if not out["checks"][c["name"]].get("within_range", True)]
    aside, ends_lbf = "", {}
    if ends and len(ends) < len(scored):
        out["set_aside"] = ends
        ends_lbf = {c["name"]: c["log_bayes_factor"] for c in scored if c["name"] in ends}
        scored = [c for c in scored if c["name"] not in ends]
        aside = f"{', '.join(ends)} fit(s) at the end of the range (fails within_range) and is set aside; "
    best = scored[0] if scored else None
    if best is not None:
        tl = 2 * best["log_bayes_factor"]
        out["two_ln_bf"] = tl
        if len(scored) > 1:
            out["runner_up"] = scored[1]["name"]
            out["two_ln_bf_over_runner_up"] = 2 * (best["log_bayes_factor"] - max(scored[1]["log_bayes_factor"], 0.0))
        else:
            out["two_ln_bf_over_runner_up"] = tl
        ck = out["checks"][best["name"]]
        failed = [k for k, v in ck.items() if not v]
        partial = (failed == ["explains"] and bool(_significant_items(best, th))
                   and _explained(best, th) >= th.explain_partial_min)
        if partial:
            out.update(partial=True, explained_share=_explained(best, th),
                       remainder=remainder(best, located_before, th))
        if not failed or partial:
            ex_best = _explained(best, th)
            close = [c["name"] for c in scored[1:]
                     if out["checks"][c["name"]]["evidence"]
                     and 2 * (best["log_bayes_factor"] - c["log_bayes_factor"]) < th.margin_min]
            better = [c["name"] for c in scored[1:] if out["checks"][c["name"]]["explains"]
                      and _explained(c, th) > ex_best and _explained(c, th) >= ex_best + th.explain_margin]
            beyond = [n for n, v in ends_lbf.items() if v > best["log_bayes_factor"]]
            if close or better or beyond:
                why = []
                if beyond:
                    why.append(f"{', '.join(beyond)}, set aside at the end of its range, has more evidence")
                if close:
                    why.append(f"{', '.join(close)} also pass(es) the evidence check within 2 ln BF {th.margin_min}")
                if better:
                    why.append(f"{', '.join(better)} explain(s) more of the located mismatch "
                               f"({', '.join(f'{_explained(c, th):.2f}' for c in scored if c['name'] in better)} vs "
                               f"{ex_best:.2f})")
                comp = close + [b for b in better if b not in close] + beyond
                alts = [best["name"]] + comp
                out.update(verdict="missing_physics", missing_physics=" or ".join(alts), ambiguous=True,
                           competitors=comp, alternatives=alts,
                           reason=f"{best['name']} has the largest evidence (2 ln BF = {tl:.1f}) and passes every "
                                  f"check, but {'; '.join(why)}: the data do not separate them ({' or '.join(alts)})")
                return _prefixed(out, aside)
            out.update(verdict="missing_physics", missing_physics=best["name"], ambiguous=False,
                       reason=f"{best['name']}: 2 ln BF = {tl:.1f} (lower bound {best['two_ln_bf_lower']:.1f} >= "
                              f"{th.bf_min:.1f}); Savage-Dickey, out-of-sample, misfit and located-structure checks pass")
            if partial:
                out["reason"] = (f"{best['name']}: 2 ln BF = {tl:.1f} (lower bound {best['two_ln_bf_lower']:.1f} >= "
                                 f"{th.bf_min:.1f}); every check but the located structure passes: it removes "
                                 f"{100 * out['explained_share']:.0f} % of the located mismatch; "
                                 + (f"unexplained: {'; '.join(_describe(r) for r in out['remainder'])}"
                                    if out["remainder"] else "no located mismatch stays above "
                                    f"{th.located_min:.1f}"))
            return _prefixed(out, aside)
        if ck["evidence"] and (sig_before or flags):
            out.update(verdict="unexplained",
                       reason=f"{best['name']} is supported by the evidence (2 ln BF = {tl:.1f}) but fails "
                              f"{', '.join(failed)}: not named" + (f" ({flagged})" if flags else ""))
            return _prefixed(out, aside)
        if ck["evidence"]:
            out.update(verdict="no_missing_physics",
                       reason=f"{best['name']} gains evidence (2 ln BF = {tl:.1f}) but fails {', '.join(failed)}, and "
                              f"the baseline leaves no located mismatch above {th.located_min:.1f} and no observable "
                              f"beyond its null level: what discretisation alone gives on null data")
            return _prefixed(out, aside)
    why = ("no candidate refitted" if best is None else
           f"best candidate {best['name']}: 2 ln BF lower bound "
           f"{best.get('two_ln_bf_lower', float('nan')):.1f} < {th.bf_min:.1f}")
    if sig_before or flags:
        where = ([f"{len(sig_before)} located mismatch(es) above {th.located_min:.1f}"] if sig_before else []) + \
            ([flagged] if flags else [])
        out.update(verdict="unexplained", reason=f"{'; '.join(where)}; {why}")
    else:
        out.update(verdict="no_missing_physics", reason=f"no located mismatch above {th.located_min:.1f}; {why}")
    return _prefixed(out, aside)


def _prefixed(out: dict, aside: str) -> dict:
    out["reason"] = aside + out["reason"]
    return out
