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
2. baseline: calibration (or a given CalibrationResult), posterior-predictive runs and the verified
   evidence (importance weights of those runs, verify.verified_evidence);
3. localisation of the mismatches (per observable, residual-map clusters, gauge windows);
4. screening: one batched call of finite differences ranks the candidates (screen.py);
5. refits of the ``top_k`` candidates (refit_candidate: active learning in the enlarged space and its
   verified evidence, continued to n_total_max runs while that is not trustworthy);
6. per candidate: verified evidence and Bayes factor, Savage-Dickey, WAIC, the located mismatches
   re-scored, 90 % intervals; subset consistency at the baseline (reported, not decided on);
7. the verdict (decide.py) and the fit after the named (or best) candidate.
"""
from __future__ import annotations

import dataclasses
import math
import tempfile
import time
from pathlib import Path
from dataclasses import dataclass, field

import numpy as np

from ..tradeoff import conflicts
from .candidates import CANDIDATES
from .consistency import subset_consistency
from .decide import Thresholds, decide
from .localise import Localisation, localise
from .predictive import Predictive, map_mismatches, posterior_mode, posterior_predictive, posterior_samples
from .refit import calibrate_evaluator, candidate_evaluator, refit
from .resolution import removed_by_resolution
from .verify import hdi_from_grid, hdi_interval, rescore, savage_dickey, verified_evidence, waic
from .power import detectable_switch
from .screen import ScreenResult, screen
from .local_path import (candidate_fit, choose_path, fit_candidates, fit_model, laplace_result, profile_ends,
                         profile_intervals90, profile_two_ln_bf, refit_from)


@dataclass
class Budgets:
    inference: str = "auto"            # "local": every model fitted on the solver, Laplace evidence (local_path.py);
                                       # "emulator": GP emulator over the box (the stages below); "auto": local
                                       # when the baseline's 90 % Laplace region fills less than
                                       # local_max_fraction of the prior box (local_path.choose_path): a GP
                                       # over the box with the refits' few tens of runs resolves features
                                       # of several per cent of it, not a peak of a per cent
    local_max_fraction: float = 0.05
    local_lhs: int = 16                # local path: maximin-LHS runs ranking the baseline's start points ...
    local_starts: int = 2              # ... local fits from this many of the best
    local_rel_step: float = 3e-3       # finite-difference step, share of each prior range
    local_max_iter: int = 30           # trial points per local fit (one run each, 2p more where a step is accepted)
    n_posterior_samples: int = 32      # posterior-predictive members (baseline)
    n_posterior_samples_after: int = 16  # posterior-predictive members of every refit (verification)
    n_initial: int = 16                # emulator path: refit LHS runs ...
    n_total: int = 32                  # ... refit total runs
    n_total_max: int = 48              # ... a refit whose verified evidence is not trustworthy is continued to this
    baseline_n_initial: int = 12
    baseline_n_total: int = 24
    baseline_grid_size: int = 160      # p = 2 baseline: active-learning estimation grid
    verify_ess_fraction: float = 0.3   # "trustworthy": importance ESS >= this fraction of the draws ...
    verify_se: float = 1.0             # ... and bootstrap se of the verified log Z <= this
    model_error_runs: int = 12         # > 0: approximation error of the grid (model_error) sampled at this many
                                       # posterior draws of the pilot fit (local path) or calibration (emulator
                                       # path), in the likelihood of every model; 0: off
    model_error_factor: int = 2        # ... against runs on cells this many times smaller
    release_volume_sd: float = 0.0     # > 0: the release volume's relative sd, marginalised in the same
                                       # likelihoods (model_error module doc; needs model_error_runs >= 2)
    profile_top: int = 2               # local path: candidates profiled at the ends of their switch's 90 %
                                       # interval, those with the largest 2 ln BF (0: off); a profile point
                                       # that beats the fit restarts the fit from there
    profile_restarts: int = 2          # local path: restarts from a profile point that beats the fit, at most
    candidate_error_rounds: int = 2    # local path, with a finer terrain (fine_terrain): rounds in which the
                                       # grid's mean error of the baseline and of the profile_top candidates
                                       # is taken at draws of their own fit (model_error_runs run pairs each)
                                       # and the model refitted with it (0: off); the covariance stays the
                                       # first sample's. Without a finer terrain no rounds (error_rounds)
    finer_shift: float = 1.0           # local path, with a finer terrain: when a round moved the grid's mean error
                                       # at one of the profile_top candidates' fits by more than this (rms over an
                                       # observation's values, in its sigmas), or a candidate reaches bf_min, the
                                       # baseline and the supported candidates are fitted again on the finer grid
                                       # and their evidence taken there (_finer_grid_stage; 0: off)
    candidate_lhs: int = 8             # local path: a candidate's global starts, maximin-LHS points over its
    candidate_starts: int = 1          #     switch's prior range and candidate_box of each baseline parameter's
    candidate_box: float = 0.25        #     range around the baseline's mode; fits from the candidate_starts best
    batch_size: int = 8
    top_k: int = 2
    n_perm: int = 99
    seed: int = 0
    model_error_seed: int | None = None  # seed of the pilot calibration and draws that estimate the grid's
                                       # approximation error (None: seed); fixing it holds the likelihood
                                       # constant while seed changes the rest of the inference
    mcmc_steps: int = 1500             # emulator MCMC steps per chain (p > 2 refits)
    detectability: str = "measured"    # each candidate's detectable switch: "measured" on the solver with the
                                       # baseline refitted (power.py; tens of seconds), or "linearised" from
                                       # the screening alone (no runs; off by a factor 2-3 for threshold and
                                       # saturating terms)


def error_rounds(evaluator, bud: Budgets) -> int:
    """The grid-error rounds this diagnosis runs: ``candidate_error_rounds`` when the finer runs use a finer
    terrain (``fine_terrain``), 0 when they interpolate the inversion DEM: the error the interpolated grid
    measures is not the recordings' own, and the rounds would converge to its fit (docs/diagnosis.md)."""
    return bud.candidate_error_rounds if getattr(evaluator, "fine_terrain", None) is not None else 0


