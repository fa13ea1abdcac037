"""``torchslide predict CONFIG.toml --calibration CAL_DIR --out DIR``: posterior-predictive runs.

Draws ``--n`` parameter sets from the posterior that ``torchslide calibrate CONFIG.toml --out CAL_DIR``
wrote, runs them in batched solver calls with the config's terrain, fixed parameters and solver
settings, and writes (all rasters on the DEM grid; ESRI ASCII, or GeoTIFF with ``[output] format = "tif"``)::

    DIR/impact_probability.asc   share of the draws with h_max > --threshold (0-1; default: the config's
                                 impact_area threshold, else 0.5 m)
    DIR/h_max_p05.asc, h_max_p50.asc, h_max_p95.asc       per-cell quantiles of h_max, m
    DIR/v_max_p50.asc, v_max_p95.asc                      of v_max, m/s
    DIR/h_final_p50.asc, h_final_p95.asc                  of the deposit, m
    DIR/predictive.json          the draws' summary and each observation's posterior-predictive check
    DIR/draws.csv                one line per successful draw: parameters and predicted observables
    DIR/impact_probability.png   the impact probability over the hillshaded terrain, observations marked
    DIR/observations.png         each scalar observation: the 90 % interval of a new recording against the value
    DIR/front.png                where the observations map a footprint: the run-out against the share of the
                                 reached cells outside the map, over the calibration's runs and the draws
                                 (front.json: the points)
    DIR/outlines.png             and the mapped footprint against the cells with impact probability >= 0.5,
                                 the clusters of predictive.json's ``mismatches`` numbered

predictive.json ``figures``: the draws' 90 % intervals of the impact area (h_max > --threshold, map m^2) and of
the run-out from the release's crown (m); ``with_grid_error``: the same when ``--grid-error N`` of the draws
(4 by default) also run on cells half the size and the draws are spread by a zero-mean error of their
differences' rms (the grid's error of these figures, measured; of either sign, since the calibrated
parameters may already absorb it), and the run-out, which the grid knows to a cell, by a uniform error of
+- half a cell.

predictive.json ``mismatches``: where the draws and the first mapped footprint disagree, in a modeller's terms
(torchslide.survey.mismatch_clusters): the clusters of cells reached (impact probability >= 0.5) but not
mapped and mapped but not reached, each with its box, cells, area, distance from the crown, score and volume,
and the run-out's shortfall or overshoot against the mapped one; ``path_width``: how many cells across the
mapped path is (torchslide.survey.path_width: fewer than 3 over most of it, and the DEM does not resolve it).

predictive.json ``observations``: per scalar observation the model's mean, sd and 5/50/95 % quantiles over
the draws, the 90 % interval of a new recording (the draws plus the likelihood's noise), the recorded value's
percentile in it, and ``inside``. A value outside is one the calibrated model does not reproduce (see also
posterior.json's ``best_run_fit``). With the learnt discrepancy (``[calibration] discrepancy``, the default)
also ``interval90_model_error``: the interval of a new recording when the model's own error, as the
calibration learnt it from these data, is counted too (the honest forecast of what would be recorded). Maps and gauge series: ``maps_and_series`` gives the share of each
one's values inside their 90 % intervals, ``values`` the check of every value. ``against_observations``:
where the observations map a footprint (footprint, impact_map, elevation_change), the draws' footprint
Jaccard, shares of mapped cells reached and of reached cells unmapped, run-out and volumes against it
(torchslide.survey; median, q05, q95).

The config must be the one the calibration ran with (same calibrated parameters and prior box); nothing is
half-written (a temporary folder next to DIR is moved into place at the end). Exit code 0; 1 when some draws
failed (they are left out and listed in predictive.json); 2 on bad input.
"""
from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np

from ..config import ConfigError
from . import add_executor_arguments, executor_for
from ..observe import DEFAULT_THRESHOLD, KINDS

HELP = "posterior-predictive runs of a calibration: impact probability and quantile maps, data checks"

