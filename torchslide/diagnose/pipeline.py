"""``diagnose(evaluator, candidates, ...)``: the whole missing-physics diagnosis in one call.

Two inference paths, chosen by Budgets.inference and reported in decision["inference"] with the reason:

* local (``_diagnose_local``, local_path.py), for posteriors far narrower than the prior box (rich
  data): the baseline fitted on the solver (pilot fit, then the grid's approximation error at its
  Laplace draws and the refit), localisation, screening, each candidate fitted on the solver with its
  Laplace evidence, likelihood ratio and profile, decision;
* emulator (below), for broad posteriors of sparse data: GP active learning over the box.

The emulator path's stages (``_diagnose``; their wall times in Diagnosis.timings):

1. model error (Budgets.model_error_runs > 0): the grid's approximation error from a pilot
   calibration's posterior draws run on the inversion grid and on finer cells, with
   Budgets.release_volume_sd > 0 also the release volume's error, in every model's likelihood
   (grid_model_error, model_error.py);
2. baseline: calibration (or a given CalibrationResult), then its verified evidence (for a 2-D
   posterior verify.refine_baseline: a zoomed grid proposal refitted with the verification runs until
   the evidence is trustworthy and stable) and posterior-predictive runs;
3. localisation of the mismatches (per observable, residual-map clusters, gauge windows);
4. screening: one batched call of finite differences ranks the candidates (screen.py);
5. refits of the ``top_k`` candidates (refit_candidate: active learning in the enlarged space, a local
   search on the solver from its best runs, the nested baseline's and the screening's linearised
   optimum, refinement of a refit that missed its mode or leans on an unsampled switch bound), then
   checks that the baseline itself sat on its mode (the beta = 0 slice of the best refits,
   baseline_mode_check), a re-check of the refits when the baseline changed (refit_recheck), and a
   profile along the leading switches (profile_refit);
6. per candidate: verified evidence and Bayes factor, Savage-Dickey, WAIC, the located mismatches
   re-scored, 90 % intervals; subset consistency at the final baseline (reported, not decided on);
7. the verdict (decide.py) and the fit after the named (or best) candidate.
"""
from __future__ import annotations

import math
import tempfile
import time
from pathlib import Path
from dataclasses import dataclass, field

import numpy as np
import torch

from .candidates import CANDIDATES
from .consistency import subset_consistency
from .decide import Thresholds, decide
from .localise import Localisation, localise
from .predictive import Predictive, posterior_mode, posterior_predictive, posterior_samples
from .refit import calibrate_evaluator, refit
from .verify import (grid_result, hdi_from_grid, hdi_interval, logmeanexp, needs_bound_probe, refine_baseline,
                     refine_refit, rescore, runs_start, savage_dickey, slice_proposal, solver_z, verified_evidence, waic)
from .polish import local_search
from .profile import sampling_log_density, switch_profile
from .screen import ScreenResult, detectable_switch, screen
from .local_path import choose_path, fit_candidate, fit_model, laplace_result, profile_ends


@dataclass
class Budgets:
    inference: str = "auto"            # "local": every model fitted on the solver, Laplace evidence (local_path.py);
                                       # "emulator": GP emulator over the box (the stages below); "auto": local
                                       # when the baseline's 90 % Laplace region fills less than
                                       # local_max_fraction of the prior box (local_path.choose_path): a GP
                                       # over the box with the refits' few tens of runs resolves features
                                       # of a few per cent of it, not less
    local_max_fraction: float = 0.01
    local_lhs: int = 16                # local path: maximin-LHS runs ranking the baseline's start points ...
    local_starts: int = 2              # ... local fits from this many of the best
    local_rel_step: float = 3e-3       # finite-difference step, share of each prior range
    local_max_iter: int = 30           # evaluations (each one batch of 2p + 1 members) per local fit
    n_posterior_samples: int = 32      # posterior-predictive members (baseline)
    n_posterior_samples_after: int = 16  # posterior-predictive members of every refit (verification)
    n_initial: int = 16                # refit LHS runs
    n_total: int = 32                  # refit total runs (first stage)
    n_total_max: int = 48              # a refit whose verified evidence is not trustworthy is continued to this
                                       # (only when refit_refine_rounds = 0)
    refit_refine_rounds: int = 4       # refits whose posterior leans against an unsampled switch bound
                                       # (verify.needs_bound_probe) or whose first verified evidence is not
                                       # trustworthy: verify.refine_refit rounds (M = n_posterior_samples_after
                                       # runs each; they stop once the verified evidence is trustworthy and
                                       # stable) instead of the continuation to n_total_max; 0: never
    refit_grid: tuple = (48, 40)       # ... its zoomed grid posterior, points per axis (coarse, fine)
    baseline_n_initial: int = 12
    baseline_n_total: int = 24
    baseline_grid_size: int = 160      # p = 2 baseline: active-learning estimation grid
    baseline_refine_rounds: int = 3    # rounds of verify.refine_baseline (M solver runs each)
    baseline_tv_tol: float = 0.15      # ... stop when the zoomed posterior moves by less (or log Z is stable)
    verify_ess_fraction: float = 0.3   # "trustworthy": importance ESS >= this fraction of the draws ...
    verify_se: float = 1.0             # ... and bootstrap se of the verified log Z <= this
    slice_check: bool = True           # baseline evidence also from the beta = 0 slice of refits ...
    slice_top: int = 2                 # ... of this many, those with the largest verified evidence
    baseline_mode_check: bool = True   # the baseline run at the refits' nested points (best runs, switch dropped)
                                       # + a local search from them; one that beats every baseline run by more
                                       # than mode_margin: the baseline missed its mode -> refined from all runs
    refit_recheck: bool = True         # after the baseline changed (mode check or slice adopted): every refit run
                                       # at the new baseline's best points with its switch at 0; one whose best
                                       # posterior draw they beat by more than mode_margin is refined from them
    model_error_runs: int = 12         # > 0: approximation error of the grid (model_error) sampled at this many
                                       # posterior draws of a pilot baseline calibration, in the likelihood of
                                       # every model; 0: off
    model_error_factor: int = 2        # ... against runs on cells this many times smaller
    release_volume_sd: float = 0.0     # > 0: the release volume's relative sd, marginalised in the same
                                       # likelihoods (model_error module doc; needs model_error_runs >= 2)
    mode_search_iters: int = 4         # refits: iterations of polish.local_search on the solver from the refit's
                                       # best runs, the nested baseline's and the screening's linearised optimum
                                       # (0: off); a search that beats every refit run, or the refit's best
                                       # posterior draw, by more than mode_margin in z means the refit missed its
                                       # mode: refined with those runs
    mode_search_pop: int = 6           # ... moves per start and iteration (2 starts; one batched call per iteration)
    mode_search_max_iters: int = 0     # > mode_search_iters: every mode search (refits', baseline mode check, refit
                                       # recheck) goes on while it still climbs, by more than mode_search_tol in z
                                       # over its last 4 iterations, up to this many iterations (polish.local_search
                                       # max_iter); 0: exactly mode_search_iters
    mode_search_tol: float = 1.0
    mode_margin: float = 3.0
    profile_top: int = 2               # refits profiled along their switch (profile.switch_profile): this many with
                                       # the largest verified evidence among those above the baseline's (0: off);
                                       # the profile's runs join a re-refinement when it finds mass the posterior
                                       # missed (pipeline.profile_refit)
    profile_rounds: int = 3            # ... profile + refinement repeated (around the refined posterior) while the
                                       # profile still finds mass outside it, at most this many times
    profile_values: int = 5            # ... switch values of its ladder
    profile_iters: int = 2             # ... local-search iterations (mode_search_pop moves) per value, switch held
    profile_extend: int = 2            # ... extra values per side where the ridge goes on beyond the ladder
    profile_drop: float = 2.0          # ... "goes on": profile within this of its maximum
    profile_outside: float = 1.0       # ... a profile optimum whose importance weight exceeds the mean of the
                                       # posterior draws' by more than this (ln) lies where the proposal has
                                       # too little mass: refine
    batch_size: int = 8
    top_k: int = 2
    n_perm: int = 99
    seed: int = 0
    model_error_seed: int | None = None  # seed of the pilot calibration and draws that estimate the grid's
                                       # approximation error (None: seed); fixing it holds the likelihood
                                       # constant while seed changes the rest of the inference
    mcmc_steps: int = 1500             # emulator MCMC steps per chain (p > 2 refits)


def check_candidates(candidates) -> list[str]:
    bad = [c for c in candidates if c not in CANDIDATES]
    if bad:
        raise ValueError(f"unknown candidate(s) {bad}; known: {', '.join(CANDIDATES)}")
    return list(candidates)