def check_candidates(candidates) -> list[str]:
    bad = [c for c in candidates if c not in CANDIDATES]
    if bad:
        raise ValueError(f"unknown candidate(s) {bad}; known: {', '.join(CANDIDATES)}")
    return list(candidates)


DECISION_CONTEXT = ("fit_z", "fit_z_source", "baseline_verification", "elpd_waic_baseline", "inference", "resolution",
                    "finer_grid")
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
    consistency: list | None = None     # consistency.subset_consistency at the final baseline (None: not computable)
    null_calibration: dict | None = None  # thresholds set on null simulations of this design (diagnose.null)
    grid: dict | None = None            # how the inversion grid was chosen (resolution.choose_grid; None: as configured)
    tradeoffs: dict | None = None       # what the baseline's runs cannot meet together (torchslide.tradeoff.conflicts)
    mismatches: dict | None = None      # the baseline against the mapped footprint (predictive.map_mismatches; {}: none mapped)

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
        sep = self.decision.get("separate") or {}
        if dec.get("alternatives") and sep.get("alternatives") == dec["alternatives"]:
            dec["separate"] = sep
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
                         "parameters": _params(self.baseline)},
            "thresholds": self.thresholds.to_json(),
            "timings": self.timings,
            "model_error": self.model_error,
            "subset_consistency": self.consistency,
            "null_calibration": None if self.null_calibration is None else
            {**self.null_calibration, "thresholds": self.null_calibration["thresholds"].to_json()},
            "grid": self.grid,
            "tradeoffs": self.tradeoffs,
            "mismatches": {k: v for k, v in (self.mismatches or {}).items() if k not in ("mapped", "p_reached")},
        })


def at_range_end(c: str, params: dict) -> bool:
    """Whether candidate ``c``'s switch sits at the upper end of an open range (Candidate.open_range): its
    90 % interval reaches the range's last thousandth."""
    cd = CANDIDATES[c]
    iv = (params.get(cd.param) or {}).get("hdr90")
    return bool(cd.open_range and iv is not None and iv[1] >= cd.prior[1] - 1e-3 * (cd.prior[1] - cd.prior[0]))


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


def refit_candidate(evaluator, c: str, bud: Budgets, checkpoint, log=print):
    """Refit candidate ``c`` (refit.refit: n_initial / n_total runs of active learning in the enlarged
    space), then its verified evidence from n_posterior_samples_after posterior-predictive runs; a refit
    whose verified evidence is not trustworthy (_trusted) is continued to n_total_max runs.
    Returns (candidate evaluator, result, predictive, verification, evidence history)."""
    Ma = bud.n_posterior_samples_after
    ev_c, cal_c = refit(evaluator, c, bud.n_initial, bud.n_total, batch_size=bud.batch_size, seed=bud.seed,
                        mcmc_steps=bud.mcmc_steps, checkpoint=checkpoint)
    p_c = posterior_predictive(ev_c, posterior_samples(cal_c, Ma, seed=bud.seed + 1))
    ver = verified_evidence(ev_c, cal_c, p_c.x, p_c.draws, seed=bud.seed)
    history = [{"n_runs": cal_c.n_runs, "log_evidence": ver["log_evidence"],
                "log_evidence_emulator": cal_c.log_evidence, "ess": ver["ess"], "se": ver["se"]}]
    if not _trusted(ver, bud) and bud.n_total_max > bud.n_total:
        log(f"[diagnose] refit {c}: evidence not trustworthy (ESS {ver['ess']:.1f}/{ver['n_draws']}, "
            f"se {ver['se']:.2f}): continuing to {bud.n_total_max} runs")
        cal_c = calibrate_evaluator(ev_c, bud.n_initial, bud.n_total_max, batch_size=bud.batch_size,
                                    seed=bud.seed, mcmc_steps=bud.mcmc_steps, checkpoint=checkpoint)
        p_c = posterior_predictive(ev_c, posterior_samples(cal_c, Ma, seed=bud.seed + 2))
        ver = verified_evidence(ev_c, cal_c, p_c.x, p_c.draws, seed=bud.seed)
        history.append({"n_runs": cal_c.n_runs, "log_evidence": ver["log_evidence"],
                        "log_evidence_emulator": cal_c.log_evidence, "ess": ver["ess"], "se": ver["se"]})
    return ev_c, cal_c, p_c, ver, history


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
    if evaluator.discrepancy_factors is None:
        evaluator.set_discrepancy_factors(stated_correlation(evaluator))
    try:
        d = _diagnose(evaluator, candidates, bud, th, baseline, log, workdir)
        d.tradeoffs = conflicts(evaluator.records, evaluator)      # the baseline's runs over its prior box
        add_mismatches(d)
        return d
    finally:
        if tmp is not None:
            tmp.cleanup()


def add_mismatches(d: Diagnosis) -> None:
    """d.mismatches: the baseline's posterior runs against the mapped footprint (predictive.map_mismatches),
    timed as d.timings["mismatches_s"]."""
    t0 = time.perf_counter()
    d.mismatches = map_mismatches(d.evaluator, d.predictive.x)
    d.timings["mismatches_s"] = time.perf_counter() - t0


