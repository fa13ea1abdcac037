"""Posterior-predictive runs of a calibration: what the calibrated model says will happen, with its spread.

M parameter sets drawn from the posterior run in batched solver calls (chunks of ``max_batch``); from
them:

* hazard maps on the DEM grid: the impact probability P(h_max > threshold) per cell (the share of the
  draws that reach it), and per-cell quantiles of h_max, v_max and the deposit h_final;
* each observation's predictive distribution against its recorded value (a posterior-predictive
  check): the model's spread f(x) over the draws, and the spread of a new recording f(x) + e with e
  drawn from the likelihood's error model. A recorded value far in a tail of the latter is one the
  calibrated model does not reproduce (its percentile near 0 or 1);
* where the observations map a footprint (torchslide.survey), each draw's footprint Jaccard, reached
  shares, run-out and volumes against it, as medians and 90 % intervals.

Shapes: M draws, p calibrated parameters, k observations, (ny, nx) the DEM grid.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch

from .survey import (FOOTPRINT_KINDS, crown_point, mapped_footprint, mapped_runout, mismatch_clusters, path_width,
                     run_figures, runout_mismatch, spread)

QUANTILES = (0.05, 0.5, 0.95)


def posterior_samples(cal, M: int, seed: int = 0) -> np.ndarray:
    """(M, p) draws from a CalibrationResult: its MCMC samples (p > 2) or its grid density (p <= 2),
    jittered uniformly within the grid cell (clipped to the prior box)."""
    rng = np.random.default_rng(seed)
    if cal.samples is not None and len(cal.samples):
        idx = rng.choice(len(cal.samples), size=M, replace=len(cal.samples) < M)
        return np.asarray(cal.samples)[idx]
    dens = np.asarray(cal.posterior_grid, dtype=np.float64)
    p = dens.ravel() / dens.sum()
    flat = rng.choice(p.size, size=M, p=p)
    ii = np.unravel_index(flat, dens.shape)
    out = np.empty((M, len(cal.grid_axes)))
    for d, ax in enumerate(cal.grid_axes):
        h = (ax[1] - ax[0]) if len(ax) > 1 else 0.0
        out[:, d] = ax[ii[d]] + rng.uniform(-0.5, 0.5, size=M) * h
        out[:, d] = np.clip(out[:, d], cal.bounds[0, d], cal.bounds[1, d])
    return out


FIGURES = ("impact_area_m2", "runout_m")
"""The figures of every draw (``draw_figures``): its impact area (map m^2 of h_max > threshold) and its run-out
from the release's crown (m, torchslide.survey)."""


def draw_figures(h_max: np.ndarray, dem, release: np.ndarray, threshold: float) -> np.ndarray:
    """(B, 2) FIGURES of the (B, ny, nx) h_max of a run set on ``dem`` (its release (ny, nx), m)."""
    from .survey import runout_from_crown

    reached = np.asarray(h_max) > threshold
    return np.array([[float(r.sum() * dem.cellsize**2), runout_from_crown(dem.z, release, r, dem.cellsize)]
                     for r in reached])


def grid_error(evaluator, x: np.ndarray, threshold: float, factor: int = 2) -> np.ndarray:
    """(n, 2) the grid's error of the FIGURES at the (n, p) parameter sets ``x``: each run on cells ``factor``
    times smaller (the DEM refined, or the evaluator's fine terrain: torchslide.diagnose.model_error) minus
    the same run on the evaluator's grid; rows of failed runs are NaN."""
    from .diagnose.model_error import fine_result, refine_dem

    x = np.atleast_2d(np.asarray(x, dtype=np.float64))
    out = []
    for chunk in evaluator.value_chunks({n: x[:, i] for i, n in enumerate(evaluator.names)}):
        from .physics import Params

        nb = max(np.size(v) for v in chunk.values())
        p = Params.make(B=nb, dtype=evaluator.dtype, device=evaluator.device, **chunk)
        coarse = evaluator.simulate_params(p)
        fine, rel_f = fine_result(evaluator, p, factor)
        ft = getattr(evaluator, "fine_terrain", None)
        dem_f = ft.dem if ft is not None else refine_dem(evaluator.dem, factor)
        d = (draw_figures(fine.h_max.cpu().numpy(), dem_f, rel_f, threshold)
             - draw_figures(coarse.h_max.cpu().numpy(), evaluator.dem, evaluator.release, threshold))
        bad = (fine.failed.cpu().numpy() if fine.failed is not None else False) | \
              (coarse.failed.cpu().numpy() if coarse.failed is not None else False)
        out.append(np.where(np.asarray(bad, bool).reshape(-1, 1), np.nan, d))
    return np.concatenate(out)


