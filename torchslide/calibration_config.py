"""The calibration case file: the ``simulate`` config plus [prior], [[observations]] and [calibration].

``load_calibration_config(path)`` reads and checks it (ConfigError naming the file, field and value);
``make_evaluator(cfg)`` turns it into the solver-backed log-posterior of torchslide.evaluator;
``load_calibration(folder, prior)`` reads a finished calibration and checks it belongs to the config.
Used by the calibrate, predict, sweep and diagnose commands.

    [prior]                      # one entry per calibrated parameter (names of torchslide.physics.Params)
    mu = [0.02, 0.3]             # uniform on [low, high]
    xi = { dist = "lognormal", mean_log = 6.9, sd_log = 0.5, low = 100, high = 2200 }
    # dist = "uniform" | "truncnormal" (mean, sd) | "lognormal" (mean_log, sd_log) | "gamma" (concentration, rate)

    [[observations]]
    kind = "max_velocity"        # impact_area, deposit_area, deposit_volume, max_velocity, deposit_height, ...
    x = 1500.0                   # map coordinates (m) for point kinds
    y = 900.0
    value = 29.4
    sigma = 2.94

    [calibration]
    n_initial = 40               # maximin Latin hypercube
    n_total = 120
    batch_size = 4               # q points per iteration, run as one solver batch
    seed = 0
    grid_size = 100
    acquisition = "entropy"      # or "expvar"
    tv_threshold = 0.0           # optional early stop on TV(p_i, p_{i-10})
    max_batch = 32               # most members per solver call
    inference = "auto"           # "auto": a posterior whose 90 % region fills less than local_max_fraction of
    local_max_fraction = 0.05    #     the prior box is fitted on the solver (mode + Laplace); "emulator" | "local"
    truth = { mu = 0.23, xi = 1000.0 }   # optional, synthetic cases: drawn as a cross, reported in posterior.json
"""
from __future__ import annotations

import json
import math
from typing import Any

import numpy as np

from .config import Config, ConfigError, check_keys, load_config
from .observe import Observation

_CAL_KEYS = {"n_initial", "n_total", "batch_size", "seed", "grid_size", "acquisition", "tv_threshold",
             "max_batch", "clip_range", "truth", "inference", "local_max_fraction", "discrepancy"}
_PRIOR_DISTS = {
    "uniform": ({"low", "high"}, set()),
    "truncnormal": ({"low", "high", "mean", "sd"}, set()),
    "lognormal": ({"low", "high", "mean_log", "sd_log"}, set()),
    "gamma": ({"low", "high", "concentration", "rate"}, set()),
}


_PRIOR_ARGS = {"truncnormal": {"mean": "loc", "sd": "scale"}, "lognormal": {"mean_log": "mu", "sd_log": "sigma"}}


def parse_prior(table: Any, cfg: Config):
    """[prior] -> torchslide.bayes.Prior (raises ConfigError naming the parameter)."""
    from .bayes import Gamma, LogNormal, Prior, TruncatedNormal, Uniform
    from .physics import Params, check_range

    path = cfg.path
    if not isinstance(table, dict) or not table:
        raise ConfigError(f"{path}: [prior] must list at least one parameter, e.g. mu = [0.02, 0.3]")
    comps = {}
    for name, spec in table.items():
        if name not in Params.names():
            raise ConfigError(f"{path}: [prior] unknown parameter {name!r} (known: {', '.join(Params.names())})")
        try:
            if isinstance(spec, list):
                if len(spec) != 2:
                    raise ConfigError(f"{path}: [prior] {name} must be [low, high], got {spec!r}")
                low, high = float(spec[0]), float(spec[1])
                if not (math.isfinite(low) and math.isfinite(high)) or low >= high:
                    raise ConfigError(f"{path}: [prior] {name}: need low < high, got low={low}, high={high}")
                comps[name] = Uniform(low, high)
                continue
            if not isinstance(spec, dict):
                raise ConfigError(f"{path}: [prior] {name} must be [low, high] or a table with dist, got {spec!r}")
            dist = spec.get("dist", "uniform")
            if dist not in _PRIOR_DISTS:
                raise ConfigError(f"{path}: [prior] {name}: unknown dist {dist!r} (known: {', '.join(_PRIOR_DISTS)})")
            allowed = _PRIOR_DISTS[dist][0] | {"dist"}
            check_keys(spec, allowed, f"[prior] {name}", path)
            missing = sorted(_PRIOR_DISTS[dist][0] - set(spec))
            if missing:
                raise ConfigError(f"{path}: [prior] {name}: dist {dist!r} needs {', '.join(missing)}")
            rename = _PRIOR_ARGS.get(dist, {})      # config key -> torchslide.bayes constructor argument
            kw = {rename.get(k, k): float(v) for k, v in spec.items() if k != "dist"}
            cls = {"uniform": Uniform, "truncnormal": TruncatedNormal, "lognormal": LogNormal, "gamma": Gamma}[dist]
            comp = cls(**kw)
            comp._check(name)
            comps[name] = comp
        except ConfigError:
            raise
        except (TypeError, ValueError) as e:
            raise ConfigError(f"{path}: [prior] {name}: {e}") from None
    try:
        for name, comp in comps.items():       # a range the model refuses (mu <= 0, a switch beyond 1, ...)
            check_range(name, comp.low, comp.high)
        return Prior(comps)
    except ValueError as e:
        raise ConfigError(f"{path}: [prior] {e}") from None