def stated_correlation(evaluator) -> dict:
    """The diagnosis' discrepancy correlated as the stated errors are (factor 1 for every map and series).

    A calibration learns the discrepancy's correlation from its best initial run's residual
    (LandslideEvaluator.learn_discrepancy): there it stands for everything the model leaves unexplained. In
    the diagnosis the baseline's residual holds the very structure the candidates are tested for (a term's
    signature is as smooth as a grid's error), and the grid's error is measured (model_error: fine-minus-coarse
    runs, their covariance in the likelihood): learnt from that residual, the discrepancy would take the
    term's signature as its own and leave no candidate anything to explain (on the harness' narrow channel
    earth pressure at 1 fell from 2 ln BF 11-21 to 3-5, the nulls' best staying below 4 either way)."""
    return {b.name: 1.0 for b in evaluator.blocks if b.is_vector}


@dataclass
class _Baseline:
    """The baseline the verdict rests on: its calibration, posterior-predictive runs, verified evidence,
    localisation, WAIC and misfit."""

    calibration: object
    pred: Predictive
    ver: dict
    loc: Localisation | None = None
    elpd: dict | None = None
    misfit: float = float("nan")
    source: str = "baseline calibration"
    resolution: list | None = None     # located mismatches the grid's error accounts for (resolution.py)


@dataclass
class _Refit:
    """One candidate's refit: its evaluator, calibration, posterior-predictive runs, verified evidence
    and evidence history."""

    evaluator: object
    calibration: object
    pred: Predictive
    ver: dict
    history: list


def check_budgets(bud: Budgets, baseline=None) -> None:
    """ValueError naming the field when ``bud`` (with a given ``baseline``, or None) cannot be run."""
    if not 0 <= bud.release_volume_sd < 0.5:
        raise ValueError(f"release_volume_sd must be in [0, 0.5) (a relative sd), got {bud.release_volume_sd!r}")
    if bud.release_volume_sd > 0 and bud.model_error_runs < 2:
        raise ValueError(f"release_volume_sd = {bud.release_volume_sd:g} needs model_error_runs >= 2 (its Jacobian is "
                         f"taken at the pilot's posterior draws), got model_error_runs = {bud.model_error_runs}")
    if bud.inference not in ("auto", "local", "emulator"):
        raise ValueError(f"inference must be \"auto\", \"local\" or \"emulator\", got {bud.inference!r}")
    if bud.detectability not in ("measured", "linearised"):
        raise ValueError(f"detectability must be \"measured\" or \"linearised\", got {bud.detectability!r}")
    if bud.model_error_runs > 0 and baseline is not None:
        raise ValueError("model_error_runs > 0 changes the likelihood: the baseline must be calibrated here, not given")


def _baseline_stage(evaluator, bud: Budgets, baseline, workdir: Path, log) -> _Baseline:
    """Calibrate the baseline (unless given), its posterior-predictive runs and their verified evidence."""
    M = bud.n_posterior_samples
    if baseline is None:
        log(f"[diagnose] baseline calibration ({bud.baseline_n_total} runs)")
        baseline = calibrate_evaluator(evaluator, bud.baseline_n_initial, bud.baseline_n_total,
                                       batch_size=bud.batch_size, seed=bud.seed, mcmc_steps=bud.mcmc_steps,
                                       checkpoint=workdir / "baseline.pt", grid_size=bud.baseline_grid_size)
    pred = posterior_predictive(evaluator, posterior_samples(baseline, M, seed=bud.seed))
    return _Baseline(baseline, pred, verified_evidence(evaluator, baseline, pred.x, pred.draws, seed=bud.seed))


def _assess(evaluator, base: _Baseline, th: Thresholds, bud: Budgets) -> None:
    """Localise the baseline's mismatches, its WAIC and misfit (again whenever the baseline changes)."""
    base.loc = localise(evaluator, base.pred.draws, z_threshold=th.z_threshold, n_perm=bud.n_perm, seed=bud.seed)
    base.elpd = waic(evaluator, base.pred.draws)
    base.misfit = evaluator.misfit(base.pred.mean)
    if getattr(evaluator, "model_error", None) is not None:
        raw = localise(evaluator.with_model_error(None), base.pred.draws, z_threshold=th.z_threshold, n_perm=bud.n_perm,
                       seed=bud.seed)
        significant = lambda loc: [l for l in loc if abs(l["standardised_residual"]) >= th.located_min]
        base.resolution = removed_by_resolution(significant(raw.located), significant(base.loc.located))


def _screen_stage(evaluator, x0: np.ndarray, candidates, th: Thresholds, bud: Budgets, log) -> ScreenResult:
    """One-batch screening at the baseline's posterior mode x0 (p,), with each candidate's detectable switch
    (measured or linearised: ``bud.detectability``)."""
    scr = screen(evaluator, x0, candidates)
    scr.detectable = detectable_switch(scr, evaluator, th.bf_min, measure=bud.detectability == "measured")
    log("[diagnose] screening: " + ", ".join(f"{c} {scr.scores[c]:.1f}" for c in scr.ranking))
    unseen = [f"{c} (from {d['switch']:.3g}; prior up to {CANDIDATES[c].prior[1]:g})"
              for c, d in scr.detectable.items() if d and not d["within_prior"]]
    if unseen:
        log("[diagnose] beyond what these data can detect on this grid: " + ", ".join(unseen))
    return scr


def baseline_screening(evaluator, candidates, budgets: Budgets, thresholds: Thresholds, log=print) -> ScreenResult:
    """The local path's screening as :func:`diagnose` computes it (the baseline's pilot fit, the grid's error
    rounds and refits, the screening at its mode with each candidate's detectable switch), without the
    candidates' fits: what a saved diagnosis' detectable switches are measured again from."""
    pilot = _pilot_stage(evaluator, budgets, None, log)
    if pilot is None:
        raise RuntimeError("the baseline cannot be fitted locally (see the log)")
    evaluator, f0, _ = _local_baseline(evaluator, pilot, budgets, log)
    return _screen_stage(evaluator, f0.x, candidates, thresholds, budgets, log)