def figure_intervals(figures: np.ndarray, error: np.ndarray | None = None, seed: int = 0,
                     level: float = 0.9, cellsize: float = 0.0) -> dict:
    """{figure: {"median", "q05", "q95"}} over the draws' FIGURES (M, 2); with the grid's error ``error``
    (n, 2) also "with_grid_error": the draws spread by a zero-mean normal whose sd is the error's rms
    (sqrt(mean^2 + its variance, plus that of the mean)) and, for the run-out, which a grid of ``cellsize`` m
    knows to a cell, by a uniform error of +- cellsize / 2; {"median", "q05", "q95", "shift", "sd", "n"}
    ("shift": the measured mean difference, "sd": the normal's).

    Zero-mean because the draws come from parameters calibrated on the coarse grid: they absorb the grid's
    bias of the data (all of it for a figure the data pin, none for one they leave free), so its sign on a
    figure is not known, only its size (its coverage, measured by bench/coverage.py: docs/model-error.md)."""
    rng = np.random.default_rng(seed)
    lo_q, hi_q = (1 - level) / 2, 1 - (1 - level) / 2
    out = {}
    for j, name in enumerate(FIGURES):
        f = figures[:, j]
        out[name] = {"median": float(np.median(f)), "q05": float(np.quantile(f, lo_q)), "q95": float(np.quantile(f, hi_q))}
        e = None if error is None else error[np.isfinite(error[:, j]), j]
        if e is None or e.size < 2:
            continue
        sd = float(np.sqrt(e.mean() ** 2 + np.var(e, ddof=1) * (1.0 + 1.0 / e.size)))
        g = f[:, None] + sd * rng.standard_normal((f.size, 200))
        if name == "runout_m":
            g = g + cellsize * rng.uniform(-0.5, 0.5, size=g.shape)
        g = np.maximum(g, 0.0).ravel()          # an area or a length
        out[name]["with_grid_error"] = {"median": float(np.median(g)), "q05": float(np.quantile(g, lo_q)),
                                        "q95": float(np.quantile(g, hi_q)), "shift": float(e.mean()),
                                        "sd": sd, "n": int(e.size)}
    return out


@dataclass
class PredictiveRuns:
    """The successful draws of a posterior-predictive run set.

    x: (M_ok, p) parameters; predictions: (M_ok, k) observables; threshold: m.
    impact_probability: (ny, nx) share of the draws with h_max > threshold.
    cell_area: (ny, nx) map area of each cell, m^2 (what observe's areas sum), so sum(P * cell_area) is
        the draws' mean impact area.
    quantiles: {"h_max" | "v_max" | "h_final": {q: (ny, nx)}} for q in QUANTILES (m, m/s, m).
    n_failed: draws whose run failed (left out; their reasons in ``failures``).
    survey: the draws' figures against the mapped footprints among the observations (torchslide.survey.spread:
        median and 90 % interval of each; {} when none).
    figures: (M_ok, 2) each draw's FIGURES (impact area m^2, run-out from the crown m).
    survey_runs: each draw's figures against the mapped footprints (torchslide.survey.run_figures).
    """

    x: np.ndarray
    predictions: np.ndarray
    threshold: float
    impact_probability: np.ndarray
    cell_area: np.ndarray
    quantiles: dict
    n_failed: int = 0
    failures: list = field(default_factory=list)
    survey: dict = field(default_factory=dict)
    figures: np.ndarray | None = None
    survey_runs: list = field(default_factory=list)


