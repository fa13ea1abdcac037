"""``torchslide calibrate CONFIG.toml --out DIR [--resume]``: Bayesian active-learning calibration.

The config is the ``simulate`` config plus::

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
    truth = { mu = 0.23, xi = 1000.0 }   # optional, synthetic cases: drawn as a cross, reported in posterior.json

[model] gives the values of the parameters that are not calibrated (mu and xi in [model] are
ignored when they are in [prior]). Writes posterior.json, posterior.npz, posterior.png, tv.png,
runs.csv, a checkpoint (so ``--resume`` continues an interrupted run without repeating a finished
run) and TensorBoard logs under DIR/tensorboard. posterior.json's ``best_run_fit`` gives each
observation's standardised residual on the best run, and calibrate warns (stderr) about every
observation that even the best run misses by more than 3 sigma.
"""
from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path
from typing import Any

import numpy as np

from ..config import Config, ConfigError, check_keys, load_config
from ..observe import Observation

HELP = "calibrate rheological parameters by Bayesian active learning"

_CAL_KEYS = {"n_initial", "n_total", "batch_size", "seed", "grid_size", "acquisition", "tv_threshold",
             "max_batch", "clip_range", "truth"}
_PRIOR_DISTS = {
    "uniform": ({"low", "high"}, set()),
    "truncnormal": ({"low", "high", "mean", "sd"}, set()),
    "lognormal": ({"low", "high", "mean_log", "sd_log"}, set()),
    "gamma": ({"low", "high", "concentration", "rate"}, set()),
}


_PRIOR_ARGS = {"truncnormal": {"mean": "loc", "sd": "scale"}, "lognormal": {"mean_log": "mu", "sd_log": "sigma"}}


def parse_prior(table: Any, cfg: Config):
    """[prior] -> torchslide.bayes.Prior (raises ConfigError naming the parameter)."""
    from ..bayes import Gamma, LogNormal, Prior, TruncatedNormal, Uniform
    from ..physics import Params, check_range

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


def parse_observations(table: Any, cfg: Config) -> list[Observation]:
    """[[observations]] -> validated Observation list (kinds, sigma > 0, points inside the DEM)."""
    path = cfg.path
    if not isinstance(table, list) or not table:
        raise ConfigError(f"{path}: [[observations]] must list at least one observation")
    out = []
    thalweg = getattr(cfg.terrain.case, "thalweg", None)
    for i, d in enumerate(table):
        if not isinstance(d, dict):
            raise ConfigError(f"{path}: observation {i + 1} must be a table")
        try:
            d = dict(d)
            if d.get("kind") == "runout_length" and "thalweg" not in d and thalweg is not None:
                d["thalweg"] = np.asarray(thalweg).tolist()
            o = Observation.from_dict(d)
            o.validate(cfg.terrain.dem).check_recorded()
        except ValueError as e:
            raise ConfigError(f"{path}: observation {i + 1}: {e}") from None
        out.append(o)
    check_unique_names(out, path)
    return out


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
         "acquisition": "entropy", "tv_threshold": None, "max_batch": 32, "clip_range": 1000.0}
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
    from ..evaluator import LandslideEvaluator

    prior = cfg.extra["prior"]
    m = cfg.model
    fixed = {k: (float(v[0]) if isinstance(v, (list, tuple)) else float(v))
             for k, v in m.values.items() if k not in prior.names}
    gauges = [(g.name, g.x, g.y) for g in cfg.gauges]
    return LandslideEvaluator(
        dem=cfg.terrain.dem, release=cfg.terrain.release, observations=cfg.extra["observations"], prior=prior,
        fixed=fixed, t_end=cfg.run.t_end, gauges=gauges, erodible_depth=cfg.terrain.erodible_depth,
        solver_config=cfg.solver_config(), dtype=cfg.run.torch_dtype, device=cfg.run.device,
        max_batch=cfg.extra["calibration"]["max_batch"])


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("config", help="TOML config (simulate config + [prior], [[observations]], [calibration])")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--resume", action="store_true", help="continue an interrupted calibration in --out")
    p.add_argument("--quiet", action="store_true", help="no progress bar")


def write_runs_csv(path: Path, res, obs_names, records) -> None:
    """One line per run of the result (in run order): parameters, predicted observables (blank for runs
    made before a resume, whose outputs this session did not see), z, failed, reason, initial."""
    preds = {tuple(np.round(r.x, 12)): r.predictions for r in records}
    with open(path, "w") as f:
        f.write(",".join(list(res.names) + list(obs_names) + ["z", "failed", "reason", "initial"]) + "\n")
        for i, (x, z, fl, why) in enumerate(zip(res.x, res.z, res.failed, res.reasons)):
            p = preds.get(tuple(np.round(x, 12)))
            pv = [f"{v:.10g}" for v in p] if p is not None else [""] * len(obs_names)
            f.write(",".join([f"{v:.10g}" for v in x] + pv + [f"{z:.10g}", str(int(fl)), str(why).replace(",", ";"),
                                                               str(int(i < res.n_initial))]) + "\n")