def _refit_stage(evaluator, top: list, bud: Budgets, workdir: Path, log) -> dict:
    """{candidate: _Refit} of the ``top`` candidates."""
    out = {}
    for c in top:
        out[c] = _Refit(*refit_candidate(evaluator, c, bud, workdir / f"refit_{c}.pt", log))
    return out


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
           "two_ln_bf_savage_dickey": sd["two_ln_bf"], "savage_dickey": sd,
           "delta_waic": 2 * (el["elpd"] - base.elpd["elpd"]), "located_rescored": rs,
           "misfit_after": misfit, "screening_score": scr.scores[c], "mimic": scr.mimic[c],
           "parameters": _params(cal_c), "at_range_end": at_range_end(c, _params(cal_c)),
           "best_misfit": r.evaluator.misfit(rb.predictions) if rb is not None else float("inf"),
           "n_runs": cal_c.n_runs, "best_x": cal_c.x[best_i].tolist()}
    log(f"[diagnose] refit {c}: 2 ln BF {2 * lbf:.1f} (lower {out['two_ln_bf_lower']:.1f}; emulator "
        f"{out['two_ln_bf_emulator']:.1f}; ESS {ver['ess']:.1f}), SD {sd['two_ln_bf']:.1f}, "
        f"dWAIC {out['delta_waic']:.1f}, explained (all located) {rs.get('explained_all')}, misfit {misfit:.1f}")
    return out


def _not_refit(c: str, scr: ScreenResult, why: str) -> dict:
    """The report row of a candidate that was screened but not refitted (``why``)."""
    return {"name": c, "param": CANDIDATES[c].param, "log_evidence": None, "log_bayes_factor": None,
            "two_ln_bf": None, "screening_score": scr.scores[c], "mimic": scr.mimic[c], "parameters": {},
            "not_refit": why}


def _consistency_stage(evaluator, scr: ScreenResult, log) -> list | None:
    """Subset consistency at the baseline, from the screening's linearisation."""
    if scr.jacobian is None:
        return None
    names = list(evaluator.prior.names)
    out = subset_consistency(evaluator.blocks, scr.jacobian, scr.residual, names, [scr.x0[n] for n in names])
    flagged = [e["block"] for e in out if e["conflict"]]
    log("[diagnose] subset consistency: " + (f"{', '.join(flagged)} disagree(s) with the rest about "
                                             f"{', '.join(names)}" if flagged else "no observation disagrees"))
    return out


def separation(evaluator, refits: dict, names: list, top: int = 5) -> dict:
    """Where the refits of ``names`` (two or more alternatives the evidence does not separate) predict
    differently: per observation the largest difference of their posterior-predictive means over the
    likelihood's sigma, and per block the root sum of squares of those; the ``top`` of each, largest first.
    These are the data that would tell the alternatives apart (recorded more precisely, or recorded at all)."""
    means = [np.asarray(refits[n].pred.mean, float) for n in names if n in refits and len(refits[n].pred.draws)]
    if len(means) < 2:
        return {}
    M = np.stack(means)
    d = (M.max(0) - M.min(0)) / np.asarray(evaluator.sigma, float)
    obs_names = evaluator.observation_names
    order = np.argsort(-d)[:top]
    blocks = sorted(((b.name, float(np.sqrt(np.sum(d[b.slice] ** 2)))) for b in evaluator.blocks), key=lambda t: -t[1])
    return {"alternatives": list(names),
            "values": [{"observation": obs_names[i], "difference_sigma": float(d[i])} for i in order],
            "blocks": [{"block": n, "difference_sigma_rss": v} for n, v in blocks[:top]]}


def _after_stage(cand_out: list, dec: dict, refits: dict, th: Thresholds, bud: Budgets) -> tuple:
    """(predictive, localisation, fit) after the named candidate, else after the best by verified evidence."""
    fitted = [c for c in cand_out if c.get("log_bayes_factor") is not None]
    if not fitted:
        return None, None, {}
    name = (dec.get("alternatives") or [dec["missing_physics"]])[0] or \
        max(fitted, key=lambda c: c["log_bayes_factor"])["name"]
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

    check_budgets(bud, baseline)
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
    fit_z = {b: i["Z_fit"] for b, i in base.loc.blocks.items() if i.get("Z_fit") is not None}
    lap("predictive_s")
    log(f"[diagnose] located {base.loc.n_located} mismatch(es); max |score| {base.loc.max_abs():.2f}")
    scr = _screen_stage(evaluator, posterior_mode(base.calibration), candidates, th, bud, log)
    lap("screen_s")
    top = scr.ranking[: bud.top_k]
    refits = _refit_stage(evaluator, top, bud, workdir, log)
    cand_out = [_candidate_report(evaluator, c, refits[c], base, scr, bud, log) for c in top]
    cand_out += [_not_refit(c, scr, "screening score below the top_k") for c in candidates if c not in refits]
    lap("refit_s")
    consistency = _consistency_stage(evaluator, scr, log)
    lap("consistency_s")
    fit_before = _fit(evaluator, base.pred, base.loc, base.ver["log_evidence"])
    fit_before["log_evidence_emulator"] = base.calibration.log_evidence
    dec = decide(cand_out, base.loc.located, base.ver, base.misfit, th, fit_z=fit_z)
    dec["resolution"] = base.resolution
    dec.update(fit_z=fit_z, fit_z_source="calibrated baseline",
               baseline_verification=dict(base.ver, source=base.source),
               elpd_waic_baseline=base.elpd["elpd"],
               inference={"path": "emulator", "why": path[1] if path else "inference = \"emulator\""})
    if dec.get("alternatives"):
        dec["separate"] = separation(evaluator, refits, dec["alternatives"])
    log(f"[diagnose] verdict {dec['verdict']} ({dec['reason']})")
    after_pred, after_loc, fit_after = _after_stage(cand_out, dec, refits, th, bud)
    lap("after_s")
    cand_out.sort(key=lambda c: -(c["log_bayes_factor"] if c["log_bayes_factor"] is not None else -1e300))
    return Diagnosis(verdict=dec["verdict"], decision=dec, baseline=base.calibration, predictive=base.pred,
                     localisation=base.loc, screening=scr,
                     refits={c: (r.evaluator, r.calibration) for c, r in refits.items()}, candidates=cand_out,
                     fit_before=fit_before, fit_after=fit_after, after_predictive=after_pred,
                     after_localisation=after_loc, thresholds=th, timings=T, evaluator=evaluator,
                     model_error=model_error, consistency=consistency)


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