_VEC_KEYS = {"gauge_series": {"kind", "file", "gauge", "sigma", "corr_time", "name", "quantities"},
             "deposit_map": {"kind", "file", "sigma", "corr_length", "name"},
             "impact_map": {"kind", "file", "sigma", "corr_length", "name", "threshold"},
             "elevation_change": {"kind", "file", "sigma", "corr_length", "name"},
             "footprint": {"kind", "file", "sigma", "corr_length", "name", "threshold"}}


def parse_observations(table: Any, cfg: Config) -> list:
    """[[observations]] -> validated observations: the scalar kinds (torchslide.observe.KINDS; points inside
    the DEM) and the series and map kinds read from files (gauge_series, deposit_map, impact_map,
    elevation_change, footprint; torchslide.observe_series), the same tables for every command."""
    from .observe_series import GaugeSeriesError, SeriesObservation

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
                    grid = cfg.terrain.source_dem or dem   # maps lie on the DEM file's grid
                    o = SeriesObservation.from_raster(f, kind, grid, float(d["sigma"]), name=d.get("name", kind),
                                                      corr_length=d.get("corr_length"),
                                                      threshold=float(d.get("threshold", 0.5)))
                    out.append(o.on_grid(grid, dem).validate(dem))
            except ConfigError:
                raise
            except GaugeSeriesError as e:
                raise ConfigError(f"{path}: {where}: {e}") from None
            except (TypeError, ValueError) as e:
                if type(e).__name__ == "TerrainError":
                    raise
                raise ConfigError(f"{path}: {where}: {e}") from None
            continue
        try:
            o = Observation.from_dict(with_path(dict(d), cfg))
            o.validate(dem).check_recorded()
        except ValueError as e:
            raise ConfigError(f"{path}: observation {i + 1}: {e}") from None
        out.append(o)
    check_unique_names(out, path)
    return out


def with_path(d: dict, cfg: Config) -> dict:
    """A runout_length observation's geometry and, from ``map = FILE``, its value.

    The geometry: the polyline of ``path = "name"`` (a [[paths]] entry, or a synthetic case's "thalweg", the
    default when the case has one; its max_offset comes along), else the point it is measured from: x, y
    as given, or the release's crown (torchslide.survey.crown_point). ``map``: a mapped footprint or a DEM
    of difference (a raster on the DEM file's grid, its finite non-zero cells mapped; or an outline's
    polygons): the value is the run-out of the mapped cells (survey.mapped_runout)."""
    if d.get("kind") != "runout_length":
        return d
    from .survey import crown_point, mapped_runout

    source = d.pop("map", None)
    paths = {p.name: p for p in cfg.run_out_paths()}
    name = d.pop("path", "thalweg" if "thalweg" in paths and "thalweg" not in d else None)
    if name is not None:
        if name not in paths:
            raise ValueError(f"path {name!r} is not a [[paths]] name (known: {sorted(paths)})")
        d["thalweg"] = paths[name].xy.tolist()
        if paths[name].max_offset is not None:
            d["options"] = dict(d.get("options", {}), max_offset=paths[name].max_offset)
    elif "thalweg" not in d and ("x" not in d or "y" not in d):
        d["x"], d["y"] = crown_point(cfg.terrain.dem, cfg.terrain.release)
    if source is None:
        return d
    if "value" in d:
        raise ValueError(f"give the run-out's value or the map it is measured on (map = {source!r}), not both")
    grid = cfg.terrain.source_dem or cfg.terrain.dem
    mapped = _mapped_cells(cfg.resolve(source), grid)
    d["value"] = mapped_runout(mapped, grid, point=(d.get("x"), d.get("y")), thalweg=d.get("thalweg"),
                               max_offset=d.get("options", {}).get("max_offset"))
    d.setdefault("name", "runout")
    d["options"] = dict(d.get("options", {}), map=str(source))
    return d