DECISION_CONTEXT = ("fit_z", "fit_z_source", "baseline_verification", "baseline_mode_check", "elpd_waic_baseline",
                    "inference")
"""What the pipeline adds to decide()'s output; kept when a saved case is decided again."""


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
    model_error: dict | None = None
    baseline_refined: object = None     # the baseline posterior that replaced the calibration's (mode check)
    consistency: list | None = None     # consistency.subset_consistency at the final baseline (None: not computable)
    null_calibration: dict | None = None  # thresholds set on null simulations of this design (diagnose.null)

    @property
    def missing_physics(self):
        return self.decision.get("missing_physics")

    def redecide(self, th: Thresholds, source: str) -> None:
        """Decide again with thresholds ``th`` (e.g. set on null data of this design: diagnose.null). The
        verdict is a pure function of the saved statistics and the thresholds, so this equals a run with
        ``th``; the earlier decision is kept as decision["decision_before"], ``source`` says where ``th``
        came from."""
        keep = {k: self.decision.get(k) for k in DECISION_CONTEXT}
        before = {"verdict": self.verdict, "missing_physics": self.missing_physics,
                  "reason": self.decision.get("reason"), "thresholds": self.thresholds.to_json()}
        dec = decide(self.candidates, self.localisation.located, keep["baseline_verification"] or {},
                     self.fit_before["misfit"], th, fit_z=keep["fit_z"])
        dec.update(keep, decision_before=before, thresholds_source=source)
        self.decision, self.verdict, self.thresholds = dec, dec["verdict"], th

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
            "located": self.localisation.public(),
            "located_after": self.after_localisation.public() if self.after_localisation else [],
            "candidates": self.candidates,
            "screening": self.screening.to_json(),
            "fit_before": self.fit_before,
            "fit_after": self.fit_after,
            "baseline": {"log_evidence": self.fit_before.get("log_evidence"),
                         "log_evidence_emulator": None if (self.decision.get("inference") or {}).get("path") == "local"
                         else self.baseline.log_evidence,
                         "verification": self.decision.get("baseline_verification"),
                         "parameters": _params(self.baseline_refined or self.baseline),
                         "parameters_calibration": _params(self.baseline) if self.baseline_refined else None},
            "thresholds": self.thresholds.to_json(),
            "timings": self.timings,
            "model_error": self.model_error,
            "subset_consistency": self.consistency,
            "null_calibration": None if self.null_calibration is None else
            {**self.null_calibration, "thresholds": self.null_calibration["thresholds"].to_json()},
        })


def _params(cal) -> dict:
    """Posterior mean, MAP, the calibration's 90 % interval ('hdr90': grid HDR extent or MCMC
    equal-tailed) and 'hdi90': the 90 % highest-density interval on the prior range (boundary-corrected
    KDE of the samples, or the grid marginal), which may include a prior bound."""
    s = cal.summary
    out = {}
    for i, n in enumerate(cal.names):
        lo, hi = float(cal.bounds[0][i]), float(cal.bounds[1][i])
        if getattr(cal, "samples", None) is not None and len(cal.samples):
            hdi = hdi_interval(np.asarray(cal.samples)[:, i], lo, hi)
        elif getattr(cal, "posterior_grid", None) is not None:
            hdi = hdi_from_grid(cal.posterior_grid, cal.grid_axes, i)
        else:
            hdi = list(s["hdr90"][n])
        # a grid cell's edge computed as centre + half-width can miss the bound by an ulp
        snap = lambda v: lo if abs(v - lo) <= 1e-9 * (hi - lo) else hi if abs(v - hi) <= 1e-9 * (hi - lo) else v
        out[n] = {"mean": s["mean"][n], "hdr90": [snap(float(v)) for v in s["hdr90"][n]],
                  "hdi90": [snap(float(v)) for v in hdi], "map": s["map"][n]}
    return out


def _fit(evaluator, pred: Predictive, loc: Localisation, log_evidence) -> dict:
    mean = pred.mean
    res = {}
    for b in evaluator.blocks:
        info = loc.blocks.get(b.name, {})
        if b.is_vector:
            res[b.name] = {"rms_z": info.get("rms_z"), "Z_block": info.get("Z_block"), "Z_fit": info.get("Z_fit"),
                           "p_fit": info.get("p_fit")}
        else:
            res[b.name] = {"z": info.get("z"), "data": info.get("data"), "pred_mean": info.get("pred_mean")}
    return {"log_evidence": log_evidence, "misfit": evaluator.misfit(mean), "k": evaluator.k, "residuals": res}


def _trusted(ver: dict, bud: Budgets) -> bool:
    return bool(ver.get("verified") and ver["ess_fraction"] >= bud.verify_ess_fraction and ver["se"] <= bud.verify_se)


def _refine(ev_c, cal_c, bud: Budgets, log, extra=None):
    """verify.refine_refit with the budgets' settings; returns (result, predictive, verification,
    evidence-history rows)."""
    cal_r, p_r, ver = refine_refit(ev_c, cal_c, bud.n_posterior_samples_after, seed=bud.seed + 1,
                                   max_rounds=bud.refit_refine_rounds, grid=tuple(bud.refit_grid),
                                   ess_fraction=bud.verify_ess_fraction, se_max=bud.verify_se,
                                   tv_tol=bud.baseline_tv_tol, log=log, extra=extra)
    rows = [{"n_runs": h["n_runs"], "log_evidence": h["log_evidence"], "log_evidence_emulator": h["log_evidence_grid"],
             "ess": h["ess"], "se": h["se"], "trusted": h["trusted"], "stable": h.get("stable"),
             "kept": h.get("kept", False)} for h in ver["rounds"]]
    return cal_r, p_r, ver, rows