def _error_at_fit(evaluator, runner, fit, reference, bud: Budgets, seed: int):
    """One grid-error round (module doc of _candidate_grid_error): (ModelError whose mean is the grid's
    error at ``model_error_runs`` draws of ``fit`` (a LocalFit of ``runner``'s model), whose grid-error
    covariance is ``reference``'s and whose release Jacobian (where ``reference`` states a release error) is
    taken at the same draws, {observable: rms shift of the mean in ``evaluator``'s sigmas}, run pairs), or
    None when fewer than 2 run pairs succeeded."""
    from .model_error import approximation_error

    x = fit.draws(bud.model_error_runs, runner.prior.bounds.numpy().astype(np.float64), seed=seed)
    release_sd = reference.release_sd if reference.release_jacobian is not None else 0.0
    try:
        eps = approximation_error(runner, x, reference.factor, release_sd=release_sd)
    except RuntimeError:
        return None
    shift = eps.mean - reference.mean
    sig = np.asarray(evaluator.sigma, dtype=np.float64)
    moved = {b.name: float(np.sqrt(np.mean((shift[b.slice] / sig[b.slice]) ** 2))) for b in evaluator.blocks}
    J = reference.release_jacobian if eps.release_jacobian is None else eps.release_jacobian
    return (dataclasses.replace(reference, samples=reference.samples + shift, release_jacobian=J), moved,
            len(eps.samples))


def _local_baseline(evaluator, pilot, bud: Budgets, log):
    """(evaluator, baseline fit, model-error summary): with model_error_runs > 0 the grid's approximation
    error at draws of the pilot's Laplace posterior enters the likelihood and the baseline is refitted;
    then ``candidate_error_rounds`` times its mean is taken again at draws of the refit and the baseline
    refitted (the candidates get as many rounds: _candidate_grid_error)."""
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
    # the same rounds as the candidates get (_candidate_grid_error): the mean error taken again where the
    # baseline now fits, the covariance kept, so that no model's fit gains from more rounds than another's
    s["rounds"] = []
    for k in range(error_rounds(evaluator, bud)):
        got = _error_at_fit(evaluator, evaluator, f, evaluator.model_error, bud, seed + 6 + k)
        if got is None:
            log("[diagnose] baseline: the grid's error at its fit could not be sampled (fewer than 2 run pairs)")
            break
        me_k, moved, _ = got
        evaluator = evaluator.with_model_error(me_k)
        f, _ = fit_model(evaluator, n_lhs=0, extra_starts=f.x[None], rel_step=bud.local_rel_step,
                         max_iter=bud.local_max_iter, log=log)
        s["rounds"].append(moved)
        log(f"[diagnose] baseline, round {k + 1}: the grid's error at its fit moved by " +
            ", ".join(f"{b} {v:.2g}" for b, v in moved.items()) + " sigma; ln L " + f"{f.log_like:.1f}")
    return evaluator, f, s


def _laplace_ver(f) -> dict:
    """The evidence record of a Laplace fit (the emulator path's verified-evidence keys where they apply)."""
    return {"log_evidence": float(f.log_evidence), "se": 0.0, "ess": None, "method": "laplace",
            "reliable": bool(f.converged and np.all(np.isfinite(f.covariance))), "converged": bool(f.converged),
            "message": f.message, "verified": True}


def _local_candidate(evaluator, cf, base: _Baseline, scr: ScreenResult, bud: Budgets, log):
    """(_Refit, report row) of a candidate's local fit ``cf`` (local_path.CandidateFit): its Laplace
    posterior, posterior-predictive runs, WAIC and re-scoring."""
    c = cf.name
    names = list(evaluator.prior.names) + [CANDIDATES[c].param]
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
           "at_range_end": at_range_end(c, _params(cal)),
           "n_runs": cf.n_runs + len(pred.x), "best_x": cf.fit.x.tolist(), "fit_message": cf.fit.message}
    log(f"[diagnose] local fit {c}: 2 ln BF {cf.two_ln_bf:.1f}, 2 ln LR {cf.lr:.1f} (p {cf.lr_pvalue:.2g}), "
        f"SD {cf.two_ln_bf_savage_dickey:.1f}, dWAIC {row['delta_waic']:.1f}, "
        f"explained (all located) {rs.get('explained_all')}")
    return r, row