def _mapped_cells(path, grid) -> np.ndarray:
    """(ny, nx) bool: the finite non-zero cells of a raster on ``grid`` (a footprint's 1s, a DoD's changed
    cells), or the inside of an outline's polygons."""
    from .observe_series import read_map
    from .terrain.vector import is_vector, rasterize_outline

    if is_vector(path):
        return rasterize_outline(path, grid) >= 0.5
    a = read_map(path, grid, what="runout map")
    return np.isfinite(a) & (a != 0)


def check_unique_names(observations, path) -> None:
    """Observation names label residuals and reports: they must be distinct."""
    names = [o.name for o in observations]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise ConfigError(f"{path}: observations have duplicate names {dup}; give each a distinct name")


def parse_calibration(table: Any, cfg: Config) -> dict:
    """[calibration] -> dict of calibrate() settings with defaults, checked."""
    path = cfg.path
    check_keys(table, _CAL_KEYS, "[calibration]", path)
    c = {"n_initial": 40, "n_total": 120, "batch_size": 1, "seed": 0, "grid_size": 100,
         "acquisition": "entropy", "tv_threshold": None, "max_batch": 32, "clip_range": 1000.0,
         "inference": "auto", "local_max_fraction": 0.05, "discrepancy": "learnt"}
    c.update(table)
    for k in ("n_initial", "n_total", "batch_size", "grid_size", "max_batch"):
        if not isinstance(c[k], int) or isinstance(c[k], bool) or c[k] < 1:
            raise ConfigError(f"{path}: [calibration] {k} must be a positive integer, got {c[k]!r}")
    if c["n_initial"] < 2:
        raise ConfigError(f"{path}: [calibration] n_initial must be >= 2 (the emulator needs two runs to start), "
                          f"got {c['n_initial']}")
    if c["grid_size"] < 2:
        raise ConfigError(f"{path}: [calibration] grid_size must be >= 2 points per axis, got {c['grid_size']}")
    if c["n_total"] < c["n_initial"]:
        raise ConfigError(f"{path}: [calibration] n_total ({c['n_total']}) must be >= n_initial ({c['n_initial']})")
    if not isinstance(c["seed"], int) or isinstance(c["seed"], bool) or c["seed"] < 0:
        raise ConfigError(f"{path}: [calibration] seed must be an integer >= 0, got {c['seed']!r}")
    for k, lo in (("clip_range", "> 0"), ("tv_threshold", ">= 0")):
        v = c[k]
        if v is None:
            continue
        if not isinstance(v, (int, float)) or isinstance(v, bool) or not math.isfinite(v) or \
                (v <= 0 if lo == "> 0" else v < 0):
            raise ConfigError(f"{path}: [calibration] {k} must be a finite number {lo}, got {v!r}")
    if c.get("truth") is not None:
        t = c["truth"]
        if not isinstance(t, dict) or not all(isinstance(v, (int, float)) for v in t.values()):
            raise ConfigError(f"{path}: [calibration] truth must be a table of numbers, e.g. {{ mu = 0.23, xi = 1000.0 }}")
    if c["inference"] not in ("auto", "local", "emulator"):
        raise ConfigError(f"{path}: [calibration] inference must be \"auto\", \"local\" or \"emulator\", got "
                          f"{c['inference']!r}")
    v = c["local_max_fraction"]
    if not isinstance(v, (int, float)) or isinstance(v, bool) or not 0 < v <= 1:
        raise ConfigError(f"{path}: [calibration] local_max_fraction must be a share of the prior box in (0, 1], "
                          f"got {v!r}")
    from .discrepancy import MODELS

    if c["discrepancy"] not in MODELS:
        raise ConfigError(f"{path}: [calibration] discrepancy must be " + " or ".join(f'"{m}"' for m in MODELS)
                          + f", got {c['discrepancy']!r}")
    if c["acquisition"] not in ("entropy", "expvar"):
        raise ConfigError(f"{path}: [calibration] acquisition must be 'entropy' or 'expvar', got {c['acquisition']!r}")
    return c


EXTRA_SECTIONS = {"prior": parse_prior, "observations": parse_observations, "calibration": parse_calibration}