def refit_candidate(evaluator, c: str, bud: Budgets, checkpoint, log=print, base_best=None, starts=None):
    """Refit candidate ``c`` (refit.refit: n_initial / n_total runs of active learning in the enlarged
    space), then make its posterior and verified evidence reliable: a local search on the solver from
    the refit's best runs (mode_search_iters; its runs join every refinement); probe + refine when it
    leans against an unsampled switch bound; else verify with n_posterior_samples_after runs and, when
    that is not trustworthy or the search beat every refit run by more than mode_margin, refine with
    those runs reused (or, with refit_refine_rounds = 0, continue to
    n_total_max). ``base_best``: (n, p_base) baseline points (the best baseline runs); they are run in
    the candidate's model with its switch at 0 (the nested baseline) and the search starts from them too,
    so a refit never ends below the baseline's peak for want of having looked there. ``starts``: more
    (n, p_c) start points (the screening's linearised optimum, _linear_starts). The refit missed its
    mode when the search's best beats the best of its posterior draws' runs (the verification runs:
    where the posterior's mass is) by more than mode_margin; its best run alone can sit on the peak's
    flank while the posterior lies elsewhere.
    Returns (candidate evaluator, result, predictive, verification, evidence history)."""
    Ma = bud.n_posterior_samples_after
    ev_c, cal_c = refit(evaluator, c, bud.n_initial, bud.n_total, batch_size=bud.batch_size, seed=bud.seed,
                        mcmc_steps=bud.mcmc_steps, checkpoint=checkpoint)
    ls = _mode_search(ev_c, cal_c, bud, base_best, starts)
    ls_runs = (ls["x"], ls["z"]) if ls is not None else None
    search = None if ls is None else {"runs": int(len(ls["z"])), "iters": ls["iters"], "improvement": ls["improvement"],
                                      "best_z": ls["best_z"], "missed_mode": bool(ls["improvement"] > bud.mode_margin)}
    if bud.refit_refine_rounds > 0 and needs_bound_probe(cal_c):
        # the MCMC posterior leans against the switch's upper bound where no relevant run was made:
        # probe the bound, zoomed grid posterior, emulator refitted locally with the verification runs
        # (verify.refine_refit): a 24-run GP's posterior can exclude a bound it never sampled
        cal_c, p_c, ver, history = _refine(ev_c, cal_c, bud, log, extra=ls_runs)
        history[0]["mode_search"] = search
        return ev_c, cal_c, p_c, ver, history
    p_c = posterior_predictive(ev_c, posterior_samples(cal_c, Ma, seed=bud.seed + 1))
    ver = verified_evidence(ev_c, cal_c, p_c.x, p_c.draws, seed=bud.seed)
    zd = solver_z(ev_c, p_c)
    missed = False
    if search is not None:
        zd_max = float(np.max(np.where(np.isfinite(zd), zd, -np.inf), initial=-np.inf))
        search["gap_to_draws"] = float(ls["best_z"] - zd_max)
        missed = search["missed_mode"] = bool(search["missed_mode"] or search["gap_to_draws"] > bud.mode_margin)
        if missed:
            log(f"[diagnose] refit {c}: the local search on the solver beats every refit run by "
                f"{ls['improvement']:.1f} and the best posterior draw by {search['gap_to_draws']:.1f} in ln "
                f"posterior: the refit's posterior missed the peak")
    history = [{"n_runs": cal_c.n_runs, "log_evidence": ver["log_evidence"],
                "log_evidence_emulator": cal_c.log_evidence, "ess": ver["ess"], "se": ver["se"],
                "mode_search": search}]
    if (missed or not _trusted(ver, bud)) and bud.refit_refine_rounds > 0:
        # the global GP's posterior is not a good proposal (or not where the mass is): local GP with
        # these runs and the search's, zoomed grid posterior, rounds until the verified evidence is
        # trustworthy and stable (verify.refine_refit)
        why = "peak not sampled" if missed else (f"evidence not trustworthy (ESS {ver['ess']:.1f}/{ver['n_draws']}, "
                                                f"se {ver['se']:.2f})")
        log(f"[diagnose] refit {c}: {why}: refining with a local emulator")
        xe, ze = p_c.x, zd
        if ls_runs is not None:
            xe, ze = np.vstack([xe, ls_runs[0]]) if len(xe) else ls_runs[0], np.concatenate([ze, ls_runs[1]])
        r_cal, r_p, r_ver, r_hist = _refine(ev_c, cal_c, bud, log, extra=(xe, ze))
        history += r_hist
        # a proposal that missed the mode is never kept: its ESS says nothing about the mass it missed
        if missed or _trusted(r_ver, bud) or r_ver["ess"] >= ver["ess"]:
            cal_c, p_c, ver = r_cal, r_p, r_ver
        else:
            # no refinement round beat the first proposal's ESS: keep the first (both are valid
            # importance-sampling estimates of the same log Z; the larger ESS is the better one)
            for h in history:
                h["kept"] = False
            history[0]["kept"] = True
    elif not _trusted(ver, bud) and bud.n_total_max > bud.n_total:
        log(f"[diagnose] refit {c}: evidence not trustworthy (ESS {ver['ess']:.1f}/{ver['n_draws']}, "
            f"se {ver['se']:.2f}): continuing to {bud.n_total_max} runs")
        cal_c = calibrate_evaluator(ev_c, bud.n_initial, bud.n_total_max, batch_size=bud.batch_size,
                                    seed=bud.seed, mcmc_steps=bud.mcmc_steps, checkpoint=checkpoint)
        p_c = posterior_predictive(ev_c, posterior_samples(cal_c, Ma, seed=bud.seed + 2))
        ver = verified_evidence(ev_c, cal_c, p_c.x, p_c.draws, seed=bud.seed)
        history.append({"n_runs": cal_c.n_runs, "log_evidence": ver["log_evidence"],
                        "log_evidence_emulator": cal_c.log_evidence, "ess": ver["ess"], "se": ver["se"]})
    return ev_c, cal_c, p_c, ver, history


def _climb(bud: Budgets) -> dict:
    """polish.local_search's keywords for a search that goes on while it climbs (Budgets.mode_search_max_iters)."""
    return {"max_iter": bud.mode_search_max_iters, "tol": bud.mode_search_tol}


def _mode_search(ev_c, cal_c, bud: Budgets, base_best=None, starts=None):
    """polish.local_search from the best of the refit's runs, of ``base_best`` (baseline points, run
    here with the switch at its lower bound 0) and of ``starts`` ((n, p_c) points of the candidate's
    model, e.g. the screening's linearised optimum); None when switched off. Initial steps: twice the
    refit posterior's sd per axis in unit-cube units, within [0.01, 0.1]. The returned runs include
    the extra points' runs; ``improvement`` is over the refit's own runs."""
    if bud.mode_search_iters <= 0:
        return None
    b = np.asarray(cal_c.bounds, float)
    X = np.asarray(cal_c.x, float)
    z = np.where(np.asarray(cal_c.failed, bool), -np.inf, np.asarray(cal_c.z, float))
    n_refit = len(X)
    pts = []
    if base_best is not None and len(base_best):
        pts.append(np.hstack([np.asarray(base_best, float), np.full((len(base_best), 1), b[0, -1])]))
    if starts is not None and len(starts):
        pts.append(np.clip(np.asarray(starts, float), b[0], b[1]))
    xb = zb = None
    if pts:
        xb = np.vstack(pts)
        r = ev_c(torch.as_tensor(xb))
        zb = np.where(r.failed.detach().cpu().numpy(), -np.inf, r.z.detach().cpu().numpy().astype(float))
        X, z = np.vstack([X, xb]), np.concatenate([z, zb])
    samples = getattr(cal_c, "samples", None)
    step = (np.clip(2 * np.asarray(samples).std(0) / (b[1] - b[0]), 0.01, 0.1)
            if samples is not None and len(samples) > 1 else None)
    ls = local_search(ev_c, X, z, b, n_iter=bud.mode_search_iters, pop=bud.mode_search_pop, step0=step,
                      seed=bud.seed + 11, **_climb(bud))
    if xb is not None:
        # the improvement is over the refit's own runs (did the refit miss its mode?), so the extra
        # points count as search runs
        ls["x"], ls["z"] = np.vstack([xb, ls["x"]]), np.concatenate([zb, ls["z"]])
        if np.max(zb) > ls["best_z"]:
            i = int(np.argmax(zb))
            ls["best_x"], ls["best_z"] = xb[i], float(zb[i])
        ls["improvement"] = float(ls["best_z"] - np.max(z[:n_refit], initial=-np.inf))
    return ls


def nested_points(refits: dict, p: int, low_fraction: float = 0.1) -> np.ndarray:
    """(n, p) baseline points nested in the refits: from every refit (candidate -> (evaluator, result)
    with the switch as the last of its p + 1 parameters) its best run and its best run with the switch
    in the lowest ``low_fraction`` of its prior box, the switch dropped; duplicates removed."""
    pts = []
    for _, cal_c in refits.values():
        ok = ~np.asarray(cal_c.failed, bool) & np.isfinite(np.asarray(cal_c.z, float))
        X, Z = np.asarray(cal_c.x, float)[ok], np.asarray(cal_c.z, float)[ok]
        if not len(X):
            continue
        b = np.asarray(cal_c.bounds, float)
        idx = [int(np.argmax(Z))]
        low = np.flatnonzero(X[:, -1] <= b[0, -1] + low_fraction * (b[1, -1] - b[0, -1]))
        if len(low):
            idx.append(int(low[np.argmax(Z[low])]))
        pts.append(X[idx, :p])
    return np.unique(np.vstack(pts), axis=0) if pts else np.zeros((0, p))


def baseline_mode_check(evaluator, runs, refits: dict, bud: Budgets, log=print) -> dict:
    """Did the baseline calibration miss its mode? The refits explore (mu, xi) with more runs than the
    baseline and every candidate nests the baseline, so their best points with the switch dropped
    (nested_points) are run in the baseline model, and polish.local_search continues from the best of
    all baseline runs. When a run beats every earlier baseline run (``runs`` = (X (n, p), Z (n,)): the
    calibration's, its refinement's and the predictive runs) by more than ``mode_margin`` in ln
    posterior, the baseline's proposal provably missed mass (on the long mu-xi ridge a 16-24-run calibration can settle on
    a secondary peak: on a null recording of the harness, mu 0.31, xi 990, best z 17.8 below that of
    mu 0.25, xi 405, a point the refits had found): its
    posterior is refined again (verify.refine_baseline) from all runs, the new ones included. Returns a
    JSON-able dict (runs, improvement, missed_mode) plus, when refined, "verification", "predictive"
    and "proposal" for the caller to compare with the first estimate."""
    X0, Z0 = np.asarray(runs[0], float), np.asarray(runs[1], float)
    p = X0.shape[1]
    b = evaluator.prior.bounds.numpy()
    xp = nested_points(refits, p)
    out = {"nested_points": int(len(xp)), "improvement": 0.0, "missed_mode": False}
    if not len(xp) or not len(X0):
        return out
    r = evaluator(torch.as_tensor(xp))
    zp = np.where(r.failed.detach().cpu().numpy(), -np.inf, r.z.detach().cpu().numpy().astype(float))
    X, Z = np.vstack([X0, xp]), np.concatenate([Z0, zp])
    ls = local_search(evaluator, X, Z, b, n_iter=bud.mode_search_iters, pop=bud.mode_search_pop, seed=bud.seed + 13,
                      **_climb(bud))
    Xn, Zn = np.vstack([xp, ls["x"]]), np.concatenate([zp, ls["z"]])
    best = float(np.max(Zn, initial=-np.inf))
    i = int(np.argmax(Zn)) if len(Zn) else None
    out.update(runs=int(len(Zn)), improvement=float(best - Z0.max()), best_x=None if i is None else Xn[i].tolist(),
               best_z=best, baseline_best_z=float(Z0.max()))
    if out["improvement"] <= bud.mode_margin:
        return out
    out["missed_mode"] = True
    log(f"[diagnose] baseline mode check: a run at the refits' nested points beats every baseline run by "
        f"{out['improvement']:.1f} in ln posterior (at {np.round(Xn[i], 4).tolist()}): refining the baseline")
    good = np.isfinite(Zn)
    Xa, Za = np.vstack([X0, Xn[good]]), np.concatenate([Z0, Zn[good]])
    start = runs_start(Xa, Za, b, coarse=bud.baseline_grid_size, fine=120)
    prop, pred, ver, _ = refine_baseline(evaluator, start, bud.n_posterior_samples, seed=bud.seed + 5,
                                         max_rounds=bud.baseline_refine_rounds, tv_tol=bud.baseline_tv_tol,
                                         ess_fraction=bud.verify_ess_fraction, se_max=bud.verify_se, log=log,
                                         label="baseline (mode check)")
    log(f"[diagnose] baseline mode check: log Z {ver['log_evidence']:.2f} (ESS {ver['ess']:.1f}/{ver['n_draws']}, "
        f"se {ver['se']:.2f})")
    out.update(verification=ver, predictive=pred, proposal=prop, log_evidence=ver["log_evidence"], ess=ver["ess"])
    return out