def _candidate_grid_error(evaluator, rows: list, fits: dict, refits: dict, base: _Baseline, f0, scr: ScreenResult,
                          bud: Budgets, log) -> None:
    """The grid's approximation error where each of the ``profile_top`` candidates (largest 2 ln BF) fits:
    its mean eps_bar taken again from ``model_error_runs`` run pairs at draws of the candidate's Laplace
    posterior (a term changes where the flow goes, so the grid's error at the baseline's fit is not the
    error at the candidate's), the grid error's covariance kept the baseline's (the evidences'
    normalisations stay comparable), the release volume's Jacobian taken at the same draws (a term such as
    entrainment amplifies a release error; docs/diagnosis.md), and the candidate refitted from its mode
    with it (local_path.refit_with_error), for
    ``candidate_error_rounds`` rounds (a fixed-point iteration: the refit moves the fit, so the error is taken
    again there); the row's ``grid_error_at_fit`` lists per round the shift of eps_bar per observable (rms,
    in the likelihood's sigmas), the 2 ln BF and the switch."""
    from .local_path import refit_with_error

    ranked = sorted((r for r in rows if r["name"] in fits), key=lambda r: -r["two_ln_bf"])[: bud.profile_top]
    me0 = evaluator.model_error
    seed = (bud.seed if bud.model_error_seed is None else bud.model_error_seed) + 7
    for row in ranked:
        c, history = row["name"], []
        for k in range(error_rounds(evaluator, bud)):
            cf = fits[c]
            got = _error_at_fit(evaluator, cf.evaluator, cf.fit, me0, bud, seed + k)
            if got is None:                 # fewer than 2 run pairs succeeded: the error stays as it is
                log(f"[diagnose] {c}: the grid's error at its fit could not be sampled (fewer than 2 run pairs)")
                break
            me_c, moved, n_pairs = got
            new_cf = refit_with_error(cf, me_c, f0, bud, log)
            fits[c] = new_cf
            refits[c], new = _local_candidate(evaluator, new_cf, base, scr, bud, log)
            i = list(new_cf.evaluator.prior.names).index(row["param"])
            history.append({"n": int(n_pairs), "mean_shift_sigma": moved, "two_ln_bf": new["two_ln_bf"],
                            row["param"]: float(new_cf.fit.x[i])})
            log(f"[diagnose] {c}, round {k + 1}: the grid's error at its own fit ({n_pairs} run pairs) "
                f"is {', '.join(f'{b} {v:.2g}' for b, v in moved.items())} sigma from the baseline's; 2 ln BF "
                f"{row['two_ln_bf']:.1f} -> {new['two_ln_bf']:.1f}, {row['param']} {cf.fit.x[i]:.4g} -> "
                f"{new_cf.fit.x[i]:.4g}")
            pairs = 4 if me0.release_jacobian is not None else 2     # coarse, fine (and the release's two)
            runs = new["n_runs"] + (row["n_runs"] - cf.n_runs) + pairs * bud.model_error_runs   # the fits' runs, once
            row.clear()
            row.update(new, n_runs=runs, grid_error_at_fit=history)


def _release_only(me):
    """The release volume's part of a grid-error model (no grid part: the finer grid's runs are the model),
    or None when it states no release error."""
    from .model_error import ModelError

    if me is None or me.release_jacobian is None:
        return None
    return ModelError(samples=np.zeros((2, me.samples.shape[1])), x=me.x[:2], factor=me.factor,
                      release_jacobian=me.release_jacobian, release_sd=me.release_sd)


def _largest_shift(row: dict) -> float:
    """The largest move of the grid's mean error over a candidate's rounds (rms per observation, sigmas)."""
    return max((v for h in row.get("grid_error_at_fit") or () for v in h["mean_shift_sigma"].values()), default=0.0)


def _finer_grid_reason(rows: list, fits: dict, bud: Budgets, bf_min: float) -> str | None:
    """Why the comparison moves to the finer grid (_finer_grid_stage), or None where it stays: a round at a
    fitted candidate moved the grid's mean error by more than ``finer_shift`` sigma, or a fitted candidate
    reaches 2 ln BF >= ``bf_min``; never with ``finer_shift`` <= 0."""
    if bud.finer_shift <= 0:
        return None
    shift = max((_largest_shift(r) for r in rows if r["name"] in fits), default=0.0)
    if shift > bud.finer_shift:
        return f"the grid's error moved by up to {shift:.2g} sigma at a candidate's fit (> {bud.finer_shift:g})"
    if max((r["two_ln_bf"] for r in rows if r["name"] in fits), default=-np.inf) >= bf_min:
        return f"a candidate reaches 2 ln BF >= {bf_min:g}"
    return None


