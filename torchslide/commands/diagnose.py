"""``torchslide diagnose CONFIG.toml --out DIR``: find, name and refit missing physics.

The config is the ``calibrate`` config (see torchslide.commands.calibrate) plus vector observations
and a [diagnose] section::

    [[observations]]             # gauge series: CSV with t,h and/or t,speed (times strictly increasing)
    kind = "gauge_series"
    file = "g1.csv"
    gauge = "G1"                 # a [[gauges]] name
    sigma = { h = 0.5, speed = 2.0 }   # or one number for every column
    corr_time = 4.0              # optional exponential correlation time, s

    [[observations]]             # maps on the DEM file's grid (ESRI ASCII / GeoTIFF; nodata = not
                                 #     mapped), averaged onto the [terrain] cellsize grid when it is coarser
    kind = "deposit_map"         # or "impact_map" (0/1 raster, threshold = 0.5 m)
    file = "deposit.asc"
    sigma = 0.5
    corr_length = 60.0           # optional exponential correlation length, m

    [diagnose]                   # every key optional; defaults shown
    candidates = ["entrainment", "curvature", "earth_pressure", "yield_stress", "mu_i", "release_volume", "deposition"]
                                 # release_volume: a release holding more than stated (an input error, checked
                                 #     like the terms, so that extra mass is not named entrainment)
    inference = "auto"           # "local": baseline and candidates fitted on the solver (trust-region least squares,
                                 #     Laplace evidence, likelihood ratio, profile); "emulator": GP emulator over the
                                 #     prior box; "auto": local when the baseline's 90 % Laplace region fills less
                                 #     than local_max_fraction of the prior box (rich data: a GP with tens of runs
                                 #     cannot resolve such a peak), else emulator
    local_max_fraction = 0.05
    local_lhs = 16               # local path: maximin-LHS runs ranking the baseline's starts, fits from the
    local_starts = 2             #     local_starts best; local_max_iter trial points (a run each) per fit
    local_max_iter = 30
    n_posterior_samples = 32     # baseline posterior-predictive members
    n_posterior_samples_after = 16   # posterior-predictive members of every candidate's fit
    n_initial = 16               # emulator path, refit budgets: LHS runs, first-stage total ...
    n_total = 32
    n_total_max = 48             # ... and the total a refit with untrustworthy evidence is continued to
    # cellsize = "auto"          # choose the inversion grid by its own error: cells 8, 4, 2, 1 times [terrain]'s,
    max_cells = 20000            #     the coarsest whose error (run pairs on cells half as large) is below the
                                 #     stated noise in every observable, else the finest within max_cells
                                 #     (torchslide.diagnose.resolution); maps are averaged onto it
    model_error_runs = 12        # > 0: the grid's approximation error (runs on cells model_error_factor times
    model_error_factor = 2       #     smaller at this many pilot posterior draws) enters every likelihood; 0: off
    # fine_terrain = { dem = "dem_5m.asc", release = "release_5m.asc", erodible = "erodible_5m.asc" }
                                 # optional: the terrain on cells model_error_factor times smaller (same
                                 #     lower-left corner, shape x factor; keys as in [terrain]) for the model
                                 #     error's finer runs, e.g. the LiDAR DEM the inversion DEM was coarsened
                                 #     from; default: the inversion DEM interpolated bilinearly
    release_volume_sd = 0.0      # > 0: the release volume's relative sd (e.g. 0.058 for a volume known to
                                 #     +-10 %, the sd of that uniform error), marginalised in every likelihood
                                 #     with the grid's error (needs model_error_runs >= 2); 0: taken as exact
    profile_top = 2              # local path: candidates (largest 2 ln BF) profiled at the ends of their
                                 #     switch's 90 % interval (a profile point beating the fit restarts it); 0: off
    profile_restarts = 2         # local path: restarts from a profile point that beats the fit, at most
    candidate_error_rounds = 2   # local path, with a finer terrain (fine_terrain or cellsize = "auto"): rounds in
                                 #     which the grid's mean error of the baseline and the profile_top candidates is
                                 #     taken at draws of their own fit and the model refitted with it (0: off)
    finer_shift = 1.0            # ... when a round moves a candidate's grid error by more than this (sigmas, rms
                                 #     per observable) or a candidate reaches bf_min, the baseline and the supported
                                 #     candidates are fitted again on the finer grid and compared there (0: never)
    candidate_lhs = 8            # local path: a candidate's global starts (maximin LHS over its switch's range and
    candidate_starts = 1         #     the baseline's mode +- 25 % of each range); fits from the best of them too
    top_k = 2                    # candidates fitted (by screening rank)
    detectability = "measured"   # each candidate's detectable switch in the report: measured on the solver (tens
                                 #     of seconds) or "linearised" from the screening alone (off 2-3 times for
                                 #     threshold and saturating terms)
    batch_size = 8
    n_perm = 99                  # permutations for the map cluster p-values
    seed = 0
    # decision thresholds (torchslide.diagnose.decide.Thresholds; set them on null data):
    bf_min = 6.0                 # lower bound of the verified 2 ln BF vs the baseline
    margin_min = 6.0             # 2 ln BF over a competing candidate for an unambiguous name
    located_min = 8.0            # |score| of a located mismatch that counts as significant
    waic_min = 6.0               # out-of-sample check: 2 (elpd_WAIC candidate - baseline)
    explain_min = 0.5            # fraction of the located structure a named term must remove (0..1)
    explain_partial_min = 0.25   # ... or this fraction, when it passes every other check: named with what it
                                 #     leaves unexplained
    explain_margin = 0.1         # another candidate contests that name only when it removes this much more
    ess_min = 2.0                # importance-sampling ESS a verified evidence needs (>= 1)
    z_threshold = 3.0            # per-value / cluster / window detection level
    lr_alpha = 0.01              # local path: a candidate's likelihood ratio must reach this boundary-corrected p-value
    # fit_max = 4.0              # not set by default (off): an observable whose fit Z (its chi-square with the
                                 #     likelihood's covariance, as a normal score) exceeds it is a mismatch; one
                                 #     number, or a table per observable name ([diagnose.fit_max] "g1:speed" = -1.5)

``--null-runs N``: the thresholds bf_min, located_min and (N >= 3) fit_max set on N null recordings of this
design (torchslide.diagnose.null: the baseline's posterior draws run on the finer grid, the release
volume's error when release_volume_sd states one, and noise drawn from the stated error model, correlations
included, each diagnosed like the data); report.json gets
"null_calibration" (per null case every candidate's lower-bound 2 ln BF, "lower_by_candidate"; report.md says
which came out best there and whether the data's best is among them) and the decision with the thresholds
given before as decision["decision_before"].

Unknown keys stop with a clear error (exit code 2) listing the allowed ones.
The baseline calibration uses [calibration] n_initial / n_total / batch_size / seed. Writes DIR/report.json,
DIR/report.md and figures. Bad input (a gauge series with non-increasing times, a map on another grid,
an unknown candidate, ...) stops with exit code 2 before any run.
"""
from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path
from typing import Any