def refit_recheck(ev_c, cal_c, p_c, ver: dict, history: list, points, bud: Budgets, log=print, name: str = ""):
    """Re-check a refit against a baseline that changed after it was made. The refit's mode search
    started from the first baseline's best runs; when the baseline was then refined to a peak elsewhere
    on the mu-xi ridge (baseline_mode_check), the candidate, which nests the baseline, can sit far below
    its own nested baseline there. ``points`` (n, p) of the new baseline (its best runs) are run in the candidate's model
    with the switch at its lower bound (= the nested baseline); when the best of them beats the best of
    the refit's posterior draws' runs (``p_c``: where its mass is) by more than ``mode_margin``, the
    refit missed that peak: polish.local_search continues from all of its runs and these, and the refit
    is refined (verify.refine_refit, local emulator) with the draws', the points' and the search's runs.
    The refined estimate replaces the first one, whose proposal provably missed mass.
    Returns (result, predictive, verification, history, summary dict)."""
    b = np.asarray(cal_c.bounds, float)
    pts = np.asarray(points, float)
    out = {"points": int(len(pts)), "gap_to_draws": None, "refined": False}
    if not len(pts) or bud.refit_refine_rounds <= 0:
        return cal_c, p_c, ver, history, out
    xb = np.hstack([pts, np.full((len(pts), 1), b[0, -1])])
    r = ev_c(torch.as_tensor(xb))
    zb = np.where(r.failed.detach().cpu().numpy(), -np.inf, r.z.detach().cpu().numpy().astype(float))
    zdraw = solver_z(ev_c, p_c)
    fin = np.isfinite(zdraw)
    zd_max = float(zdraw[fin].max()) if fin.any() else -np.inf
    out["gap_to_draws"] = float(np.max(zb) - zd_max) if np.isfinite(np.max(zb)) else None
    if out["gap_to_draws"] is None or out["gap_to_draws"] <= bud.mode_margin:
        return cal_c, p_c, ver, history, out
    log(f"[diagnose] refit {name}: the refined baseline's best points (switch 0) beat its best posterior draw "
        f"by {out['gap_to_draws']:.1f} in ln posterior: refining it from them")
    ok = ~np.asarray(cal_c.failed, bool) & np.isfinite(np.asarray(cal_c.z, float))
    good = np.isfinite(zb)
    X = np.vstack([np.asarray(cal_c.x, float)[ok], p_c.x[fin], xb[good]])
    Z = np.concatenate([np.asarray(cal_c.z, float)[ok], zdraw[fin], zb[good]])
    ls = local_search(ev_c, X, Z, b, n_iter=max(1, bud.mode_search_iters), pop=bud.mode_search_pop,
                      seed=bud.seed + 17, **_climb(bud))
    xe = np.vstack([p_c.x[fin], xb[good], ls["x"]])
    ze = np.concatenate([zdraw[fin], zb[good], ls["z"]])
    r_cal, r_p, r_ver, r_hist = _refine(ev_c, cal_c, bud, log, extra=(xe, ze))
    for h in history:
        h["kept"] = False
    for h in r_hist:
        h["recheck"] = True
    out.update(refined=True, search_runs=int(len(ls["z"])), best_z=float(max(ls["best_z"], np.max(zb))),
               log_evidence_before=float(ver["log_evidence"]), log_evidence=float(r_ver["log_evidence"]),
               ess=float(r_ver["ess"]))
    log(f"[diagnose] refit {name} re-checked: log Z {ver['log_evidence']:.2f} -> {r_ver['log_evidence']:.2f} "
        f"(ESS {r_ver['ess']:.1f}/{r_ver['n_draws']})")
    return r_cal, r_p, r_ver, history + r_hist, out


def profile_refit(ev_c, cal_c, p_c, ver: dict, history: list, bud: Budgets, log=print, name: str = ""):
    """Profile the refit along its switch (profile.switch_profile) and refine it with the profile's runs
    when the profile finds mass its posterior missed. Test: the importance weight z - ln q of each
    profile optimum (q: what the refit's draws come from, profile.sampling_log_density) against the mean weight of
    its posterior draws' runs (the verified evidence's); more than ``profile_outside`` above it in ln
    means the proposal gives that stretch of the ridge e^1 or more times too little mass (a point
    beyond a zoomed grid is weighed against the grid's edge cell, verify.proposal_log_density). Also
    when a profile value beats the best draw by more than ``mode_margin`` (a missed peak). The refinement (verify.refine_refit: local emulator on all runs,
    zoomed grid posterior, verified) replaces the first estimate when it missed a peak, or when the
    new one is trustworthy or has the larger ESS. Returns (result, predictive, verification, history,
    summary)."""
    b = np.asarray(cal_c.bounds, float)
    draws = posterior_samples(cal_c, 400, seed=bud.seed + 19)
    par = _params(cal_c)[cal_c.names[-1]]
    prof = switch_profile(ev_c, draws, par["hdi90"], b, n_values=bud.profile_values, n_iter=bud.profile_iters,
                          pop=bud.mode_search_pop, extend=bud.profile_extend, drop=bud.profile_drop,
                          seed=bud.seed + 23)
    zdraw = solver_z(ev_c, p_c)
    fin = np.isfinite(zdraw)
    zd_max = float(zdraw[fin].max()) if fin.any() else -np.inf
    pz = prof["z"]
    lw_d = zdraw[fin] - sampling_log_density(cal_c, p_c.x[fin]) if fin.any() else np.zeros(0)
    lw_d = lw_d[np.isfinite(lw_d)]
    lw_p = pz - sampling_log_density(cal_c, prof["x"])
    excess = (float(np.max(lw_p[np.isfinite(pz)]) - logmeanexp(lw_d)) if len(lw_d) and np.isfinite(pz).any()
              else None)
    gap_all = float(np.max(pz) - zd_max)
    lo_i, hi_i = par["hdi90"]
    out = {"switch": prof["switch"].tolist(), "z": [float(v) if np.isfinite(v) else None for v in pz],
           "log_weight_excess": [None if not np.isfinite(v) else float(v - logmeanexp(lw_d)) for v in lw_p]
           if len(lw_d) else None, "runs": int(len(prof["runs_z"])), "interval_before": [float(lo_i), float(hi_i)],
           "best_draw_z": zd_max, "max_log_weight_excess": excess, "gap": gap_all, "refined": False}
    log(f"[diagnose] refit {name}: profile along {cal_c.names[-1]} "
        + ", ".join(f"{s:.3g}: {z:.1f}" for s, z in zip(prof["switch"], pz)) + f" (best posterior draw {zd_max:.1f}; "
        f"largest importance weight over the draws' mean: {excess if excess is None else round(excess, 2)} in ln)")
    missed = gap_all > bud.mode_margin
    if not (missed or (excess is not None and excess > bud.profile_outside)) or bud.refit_refine_rounds <= 0:
        return cal_c, p_c, ver, history, out
    good = np.isfinite(prof["runs_z"])
    xe = np.vstack([p_c.x[fin], prof["runs_x"][good]])
    ze = np.concatenate([zdraw[fin], prof["runs_z"][good]])
    log(f"[diagnose] refit {name}: the profile finds mass outside its posterior: refining with its runs")
    r_cal, r_p, r_ver, r_hist = _refine(ev_c, cal_c, bud, log, extra=(xe, ze))
    take = missed or _trusted(r_ver, bud) or r_ver["ess"] >= ver["ess"]
    out.update(refined=True, adopted=bool(take), log_evidence_before=float(ver["log_evidence"]),
               log_evidence_refined=float(r_ver["log_evidence"]), ess=float(r_ver["ess"]),
               interval_after=_params(r_cal)[cal_c.names[-1]]["hdi90"])
    log(f"[diagnose] refit {name} after the profile: log Z {ver['log_evidence']:.2f} -> {r_ver['log_evidence']:.2f} "
        f"(ESS {r_ver['ess']:.1f}/{r_ver['n_draws']}), {cal_c.names[-1]} 90 % interval "
        f"[{lo_i:.3g}, {hi_i:.3g}] -> [{out['interval_after'][0]:.3g}, {out['interval_after'][1]:.3g}]"
        + ("" if take else ": kept the first estimate"))
    for h in r_hist:
        h["profile"] = True
    if not take:
        for h in r_hist:
            h["kept"] = False
        return cal_c, p_c, ver, history + r_hist, out
    for h in history:
        h["kept"] = False
    return r_cal, r_p, r_ver, history + r_hist, out