def _finer_grid_stage(evaluator, rows: list, fits: dict, refits: dict, base: _Baseline, f0, scr: ScreenResult,
                      bud: Budgets, log, before: dict, bf_min: float = np.inf) -> tuple[dict | None, tuple | None]:
    """Where the grid's error depends on the parameters more than the rounds can follow (a round at a
    candidate's fit (_candidate_grid_error) moved its mean by more than ``finer_shift`` sigma: threshold terms
    stop the flow in another cell on the finer grid), or where a verdict would rest on a candidate (2 ln BF
    >= ``bf_min`` on the inversion grid: a term that mimics the grid's error must not be named for it), the
    comparison is made on the finer grid itself: the baseline and every candidate with 2 ln BF > 0 on the
    inversion grid, after its rounds or ``before`` them ({name: 2 ln BF}), or a positive screening score,
    fitted again there (finer_grid: every run on the fine terrain, seen on the inversion cells; the same data
    and stated errors, the release volume's error kept, no grid error), each from its fit on the inversion
    grid, their Laplace evidence replacing the inversion grid's in the rows (``finer_grid`` in each row keeps
    the inversion grid's 2 ln BF and switch). Returns (the stage's record, (the finer grid's evaluator, the
    baseline's LocalFit and _Baseline there)), or (None, None) when neither holds."""
    why = _finer_grid_reason(rows, fits, bud, bf_min)
    if why is None:
        return None, None
    # every candidate the inversion grid supported before or after its rounds (the rounds can sink the right
    # one), or that the screening finds the data respond to (its fit there may have stopped short of its mode)
    ranked = [r for r in rows if r["name"] in fits and (max(r["two_ln_bf"], before.get(r["name"], -np.inf)) > 0
                                                        or (r.get("screening_score") or 0.0) > 0)]
    moved = {r["name"]: _largest_shift(r) for r in ranked}
    fine_ev = evaluator._copy(finer_grid=True, model_error=_release_only(evaluator.model_error),
                              fixed=dict(evaluator.fixed))
    log(f"[diagnose] {why}: the baseline and {', '.join(moved)} are fitted again on the finer grid")
    F0, n0 = fit_model(fine_ev, n_lhs=0, extra_starts=f0.x[None], rel_step=bud.local_rel_step,
                       max_iter=bud.local_max_iter, log=log)
    names = list(evaluator.prior.names)
    cal0 = laplace_result(F0, names, evaluator.prior.bounds.numpy(), seed=bud.seed)
    pred0 = posterior_predictive(fine_ev, cal0.samples[: bud.n_posterior_samples_after])
    base_f = _Baseline(cal0, pred0, _laplace_ver(F0), loc=base.loc, elpd=waic(fine_ev, pred0.draws),
                       misfit=fine_ev.misfit(pred0.mean), source="local fit on the finer grid (Laplace)")
    log(f"[diagnose] finer grid, baseline: " + ", ".join(f"{k} {v:.4g}" for k, v in zip(names, F0.x)) +
        f"; ln L {F0.log_like:.1f}" + ("" if F0.converged else f" (not converged: {F0.message})"))
    runs = n0 + len(pred0.x)
    for row in ranked:
        c, cf = row["name"], fits[row["name"]]
        ev_c = candidate_evaluator(fine_ev, c).with_model_error(_release_only(cf.evaluator.model_error))
        fc, n = fit_model(ev_c, n_lhs=0, extra_starts=cf.fit.x[None], rel_step=bud.local_rel_step,
                          max_iter=bud.local_max_iter, log=log)
        new_cf = candidate_fit(c, ev_c, fc, F0, n)
        refits[c], new = _local_candidate(fine_ev, new_cf, base_f, scr, bud, log)
        fits[c] = new_cf
        i = list(ev_c.prior.names).index(row["param"])
        log(f"[diagnose] finer grid, {c}: 2 ln BF {row['two_ln_bf']:.1f} -> {new['two_ln_bf']:.1f}, {row['param']} "
            f"{cf.fit.x[i]:.4g} -> {fc.x[i]:.4g}")
        record = {"two_ln_bf_inversion_grid": row["two_ln_bf"], row["param"] + "_inversion_grid": float(cf.fit.x[i]),
                  "moved_sigma": moved[c]}
        new.update(n_runs=row["n_runs"] + new["n_runs"], grid_error_at_fit=row.get("grid_error_at_fit"),
                   finer_grid=record)
        row.clear()
        row.update(new)
    return ({"moved_sigma": moved, "threshold": bud.finer_shift, "why": why, "candidates": list(moved),
             "baseline_log_evidence": float(F0.log_evidence), "baseline_x": F0.x.tolist(), "n_runs_baseline": int(runs),
             "baseline_converged": bool(F0.converged), "baseline_message": str(F0.message)},
            (fine_ev, F0, base_f))


def _local_profiles(evaluator, rows: list, fits: dict, refits: dict, base: _Baseline, f0, scr: ScreenResult,
                    bud: Budgets, log, fine: tuple | None = None) -> None:
    """profile_ends of the ``profile_top`` candidates with the largest 2 ln BF, into their rows. A profile
    point that beats a fit by more than 1 in 2 ln L restarts that fit from there (local_path.refit_from;
    ``restarted_from_profile`` counts the restarts); the restarted fit is profiled again, up to
    ``profile_restarts`` times, and a fit that its profile still beats is marked unreliable. A profiled
    candidate at its mode gets its 90 % profile-likelihood interval (all of them in lockstep,
    local_path.profile_intervals90) and its 2 ln BF with the switch's factor from the profile
    (local_path.profile_two_ln_bf; ``two_ln_bf_laplace`` keeps the Laplace value). Candidates fitted on the finer grid (_finer_grid_stage) are profiled there, against its baseline (``fine``: the
    stage's (evaluator, baseline LocalFit, _Baseline))."""
    ranked = sorted((r for r in rows if r["name"] in fits), key=lambda r: -r["two_ln_bf"])[: bud.profile_top]
    groups = [[r for r in ranked if ("finer_grid" in r) == on_fine] for on_fine in (False, True)]
    ends = [e for g in groups if g for e in zip(g, profile_ends(evaluator, [fits[r["name"]] for r in g], bud, log))]
    at_mode = []
    for row, (prof, n) in ends:
        c = row["name"]
        ev_r, base_fit, base_r = fine if "finer_grid" in row else (evaluator, f0, base)
        keep = {k: row[k] for k in ("finer_grid", "grid_error_at_fit") if k in row}
        row["profile_ends"], row["n_runs"] = prof, row["n_runs"] + n
        for _ in range(bud.profile_restarts):
            if min(prof["two_ln_drop"]) >= -1.0:    # the profile does not beat the fit
                break
            cf = refit_from(evaluator, fits[c], np.asarray(prof["lowest_point"]), base_fit, bud, log)
            if cf is fits[c]:                       # nothing better from there
                break
            fits[c] = cf
            refits[c], new = _local_candidate(ev_r, cf, base_r, scr, bud, log)
            log(f"[diagnose] {c}: a profile point beat the fit by {-min(prof['two_ln_drop']):.1f}; fitted again "
                f"from it: 2 ln BF {row['two_ln_bf']:.1f} -> {new['two_ln_bf']:.1f}")
            (prof, n2), = profile_ends(evaluator, [cf], bud, log)
            runs, k = row["n_runs"], row.get("restarted_from_profile", 0)
            row.clear()
            row.update(new, **keep, profile_ends=prof, restarted_from_profile=k + 1, n_runs=runs + new["n_runs"] + n2)
        log(f"[diagnose] profile of {c}: 2 ln drop {[round(v, 2) for v in prof['two_ln_drop']]} at "
            f"{row['param']} = {[round(v, 5) for v in prof['interval90']]} (Gaussian {prof['gaussian']:.2f})")
        if min(prof["two_ln_drop"]) < -1.0:         # still beaten: the fit is not at its mode
            row["reliable"] = False
        else:
            at_mode.append((row, c, prof))
    p90s = profile_intervals90(evaluator, [(fits[c], prof) for _, c, prof in at_mode], bud, log=log)
    for (row, c, _), (p90, n3) in zip(at_mode, p90s):
        row["n_runs"] += n3
        row["parameters"][row["param"]]["profile90"] = p90["interval"]
        row["parameters"][row["param"]]["profile90_closed"] = p90["closed"]
        bf = profile_two_ln_bf(fits[c], p90)
        log(f"[diagnose] {c}: 2 ln BF {row['two_ln_bf']:.1f} (Laplace) -> {bf:.1f} with the switch's profile "
            f"likelihood at {len(p90['points'])} points")
        row.update(two_ln_bf_laplace=row["two_ln_bf"], two_ln_bf=bf, two_ln_bf_lower=bf, log_bayes_factor=0.5 * bf,
                   log_evidence_laplace=row["log_evidence"],
                   log_evidence=row["log_evidence"] + 0.5 * (bf - row["two_ln_bf"]), profile_points=p90["points"])
        log(f"[diagnose] {c}: 90 % profile-likelihood interval of {row['param']} "
            f"{[round(v, 5) for v in p90['interval']]}" + ("" if all(p90["closed"]) else " (open: the drop "
            "stays below 2.71 up to there)"))