from ..config import Config, ConfigError, check_keys, load_config
from ..calibration_config import parse_calibration, parse_observations, parse_prior
from . import add_executor_arguments, executor_for

HELP = "diagnose missing physics: locate misfit, screen candidate terms, refit, compare evidence"

_INT_KEYS = ("n_posterior_samples", "n_posterior_samples_after", "n_initial", "n_total", "n_total_max",
             "model_error_runs", "model_error_factor", "profile_top", "top_k", "batch_size", "n_perm",
             "local_lhs", "local_starts", "local_max_iter", "candidate_lhs", "candidate_starts", "profile_restarts",
             "candidate_error_rounds")
_THRESHOLD_KEYS = ("bf_min", "margin_min", "located_min", "waic_min", "explain_min", "explain_partial_min",
                   "explain_margin", "ess_min",
                   "z_threshold", "lr_alpha")
_DIAG_KEYS = {"candidates", "seed", "fine_terrain", "release_volume_sd", "fit_max", "inference", "local_max_fraction",
              "finer_shift", "detectability",
              "cellsize", "max_cells", *_INT_KEYS, *_THRESHOLD_KEYS}


def diagnose_defaults() -> dict:
    """[diagnose] defaults, taken from Budgets() and Thresholds() (one source of truth)."""
    from ..diagnose import Budgets, Thresholds
    from ..diagnose.candidates import CANDIDATES

    b, t = Budgets(), Thresholds()
    return {"candidates": list(CANDIDATES), "seed": b.seed, "release_volume_sd": b.release_volume_sd,
            "inference": b.inference, "local_max_fraction": b.local_max_fraction, "finer_shift": b.finer_shift,
            "detectability": b.detectability,
            **{k: getattr(b, k) for k in _INT_KEYS},
            **{k: getattr(t, k) for k in _THRESHOLD_KEYS}}