def adopt_refined_baseline(v_new: dict, v_old: dict, n_draws: int, ess_min: float) -> bool:
    """Does the mode check's refined baseline evidence ``v_new`` replace ``v_old`` (verification dicts:
    log_evidence, se, ess)? The old proposal provably missed mass (a run beat all of its runs by more
    than mode_margin), so the new estimate replaces it when it is larger beyond the noise of both
    (2 x the combined bootstrap se) and rests on more than one draw and an ESS >= ``ess_min``."""
    gap = v_new["log_evidence"] - v_old["log_evidence"]
    return bool(n_draws > 1 and v_new["ess"] >= ess_min and gap > 2 * math.hypot(v_new["se"], v_old["se"]))


def _best_draws(evaluator, pred: Predictive, n: int) -> np.ndarray:
    """(n, p) the ``n`` posterior-predictive draws of ``pred`` with the largest solver z (failed last)."""
    z = solver_z(evaluator, pred)
    return pred.x[np.argsort(-np.where(np.isfinite(z), z, -np.inf))[:n]]


def _linear_starts(scr: ScreenResult, c: str, names, factors=(0.5, 1.0, 2.0)):
    """(n, p_c) points on the line from the baseline mode to the screening's linearised optimum of
    candidate ``c`` (ScreenResult.linear_opt) at ``factors`` of the step; None when it has none."""
    lo = scr.linear_opt.get(c) if scr is not None else None
    if not lo:
        return None
    x0 = np.array([scr.x0.get(n, 0.0) for n in names[:-1]] + [0.0])
    x1 = np.array([lo[n] for n in names])
    return np.array([x0 + f * (x1 - x0) for f in factors])


def grid_model_error(evaluator, bud: Budgets, workdir, log=print):
    """(evaluator with the grid's approximation error in its likelihood, ModelError): a pilot baseline
    calibration (baseline budgets), ``model_error_runs`` draws of its posterior, each run on the
    inversion grid and on cells ``model_error_factor`` times smaller (torchslide.diagnose.model_error)."""
    from .model_error import approximation_error

    seed = bud.seed if bud.model_error_seed is None else bud.model_error_seed
    pilot = calibrate_evaluator(evaluator, bud.baseline_n_initial, bud.baseline_n_total, batch_size=bud.batch_size,
                                seed=seed, mcmc_steps=bud.mcmc_steps, checkpoint=Path(workdir) / "pilot.pt",
                                grid_size=bud.baseline_grid_size)
    x = posterior_samples(pilot, bud.model_error_runs, seed=seed + 5)
    me = approximation_error(evaluator, x, bud.model_error_factor, release_sd=bud.release_volume_sd)
    s = me.summary(evaluator.blocks)
    log(f"[diagnose] approximation error of the grid from {s['n']} run pairs (x{s['factor']} finer): " +
        ", ".join(f"{k} rms mean {v['rms_mean']:.3g} sd {v['rms_sd']:.3g}" for k, v in s["blocks"].items()))
    if "release_sd" in s:
        log(f"[diagnose] release volume error (relative sd {s['release_sd']:.3g}), rms sd: " +
            ", ".join(f"{k} {v['rms_sd_release']:.3g}" for k, v in s["blocks"].items()))
    return evaluator.with_model_error(me), me


def diagnose(evaluator, candidates, budgets: Budgets | None = None, thresholds: Thresholds | None = None,
             baseline=None, log=print, workdir=None) -> Diagnosis:
    """Run the diagnosis (see module doc). ``evaluator``: a DiagnosisEvaluator with the baseline prior.
    ``workdir``: where the refit checkpoints go (default: a temporary folder)."""
    bud = budgets or Budgets()
    th = thresholds or Thresholds()
    candidates = check_candidates(candidates)
    tmp = None
    if workdir is None:
        tmp = tempfile.TemporaryDirectory(prefix="diagnose_")
        workdir = tmp.name
    workdir = Path(workdir)
    workdir.mkdir(parents=True, exist_ok=True)
    try:
        return _diagnose(evaluator, candidates, bud, th, baseline, log, workdir)
    finally:
        if tmp is not None:
            tmp.cleanup()


@dataclass
class _Baseline:
    """The baseline the verdict rests on: its calibration, posterior-predictive runs, verified evidence
    (and where they came from), localisation, WAIC and misfit; the refinement's runs (x, z) when the
    2-D refinement ran, and the refined posterior when the mode check replaced the calibration's."""

    calibration: object
    pred: Predictive
    ver: dict
    runs: tuple | None
    loc: Localisation | None = None
    elpd: dict | None = None
    misfit: float = float("nan")
    source: str = "baseline calibration"
    refined: object = None

    def adopt(self, ver: dict, pred: Predictive, source: str) -> None:
        self.ver, self.pred, self.source = ver, pred, source

    @property
    def changed(self) -> bool:
        return self.source != "baseline calibration"


@dataclass
class _Refit:
    """One candidate's refit: its evaluator, calibration, posterior-predictive runs, verified evidence
    and evidence history, and the re-check / profile records of later stages."""

    evaluator: object
    calibration: object
    pred: Predictive
    ver: dict
    history: list
    recheck: dict | None = None
    profile: list | None = None


def _check_budgets(bud: Budgets, baseline) -> None:
    if not 0 <= bud.release_volume_sd < 0.5:
        raise ValueError(f"release_volume_sd must be in [0, 0.5) (a relative sd), got {bud.release_volume_sd!r}")
    if bud.release_volume_sd > 0 and bud.model_error_runs < 2:
        raise ValueError(f"release_volume_sd = {bud.release_volume_sd:g} needs model_error_runs >= 2 (its Jacobian is "
                         f"taken at the pilot's posterior draws), got model_error_runs = {bud.model_error_runs}")
    if bud.inference not in ("auto", "local", "emulator"):
        raise ValueError(f"inference must be \"auto\", \"local\" or \"emulator\", got {bud.inference!r}")
    if bud.model_error_runs > 0 and baseline is not None:
        raise ValueError("model_error_runs > 0 changes the likelihood: the baseline must be calibrated here, not given")


def _baseline_stage(evaluator, bud: Budgets, baseline, workdir: Path, log) -> _Baseline:
    """Calibrate the baseline (unless given), then its verified evidence: for a 2-D posterior a zoomed grid
    proposal refitted with the verification runs until the evidence is trustworthy and stable
    (verify.refine_baseline), else importance weights of posterior draws."""
    M = bud.n_posterior_samples
    if baseline is None:
        log(f"[diagnose] baseline calibration ({bud.baseline_n_total} runs)")
        baseline = calibrate_evaluator(evaluator, bud.baseline_n_initial, bud.baseline_n_total,
                                       batch_size=bud.batch_size, seed=bud.seed, mcmc_steps=bud.mcmc_steps,
                                       checkpoint=workdir / "baseline.pt", grid_size=bud.baseline_grid_size)
    if baseline.emulator is not None and len(baseline.names) <= 2:
        prop, pred, ver, _ = refine_baseline(evaluator, baseline, M, seed=bud.seed,
                                             max_rounds=bud.baseline_refine_rounds, tv_tol=bud.baseline_tv_tol,
                                             ess_fraction=bud.verify_ess_fraction, se_max=bud.verify_se, log=log)
        return _Baseline(baseline, pred, ver, prop.runs)
    pred = posterior_predictive(evaluator, posterior_samples(baseline, M, seed=bud.seed))
    return _Baseline(baseline, pred, verified_evidence(evaluator, baseline, pred.x, pred.draws, seed=bud.seed), None)


