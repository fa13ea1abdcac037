"""Decision thresholds set on null data of the user's own design (a parametric bootstrap of the baseline).

The verdict's thresholds (decide.Thresholds: bf_min, located_min, fit_max) must come from data with
nothing missing, and what such data give depends on the design: the grid, the observations, their
errors, the terrain. This module makes such data for the user's case and runs the whole diagnosis
on each:

1. n parameter sets theta_i from the posterior draws of the baseline the data's verdict rests on
   (Diagnosis.predictive.x: the local fit's Laplace draws or the calibration's posterior), taken in one
   fixed random order of the draws: the first
   n of it, so that a calibration with more runs starts with the runs of one with fewer;
2. each run on cells ``factor`` times smaller than the inversion grid (model_error.fine_run: the user's
   fine terrain when given, else the DEM interpolated bilinearly), seen on the inversion grid, with the
   release volume scaled by (1 + delta_i), delta_i uniform with sd ``release_sd`` (0: exact), and
   Gaussian noise of the error model the user stated (per value sigma; maps and series with their
   exponential correlation of corr_length: SeriesObservation.sample_errors), not the likelihood's
   stand-in for it (independent values of the wider sigma_eff):

       d_i = y_{h/f}(theta_i; V (1 + delta_i)) + e_i,   e_i ~ N(0, Sigma_stated)

   delta_i and e_i from a random stream of their own per i (seed, i);
3. the diagnosis (pipeline.diagnose, same candidates and budgets, seed + 101 + i, the detectable switches
   linearised: no statistic below uses them) on each d_i, recording
   the largest lower-bound 2 ln BF of any refitted candidate, the largest located |score| and every
   observable's Z_fit of the calibrated baseline;
4. thresholds by the rule :data:`RULE` (:func:`thresholds_from_null`; the blind test's calibrate_thresholds uses it too):

       bf_min = max(6, 1.25 max_i 2 ln BF_lower,i),  located_min = max(8, 1.25 max_i |score|_i),
       fit_max_b = mean_b + t_{n-1}(1 - alpha / B) sd_b sqrt(1 + 1/n)   (n >= 3 null cases; B observables)

   the other thresholds are kept (and fit_max when n < 3).

What it cannot include: whatever the finer grid does not know about the real terrain (a DEM error, a
channel the DEM smooths away) and errors larger than the stated sigmas. A null level from this
bootstrap is the level for a world in which the baseline and the stated errors are right; with a fine
terrain (``[diagnose] fine_terrain``) it also carries the DEM's resolution. The cost is n whole
diagnoses.
"""
from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import shutil
from pathlib import Path

import numpy as np

from ..files import write_text_atomic
from .model_error import fine_predictions

RULE = ("bf_min = max(6, 1.25 x the largest lower-bound 2 ln BF of any refitted candidate on the null cases); "
        "located_min = max(8, 1.25 x the largest located |score|); fit_max per observable = mean + "
        "t_{n-1}(1 - 0.05/B) sd sqrt(1 + 1/n) of the null cases' Z_fit (n >= 3; B observables)")


def fit_max_from_null(rows: list, alpha: float = 0.05) -> dict:
    """{observable: fit_max} from null Z_fit rows [{observable: Z_fit}] (module doc, step 4): a one-sided
    (1 - alpha) prediction bound for a new null case, Bonferroni over the observables; observables with
    fewer than 3 null values get no level."""
    from scipy import stats as st

    vals = {}
    for r in rows:
        for k, v in r.items():
            if v is not None and math.isfinite(v):
                vals.setdefault(k, []).append(float(v))
    vals = {k: np.asarray(v) for k, v in vals.items() if len(v) >= 3}
    B = max(len(vals), 1)
    out = {}
    for k, v in vals.items():
        n = len(v)
        q = st.t.ppf(1 - alpha / B, n - 1)
        out[k] = float(v.mean() + q * v.std(ddof=1) * np.sqrt(1 + 1 / n))
    return out


def thresholds_from_null(stats: dict, fit_rows: list | None = None) -> dict:
    """Thresholds (a dict of decide.Thresholds fields) from null statistics {"bf": [largest lower-bound
    2 ln BF per case], "located": [largest located |score| per case]} and optional Z_fit rows (module doc)."""
    th = {"bf_min": max(6.0, 1.25 * max(stats["bf"], default=0.0)),
          "located_min": max(8.0, 1.25 * max(stats["located"], default=0.0)),
          "waic_min": 6.0, "margin_min": 6.0, "explain_min": 0.5, "ess_min": 2.0, "z_threshold": 3.0}
    if fit_rows:
        fm = fit_max_from_null(fit_rows)
        if fm:
            th["fit_max"] = fm
    return th