FIT_WARN_Z = 3.0  # |standardised residual| of the best run above which calibrate warns


def merge_best_fits(earlier: dict | None, now: dict | None) -> dict | None:
    """The best-run fit over two sessions of one calibration (a resume): the one with the larger z, its
    ``n_runs`` the runs of both."""
    if earlier is None or now is None:
        return now if earlier is None else earlier
    best = dict(now if now["z"] >= earlier["z"] else earlier)
    best["n_runs"] = int(earlier["n_runs"]) + int(now["n_runs"])
    return best


def misfit_warnings(fit: dict, z_max: float = FIT_WARN_Z) -> list[str]:
    """One line per observation that even the best run (LandslideEvaluator.best_fit) misses by more than
    ``z_max`` sigma: the calibration cannot have learnt from it, and the user should know why."""
    out = []
    for o in fit["observations"]:
        r = o["standardised_residual"]
        if abs(r) > z_max:
            out.append(f"the best of {fit['n_runs']} runs misses {o['name']} by {r:+.1f} sigma (predicted "
                       f"{o['predicted']:.4g}, recorded {o['value']:.4g} +- {o['sigma']:.3g}): no parameter set tried "
                       "reproduces it, so the posterior follows the other data or the prior there. Check its value, "
                       "unit and location (does the flow reach it by t_end?), or run `torchslide diagnose` for "
                       "missing physics.")
    return out


def run(args: argparse.Namespace) -> int:
    from ..calibration import calibrate
    from ..figures import plot_posterior_any, plot_tv

    cfg = load_calibration_config(args.config)
    cal = cfg.extra["calibration"]
    out = Path(args.out)
    ckpt = out / "checkpoint.pt"
    if ckpt.exists() and not args.resume:
        raise ConfigError(f"{out} holds an earlier calibration (checkpoint.pt): pass --resume to continue it "
                          f"or choose another --out")
    if args.resume and not ckpt.exists():
        print(f"torchslide: note: no checkpoint in {out}; starting a new calibration", file=sys.stderr)
    out.mkdir(parents=True, exist_ok=True)
    ev = make_evaluator(cfg)
    prior = ev.prior
    res = calibrate(ev, prior.bounds, n_initial=cal["n_initial"], n_total=cal["n_total"],
                    batch_size=cal["batch_size"], seed=cal["seed"], grid_size=cal["grid_size"],
                    acquisition=cal["acquisition"], checkpoint=ckpt, log_dir=out / "tensorboard",
                    tv_threshold=cal["tv_threshold"], names=prior.names, progress=not args.quiet,
                    clip_range=cal["clip_range"])
    # the best-run fit of the runs an earlier (interrupted) session made: this session's records lack them
    prev_fit = None
    if args.resume and (out / "posterior.json").exists():
        try:
            prev_fit = json.loads((out / "posterior.json").read_text()).get("best_run_fit")
        except (OSError, ValueError):
            prev_fit = None
    res.save(out)
    info = json.loads((out / "posterior.json").read_text())
    info["observations"] = [{"name": o.name, "kind": o.kind, "value": float(o.value), "sigma": float(o.sigma),
                             "x": o.x, "y": o.y} for o in ev.observations]
    info["solver_seconds_this_session"] = ev.solver_seconds
    fit = merge_best_fits(prev_fit, ev.best_fit())
    if fit is not None:
        info["best_run_fit"] = fit
    truth = cal.get("truth")
    if truth is not None:
        info["truth"] = {n: float(truth[n]) for n in prior.names}
    (out / "posterior.json").write_text(json.dumps(info, indent=2))
    write_runs_csv(out / "runs.csv", res, ev.observation_names, ev.records)
    for w in misfit_warnings(fit) if fit is not None else []:
        print(f"torchslide: warning: {w}", file=sys.stderr)
    plot_posterior_any(res, out / "posterior.png", truth=None if truth is None else [truth[n] for n in prior.names])
    if res.tv_history:
        plot_tv({Path(args.config).stem: res.tv_history}, out / "tv.png")
    s = res.summary
    for n in prior.names:
        print(f"{n}: mean {s['mean'][n]:.4g}  sd {s['sd'][n]:.3g}  MAP {s['map'][n]:.4g}  "
              f"90% HDR [{s['hdr90'][n][0]:.4g}, {s['hdr90'][n][1]:.4g}]")
    print(f"log evidence {res.log_evidence:.3f}; {res.n_runs} runs; results in {out}")
    return 0