def _assess(evaluator, base: _Baseline, th: Thresholds, bud: Budgets) -> None:
    """Localise the baseline's mismatches, its WAIC and misfit (again whenever the baseline changes)."""
    base.loc = localise(evaluator, base.pred.draws, z_threshold=th.z_threshold, n_perm=bud.n_perm, seed=bud.seed)
    base.elpd = waic(evaluator, base.pred.draws)
    base.misfit = evaluator.misfit(base.pred.mean)


def _screen_stage(evaluator, base: _Baseline, candidates, th: Thresholds, log) -> ScreenResult:
    """One-batch screening at the baseline's posterior mode, with each candidate's detectable switch."""
    scr = screen(evaluator, posterior_mode(base.calibration), candidates)
    scr.detectable = detectable_switch(scr, evaluator, th.bf_min)
    log("[diagnose] screening: " + ", ".join(f"{c} {scr.scores[c]:.1f}" for c in scr.ranking))
    unseen = [f"{c} (from {d['switch']:.3g}; prior up to {CANDIDATES[c].prior[1]:g})"
              for c, d in scr.detectable.items() if d and not d["within_prior"]]
    if unseen:
        log("[diagnose] beyond what these data can detect on this grid (linearised): " + ", ".join(unseen))
    return scr


def _refit_stage(evaluator, top: list, base: _Baseline, scr: ScreenResult, bud: Budgets, workdir: Path,
                 log) -> dict:
    """{candidate: _Refit} of the ``top`` candidates; each refit's local search also starts from the two
    best baseline runs (switch at 0) and the screening's linearised optimum."""
    base_best = _best_draws(evaluator, base.pred, 2) if len(base.pred.x) else None
    out = {}
    for c in top:
        names = list(evaluator.prior.names) + [CANDIDATES[c].param]
        ev_c, cal_c, p_c, ver, history = refit_candidate(evaluator, c, bud, workdir / f"refit_{c}.pt", log,
                                                         base_best=base_best, starts=_linear_starts(scr, c, names))
        out[c] = _Refit(ev_c, cal_c, p_c, ver, history)
    return out


def _slice_check(evaluator, base: _Baseline, refits: dict, bud: Budgets, log) -> None:
    """The baseline's evidence from a second proposal: the beta = 0 slice of the ``slice_top`` refits with
    the largest verified evidence (nested models: a refit that finds a better (mu, xi) must not be credited
    to its switch). Adopted only when trustworthy and larger beyond the noise of both estimates."""
    order = sorted(refits, key=lambda c: -refits[c].ver["log_evidence"])[: max(1, bud.slice_top)]
    for c in order:
        sl = slice_proposal(refits[c].calibration, evaluator.prior.bounds.numpy())
        p_s = posterior_predictive(evaluator, posterior_samples(sl, bud.n_posterior_samples, seed=bud.seed + 3))
        v_s = verified_evidence(evaluator, sl, p_s.x, p_s.draws, seed=bud.seed)
        log(f"[diagnose] baseline via the beta = 0 slice of the {c} refit: log Z {v_s['log_evidence']:.2f} "
            f"(ESS {v_s['ess']:.1f})")
        gap = v_s["log_evidence"] - base.ver["log_evidence"]
        if (_trusted(v_s, bud) and len(p_s.draws) > 1 and
                (not _trusted(base.ver, bud) or gap > 2 * math.hypot(v_s["se"], base.ver["se"]))):
            base.adopt(v_s, p_s, f"beta = 0 slice of the {c} refit")


def _mode_check_stage(evaluator, base: _Baseline, refits: dict, bud: Budgets, th: Thresholds, log) -> dict:
    """baseline_mode_check from the baseline's runs and the refits' nested points; its refined baseline
    is adopted when larger beyond noise and reliable (adopt_refined_baseline)."""
    zp = solver_z(evaluator, base.pred)
    good = np.isfinite(zp)
    runs = (np.vstack([base.runs[0], base.pred.x[good]]), np.concatenate([base.runs[1], zp[good]]))
    check = baseline_mode_check(evaluator, runs, {c: (r.evaluator, r.calibration) for c, r in refits.items()},
                                bud, log)
    if check.get("verification") is not None:
        v_m, p_m, prop_m = check.pop("verification"), check.pop("predictive"), check.pop("proposal")
        check["adopted"] = adopt_refined_baseline(v_m, base.ver, len(p_m.draws), th.ess_min)
        check["log_evidence_gain"] = float(v_m["log_evidence"] - base.ver["log_evidence"])
        if check["adopted"]:
            base.adopt(v_m, p_m, "baseline refined from the refits' nested points")
            base.refined = grid_result(prop_m, evaluator.prior.names, evaluator.prior.bounds.numpy())
    return check


def _recheck_stage(evaluator, base: _Baseline, refits: dict, check: dict | None, bud: Budgets, log) -> None:
    """After the baseline changed: every refit run at the new baseline's best points (switch at 0) and
    refined from them when they beat its posterior draws (refit_recheck)."""
    pts = _best_draws(evaluator, base.pred, 2)
    if check and check.get("best_x") is not None:
        pts = np.vstack([pts, np.asarray(check["best_x"], float)[None]])
    for c, r in refits.items():
        r.calibration, r.pred, r.ver, r.history, r.recheck = refit_recheck(
            r.evaluator, r.calibration, r.pred, r.ver, r.history, pts, bud, log, name=c)


def _profile_stage(base: _Baseline, refits: dict, bud: Budgets, log) -> None:
    """The ``profile_top`` refits above the baseline's evidence profiled along their switch (ridges),
    re-refined while the profile finds mass their posterior missed (profile_refit)."""
    above = [c for c, r in refits.items() if r.ver["log_evidence"] > base.ver["log_evidence"]]
    for c in sorted(above, key=lambda c: -refits[c].ver["log_evidence"])[: bud.profile_top]:
        r = refits[c]
        r.profile = []
        for _ in range(bud.profile_rounds):
            r.calibration, r.pred, r.ver, r.history, pr = profile_refit(r.evaluator, r.calibration, r.pred, r.ver,
                                                                        r.history, bud, log, name=c)
            r.profile.append(pr)
            if not (pr["refined"] and pr.get("adopted")):
                break


def _candidate_report(evaluator, c: str, r: _Refit, base: _Baseline, scr: ScreenResult, bud: Budgets, log) -> dict:
    """A refitted candidate's row: verified and emulator Bayes factors, Savage-Dickey, WAIC, the located
    mismatches re-scored, misfit, parameters."""
    cal_c, ver = r.calibration, r.ver
    ok = ~cal_c.failed
    best_i = int(np.nanargmax(np.where(ok, cal_c.z, -np.inf)))
    recs = [x for x in r.evaluator.records if not x.failed]
    rb = max(recs, key=lambda x: x.z) if recs else None
    cd = CANDIDATES[c]
    lbf = ver["log_evidence"] - base.ver["log_evidence"]
    se_tot = math.sqrt(ver["se"] ** 2 + base.ver["se"] ** 2)
    sd = savage_dickey(cal_c, cd.param, cd.prior)
    el = waic(r.evaluator, r.pred.draws) if len(r.pred.draws) > 1 else {"elpd": float("nan")}
    rs = rescore(evaluator, base.loc.located, base.pred.draws, r.pred.draws) if len(r.pred.draws) > 1 else {}
    misfit = r.evaluator.misfit(r.pred.mean) if len(r.pred.draws) else float("inf")
    out = {"name": c, "param": cd.param, "log_evidence": ver["log_evidence"],
           "log_evidence_emulator": cal_c.log_evidence, "log_bayes_factor": lbf, "two_ln_bf": 2 * lbf,
           "two_ln_bf_emulator": 2 * (cal_c.log_evidence - base.calibration.log_evidence),
           "two_ln_bf_lower": 2 * lbf - 4 * se_tot, "evidence_se": ver["se"], "ess": ver["ess"],
           "ess_fraction": ver["ess_fraction"], "evidence_history": r.history,
           "evidence_converged": bool(ver.get("converged", _trusted(ver, bud))),
           "mode_search": r.history[0].get("mode_search"), "refit_recheck": r.recheck, "profile": r.profile,
           "two_ln_bf_savage_dickey": sd["two_ln_bf"], "savage_dickey": sd,
           "delta_waic": 2 * (el["elpd"] - base.elpd["elpd"]), "located_rescored": rs,
           "misfit_after": misfit, "screening_score": scr.scores[c], "mimic": scr.mimic[c],
           "parameters": _params(cal_c),
           "best_misfit": r.evaluator.misfit(rb.predictions) if rb is not None else float("inf"),
           "n_runs": cal_c.n_runs, "best_x": cal_c.x[best_i].tolist()}
    log(f"[diagnose] refit {c}: 2 ln BF {2 * lbf:.1f} (lower {out['two_ln_bf_lower']:.1f}; emulator "
        f"{out['two_ln_bf_emulator']:.1f}; ESS {ver['ess']:.1f}), SD {sd['two_ln_bf']:.1f}, "
        f"dWAIC {out['delta_waic']:.1f}, explained {rs.get('explained')}, misfit {misfit:.1f}")
    return out