def with_data(evaluator, data: np.ndarray):
    """A copy of ``evaluator`` (no model error) whose observations hold ``data`` (k,) in its flat order."""
    data = np.asarray(data, dtype=np.float64).reshape(-1)
    if data.size != evaluator.k:
        raise ValueError(f"data has {data.size} values, the evaluator's observations {evaluator.k}")
    obs = []
    for b in evaluator.blocks:
        o = b.obs
        v = data[b.slice]
        obs.append(dataclasses.replace(o, values=v.copy()) if b.is_vector
                   else dataclasses.replace(o, value=float(v[0])))
    return evaluator._copy(observations=obs, model_error=None)


NOISE_MODEL = "stated"   # the null runs' noise (module doc, step 2); a checkpoint with another is run again


def stated_errors(evaluator, rng: np.random.Generator) -> np.ndarray:
    """(k,) one draw of the stated measurement errors of every observation, in the evaluator's flat order:
    SeriesObservation.sample_errors for maps and series, N(0, sigma^2) for scalar observations."""
    e = np.empty(evaluator.k)
    for b in evaluator.blocks:
        o = b.obs
        e[b.slice] = o.sample_errors(rng, 1)[0] if b.is_vector else float(o.sigma) * rng.standard_normal()
    return e


def null_recordings(evaluator, theta: np.ndarray, factor: int = 2, release_sd: float = 0.0,
                    seed: int = 0, noise: bool = True, start: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """(data (n, k), release factors (n,)): null recordings at the (n, p) parameter sets ``theta`` (module
    doc, step 2); recording i from the random stream (seed, start + i), so that it does not depend on n.
    ``evaluator``: without model error; ``noise`` False: the finer-grid runs alone. Raises RuntimeError when a
    run fails on the finer grid."""
    if getattr(evaluator, "model_error", None) is not None:
        raise ValueError("null_recordings needs the evaluator without model error (the measurement errors alone)")
    if not 0 <= release_sd < 0.5:
        raise ValueError(f"release_volume_sd must be in [0, 0.5) (a relative sd), got {release_sd!r}")
    theta = np.asarray(theta, dtype=np.float64).reshape(-1, len(evaluator.names))
    n = len(theta)
    a = math.sqrt(3.0) * release_sd
    out = np.empty((n, evaluator.k))
    vf = np.ones(n)
    for i in range(n):
        rng = np.random.default_rng([seed, start + i])
        vf[i] = 1.0 + rng.uniform(-a, a) if a > 0 else 1.0
        ev = evaluator
        if vf[i] != 1.0:
            ft = getattr(evaluator, "fine_terrain", None)
            if ft is not None:
                ft = dataclasses.replace(ft, release=np.asarray(ft.release) * vf[i])
            ev = evaluator._copy(release=np.asarray(evaluator.release, np.float64) * vf[i], fine_terrain=ft)
        y, failed = fine_predictions(ev, theta[i:i + 1], factor)
        if failed[0]:
            raise RuntimeError(f"null recording {i}: the finer-grid run at {theta[i].tolist()} failed")
        out[i] = y[0] + (stated_errors(evaluator, rng) if noise else 0.0)
    return out, vf


def _case_workdir(path: Path, data: np.ndarray, candidates, budgets) -> Path:
    """``path`` for a null case's checkpoints: its active-learning checkpoints do not know the data they
    were made on, so the folder is cleared unless recording.sha256 in it names this recording, candidates
    and budgets (an interrupted case resumes; one whose recording changed starts afresh)."""
    key = hashlib.sha256(np.ascontiguousarray(data, dtype=np.float64).tobytes()
                         + json.dumps([list(candidates), dataclasses.asdict(budgets)], sort_keys=True,
                                      default=str).encode()).hexdigest()
    stamp = path / "recording.sha256"
    if path.exists() and not (stamp.exists() and stamp.read_text() == key):
        shutil.rmtree(path)
    path.mkdir(parents=True, exist_ok=True)
    stamp.write_text(key)
    return path


def null_case_statistics(diag) -> dict:
    """The statistics a null case contributes (module doc, step 3) from a pipeline.Diagnosis, with every
    refitted candidate's lower-bound 2 ln BF (``lower_by_candidate``: which terms the grid's error and the
    noise favour when nothing is missing; the report shows how often each comes out best)."""
    by = {c["name"]: float(c["two_ln_bf_lower"]) for c in diag.candidates if c.get("two_ln_bf_lower") is not None}
    loc = [abs(x["standardised_residual"]) for x in diag.localisation.located]
    return {"max_two_ln_bf_lower": float(max(by.values(), default=float("-inf"))),
            "max_located": float(max(loc, default=0.0)), "lower_by_candidate": by,
            "fit_z": dict(diag.decision.get("fit_z") or {}), "verdict": diag.verdict,
            "missing_physics": diag.missing_physics}


def null_calibration(evaluator, candidates, budgets, thresholds, posterior_draws, n: int, workdir,
                     log=print) -> dict:
    """Thresholds from ``n`` null recordings of this design (module doc). ``evaluator``: the real data's
    evaluator without model error; ``posterior_draws``: (M, p) parameter sets of the data's baseline posterior
    (Diagnosis.predictive.x), the first n of one fixed random order of them (cycling when M < n);
    ``workdir``: one JSON per finished null case (a rerun with the same seed skips them: an interrupted
    calibration resumes, and one with more runs starts with those of one with fewer; a case whose theta or noise
    model differs is run again) and each case's checkpoints in case_<i>/, kept for a rerun only while the
    recording, candidates and budgets are the same (recording.sha256), else cleared.
    Returns {"n", "rule", "cases": [statistics + theta, release_factor], "thresholds": decide.Thresholds,
    "noise_model", "release_volume_sd", "terrain"} (terrain: "fine_terrain" when the finer runs used the user's
    finer DEM, "interpolated" when they used the inversion DEM interpolated bilinearly):
    bf_min, located_min and (n >= 3) fit_max set on the null cases, the other fields those of ``thresholds``."""
    from .pipeline import diagnose

    if n < 1:
        raise ValueError(f"null runs must be >= 1, got {n}")
    workdir = Path(workdir)
    workdir.mkdir(parents=True, exist_ok=True)
    pool = np.asarray(posterior_draws, dtype=np.float64).reshape(-1, len(evaluator.names))
    if not len(pool):
        raise ValueError("null runs need posterior draws of the baseline, got none")
    order = np.random.default_rng(budgets.seed + 97).permutation(len(pool))
    theta = pool[order[np.arange(n) % len(pool)]]      # module doc, step 1 (cycling when M < n)
    cases = []
    for i in range(n):
        f = workdir / f"null_{i}.json"
        if f.exists():
            c = json.loads(f.read_text())
            if c.get("theta") == theta[i].tolist() and c.get("noise_model") == NOISE_MODEL:
                cases.append(c)
                log(f"[null] case {i + 1}/{n}: done earlier")
                continue
        d_i, vf = null_recordings(evaluator, theta[i:i + 1], budgets.model_error_factor, budgets.release_volume_sd,
                                  seed=budgets.seed + 98, start=i)
        log(f"[null] case {i + 1}/{n}: theta {np.round(theta[i], 4).tolist()}, release x{vf[0]:.3f}")
        bud_i = dataclasses.replace(budgets, seed=budgets.seed + 101 + i, detectability="linearised")
        d = diagnose(with_data(evaluator, d_i[0]), candidates, bud_i, thresholds, log=lambda s: None,
                     workdir=_case_workdir(workdir / f"case_{i}", d_i[0], candidates, bud_i))
        c = dict(null_case_statistics(d), theta=theta[i].tolist(), release_factor=float(vf[0]),
                 noise_model=NOISE_MODEL)
        write_text_atomic(f, json.dumps(c, indent=1))
        log(f"[null] case {i + 1}/{n}: largest lower 2 ln BF {c['max_two_ln_bf_lower']:.1f}, largest located "
            f"{c['max_located']:.1f}, verdict {c['verdict']}")
        cases.append(c)
    th = thresholds_from_null({"bf": [c["max_two_ln_bf_lower"] for c in cases],
                               "located": [c["max_located"] for c in cases]},
                              [c["fit_z"] for c in cases if c["fit_z"]] if n >= 3 else None)
    # bf_min, located_min and (n >= 3) fit_max from the null cases; every other threshold as given
    new = dataclasses.replace(thresholds, bf_min=th["bf_min"], located_min=th["located_min"],
                              fit_max=th.get("fit_max", thresholds.fit_max))
    return {"n": n, "rule": RULE, "cases": cases, "thresholds": new, "noise_model": NOISE_MODEL,
            "release_volume_sd": float(budgets.release_volume_sd),
            "terrain": "fine_terrain" if getattr(evaluator, "fine_terrain", None) is not None else "interpolated"}