def run_predictive(evaluator, samples: np.ndarray, threshold: float,
                   quantiles: tuple = QUANTILES, progress=None) -> PredictiveRuns:
    """Run ``samples`` (M, p) through ``evaluator`` (a LandslideEvaluator: its terrain, fixed parameters,
    solver settings and observations), ``evaluator.max_batch`` members per solver call, and reduce the
    maps. ``progress``: an optional callable(n_done) after each call. Raises RuntimeError when every run
    failed."""
    x = torch.as_tensor(np.asarray(samples, dtype=np.float64)).reshape(-1, len(evaluator.names))
    keep_x, preds_all, fields, failures = [], [], {"h_max": [], "v_max": [], "h_final": []}, []
    chunks = evaluator.value_chunks({n: x[:, i].numpy() for i, n in enumerate(evaluator.names)})
    starts = list(range(0, x.shape[0], evaluator.max_batch))
    cell_area = None
    tick = None if progress is None else (lambda i, _: progress(min(starts[i] + evaluator.max_batch, x.shape[0])))
    figures, own = [], []
    for s, (preds, failed, why, maps, area, _) in zip(starts, evaluator.map_chunks(evaluator.maps_chunk, chunks, tick)):
        xb = x[s:s + evaluator.max_batch]
        cell_area = np.broadcast_to(area, maps["h_max"].shape[1:])
        ok = ~failed.numpy()
        failures += [{"x": xb[i].tolist(), "reason": why[i]} for i in np.nonzero(~ok)[0]]
        keep_x.append(xb.numpy()[ok])
        preds_all.append(preds.numpy()[ok])
        for name in fields:  # float32 on the host: M maps of the grid fit in memory
            fields[name].append(maps[name][ok])
        figures += _survey_figures(evaluator, maps, ok, threshold)
        own.append(draw_figures(maps["h_max"][ok], evaluator.dem, evaluator.release, threshold))
    maps = {k: np.concatenate(v) for k, v in fields.items()}
    if maps["h_max"].shape[0] == 0:
        raise RuntimeError(f"all {x.shape[0]} posterior-predictive runs failed; first: {failures[0]['reason']}")
    qs = {k: {q: np.quantile(v, q, axis=0).astype(np.float64) for q in quantiles} for k, v in maps.items()}
    return PredictiveRuns(x=np.concatenate(keep_x), predictions=np.concatenate(preds_all), threshold=float(threshold),
                          impact_probability=(maps["h_max"] > threshold).mean(axis=0).astype(np.float64),
                          cell_area=np.broadcast_to(cell_area, maps["h_max"].shape[1:]).copy(), quantiles=qs, n_failed=len(failures), failures=failures,
                          survey=spread(figures), figures=np.concatenate(own), survey_runs=figures)


def _survey_figures(evaluator, maps: dict, ok: np.ndarray, threshold: float) -> list[dict]:
    """torchslide.survey.run_figures of each successful member of a chunk of maps (float64)."""
    dz = maps.get("elevation_change")
    return [run_figures(maps["h_max"][i].astype(np.float64), None if dz is None else dz[i].astype(np.float64),
                        evaluator.observations, evaluator.dem.z, evaluator.release, evaluator.dem.cellsize, threshold)
            for i in np.nonzero(ok)[0]]


def predictive_sd(evaluator, predictions: np.ndarray, seed: int = 0) -> np.ndarray:
    """(M, k) the sd of a new recording per draw: the likelihood's marginal sd, times sqrt(u) where the
    evaluator learns the model's own error (u drawn per draw and observation from its posterior given the
    draw's misfit: torchslide.discrepancy.DiscrepancyLikelihood.sample_variance_factors)."""
    from .discrepancy import DiscrepancyLikelihood

    sd = np.broadcast_to(evaluator.observation_sd(), np.shape(predictions)).copy()
    lik = evaluator.likelihood
    if not isinstance(lik, DiscrepancyLikelihood):
        return sd
    return sd * np.sqrt(lik.sample_variance_factors(predictions, np.random.default_rng(seed)))