def load_calibration_config(path) -> Config:
    """Load a calibrate config; [prior] and [[observations]] are required."""
    cfg = load_config(path, extra_sections=EXTRA_SECTIONS)
    for sec in ("prior", "observations"):
        if sec not in cfg.extra:
            raise ConfigError(f"{cfg.path}: section [{sec}] is missing (needed to calibrate)")
    if "calibration" not in cfg.extra:
        cfg.extra["calibration"] = parse_calibration({}, cfg)
    truth = cfg.extra["calibration"].get("truth")
    if truth is not None and sorted(truth) != sorted(cfg.extra["prior"].names):
        raise ConfigError(f"{cfg.path}: [calibration] truth must give exactly the calibrated parameters "
                          f"{cfg.extra['prior'].names}, got {sorted(truth)}")
    if cfg.batch_size != 1:
        raise ConfigError(f"{cfg.path}: [model] must give single values when calibrating, got a batch of {cfg.batch_size}")
    return cfg


def make_evaluator(cfg: Config):
    """LandslideEvaluator for a loaded calibration config."""
    from .evaluator import LandslideEvaluator

    prior = cfg.extra["prior"]
    m = cfg.model
    fixed = {k: (float(v[0]) if isinstance(v, (list, tuple)) else float(v))
             for k, v in m.values.items() if k not in prior.names}
    gauges = [(g.name, g.x, g.y) for g in cfg.gauges]
    return LandslideEvaluator(
        dem=cfg.terrain.dem, release=cfg.terrain.release, observations=cfg.extra["observations"], prior=prior,
        fixed=fixed, t_end=cfg.run.t_end, gauges=gauges, erodible_depth=cfg.terrain.erodible_depth,
        solver_config=cfg.solver_config(), dtype=cfg.run.torch_dtype, device=cfg.run.device,
        max_batch=cfg.extra["calibration"]["max_batch"], thickness=cfg.terrain.thickness,
        discrepancy=cfg.extra["calibration"]["discrepancy"])


def load_calibration(directory, prior):
    """The CalibrationResult in ``directory``, checked against the config's prior: ConfigError otherwise."""
    from .calibration import CalibrationResult

    try:
        cal = CalibrationResult.load(directory)
    except (FileNotFoundError, ValueError, KeyError) as e:
        raise ConfigError(f"--calibration: {e}") from None
    if list(cal.names) != list(prior.names):
        raise ConfigError(f"--calibration {directory} calibrated {list(cal.names)}, but the config's [prior] "
                          f"names {list(prior.names)}: pass the config the calibration ran with")
    if not np.allclose(np.asarray(cal.bounds, dtype=float), np.asarray(prior.bounds, dtype=float), rtol=1e-9):
        raise ConfigError(f"--calibration {directory} ran on the prior box {np.asarray(cal.bounds).tolist()}, the "
                          f"config's [prior] is {np.asarray(prior.bounds).tolist()}: pass the config it ran with")
    return cal


def case_fingerprint(ev) -> dict:
    """What defines z = ln[L(x|d) pi(x)] of an evaluator, JSON-able: the observations, the prior, the
    fixed parameters, the terrain (digests of the DEM, release and erodible rasters), the run and solver
    settings. A calibration resumed under another fingerprint would mix two posteriors in one GP."""
    import dataclasses
    import hashlib

    def digest(a) -> str | None:
        return None if a is None else hashlib.sha256(np.ascontiguousarray(a, dtype=np.float64).tobytes()).hexdigest()

    def obs(o) -> dict:
        d = dataclasses.asdict(o)
        return json.loads(json.dumps(d, default=lambda v: np.asarray(v).tolist()))

    return {"observations": [obs(o) for o in ev.observations],
            "prior": {n: repr(c) for n, c in ev.prior.components.items()},
            "fixed": {k: float(v) for k, v in ev.fixed.items()},
            "discrepancy": getattr(ev, "discrepancy", "none"),
            "terrain": {"dem": digest(ev.dem.z), "cellsize": float(ev.dem.cellsize),
                        "origin": [float(ev.dem.xll), float(ev.dem.yll)], "release": digest(ev.release),
                        "erodible_depth": digest(ev.erodible_depth)},
            "run": {"t_end": float(ev.t_end), "dtype": str(ev.dtype),
                    "solver": json.loads(json.dumps(dataclasses.asdict(ev.solver_config), default=str))
                    if ev.solver_config is not None else None}}


def fingerprint_difference(saved: dict, now: dict) -> str | None:
    """The first part of a case fingerprint that differs ("observations", "prior", ...), else None."""
    for key in now:
        if saved.get(key) != now[key]:
            return key
    return None