def parse_diagnose(table: Any, cfg: Config) -> dict:
    from ..diagnose.candidates import CANDIDATES

    path = cfg.path
    check_keys(table, _DIAG_KEYS, "[diagnose]", path)
    c = diagnose_defaults()
    c.update(table)
    if not isinstance(c["candidates"], list) or not c["candidates"]:
        raise ConfigError(f"{path}: [diagnose] candidates must be a non-empty list of names")
    bad = [n for n in c["candidates"] if n not in CANDIDATES]
    if bad:
        raise ConfigError(f"{path}: [diagnose] unknown candidate(s) {bad} (known: {', '.join(CANDIDATES)})")
    dup = sorted({n for n in c["candidates"] if c["candidates"].count(n) > 1})
    if dup:
        raise ConfigError(f"{path}: [diagnose] candidates lists {dup} more than once")
    for k in _INT_KEYS:
        low = {"model_error_runs": 0, "profile_top": 0, "model_error_factor": 2, "n_initial": 2,
               "local_lhs": 0, "candidate_lhs": 0, "candidate_starts": 0, "candidate_error_rounds": 0}.get(k, 1)
        if not isinstance(c[k], int) or isinstance(c[k], bool) or c[k] < low:
            raise ConfigError(f"{path}: [diagnose] {k} must be an integer >= {low}, got {c[k]!r}")
    if c["inference"] not in ("auto", "local", "emulator"):
        raise ConfigError(f"{path}: [diagnose] inference must be \"auto\", \"local\" or \"emulator\", got "
                          f"{c['inference']!r}")
    if c["detectability"] not in ("measured", "linearised"):
        raise ConfigError(f"{path}: [diagnose] detectability must be \"measured\" or \"linearised\", got "
                          f"{c['detectability']!r}")
    v = c["local_max_fraction"]
    if not isinstance(v, (int, float)) or isinstance(v, bool) or not 0 < v <= 1:
        raise ConfigError(f"{path}: [diagnose] local_max_fraction must be a share of the prior box in (0, 1], got {v!r}")
    v = c["finer_shift"]
    if not isinstance(v, (int, float)) or isinstance(v, bool) or not v >= 0:
        raise ConfigError(f"{path}: [diagnose] finer_shift must be a number of sigmas >= 0 (0: never), got {v!r}")
    c["finer_shift"] = float(v)
    if not isinstance(c["seed"], int) or isinstance(c["seed"], bool):
        raise ConfigError(f"{path}: [diagnose] seed must be an integer, got {c['seed']!r}")
    if c["n_total"] < c["n_initial"]:
        raise ConfigError(f"{path}: [diagnose] n_total ({c['n_total']}) must be >= n_initial ({c['n_initial']})")
    if c["model_error_runs"] == 1:
        raise ConfigError(f"{path}: [diagnose] model_error_runs must be 0 (off) or >= 2 (a covariance needs two "
                          f"run pairs), got 1")
    v = c["release_volume_sd"]
    if not isinstance(v, (int, float)) or isinstance(v, bool) or not 0 <= v < 0.5:
        raise ConfigError(f"{path}: [diagnose] release_volume_sd must be a relative sd in [0, 0.5), got {v!r}")
    if v > 0 and c["model_error_runs"] < 2:
        raise ConfigError(f"{path}: [diagnose] release_volume_sd = {v!r} needs model_error_runs >= 2 (its effect is "
                          f"taken at the pilot's posterior draws), got {c['model_error_runs']}")
    c["release_volume_sd"] = float(v)
    if c["n_total_max"] < c["n_total"]:
        raise ConfigError(f"{path}: [diagnose] n_total_max ({c['n_total_max']}) must be >= n_total ({c['n_total']})")
    for k in _THRESHOLD_KEYS:
        if not isinstance(c[k], (int, float)) or isinstance(c[k], bool) or not math.isfinite(c[k]):
            raise ConfigError(f"{path}: [diagnose] {k} must be a finite number, got {c[k]!r}")
        c[k] = float(c[k])
    for k in ("margin_min", "located_min", "z_threshold"):
        if c[k] <= 0:
            raise ConfigError(f"{path}: [diagnose] {k} must be > 0, got {c[k]!r}")
    for k in ("bf_min", "waic_min"):      # 2 ln BF / 2 delta elpd a candidate must beat the baseline by
        if c[k] < 0:
            raise ConfigError(f"{path}: [diagnose] {k} must be >= 0 (a candidate must do at least as well as "
                              f"the baseline), got {c[k]!r}")
    for k in ("explain_min", "explain_partial_min", "explain_margin"):
        if not 0.0 <= c[k] <= 1.0:
            raise ConfigError(f"{path}: [diagnose] {k} is a fraction in [0, 1], got {c[k]!r}")
    if not 0.0 < c["lr_alpha"] < 1.0:
        raise ConfigError(f"{path}: [diagnose] lr_alpha is a p-value level in (0, 1), got {c['lr_alpha']!r}")
    if c["ess_min"] < 1.0:
        raise ConfigError(f"{path}: [diagnose] ess_min must be >= 1 (an effective number of draws), got {c['ess_min']!r}")
    c["fine_terrain"] = _parse_fine_terrain(table.get("fine_terrain"), cfg, c["model_error_factor"])
    c["fit_max"] = _parse_fit_max(c.get("fit_max"), path)
    c.setdefault("cellsize", None)
    c.setdefault("max_cells", 20000)
    if c["cellsize"] not in (None, "auto"):
        raise ConfigError(f"{path}: [diagnose] cellsize must be \"auto\" (the grid chosen by its own error; set a "
                          f"fixed one with [terrain] cellsize), got {c['cellsize']!r}")
    if c["cellsize"] == "auto" and c["fine_terrain"] is not None:
        raise ConfigError(f"{path}: [diagnose] cellsize = \"auto\" resamples the finer runs' terrain from [terrain] "
                          f"itself; give the finest DEM as [terrain] and leave out fine_terrain")
    if not isinstance(c["max_cells"], int) or isinstance(c["max_cells"], bool) or c["max_cells"] < 9:
        raise ConfigError(f"{path}: [diagnose] max_cells must be an integer >= 9, got {c['max_cells']!r}")
    return c