def _not_refit(c: str, scr: ScreenResult, why: str) -> dict:
    """The report row of a candidate that was screened but not refitted (``why``)."""
    return {"name": c, "param": CANDIDATES[c].param, "log_evidence": None, "log_bayes_factor": None,
            "two_ln_bf": None, "screening_score": scr.scores[c], "mimic": scr.mimic[c], "parameters": {},
            "not_refit": why}


def _consistency_stage(evaluator, base: _Baseline, scr: ScreenResult, log) -> list | None:
    """Subset consistency at the final baseline: the screening's linearisation when the baseline stayed
    the calibration's, else p + 1 runs at the refined baseline's best run."""
    if base.changed and len(base.pred.x):
        scr = screen(evaluator, _best_draws(evaluator, base.pred, 1)[0], [])
    if scr.jacobian is None:
        return None
    names = list(evaluator.prior.names)
    out = subset_consistency(evaluator.blocks, scr.jacobian, scr.residual, names, [scr.x0[n] for n in names])
    flagged = [e["block"] for e in out if e["conflict"]]
    log("[diagnose] subset consistency: " + (f"{', '.join(flagged)} disagree(s) with the rest about "
                                             f"{', '.join(names)}" if flagged else "no observation disagrees"))
    return out


def _after_stage(cand_out: list, dec: dict, refits: dict, th: Thresholds, bud: Budgets) -> tuple:
    """(predictive, localisation, fit) after the named candidate, else after the best by verified evidence."""
    fitted = [c for c in cand_out if c.get("log_bayes_factor") is not None]
    if not fitted:
        return None, None, {}
    name = dec["missing_physics"] or max(fitted, key=lambda c: c["log_bayes_factor"])["name"]
    r = refits[name]
    if len(r.pred.draws) <= 1:
        return r.pred, None, {}
    loc = localise(r.evaluator, r.pred.draws, z_threshold=th.z_threshold, n_perm=bud.n_perm, seed=bud.seed)
    fit = _fit(r.evaluator, r.pred, loc, next(c["log_evidence"] for c in fitted if c["name"] == name))
    fit["model"] = name
    return r.pred, loc, fit


def _diagnose(evaluator, candidates, bud, th, baseline, log, workdir) -> Diagnosis:
    """The stages of the module doc, timed per stage (Diagnosis.timings)."""
    T = {}
    t0 = time.perf_counter()

    def lap(key: str) -> None:
        nonlocal t0
        T[key] = time.perf_counter() - t0
        t0 = time.perf_counter()

    _check_budgets(bud, baseline)
    path = None
    if bud.inference != "emulator":
        pilot = _pilot_stage(evaluator, bud, baseline, log)
        if pilot is None:
            if bud.inference == "local":
                raise RuntimeError("inference = \"local\": the baseline cannot be fitted locally (see the log)")
            path = ("emulator", "no local fit of the baseline (fewer data values than parameters, or it failed)")
        else:
            path = ("local", "inference = \"local\"") if bud.inference == "local" else \
                choose_path(pilot, evaluator.prior.bounds.numpy(), bud.local_max_fraction)
        log(f"[diagnose] inference path: {path[0]} ({path[1]})")
        lap("pilot_s")
        if path[0] == "local":
            return _diagnose_local(evaluator, candidates, pilot, path[1], bud, th, log, T, lap)
    model_error = None
    if bud.model_error_runs > 0:
        evaluator, me = grid_model_error(evaluator, bud, workdir, log)
        model_error = me.summary(evaluator.blocks)
        lap("model_error_s")
    base = _baseline_stage(evaluator, bud, baseline, workdir, log)
    lap("baseline_s")
    log(f"[diagnose] baseline log Z {base.ver['log_evidence']:.2f} (emulator {base.calibration.log_evidence:.2f}, "
        f"ESS {base.ver['ess']:.1f}/{base.ver['n_draws']}, se {base.ver['se']:.2f})")
    _assess(evaluator, base, th, bud)
    loc_first = base.loc
    # the fit flags use the calibrated baseline's fit, before any refit can change the baseline (the
    # statistic their null levels are set on)
    fit_z_first = {b: i["Z_fit"] for b, i in loc_first.blocks.items() if i.get("Z_fit") is not None}
    lap("predictive_s")
    log(f"[diagnose] located {loc_first.n_located} mismatch(es); max |score| {loc_first.max_abs():.2f}")
    scr = _screen_stage(evaluator, base, candidates, th, log)
    lap("screen_s")
    top = scr.ranking[: bud.top_k]
    refits = _refit_stage(evaluator, top, base, scr, bud, workdir, log)
    if bud.slice_check and refits:
        _slice_check(evaluator, base, refits, bud, log)
    check = None
    if bud.baseline_mode_check and refits and base.runs is not None:
        check = _mode_check_stage(evaluator, base, refits, bud, th, log)
    if base.changed:
        log(f"[diagnose] baseline evidence and predictive taken from the {base.source}; re-localising")
        _assess(evaluator, base, th, bud)
        if bud.refit_recheck and len(base.pred.x):
            _recheck_stage(evaluator, base, refits, check, bud, log)
    if bud.profile_top > 0:
        _profile_stage(base, refits, bud, log)
    cand_out = [_candidate_report(evaluator, c, refits[c], base, scr, bud, log) for c in top]
    cand_out += [_not_refit(c, scr, "screening score below the top_k") for c in candidates if c not in refits]
    lap("refit_s")
    consistency = _consistency_stage(evaluator, base, scr, log)
    lap("consistency_s")
    fit_before = _fit(evaluator, base.pred, base.loc, base.ver["log_evidence"])
    fit_before["log_evidence_emulator"] = base.calibration.log_evidence
    dec = decide(cand_out, base.loc.located, base.ver, base.misfit, th, fit_z=fit_z_first)
    dec.update(fit_z=fit_z_first, fit_z_source="calibrated baseline",
               baseline_verification=dict(base.ver, source=base.source), baseline_mode_check=check,
               elpd_waic_baseline=base.elpd["elpd"],
               inference={"path": "emulator", "why": path[1] if path else "inference = \"emulator\""})
    log(f"[diagnose] verdict {dec['verdict']} ({dec['reason']})")
    after_pred, after_loc, fit_after = _after_stage(cand_out, dec, refits, th, bud)
    lap("after_s")
    cand_out.sort(key=lambda c: -(c["log_bayes_factor"] if c["log_bayes_factor"] is not None else -1e300))
    return Diagnosis(verdict=dec["verdict"], decision=dec, baseline=base.calibration, predictive=base.pred,
                     localisation=base.loc, screening=scr,
                     refits={c: (r.evaluator, r.calibration) for c, r in refits.items()}, candidates=cand_out,
                     fit_before=fit_before, fit_after=fit_after, after_predictive=after_pred,
                     after_localisation=after_loc, thresholds=th, timings=T, evaluator=evaluator,
                     model_error=model_error, baseline_refined=base.refined, consistency=consistency)


# ---- the local path (local_path.py): every model fitted on the solver, Laplace evidence ----

def _pilot_stage(evaluator, bud: Budgets, baseline, log):
    """The baseline's local fit on the stated likelihood (a given baseline's MAP is one more start); None
    when there are fewer data values than parameters (a ridge, not a peak) or every fit failed."""
    if evaluator.k < evaluator.prior.dim:
        log(f"[diagnose] {evaluator.k} data value(s) for {evaluator.prior.dim} parameters: no local fit")
        return None
    extra = None if baseline is None else posterior_mode(baseline)[None]
    try:
        f, n = fit_model(evaluator, n_lhs=bud.local_lhs, starts=bud.local_starts, extra_starts=extra, seed=bud.seed,
                         rel_step=bud.local_rel_step, max_iter=bud.local_max_iter, log=log)
    except (RuntimeError, np.linalg.LinAlgError) as e:
        log(f"[diagnose] local baseline fit failed: {e}")
        return None
    log(f"[diagnose] local baseline fit ({n} runs): " + ", ".join(
        f"{k} {v:.4g} +- {s:.2g}" for k, v, s in zip(evaluator.prior.names, f.x, f.sd)) + f"; ln L {f.log_like:.1f}")
    return f