def _diagnose_local(evaluator, candidates, pilot, why: str, bud: Budgets, th: Thresholds, log, T: dict, lap):
    """The stages of the local path (local_path.py): model error, baseline fit, localisation, screening,
    per-candidate fit and evidence, decision."""
    evaluator, f0, model_error = _local_baseline(evaluator, pilot, bud, log)
    names = list(evaluator.prior.names)
    cal = laplace_result(f0, names, evaluator.prior.bounds.numpy(), seed=bud.seed)
    pred = posterior_predictive(evaluator, cal.samples[: bud.n_posterior_samples])
    base = _Baseline(cal, pred, _laplace_ver(f0), source="local fit (Laplace)")
    lap("baseline_s")
    _assess(evaluator, base, th, bud)
    fit_z = {b: i["Z_fit"] for b, i in base.loc.blocks.items() if i.get("Z_fit") is not None}
    log(f"[diagnose] located {base.loc.n_located} mismatch(es); max |score| {base.loc.max_abs():.2f}")
    lap("predictive_s")
    scr = _screen_stage(evaluator, posterior_mode(base.calibration), candidates, th, bud, log)
    lap("screen_s")
    refits, cand_out, fits = {}, [], {}
    for c, cf in fit_candidates(evaluator, scr.ranking[: bud.top_k], f0, scr.linear_opt, bud, log).items():
        if isinstance(cf, (RuntimeError, np.linalg.LinAlgError)):
            log(f"[diagnose] local fit {c} failed: {cf}")
            cand_out.append(_not_refit(c, scr, f"local fit failed: {cf}"))
            continue
        if isinstance(cf, BaseException):
            raise cf
        refits[c], row = _local_candidate(evaluator, cf, base, scr, bud, log)
        fits[c] = cf
        cand_out.append(row)
    cand_out += [_not_refit(c, scr, "screening score below the top_k") for c in candidates
                 if c not in scr.ranking[: bud.top_k]]
    lap("refit_s")
    if model_error is not None and error_rounds(evaluator, bud) > 0:
        before = {r["name"]: r["two_ln_bf"] for r in cand_out if r["name"] in fits}
        _candidate_grid_error(evaluator, cand_out, fits, refits, base, f0, scr, bud, log)
        lap("candidate_model_error_s")
        finer, fine = _finer_grid_stage(evaluator, cand_out, fits, refits, base, f0, scr, bud, log, before, th.bf_min)
        lap("finer_grid_s")
    else:
        finer = fine = None
    _local_profiles(evaluator, cand_out, fits, refits, base, f0, scr, bud, log, fine=fine)
    lap("profile_s")
    consistency = _consistency_stage(evaluator, scr, log)
    lap("consistency_s")
    fit_before = _fit(evaluator, base.pred, base.loc, base.ver["log_evidence"])
    dec = decide(cand_out, base.loc.located, base.ver, base.misfit, th, fit_z=fit_z)
    dec["resolution"] = base.resolution
    dec["finer_grid"] = finer
    dec.update(fit_z=fit_z, fit_z_source="baseline local fit", baseline_verification=dict(base.ver, source=base.source),
               elpd_waic_baseline=base.elpd["elpd"],
               inference={"path": "local", "why": why, "baseline_converged": bool(f0.converged)})
    if dec.get("alternatives"):
        dec["separate"] = separation(evaluator, refits, dec["alternatives"])
    log(f"[diagnose] verdict {dec['verdict']} ({dec['reason']})")
    after_pred, after_loc, fit_after = _after_stage(cand_out, dec, refits, th, bud)
    lap("after_s")
    cand_out.sort(key=lambda c: -(c["log_bayes_factor"] if c["log_bayes_factor"] is not None else -1e300))
    return Diagnosis(verdict=dec["verdict"], decision=dec, baseline=cal, predictive=base.pred, localisation=base.loc,
                     screening=scr, refits={c: (r.evaluator, r.calibration) for c, r in refits.items()},
                     candidates=cand_out, fit_before=fit_before, fit_after=fit_after, after_predictive=after_pred,
                     after_localisation=after_loc, thresholds=th, timings=T, evaluator=evaluator,
                     model_error=model_error, consistency=consistency)