def _observable_names(observations) -> list[str]:
    return [str(o.name) for o in observations]


def _parse_fit_max(v: Any, path) -> float | dict | None:
    """[diagnose] fit_max: None (off), a finite number, or a table {observable: finite number}."""
    num = lambda x: isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)
    if v is None:
        return None
    if num(v):
        return float(v)
    if isinstance(v, dict) and v:
        bad = {k: x for k, x in v.items() if not num(x)}
        if bad:
            raise ConfigError(f"{path}: [diagnose] fit_max: every level must be a finite number, got {bad}")
        return {str(k): float(x) for k, x in v.items()}
    raise ConfigError(f"{path}: [diagnose] fit_max must be a finite number or a table {{observable = number}}, got {v!r}")


def _parse_fine_terrain(t: Any, cfg: Config, factor: int):
    """[diagnose] fine_terrain -> torchslide.diagnose.model_error.FineTerrain (None when not given): parsed
    as a [terrain] table, checked to be the inversion grid refined ``factor`` times (errors name the key)."""
    from ..config import _parse_terrain
    from ..diagnose.model_error import FineTerrain

    if t is None:
        return None
    where = "[diagnose] fine_terrain"
    if not isinstance(t, dict):
        raise ConfigError(f"{cfg.path}: {where} must be a table like [terrain] (dem, release, erodible), got {t!r}")
    try:
        tc = _parse_terrain(t, cfg.path)
    except ConfigError as e:
        raise ConfigError(str(e).replace("[terrain]", where)) from None
    ft = FineTerrain(tc.dem, tc.release, erodible_depth=tc.erodible_depth)
    try:
        f = ft.factor_for(cfg.terrain.dem)
    except ValueError as e:
        raise ConfigError(f"{cfg.path}: {where}: {e}") from None
    if f != factor:
        raise ConfigError(f"{cfg.path}: {where}: its cells are {f} times smaller than the inversion grid's, "
                          f"model_error_factor is {factor}")
    if (tc.erodible_depth is None) != (cfg.terrain.erodible_depth is None):
        raise ConfigError(f"{cfg.path}: {where}: give an erodible depth raster in both [terrain] and {where}, or in "
                          f"neither")
    v_f, v_c = tc.release_volume, cfg.terrain.release_volume
    if abs(v_f - v_c) > 0.05 * v_c:
        raise ConfigError(f"{cfg.path}: {where}: release volume {v_f:.4g} m3 differs from [terrain]'s {v_c:.4g} m3 "
                          f"by more than 5 %")
    return ft


