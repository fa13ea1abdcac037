"""``torchslide diagnose CONFIG.toml --out DIR``: find, name and refit missing physics.

The config is the ``calibrate`` config (see torchslide.commands.calibrate) plus vector observations
and a [diagnose] section::

    [[observations]]             # gauge series: CSV with t,h and/or t,speed (times strictly increasing)
    kind = "gauge_series"
    file = "g1.csv"
    gauge = "G1"                 # a [[gauges]] name
    sigma = { h = 0.5, speed = 2.0 }   # or one number for every column
    corr_time = 4.0              # optional exponential correlation time, s

    [[observations]]             # maps on the DEM grid (ESRI ASCII / GeoTIFF; nodata = not mapped)
    kind = "deposit_map"         # or "impact_map" (0/1 raster, threshold = 0.5 m)
    file = "deposit.asc"
    sigma = 0.5
    corr_length = 60.0           # optional exponential correlation length, m

    [diagnose]
    candidates = ["entrainment", "curvature", "earth_pressure", "yield_stress", "mu_i"]
    n_posterior_samples = 32     # baseline posterior-predictive members
    n_posterior_samples_after = 16
    n_initial = 16               # refit budgets
    n_total = 32
    top_k = 2                    # candidates refitted
    batch_size = 8
    n_perm = 99                  # permutations for the map cluster p-values
    bf_min = 6.0                 # decision thresholds (torchslide.diagnose.decide.Thresholds)
    margin_min = 6.0
    located_min = 8.0
    z_threshold = 3.0

The baseline calibration uses [calibration] n_initial / n_total / batch_size / seed. Writes DIR/report.json,
DIR/report.md and figures. Bad input (a gauge series with non-increasing times, a map on another grid,
an unknown candidate, ...) stops with exit code 2 before any run.
"""
from __future__ import annotations

import argparse
import math
from pathlib import Path
from typing import Any

from ..config import Config, ConfigError, check_keys, load_config
from ..observe import Observation
from .calibrate import check_unique_names, parse_calibration, parse_prior

HELP = "diagnose missing physics: locate misfit, screen candidate terms, refit, compare evidence"

_DIAG_KEYS = {"candidates", "n_posterior_samples", "n_posterior_samples_after", "n_initial", "n_total", "top_k",
              "batch_size", "n_perm", "seed", "bf_min", "margin_min", "located_min", "z_threshold"}
_VEC_KEYS = {"gauge_series": {"kind", "file", "gauge", "sigma", "corr_time", "name", "quantities"},
             "deposit_map": {"kind", "file", "sigma", "corr_length", "name"},
             "impact_map": {"kind", "file", "sigma", "corr_length", "name", "threshold"}}


def parse_observations(table: Any, cfg: Config) -> list:
    """[[observations]]: scalar kinds as in calibrate, plus gauge_series / deposit_map / impact_map."""
    from ..observe_series import GaugeSeriesError, SeriesObservation

    path = cfg.path
    if not isinstance(table, list) or not table:
        raise ConfigError(f"{path}: [[observations]] must list at least one observation")
    out = []
    gauges = {g.name for g in cfg.gauges}
    dem = cfg.terrain.dem
    for i, d in enumerate(table):
        if not isinstance(d, dict):
            raise ConfigError(f"{path}: observation {i + 1} must be a table")
        kind = d.get("kind")
        where = f"observation {i + 1} ({kind})"
        if kind in _VEC_KEYS:
            check_keys(d, _VEC_KEYS[kind], where, path)
            if "file" not in d or "sigma" not in d:
                raise ConfigError(f"{path}: {where}: 'file' and 'sigma' are required")
            f = cfg.resolve(d["file"])
            try:
                if kind == "gauge_series":
                    if d.get("gauge") not in gauges:
                        raise ConfigError(f"{path}: {where}: gauge {d.get('gauge')!r} is not a [[gauges]] name "
                                          f"(known: {sorted(gauges)})")
                    obs = SeriesObservation.from_gauge_csv(f, d["gauge"], d["sigma"], quantities=d.get("quantities"),
                                                           corr_time=d.get("corr_time"), name=d.get("name"))
                    for o in obs:
                        o.validate(dem, sorted(gauges))
                    out += obs
                else:
                    o = SeriesObservation.from_raster(f, kind, dem, float(d["sigma"]), name=d.get("name", kind),
                                                      corr_length=d.get("corr_length"),
                                                      threshold=float(d.get("threshold", 0.5)))
                    out.append(o.validate(dem))
            except GaugeSeriesError as e:
                raise ConfigError(f"{path}: {where}: {e}") from None
            except (TypeError, ValueError) as e:
                if type(e).__name__ == "TerrainError":
                    raise
                raise ConfigError(f"{path}: {where}: {e}") from None
            continue
        try:
            o = Observation.from_dict(dict(d))
            o.validate(dem)
        except ValueError as e:
            raise ConfigError(f"{path}: observation {i + 1}: {e}") from None
        out.append(o)
    check_unique_names(out, path)
    return out


