"""``diagnose(evaluator, candidates, ...)``: the whole missing-physics diagnosis in one call.

baseline calibration (or a given CalibrationResult) -> posterior-predictive runs -> localisation ->
one-batch screening -> refits of the top_k candidates -> evidence / Bayes factors -> predictive runs
of the best refit -> verdict (torchslide.diagnose.decide).
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np

from ..physics import CANDIDATES
from .decide import Thresholds, decide
from .localise import Localisation, localise
from .predictive import Predictive, posterior_mode, posterior_predictive, posterior_samples
from .refit import calibrate_evaluator, refit
from .screen import ScreenResult, screen


@dataclass
class Budgets:
    n_posterior_samples: int = 32      # posterior-predictive members (baseline)
    n_posterior_samples_after: int = 16  # posterior-predictive members of the best refit
    n_initial: int = 16                # refit LHS runs
    n_total: int = 32                  # refit total runs
    baseline_n_initial: int = 12
    baseline_n_total: int = 24
    batch_size: int = 8
    top_k: int = 2
    n_perm: int = 99
    seed: int = 0
    mcmc_steps: int = 1500             # emulator MCMC steps per chain (p > 2 refits)


def check_candidates(candidates) -> list[str]:
    bad = [c for c in candidates if c not in CANDIDATES]
    if bad:
        raise ValueError(f"unknown candidate(s) {bad}; known: {', '.join(CANDIDATES)}")
    return list(candidates)


@dataclass
class Diagnosis:
    verdict: str
    decision: dict
    baseline: object
    predictive: Predictive
    localisation: Localisation
    screening: ScreenResult
    refits: dict
    candidates: list
    fit_before: dict
    fit_after: dict
    after_predictive: Predictive | None = None
    after_localisation: Localisation | None = None
    thresholds: Thresholds = field(default_factory=Thresholds)
    timings: dict = field(default_factory=dict)
    evaluator: object = None

    @property
    def missing_physics(self):
        return self.decision.get("missing_physics")

    def to_json(self) -> dict:
        def clean(v):
            if isinstance(v, dict):
                return {str(k): clean(x) for k, x in v.items()}
            if isinstance(v, (list, tuple)):
                return [clean(x) for x in v]
            if isinstance(v, (np.floating, float)):
                return float(v) if math.isfinite(float(v)) else None
            if isinstance(v, np.integer):
                return int(v)
            if isinstance(v, np.ndarray):
                return clean(v.tolist())
            return v
        return clean({
            "verdict": self.verdict,
            "missing_physics": self.missing_physics,
            "decision": self.decision,
            "located": self.localisation.located,
            "located_after": self.after_localisation.located if self.after_localisation else [],
            "candidates": self.candidates,
            "screening": self.screening.to_json(),
            "fit_before": self.fit_before,
            "fit_after": self.fit_after,
            "baseline": {"log_evidence": self.baseline.log_evidence,
                         "parameters": _params(self.baseline)},
            "thresholds": self.thresholds.to_json(),
            "timings": self.timings,
        })


def _params(cal) -> dict:
    s = cal.summary
    return {n: {"mean": s["mean"][n], "hdr90": list(s["hdr90"][n]), "map": s["map"][n]} for n in cal.names}


def _fit(evaluator, pred: Predictive, loc: Localisation, log_evidence) -> dict:
    mean = pred.mean
    res = {}
    for b in evaluator.blocks:
        info = loc.blocks.get(b.name, {})
        if b.is_vector:
            res[b.name] = {"rms_z": info.get("rms_z"), "Z_block": info.get("Z_block")}
        else:
            res[b.name] = {"z": info.get("z"), "data": info.get("data"), "pred_mean": info.get("pred_mean")}
    return {"log_evidence": log_evidence, "misfit": evaluator.misfit(mean), "k": evaluator.k, "residuals": res}


def diagnose(evaluator, candidates, budgets: Budgets | None = None, thresholds: Thresholds | None = None,
             baseline=None, log=print) -> Diagnosis:
    """Run the diagnosis (see module doc). ``evaluator``: a DiagnosisEvaluator with the baseline prior."""
    bud = budgets or Budgets()
    th = thresholds or Thresholds()
    candidates = check_candidates(candidates)
    T = {}
    t0 = time.perf_counter()
    if baseline is None:
        log(f"[diagnose] baseline calibration ({bud.baseline_n_total} runs)")
        baseline = calibrate_evaluator(evaluator, bud.baseline_n_initial, bud.baseline_n_total,
                                       batch_size=bud.batch_size, seed=bud.seed, mcmc_steps=bud.mcmc_steps)
    T["baseline_s"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    samples = posterior_samples(baseline, bud.n_posterior_samples, seed=bud.seed)
    pred = posterior_predictive(evaluator, samples)
    loc = localise(evaluator, pred.draws, z_threshold=th.z_threshold, n_perm=bud.n_perm, seed=bud.seed)
    T["predictive_s"] = time.perf_counter() - t0
    log(f"[diagnose] located {loc.n_located} mismatch(es); max |score| {loc.max_abs():.2f}")
    t0 = time.perf_counter()
    x0 = posterior_mode(baseline)
    scr = screen(evaluator, x0, candidates)
    T["screen_s"] = time.perf_counter() - t0
    log("[diagnose] screening: " + ", ".join(f"{c} {scr.scores[c]:.1f}" for c in scr.ranking))
    top = [c for c in scr.ranking][: bud.top_k]
    refits, cand_out, misfit_after = {}, [], {}
    t0 = time.perf_counter()
    for c in top:
        ev_c, cal_c = refit(evaluator, c, bud.n_initial, bud.n_total, batch_size=bud.batch_size, seed=bud.seed,
                            mcmc_steps=bud.mcmc_steps)
        refits[c] = (ev_c, cal_c)
        ok = ~cal_c.failed
        best_i = int(np.nanargmax(np.where(ok, cal_c.z, -np.inf)))
        # misfit at the best evaluated point (no extra runs)
        recs = [r for r in ev_c.records if not r.failed]
        rb = max(recs, key=lambda r: r.z) if recs else None
        misfit_after[c] = ev_c.misfit(rb.predictions) if rb is not None else float("inf")
        lbf = cal_c.log_evidence - baseline.log_evidence
        log(f"[diagnose] refit {c}: log Z {cal_c.log_evidence:.2f}, 2 ln BF {2 * lbf:.2f}, best misfit {misfit_after[c]:.1f}")
        cand_out.append({"name": c, "param": CANDIDATES[c].param, "log_evidence": cal_c.log_evidence,
                         "log_bayes_factor": lbf, "two_ln_bf": 2 * lbf, "screening_score": scr.scores[c],
                         "mimic": scr.mimic[c], "parameters": _params(cal_c), "best_misfit": misfit_after[c],
                         "n_runs": cal_c.n_runs, "best_x": cal_c.x[best_i].tolist()})
    for c in candidates:
        if c not in refits:
            cand_out.append({"name": c, "param": CANDIDATES[c].param, "log_evidence": None, "log_bayes_factor": None,
                             "two_ln_bf": None, "screening_score": scr.scores[c], "mimic": scr.mimic[c],
                             "parameters": {}, "not_refit": "screening score below the top_k"})
    T["refit_s"] = time.perf_counter() - t0
    # best refit: posterior-predictive runs and localisation after
    fitted = [c for c in cand_out if c.get("log_bayes_factor") is not None]
    after_pred = after_loc = None
    located_after = {}
    fit_after = {}
    t0 = time.perf_counter()
    if fitted:
        best = max(fitted, key=lambda c: c["log_bayes_factor"])
        ev_b, cal_b = refits[best["name"]]
        s_b = posterior_samples(cal_b, bud.n_posterior_samples_after, seed=bud.seed + 1)
        after_pred = posterior_predictive(ev_b, s_b)
        after_loc = localise(ev_b, after_pred.draws, z_threshold=th.z_threshold, n_perm=bud.n_perm, seed=bud.seed)
        located_after[best["name"]] = after_loc.located
        misfit_after[best["name"]] = ev_b.misfit(after_pred.mean)
        fit_after = _fit(ev_b, after_pred, after_loc, cal_b.log_evidence)
        fit_after["model"] = best["name"]
    T["after_s"] = time.perf_counter() - t0
    fit_before = _fit(evaluator, pred, loc, baseline.log_evidence)
    dec = decide(cand_out, loc.located, located_after, fit_before["misfit"], misfit_after, th)
    log(f"[diagnose] verdict {dec['verdict']} ({dec['reason']})")
    cand_out.sort(key=lambda c: -(c["log_bayes_factor"] if c["log_bayes_factor"] is not None else -1e300))
    return Diagnosis(verdict=dec["verdict"], decision=dec, baseline=baseline, predictive=pred, localisation=loc,
                     screening=scr, refits=refits, candidates=cand_out, fit_before=fit_before, fit_after=fit_after,
                     after_predictive=after_pred, after_localisation=after_loc, thresholds=th, timings=T,
                     evaluator=evaluator)