SECTIONS = {"prior": parse_prior, "observations": parse_observations, "calibration": parse_calibration,
            "diagnose": parse_diagnose}


def load_diagnose_config(path) -> Config:
    cfg = load_config(path, extra_sections=SECTIONS)
    for sec in ("prior", "observations"):
        if sec not in cfg.extra:
            raise ConfigError(f"{cfg.path}: section [{sec}] is missing (needed to diagnose)")
    cfg.extra.setdefault("calibration", parse_calibration({}, cfg))
    cfg.extra.setdefault("diagnose", parse_diagnose({}, cfg))
    fm = cfg.extra["diagnose"].get("fit_max")
    if isinstance(fm, dict):
        names = _observable_names(cfg.extra["observations"])
        unknown = sorted(set(fm) - set(names))
        if unknown:
            raise ConfigError(f"{cfg.path}: [diagnose] fit_max names unknown observable(s) {unknown} "
                              f"(known: {', '.join(names)})")
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
            device=cfg.run.device, max_batch=cfg.extra["calibration"]["max_batch"],
            fine_terrain=cfg.extra["diagnose"].get("fine_terrain"), thickness=cfg.terrain.thickness,
            discrepancy=cfg.extra["calibration"]["discrepancy"])
    except ValueError as e:
        if type(e).__name__ == "TerrainError":
            raise
        raise ConfigError(f"{cfg.path}: {e}") from None


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("config", help="TOML config (calibrate config + [diagnose], vector observations)")
    p.add_argument("--out", required=True, help="output folder (report.json, report.md, figures)")
    p.add_argument("--quiet", action="store_true", help="no progress lines")
    p.add_argument("--null-runs", type=int, default=0, metavar="N",
                   help="set bf_min, located_min and fit_max (N >= 3) on N null recordings of this design made "
                        "from the baseline's posterior, each diagnosed like the data (costs N diagnoses; "
                        "torchslide.diagnose.null; N >= 10 advised); a rerun with the same seed reuses the "
                        "finished null cases in OUT/null, also those of a smaller N")
    p.add_argument("--resume", action="store_true",
                   help="finish a diagnosis that was interrupted after its inference (OUT/diagnosis.pkl): its null "
                        "runs (which resume from OUT/null) and every report file still missing, without "
                        "repeating the inference")
    p.add_argument("--design", action="store_true",
                   help="instead of the diagnosis: rank where one more gauge (peak depth and peak speed) would "
                        "reveal each candidate best, at the baseline's local fit (torchslide.diagnose.design); "
                        "writes OUT/design.json, OUT/design_<candidate>.asc and OUT/design.png")
    p.add_argument("--discriminate", default=None, metavar="A,B",
                   help="with --design: where one more gauge tells candidates A and B apart (an \"A or B\" verdict): "
                        "the switch of each that the other, with the baseline re-tuned, cannot mimic; writes "
                        "OUT/design_A_vs_B.asc and OUT/design_B_vs_A.asc")
    p.add_argument("--design-sigma", default="0.5,2.0", metavar="H,V",
                   help="the new gauge's errors: peak depth (m), peak speed (m/s) (default 0.5,2.0)")
    p.add_argument("--design-top", type=int, default=5, metavar="N", help="best cells listed per candidate")
    add_executor_arguments(p)