MAP_QUANTILES = {"h_max": (0.05, 0.5, 0.95), "v_max": (0.5, 0.95), "h_final": (0.5, 0.95)}


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("config", help="the TOML config the calibration ran with")
    p.add_argument("--calibration", required=True, metavar="CAL_DIR",
                   help="the --out folder of `torchslide calibrate` (posterior.json, posterior.npz)")
    p.add_argument("--out", "-o", required=True, metavar="DIR", help="output folder (must not exist or be empty)")
    p.add_argument("--n", type=int, default=64, help="posterior draws to run (default 64)")
    p.add_argument("--seed", type=int, default=0, help="seed of the draws (default 0)")
    p.add_argument("--threshold", type=float, default=None, metavar="M",
                   help="h_max above which a cell counts as reached, m (default: the threshold of the config's "
                        "impact_area observation, else 0.5)")
    p.add_argument("--grid-error", type=int, default=4, metavar="N",
                   help="run N of the draws on cells half the size too, so that the impact area's and the "
                        "run-out's intervals carry the grid's error (default 4; 0: the draws alone)")
    p.add_argument("--overwrite", action="store_true", help="replace DIR if it exists")
    p.add_argument("--quiet", "-q", action="store_true", help="no progress bar")
    add_executor_arguments(p)


def _write_draws_csv(path: Path, names, obs_names, x: np.ndarray, preds: np.ndarray) -> None:
    with open(path, "w") as f:
        f.write(",".join(list(names) + list(obs_names)) + "\n")
        for xi, pi in zip(x, preds):
            f.write(",".join(f"{v:.10g}" for v in list(xi) + list(pi)) + "\n")


def _front(cal_dir: Path, pr) -> tuple | None:
    """(the calibration's runs' front, the draws' front) against the first mapped footprint
    (torchslide.tradeoff.front), or None when the calibration's records (records.npz) carry no survey figures."""
    from ..evaluator import RunRecord, load_records
    from ..tradeoff import front

    if not (cal_dir / "records.npz").is_file():
        return None
    runs = front(load_records(cal_dir / "records.npz"))
    if runs is None:
        return None
    draws = front([RunRecord(x, np.zeros(1), 0.0, False, "", f) for x, f in zip(pr.x, pr.survey_runs)],
                  name=runs["footprint"])
    return runs, draws


def run(args: argparse.Namespace) -> int:
    from ..output_folder import run_locked

    return run_locked(args.out, _run, args)