def _local_baseline(evaluator, pilot, bud: Budgets, log):
    """(evaluator, baseline fit, model-error summary): with model_error_runs > 0 the grid's approximation
    error at draws of the pilot's Laplace posterior enters the likelihood and the baseline is refitted."""
    if bud.model_error_runs <= 0:
        return evaluator, pilot, None
    from .model_error import approximation_error

    seed = bud.seed if bud.model_error_seed is None else bud.model_error_seed
    x = pilot.draws(bud.model_error_runs, evaluator.prior.bounds.numpy(), seed=seed + 5)
    me = approximation_error(evaluator, x, bud.model_error_factor, release_sd=bud.release_volume_sd)
    s = me.summary(evaluator.blocks)
    log(f"[diagnose] approximation error of the grid from {s['n']} run pairs (x{s['factor']} finer): " +
        ", ".join(f"{k} rms mean {v['rms_mean']:.3g} sd {v['rms_sd']:.3g}" for k, v in s["blocks"].items()))
    evaluator = evaluator.with_model_error(me)
    f, _ = fit_model(evaluator, n_lhs=0, extra_starts=pilot.x[None], rel_step=bud.local_rel_step,
                     max_iter=bud.local_max_iter, log=log)
    return evaluator, f, s


def _laplace_ver(f) -> dict:
    """The evidence record of a Laplace fit (the emulator path's verified-evidence keys where they apply)."""
    return {"log_evidence": float(f.log_evidence), "se": 0.0, "ess": None, "method": "laplace",
            "reliable": bool(f.converged and np.all(np.isfinite(f.covariance))), "converged": bool(f.converged),
            "message": f.message, "verified": True}


def _local_candidate(evaluator, c: str, base: _Baseline, base_fit, scr: ScreenResult, bud: Budgets, log):
    """(_Refit, report row) of candidate ``c`` on the local path."""
    names = list(evaluator.prior.names) + [CANDIDATES[c].param]
    start = scr.linear_opt.get(c)
    cf = fit_candidate(evaluator, c, base_fit, start, bud, log)
    cal = laplace_result(cf.fit, names, cf.evaluator.prior.bounds.numpy(), seed=bud.seed + 1)
    pred = posterior_predictive(cf.evaluator, cal.samples[: bud.n_posterior_samples_after])
    ver = _laplace_ver(cf.fit)
    r = _Refit(cf.evaluator, cal, pred, ver, [])
    el = waic(cf.evaluator, pred.draws) if len(pred.draws) > 1 else {"elpd": float("nan")}
    rs = rescore(evaluator, base.loc.located, base.pred.draws, pred.draws) if len(pred.draws) > 1 else {}
    lbf = 0.5 * cf.two_ln_bf
    row = {"name": c, "param": CANDIDATES[c].param, "inference": "laplace", "log_evidence": ver["log_evidence"],
           "log_bayes_factor": lbf, "two_ln_bf": cf.two_ln_bf, "two_ln_bf_lower": cf.two_ln_bf,
           "reliable": ver["reliable"] and base.ver["reliable"], "likelihood_ratio": cf.lr, "lr_pvalue": cf.lr_pvalue,
           "two_ln_bf_savage_dickey": cf.two_ln_bf_savage_dickey, "profile_ends": None,
           "delta_waic": 2 * (el["elpd"] - base.elpd["elpd"]), "located_rescored": rs,
           "misfit_after": cf.evaluator.misfit(pred.mean) if len(pred.draws) else float("inf"),
           "screening_score": scr.scores[c], "mimic": scr.mimic[c], "parameters": _params(cal),
           "n_runs": cf.n_runs + len(pred.x), "best_x": cf.fit.x.tolist(), "fit_message": cf.fit.message}
    log(f"[diagnose] local fit {c}: 2 ln BF {cf.two_ln_bf:.1f}, 2 ln LR {cf.lr:.1f} (p {cf.lr_pvalue:.2g}), "
        f"SD {cf.two_ln_bf_savage_dickey:.1f}, dWAIC {row['delta_waic']:.1f}, explained {rs.get('explained')}")
    return r, row, cf


def _local_profiles(evaluator, rows: list, fits: dict, bud: Budgets, log) -> None:
    """profile_ends of the ``profile_top`` candidates with the largest 2 ln BF, into their rows."""
    ranked = sorted((r for r in rows if r["name"] in fits), key=lambda r: -r["two_ln_bf"])[: bud.profile_top]
    for row in ranked:
        prof, n = profile_ends(evaluator, fits[row["name"]], bud, log)
        row["profile_ends"], row["n_runs"] = prof, row["n_runs"] + n
        if min(prof["two_ln_drop"]) < -1.0:     # the profile beats the fit: the fit is not at its mode
            row["reliable"] = False
        log(f"[diagnose] profile of {row['name']}: 2 ln drop {[round(v, 2) for v in prof['two_ln_drop']]} at "
            f"{row['param']} = {[round(v, 5) for v in prof['interval90']]} (Gaussian {prof['gaussian']:.2f})")


def _diagnose_local(evaluator, candidates, pilot, why: str, bud: Budgets, th: Thresholds, log, T: dict, lap):
    """The stages of the local path (local_path.py): model error, baseline fit, localisation, screening,
    per-candidate fit and evidence, decision."""
    evaluator, f0, model_error = _local_baseline(evaluator, pilot, bud, log)
    names = list(evaluator.prior.names)
    cal = laplace_result(f0, names, evaluator.prior.bounds.numpy(), seed=bud.seed)
    pred = posterior_predictive(evaluator, cal.samples[: bud.n_posterior_samples])
    base = _Baseline(cal, pred, _laplace_ver(f0), None, source="local fit (Laplace)")
    lap("baseline_s")
    _assess(evaluator, base, th, bud)
    fit_z = {b: i["Z_fit"] for b, i in base.loc.blocks.items() if i.get("Z_fit") is not None}
    log(f"[diagnose] located {base.loc.n_located} mismatch(es); max |score| {base.loc.max_abs():.2f}")
    lap("predictive_s")
    scr = _screen_stage(evaluator, base, candidates, th, log)
    lap("screen_s")
    refits, cand_out, fits = {}, [], {}
    for c in scr.ranking[: bud.top_k]:
        try:
            refits[c], row, fits[c] = _local_candidate(evaluator, c, base, f0, scr, bud, log)
        except RuntimeError as e:
            log(f"[diagnose] local fit {c} failed: {e}")
            row = _not_refit(c, scr, f"local fit failed: {e}")
        cand_out.append(row)
    cand_out += [_not_refit(c, scr, "screening score below the top_k") for c in candidates
                 if c not in scr.ranking[: bud.top_k]]
    lap("refit_s")
    _local_profiles(evaluator, cand_out, fits, bud, log)
    lap("profile_s")
    consistency = _consistency_stage(evaluator, base, scr, log)
    lap("consistency_s")
    fit_before = _fit(evaluator, base.pred, base.loc, base.ver["log_evidence"])
    dec = decide(cand_out, base.loc.located, base.ver, base.misfit, th, fit_z=fit_z)
    dec.update(fit_z=fit_z, fit_z_source="baseline local fit", baseline_verification=dict(base.ver, source=base.source),
               baseline_mode_check=None, elpd_waic_baseline=base.elpd["elpd"],
               inference={"path": "local", "why": why, "baseline_converged": bool(f0.converged)})
    log(f"[diagnose] verdict {dec['verdict']} ({dec['reason']})")
    after_pred, after_loc, fit_after = _after_stage(cand_out, dec, refits, th, bud)
    lap("after_s")
    cand_out.sort(key=lambda c: -(c["log_bayes_factor"] if c["log_bayes_factor"] is not None else -1e300))
    return Diagnosis(verdict=dec["verdict"], decision=dec, baseline=cal, predictive=base.pred, localisation=base.loc,
                     screening=scr, refits={c: (r.evaluator, r.calibration) for c, r in refits.items()},
                     candidates=cand_out, fit_before=fit_before, fit_after=fit_after, after_predictive=after_pred,
                     after_localisation=after_loc, thresholds=th, timings=T, evaluator=evaluator,
                     model_error=model_error, consistency=consistency)