def parse_diagnose(table: Any, cfg: Config) -> dict:
    from ..physics import CANDIDATES

    path = cfg.path
    check_keys(table, _DIAG_KEYS, "[diagnose]", path)
    c = {"candidates": list(CANDIDATES), "n_posterior_samples": 32, "n_posterior_samples_after": 16,
         "n_initial": 16, "n_total": 32, "top_k": 2, "batch_size": 8, "n_perm": 99, "seed": 0,
         "bf_min": 6.0, "margin_min": 6.0, "located_min": 8.0, "z_threshold": 3.0}
    c.update(table)
    if not isinstance(c["candidates"], list) or not c["candidates"]:
        raise ConfigError(f"{path}: [diagnose] candidates must be a non-empty list of names")
    bad = [n for n in c["candidates"] if n not in CANDIDATES]
    if bad:
        raise ConfigError(f"{path}: [diagnose] unknown candidate(s) {bad} (known: {', '.join(CANDIDATES)})")
    for k in ("n_posterior_samples", "n_posterior_samples_after", "n_initial", "n_total", "top_k", "batch_size", "n_perm"):
        if not isinstance(c[k], int) or isinstance(c[k], bool) or c[k] < 1:
            raise ConfigError(f"{path}: [diagnose] {k} must be a positive integer, got {c[k]!r}")
    if c["n_total"] < c["n_initial"]:
        raise ConfigError(f"{path}: [diagnose] n_total ({c['n_total']}) must be >= n_initial ({c['n_initial']})")
    for k in ("bf_min", "margin_min", "located_min", "z_threshold"):
        if not isinstance(c[k], (int, float)) or not math.isfinite(c[k]):
            raise ConfigError(f"{path}: [diagnose] {k} must be a number, got {c[k]!r}")
    return c


SECTIONS = {"prior": parse_prior, "observations": parse_observations, "calibration": parse_calibration,
            "diagnose": parse_diagnose}


def load_diagnose_config(path) -> Config:
    cfg = load_config(path, extra_sections=SECTIONS)
    for sec in ("prior", "observations"):
        if sec not in cfg.extra:
            raise ConfigError(f"{cfg.path}: section [{sec}] is missing (needed to diagnose)")
    cfg.extra.setdefault("calibration", parse_calibration({}, cfg))
    cfg.extra.setdefault("diagnose", parse_diagnose({}, cfg))
    if cfg.batch_size != 1:
        raise ConfigError(f"{cfg.path}: [model] must give single values when diagnosing, got a batch of {cfg.batch_size}")
    return cfg


def make_evaluator(cfg: Config):
    from ..diagnose import DiagnosisEvaluator

    prior = cfg.extra["prior"]
    fixed = {k: (float(v[0]) if isinstance(v, (list, tuple)) else float(v))
             for k, v in cfg.model.values.items() if k not in prior.names}
    try:
        return DiagnosisEvaluator(
            dem=cfg.terrain.dem, release=cfg.terrain.release, observations=cfg.extra["observations"], prior=prior,
            fixed=fixed, t_end=cfg.run.t_end, gauges=[(g.name, g.x, g.y) for g in cfg.gauges],
            erodible_depth=cfg.terrain.erodible_depth, solver_config=cfg.solver_config(), dtype=cfg.run.torch_dtype,
            device=cfg.run.device, max_batch=cfg.extra["calibration"]["max_batch"])
    except ValueError as e:
        if type(e).__name__ == "TerrainError":
            raise
        raise ConfigError(f"{cfg.path}: {e}") from None


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("config", help="TOML config (calibrate config + [diagnose], vector observations)")
    p.add_argument("--out", required=True, help="output folder (report.json, report.md, figures)")
    p.add_argument("--quiet", action="store_true", help="no progress lines")


def run(args: argparse.Namespace) -> int:
    from ..diagnose import Budgets, Thresholds, diagnose
    from ..diagnose.report import write_report

    cfg = load_diagnose_config(args.config)
    ev = make_evaluator(cfg)
    cal, dg = cfg.extra["calibration"], cfg.extra["diagnose"]
    if "entrainment" in dg["candidates"] and cfg.terrain.erodible_depth is None:
        raise ConfigError(f"{cfg.path}: candidate 'entrainment' needs an erodible depth raster ([terrain] erodible)")
    bud = Budgets(n_posterior_samples=dg["n_posterior_samples"], n_posterior_samples_after=dg["n_posterior_samples_after"],
                  n_initial=dg["n_initial"], n_total=dg["n_total"], baseline_n_initial=cal["n_initial"],
                  baseline_n_total=cal["n_total"], batch_size=dg["batch_size"], top_k=dg["top_k"], n_perm=dg["n_perm"],
                  seed=dg["seed"])
    th = Thresholds(bf_min=float(dg["bf_min"]), margin_min=float(dg["margin_min"]),
                    located_min=float(dg["located_min"]), z_threshold=float(dg["z_threshold"]))
    out = Path(args.out)
    d = diagnose(ev, dg["candidates"], bud, th, log=(lambda s: None) if args.quiet else print)
    write_report(d, out)
    print(f"verdict: {d.verdict}" + (f" ({d.missing_physics})" if d.missing_physics else "") + f"; report in {out}")
    return 0