def _run(args: argparse.Namespace) -> int:
    from ..figures import plot_front, plot_predictive_check
    from ..mapplots import plot_field_map, plot_outlines
    from ..predict import (figure_intervals, footprint_mismatches, grid_error, observation_check, posterior_samples,
                           predictive_sd, run_predictive, with_model_error)
    from ..survey import cluster_labels, mismatch_line, width_line
    from ..terrain.io import write_named_raster
    from ..calibration_config import load_calibration, load_calibration_config, make_evaluator
    from ..output_folder import check_output, staged_output

    if args.n < 1:
        raise ConfigError(f"--n must be >= 1 posterior draws, got {args.n}")
    if args.grid_error < 0 or args.grid_error == 1:
        raise ConfigError(f"--grid-error must be 0 (off) or >= 2 runs, got {args.grid_error}")
    if args.seed < 0:
        raise ConfigError(f"--seed must be >= 0, got {args.seed}")
    if args.threshold is not None and not (math.isfinite(args.threshold) and args.threshold >= 0):
        raise ConfigError(f"--threshold must be >= 0 m, got {args.threshold}")
    cfg = load_calibration_config(args.config)
    ev = make_evaluator(cfg)
    ev.solver_progress = not args.quiet
    if args.threshold is None:  # the map then agrees with the impact area the calibration fitted
        args.threshold = next((float(o.threshold) for o in ev.observations if o.kind == "impact_area"),
                              DEFAULT_THRESHOLD)
    cal = load_calibration(args.calibration, ev.prior)
    ev.set_discrepancy_factors(cal.discrepancy_factors)   # the likelihood the calibration learnt
    out = Path(args.out)
    anc = check_output(out, args.overwrite)

    samples = posterior_samples(cal, args.n, seed=args.seed)
    bar = None
    if not args.quiet:
        from tqdm.auto import tqdm

        bar = tqdm(total=args.n, desc="predictive runs", unit="run")
    done = [0]

    def progress(n):
        if bar is not None:
            bar.update(n - done[0])
        done[0] = n

    try:
        with executor_for(args, cfg, ev):
            pr = run_predictive(ev, samples, args.threshold, progress=progress)
    except RuntimeError as e:
        raise ConfigError(str(e)) from None
    finally:
        if bar is not None:
            bar.close()

    error = None
    if args.grid_error >= 2:
        with executor_for(args, cfg, ev):
            error = grid_error(ev, pr.x[: args.grid_error], args.threshold)
    figures = figure_intervals(pr.figures, error, seed=args.seed, cellsize=ev.dem.cellsize)
    mismatches = footprint_mismatches(ev, pr)
    lower = np.concatenate([np.full(b.stop - b.start, 0.0 if KINDS[b.kind].nonnegative else -np.inf) for b in ev.blocks])
    checks = observation_check(pr.predictions, ev.data_recorded, ev.observation_sd(), ev.observation_names,
                               seed=args.seed, lower=lower)
    if ev.discrepancy == "learnt":
        checks = with_model_error(checks, pr.predictions, ev.data_recorded, predictive_sd(ev, pr.predictions, args.seed),
                                  seed=args.seed, lower=lower)
    scalar = [checks[b.start] for b in ev.blocks if not b.is_vector]
    series = {b.name: {"kind": b.kind, "n": b.stop - b.start,
                       "share_inside_90": float(np.mean([c["inside"] for c in checks[b.slice]]))}
              for b in ev.blocks if b.is_vector}
    dem = cfg.terrain.dem
    points = {o.name: (o.x, o.y) for o in ev.observations if getattr(o, "x", None) is not None and o.y is not None}
    with staged_output(out, anc, "predict") as tmp:
        fmt = cfg.output_format
        write_named_raster(tmp, "impact_probability", pr.impact_probability, dem, fmt)
        for name, qs in MAP_QUANTILES.items():
            for q in qs:
                write_named_raster(tmp, f"{name}_p{round(100 * q):02d}", pr.quantiles[name][q], dem, fmt)
        _write_draws_csv(tmp / "draws.csv", ev.names, ev.observation_names, pr.x, pr.predictions)
        info = {
            "calibration": str(Path(args.calibration)), "config": str(Path(args.config)),
            "n_draws": int(args.n), "n_ok": int(len(pr.x)), "n_failed": pr.n_failed, "failures": pr.failures,
            "seed": int(args.seed), "threshold_m": float(args.threshold),
            "parameters": {n: {"mean": float(pr.x[:, i].mean()), "sd": float(pr.x[:, i].std(ddof=1)) if len(pr.x) > 1
                               else 0.0} for i, n in enumerate(ev.names)},
            "fixed": {k: float(v) for k, v in ev.fixed.items()},
            "impact_area_m2": {"mean": float((pr.impact_probability * pr.cell_area).sum()),
                               "p50_map": float(pr.cell_area[pr.impact_probability >= 0.5].sum())},
            "figures": figures,
            "mismatches": None if mismatches is None else {k: v for k, v in mismatches.items() if k != "mapped"},
            "observations": scalar,
            "n_inside_90": int(sum(c["inside"] for c in scalar)),
            "maps_and_series": series,
            "values": checks if series else None,
            "against_observations": pr.survey,
            "conventions": cfg.conventions(),
        }
        (tmp / "predictive.json").write_text(json.dumps(info, indent=2))
        plot_field_map(dem, pr.impact_probability, tmp / "impact_probability.png", points=points,
                       label=f"P(h_max > {args.threshold:g} m)", cmap="YlOrRd", vmin=0.0, vmax=1.0,
                       title=f"Impact probability over {len(pr.x)} posterior draws", release=ev.release)
        if scalar:
            plot_predictive_check(scalar, tmp / "observations.png")
        front = _front(Path(args.calibration), pr)
        if front is not None:
            plot_front(front[0], tmp / "front.png", draws=front[1])
            (tmp / "front.json").write_text(json.dumps({"runs": front[0], "draws": front[1]}))
        if mismatches:
            plot_outlines(dem, mismatches["mapped"], {"impact probability >= 0.5": pr.impact_probability >= 0.5},
                          tmp / "outlines.png", title=f"mapped and simulated footprints (h_max > {args.threshold:g} m)",
                          labels=cluster_labels(mismatches["clusters"]))
    if not args.quiet:
        for name, f in pr.survey.items():
            j, r = f["footprint_jaccard"], f["runout_m"]
            print(f"against {name}: footprint Jaccard {j['median']:.2f} [{j['q05']:.2f}, {j['q95']:.2f}], "
                  f"{100 * f['share_of_mapped_reached']['median']:.0f} % of the mapped cells reached, run-out "
                  f"{r['median']:.0f} m [{r['q05']:.0f}, {r['q95']:.0f}] (mapped {r['mapped']:.0f} m)")
        for name, m in series.items():
            print(f"{name}: {100 * m['share_inside_90']:.0f} % of its {m['n']} values inside their 90 % intervals")
        if mismatches:
            ro = mismatches["runout"]
            print(f"against {mismatches['footprint']}: {ro['what']} {ro['difference_m']:+.0f} m "
                  f"[{ro['interval_m'][0]:+.0f}, {ro['interval_m'][1]:+.0f}] of the mapped {ro['mapped_m']:.0f} m")
            for i, m in enumerate(mismatches["clusters"][:5]):
                print(f"  {i + 1}. {mismatch_line(m)}")
            if mismatches["path_width"]["n_rings"]:
                print(f"  the grid: {width_line(mismatches['path_width'])}")
        for c in scalar:
            lo, hi = c["interval90"]
            wide = "" if "interval90_model_error" not in c else \
                " [{:.4g}, {:.4g}] with the model's own error".format(*c["interval90_model_error"])
            print(f"{c['name']}: recorded {c['value']:.4g}, predicted {c['model_quantiles']['0.5']:.4g} "
                  f"(90 % of a new recording: [{lo:.4g}, {hi:.4g}],{wide}){'' if c['inside'] else '  <- outside'}")
        for name, f in figures.items():
            g = f.get("with_grid_error")
            extra = "" if g is None else (f", [{g['q05']:.4g}, {g['q95']:.4g}] with the grid's error "
                                          f"(+- {g['sd']:.3g}, either sign: {g['n']} runs on cells half the size differ by "
                                          f"{g['shift']:+.3g} on average)")
            print(f"{name}: 90 % of the draws [{f['q05']:.4g}, {f['q95']:.4g}]{extra}")
        print(f"impact area (mean over the draws) {info['impact_area_m2']['mean']:.4g} m^2; wrote {out}")
    for c in scalar:
        if not c["inside"]:
            print(f"torchslide: warning: {c['name']} = {c['value']:.4g} lies outside the 90 % posterior-predictive "
                  f"interval [{c['interval90'][0]:.4g}, {c['interval90'][1]:.4g}] (percentile "
                  f"{100 * c['percentile']:.1f}): the calibrated model does not reproduce it", file=sys.stderr)
    if pr.n_failed:
        print(f"torchslide: warning: {pr.n_failed} of {args.n} draws failed and were left out (predictive.json "
              f"'failures'); first: {pr.failures[0]['reason']}", file=sys.stderr)
    return 1 if pr.n_failed else 0