def budgets_and_thresholds(cfg: Config):
    """(torchslide.diagnose.Budgets, Thresholds) of a loaded diagnose config: the baseline's budget from
    [calibration], everything else from [diagnose] (defaults: Budgets() / Thresholds())."""
    from ..diagnose import Budgets, Thresholds

    cal, dg = cfg.extra["calibration"], cfg.extra["diagnose"]
    bud = Budgets(baseline_n_initial=cal["n_initial"], baseline_n_total=cal["n_total"],
                  **{k: dg[k] for k in _INT_KEYS}, release_volume_sd=dg["release_volume_sd"], seed=dg["seed"],
                  inference=dg["inference"], local_max_fraction=float(dg["local_max_fraction"]),
                  finer_shift=dg["finer_shift"], detectability=dg["detectability"])
    return bud, Thresholds(**{k: dg[k] for k in _THRESHOLD_KEYS}, fit_max=dg.get("fit_max"))


def run(args: argparse.Namespace) -> int:
    from ..output_folder import run_locked

    return run_locked(args.out, _run, args)


def _run(args: argparse.Namespace) -> int:
    cfg = load_diagnose_config(args.config)
    ev = make_evaluator(cfg)
    dg = cfg.extra["diagnose"]
    grid = None
    if dg["cellsize"] == "auto":
        from ..diagnose.resolution import choose_grid

        try:
            ev, ft, grid = choose_grid(ev, max_cells=dg["max_cells"], seed=dg["seed"],
                                       log=(lambda s: None) if args.quiet else print)
        except ValueError as e:
            raise ConfigError(f"{cfg.path}: [diagnose] {e}") from None
        ev = ev._copy(fine_terrain=ft)
    if "entrainment" in dg["candidates"] and cfg.terrain.erodible_depth is None:
        raise ConfigError(f"{cfg.path}: candidate 'entrainment' needs an erodible depth raster ([terrain] erodible)")
    bud, th = budgets_and_thresholds(cfg)
    if args.null_runs < 0:
        raise ConfigError(f"--null-runs must be >= 0, got {args.null_runs}")
    out = Path(args.out)
    log = (lambda s: None) if args.quiet else print
    with executor_for(args, cfg, ev):
        if args.discriminate and not args.design:
            raise ConfigError("--discriminate A,B goes with --design")
        if args.design:
            return _design(ev, dg["candidates"], bud, th, args, cfg, out, log)
        return _diagnose_case(ev, cfg, bud, th, args, out, log, grid=grid)


CHECKPOINT = "diagnosis.pkl"
"""The diagnosis once its inference ended ({"fingerprint", "stage": "diagnosed" | "null", "diagnosis"}),
written before the report: ``--resume`` starts from it."""
FINISHED = "finished.json"
"""Written last, once every report file is in place."""


def _fingerprint(cfg: Config, ev, args) -> str:
    """What a resumed diagnosis must share with the interrupted one: the config text and the recorded data."""
    import hashlib

    import numpy as np

    h = hashlib.sha256(Path(cfg.path).read_bytes())
    h.update(np.ascontiguousarray(ev.data_recorded, dtype=np.float64).tobytes())
    return h.hexdigest()