def with_model_error(checks: list[dict], predictions: np.ndarray, values: np.ndarray, sd: np.ndarray,
                     seed: int = 0, level: float = 0.9, lower: np.ndarray | None = None) -> list[dict]:
    """``checks`` (observation_check's, with the stated errors) with each observation's ``level`` interval of a
    new recording when the model's own error is counted too (``sd`` (M, k): predictive_sd's), as
    ``interval90_model_error``, ``inside_model_error`` and ``sigma_model_error`` (the median sd)."""
    key = f"interval{int(round(level * 100))}"
    wide = observation_check(predictions, values, sd, [c["name"] for c in checks], seed=seed, level=level, lower=lower)
    for c, w in zip(checks, wide):
        c[key + "_model_error"], c["inside_model_error"], c["sigma_model_error"] = w[key], w["inside"], w["sigma"]
    return checks


def observation_check(predictions: np.ndarray, values: np.ndarray, sigma: np.ndarray, names, seed: int = 0,
                      level: float = 0.9, lower: np.ndarray | None = None) -> list[dict]:
    """Each observation's predictive distribution against its recorded value.

    predictions: (M, k) f(x) of the draws; values: (k,) recorded; sigma: (k,) the likelihood's marginal
    sd, or (M, k) one per draw (the stated sd times sqrt(u), u the variance factor of the model's own error
    drawn given that draw: torchslide.discrepancy.sample_inflation); lower: (k,) the least value a
    recording can take (0 for speeds, thicknesses, areas, volumes; -inf or None: unbounded). Per
    observation: the model's mean, sd and quantiles over the draws; the ``level`` interval of a new
    recording max(lower, f(x) + e), e ~ N(0, sigma^2) (200 e per draw); the recorded value's percentile in
    that distribution, and whether it lies inside the interval; ``sigma`` the median sd used.
    """
    rng = np.random.default_rng(seed)
    P = np.asarray(predictions, dtype=np.float64)
    sd = np.broadcast_to(np.asarray(sigma, dtype=np.float64), P.shape)
    lo_q, hi_q = (1 - level) / 2, 1 - (1 - level) / 2
    out = []
    low = np.full(P.shape[1], -np.inf) if lower is None else np.asarray(lower, dtype=np.float64)
    for j, name in enumerate(names):
        f = P[:, j]
        rep = np.maximum(low[j], (f[:, None] + sd[:, j, None] * rng.standard_normal((f.size, 200))).ravel())
        lo, hi = np.quantile(rep, [lo_q, hi_q])
        v = float(values[j])
        out.append({"name": str(name), "value": v, "sigma": float(np.median(sd[:, j])),
                    "model_mean": float(f.mean()), "model_sd": float(f.std(ddof=1)) if f.size > 1 else 0.0,
                    "model_quantiles": {f"{q:g}": float(np.quantile(f, q)) for q in QUANTILES},
                    f"interval{int(round(level * 100))}": [float(lo), float(hi)],
                    "percentile": float((rep < v).mean()), "inside": bool(lo <= v <= hi)})
    return out


def footprint_mismatches(evaluator, pr: PredictiveRuns) -> dict | None:
    """Where the draws ``pr`` and the first mapped footprint among the evaluator's observations disagree:
    {"footprint": its name, "clusters": torchslide.survey.mismatch_clusters against the impact probability
    (excess and deficit, with the median run's flow and the survey's change as volumes), "runout": the draws'
    run-out against the mapped one (torchslide.survey.runout_mismatch), "path_width": whether the grid holds the
    mapped path (torchslide.survey.path_width), "mapped": (ny, nx) bool}; None without a mapped footprint."""
    obs = next((o for o in evaluator.observations if getattr(o, "kind", None) in FOOTPRINT_KINDS), None)
    if obs is None:
        return None
    mapped = mapped_footprint(obs)
    dod = next((o.to_grid(o.values) for o in evaluator.observations
                if getattr(o, "kind", None) == "elevation_change"), None)
    clusters = mismatch_clusters(pr.impact_probability, mapped, evaluator.dem, evaluator.release,
                                 h_p50=pr.quantiles["h_max"][0.5], survey_dz=dod)
    crown = crown_point(evaluator.dem, evaluator.release)
    runout = runout_mismatch(pr.figures[:, 1], mapped_runout(mapped, evaluator.dem, point=crown))
    return {"footprint": str(obs.name), "clusters": clusters, "runout": runout, "mapped": mapped,
            "path_width": path_width(mapped, evaluator.dem, evaluator.release)}