def _save_checkpoint(out: Path, fingerprint: str, stage: str, d) -> None:
    import pickle

    from ..files import atomic_path

    out.mkdir(parents=True, exist_ok=True)
    with atomic_path(out / CHECKPOINT) as tmp:
        tmp.write_bytes(pickle.dumps({"fingerprint": fingerprint, "stage": stage, "diagnosis": d}))


def _load_checkpoint(out: Path, fingerprint: str):
    """(diagnosis, stage) of OUT/diagnosis.pkl, or a one-line ConfigError when it is missing, unreadable or
    was made from another config or recording."""
    import pickle

    path = out / CHECKPOINT
    if not path.is_file():
        raise ConfigError(f"--resume: {out} holds no interrupted diagnosis ({CHECKPOINT}); run without --resume")
    try:
        ck = pickle.loads(path.read_bytes())
        d, stage, fp = ck["diagnosis"], ck["stage"], ck["fingerprint"]
    except Exception as e:
        raise ConfigError(f"--resume: {path} is unreadable ({type(e).__name__}); run without --resume") from None
    if fp != fingerprint:
        raise ConfigError(f"--resume: {path} was made from another config or recording; resume with the config "
                          "it was made with, or run without --resume")
    return d, stage


def _diagnose_case(ev, cfg: Config, bud, th, args, out: Path, log, grid: dict | None = None) -> int:
    """The diagnosis of the config's case, its report, and (--null-runs) its thresholds set on null runs
    (``grid``: how the inversion grid was chosen, for the report).
    The diagnosis is checkpointed (OUT/diagnosis.pkl) once inferred and once its thresholds are set on null
    runs; the report files follow, finished.json last."""
    import json

    from ..diagnose import diagnose
    from ..diagnose.report import write_report
    from ..files import write_text_atomic

    dg = cfg.extra["diagnose"]
    fp = _fingerprint(cfg, ev, args)
    (out / FINISHED).unlink(missing_ok=True)
    if args.resume:
        d, stage = _load_checkpoint(out, fp)
        log(f"resuming the diagnosis in {out} (stage: {stage})")
        if d.mismatches is None:           # a checkpoint of an earlier version: the footprint's not yet measured
            from ..diagnose.pipeline import add_mismatches
            add_mismatches(d)
    else:
        d, stage = diagnose(ev, dg["candidates"], bud, th, log=log), "diagnosed"
        d.grid = grid
        _save_checkpoint(out, fp, stage, d)
    write_report(d, out, cfg.conventions())           # with the thresholds given; rewritten below when null runs reset them
    if args.null_runs and stage != "null":
        from ..diagnose.null import null_calibration
        named = f" ({d.missing_physics})" if d.missing_physics else ""
        print(f"verdict with the thresholds given: {d.verdict}{named}; now {args.null_runs} null runs")
        try:
            d.null_calibration = null_calibration(ev, dg["candidates"], bud, th, d.predictive.x, args.null_runs,
                                                  out / "null", log=log)
        except RuntimeError as e:   # a null recording's finer-grid run failed: the report above stands
            print(f"torchslide: error: null runs stopped: {e}; {out}/report.json keeps the thresholds given",
                  file=sys.stderr)
            return 1
        d.redecide(d.null_calibration["thresholds"], f"set on {args.null_runs} null simulations of this design")
        _save_checkpoint(out, fp, "null", d)
        write_report(d, out, cfg.conventions())
    files = sorted(f.name for f in out.iterdir() if f.is_file() and not f.name.startswith("."))
    write_text_atomic(out / FINISHED, json.dumps({"files": files}, indent=1))
    print(f"verdict: {d.verdict}" + (f" ({d.missing_physics})" if d.missing_physics else "") + f"; report in {out}")
    return 0


def _design_sigma(text: str) -> tuple[float, float]:
    try:
        h, v = (float(x) for x in text.split(","))
    except ValueError:
        raise ConfigError(f"--design-sigma must be two numbers H,V (m, m/s), got {text!r}") from None
    if not (h > 0 and v > 0 and math.isfinite(h) and math.isfinite(v)):
        raise ConfigError(f"--design-sigma values must be finite and > 0, got {text!r}")
    return h, v


def _design(ev, candidates, bud, th, args, cfg: Config, out: Path, log) -> int:
    """``--design``: the baseline's local fit, then torchslide.diagnose.design at its mode."""
    import json

    import numpy as np

    from ..diagnose.design import design
    from ..diagnose.local_path import fit_model
    from ..files import write_text_atomic
    from ..terrain.io import write_named_raster

    sh, sv = _design_sigma(args.design_sigma)
    if args.design_top < 1:
        raise ConfigError(f"--design-top must be >= 1, got {args.design_top}")
    pair = None
    if args.discriminate:
        from ..diagnose.candidates import CANDIDATES

        pair = [c.strip() for c in args.discriminate.split(",")]
        if len(pair) != 2 or pair[0] == pair[1] or any(c not in CANDIDATES for c in pair):
            raise ConfigError(f"--discriminate needs two different candidates A,B of {sorted(CANDIDATES)}, "
                              f"got {args.discriminate!r}")
    f, n = fit_model(ev, n_lhs=bud.local_lhs, starts=bud.local_starts, seed=bud.seed, rel_step=bud.local_rel_step,
                     max_iter=bud.local_max_iter, log=log)
    log(f"[design] baseline local fit ({n} runs): " + ", ".join(f"{k} {v:.4g}" for k, v in zip(ev.prior.names, f.x)))
    if pair:
        from ..diagnose.design import discriminate

        d = discriminate(ev, f.x, *pair, sigma_h=sh, sigma_v=sv, threshold=th.margin_min, top=args.design_top)
        candidates = list(d.now)
    else:
        d = design(ev, f.x, candidates, sigma_h=sh, sigma_v=sv, threshold=th.bf_min, top=args.design_top)
    out.mkdir(parents=True, exist_ok=True)
    j = {"baseline": dict(zip(ev.prior.names, map(float, f.x))), **d.to_json(), "conventions": cfg.conventions()}
    write_text_atomic(out / "design.json", json.dumps(j, indent=1))
    for c, m in d.maps.items():
        write_named_raster(out, f"design_{c.replace('|', '_vs_')}", np.where(np.isfinite(m), m, np.nan), ev.dem)
    _design_figure(d, ev, out / "design.png")
    for c in candidates:
        b = d.best[c][0] if d.best[c] else None
        log(f"[design] {c}: detectable from {d.now[c]:.3g} now" +
            (f"; from {b['switch']:.3g} with a gauge at x = {b['x']:.0f}, y = {b['y']:.0f}" if b else ""))
    print(f"design written to {out}")
    return 0


def _design_figure(d, ev, path: Path) -> None:
    import matplotlib

    from ..files import save_figure

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    cs = list(d.maps)
    fig, axs = plt.subplots(1, len(cs), figsize=(4.0 * len(cs), 3.6), squeeze=False)
    for ax, c in zip(axs[0], cs):
        m = d.maps[c]
        ratio = np.where(np.isfinite(m), m / d.now[c], np.nan) if np.isfinite(d.now[c]) else m
        im = ax.imshow(ratio, origin="lower", extent=ev.dem.extent[0::2] + ev.dem.extent[1::2], cmap="viridis_r",
                       vmin=0.0, vmax=1.0)
        for g in ev.gauges:
            ax.plot(g[1], g[2], "w^", ms=6)
        for b in d.best[c]:
            ax.plot(b["x"], b["y"], "r+", ms=8)
        ax.set_title(f"{c}: now {d.now[c]:.3g}", fontsize=9)
        fig.colorbar(im, ax=ax, label="detectable switch with a new gauge / now")
    fig.tight_layout()
    save_figure(fig, path, 110)
    plt.close(fig)
