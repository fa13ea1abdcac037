"""``torchslide calibrate CONFIG.toml --out DIR [--resume]``: Bayesian active-learning calibration.

The config is the ``simulate`` config plus [prior], [[observations]] and [calibration]
(torchslide.calibration_config lists their keys).

[model] gives the values of the parameters that are not calibrated (mu and xi in [model] are
ignored when they are in [prior]). Writes posterior.json, posterior.npz, posterior.png, tv.png,
runs.csv, a checkpoint (so ``--resume`` continues an interrupted run without repeating a finished
run), TensorBoard logs under DIR/tensorboard and, last, finished.json (a resume of a calibration killed
before it writes whatever result file is missing). posterior.json's ``best_run_fit`` gives each
observation's standardised residual on the best run, and calibrate warns (stderr) about every
observation that even the best run misses by more than 3 sigma and about every pair of data that no run
meets together (``tradeoffs``: torchslide.tradeoff). ``discrepancy`` gives the model's own error as learnt
with the parameters (torchslide.discrepancy; ``[calibration] discrepancy = "none"`` leaves it out). A
posterior too sharp for the emulator (``[calibration] inference``, diagnose.local_path.local_calibration)
is fitted on the solver and described by its Laplace approximation; posterior.json's ``inference`` says
which path was taken and why.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from ..calibration_config import load_calibration_config, make_evaluator
from ..config import ConfigError
from . import add_executor_arguments, executor_for

HELP = "calibrate rheological parameters by Bayesian active learning"

def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("config", help="TOML config (simulate config + [prior], [[observations]], [calibration])")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--resume", action="store_true", help="continue an interrupted calibration in --out")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    add_executor_arguments(p)


def write_runs_csv(path: Path, res, obs_names, records) -> None:
    """One line per run of the result (in run order): parameters, predicted observables (blank where no
    record has them), z, failed, reason, initial."""
    preds = {tuple(np.round(r.x, 12)): r.predictions for r in records}
    from ..files import atomic_path

    with atomic_path(path) as tmp, open(tmp, "w") as f:
        f.write(",".join(list(res.names) + list(obs_names) + ["z", "failed", "reason", "initial"]) + "\n")
        for i, (x, z, fl, why) in enumerate(zip(res.x, res.z, res.failed, res.reasons)):
            p = preds.get(tuple(np.round(x, 12)))
            pv = [f"{v:.10g}" for v in p] if p is not None else [""] * len(obs_names)
            f.write(",".join([f"{v:.10g}" for v in x] + pv + [f"{z:.10g}", str(int(fl)), str(why).replace(",", ";"),
                                                               str(int(i < res.n_initial))]) + "\n")


FIT_WARN_Z = 3.0  # |standardised residual| of the best run above which calibrate warns
REACH_MIN = 0.01  # a point value (m/s or m) at or below this in every run: the flow never reached the point


def unreached_warnings(ev, tol: float = REACH_MIN) -> list[str]:
    """One line per point observation (a speed or thickness at (x, y)) that no successful run reached: its
    prediction <= ``tol`` in every run (wrong coordinates, or a point off the path)."""
    runs = [r.predictions for r in ev.records if not r.failed]
    if not runs:
        return []
    P = np.asarray(runs, dtype=float)
    out = []
    for b in ev.blocks:
        o, k = b.obs, b.start
        if not b.is_vector and o.spec.needs_point and np.all(np.abs(P[:, k]) <= tol):
            out.append(f"no run reaches observation {o.name} at ({o.x:g}, {o.y:g}): its {o.kind} is <= {tol:g} "
                       f"{o.spec.unit} in all {len(runs)} runs, so it cannot inform the posterior; check that the "
                       f"point lies on the flow path and that t_end is long enough")
    return out


def misfit_warnings(fit: dict, z_max: float = FIT_WARN_Z) -> list[str]:
    """One line per observation that even the best run (LandslideEvaluator.best_fit) misses by more than
    ``z_max`` sigma: the calibration cannot have learnt from it, and the user should know why."""
    out = []
    for o in fit["observations"]:
        if "rms_standardised_residual" in o:       # a map or series
            if o["rms_standardised_residual"] > z_max:
                out.append(f"the best of {fit['n_runs']} runs misses the {o['n']} values of {o['name']} by "
                           f"{o['rms_standardised_residual']:.1f} sigma rms (mean residual {o['mean_residual']:+.3g}): "
                           "no parameter set tried reproduces them; check the recording and its sigma, or run "
                           "`torchslide diagnose` for missing physics.")
            continue
        r = o["standardised_residual"]
        if abs(r) > z_max:
            out.append(f"the best of {fit['n_runs']} runs misses {o['name']} by {r:+.1f} sigma (predicted "
                       f"{o['predicted']:.4g}, recorded {o['value']:.4g} +- {o['sigma']:.3g}): no parameter set tried "
                       "reproduces it, so the posterior follows the other data or the prior there. Check its value, "
                       "unit and location (does the flow reach it by t_end?), or run `torchslide diagnose` for "
                       "missing physics.")
    return out


def model_error_summary(ev) -> dict:
    """posterior.json's ``discrepancy``: the model of the model's own error (``[calibration] discrepancy``), the
    correlation factors it learnt, and per observation at the best run its misfit per value and the learnt
    discrepancy's sd over the stated one (torchslide.discrepancy.DiscrepancyLikelihood.describe)."""
    out = {"model": ev.discrepancy, "correlation_factors": ev.discrepancy_factors or {}}
    ok = [r for r in ev.records if not r.failed and np.isfinite(r.z)]
    if ev.discrepancy == "learnt" and ok:
        best = max(ok, key=lambda r: r.z)
        out["at_best_run"] = ev.likelihood.describe(best.predictions)
    return out


FINISHED = "finished.json"
"""Written last, when every result file of a calibration is in place: {"n_runs", "files"}."""


def _finished(out: Path, n_total: int) -> bool:
    """Whether ``out`` holds a calibration that ended with at least ``n_total`` runs and wrote every result
    file (a calibration killed during its final writes is not finished: its resume writes them again)."""
    try:
        done = json.loads((out / FINISHED).read_text())
        return int(done["n_runs"]) >= n_total and all((out / f).is_file() for f in done["files"])
    except (OSError, ValueError, KeyError, TypeError):
        return False


def check_case(path: Path, ev, resume: bool) -> None:
    """Record the case's fingerprint (calibration_config.case_fingerprint) in ``path`` for a new
    calibration; for a resumed one, refuse a config that changes z, naming what changed."""
    from ..calibration_config import case_fingerprint, fingerprint_difference
    from ..files import FileStateError, write_text_atomic

    now = case_fingerprint(ev)
    if resume and path.exists():
        try:
            saved = json.loads(path.read_text())
        except ValueError:
            raise FileStateError(f"{path} is corrupt; delete the output folder to start again") from None
        diff = fingerprint_difference(saved, now)
        if diff is not None:
            raise FileStateError(f"{path.parent} was calibrated with other {diff} than the config gives now: "
                                 "resume with the config it was made with, or choose another --out")
        return
    write_text_atomic(path, json.dumps(now, indent=1))


def run(args: argparse.Namespace) -> int:
    from ..output_folder import run_locked

    return run_locked(args.out, _run, args)


def _run(args: argparse.Namespace) -> int:
    from ..calibration import calibrate
    from ..figures import plot_posterior_any, plot_tv
    from ..evaluator import load_records, unique_records
    from ..files import write_text_atomic

    cfg = load_calibration_config(args.config)
    cal = cfg.extra["calibration"]
    out = Path(args.out)
    ckpt = out / "checkpoint.pt"
    if ckpt.exists() and not args.resume:
        raise ConfigError(f"{out} holds an earlier calibration (checkpoint.pt): pass --resume to continue it "
                          f"or choose another --out")
    if args.resume and not ckpt.exists():
        print(f"torchslide: note: no checkpoint in {out}; starting a new calibration", file=sys.stderr)
    from ..output_folder import prepare_work_folder

    ev = make_evaluator(cfg)
    ev.solver_progress = not args.quiet
    prior = ev.prior
    prepare_work_folder(out)
    check_case(out / "case.json", ev, resume=ckpt.exists())
    if args.resume and ckpt.exists() and _finished(out, cal["n_total"]):
        print(f"torchslide: note: the calibration in {out} has finished its {cal['n_total']} runs; nothing to "
              "resume (raise n_total to continue it)", file=sys.stderr)
        return 0
    ev.records_file = out / "records.npz"      # every run's predictions, kept across a resume
    if ckpt.exists() and ev.records_file.exists():
        ev.records = load_records(ev.records_file)
    with executor_for(args, cfg, ev):
        res = calibrate(ev, prior.bounds, n_initial=cal["n_initial"], n_total=cal["n_total"],
                        batch_size=cal["batch_size"], seed=cal["seed"], grid_size=cal["grid_size"],
                        acquisition=cal["acquisition"], checkpoint=ckpt, log_dir=out / "tensorboard",
                        tv_threshold=cal["tv_threshold"], names=prior.names, progress=not args.quiet,
                        clip_range=cal["clip_range"], inference=cal["inference"],
                        local_max_fraction=cal["local_max_fraction"],
                        log=lambda s: None if args.quiet else print(s, file=sys.stderr))
    inference = res.inference
    ev.records = unique_records(ev.records)
    res.save(out)
    info = json.loads((out / "posterior.json").read_text())
    info["observations"] = [{"name": o.name, "kind": o.kind, "n": int(o.m), "file": o.source}
                            if b.is_vector else {"name": o.name, "kind": o.kind, "value": float(o.value),
                                                 "sigma": float(o.sigma), "x": o.x, "y": o.y}
                            for b in ev.blocks for o in [b.obs]]
    info["solver_seconds_this_invocation"] = ev.solver_seconds
    info["conventions"] = cfg.conventions()
    fit = ev.best_fit()
    if fit is not None:
        info["best_run_fit"] = fit
    info["discrepancy"] = model_error_summary(ev)
    from ..tradeoff import conflicts, lines

    info["tradeoffs"] = conflicts(ev.records, ev)
    truth = cal.get("truth")
    if truth is not None:
        info["truth"] = {n: float(truth[n]) for n in prior.names}
    write_text_atomic(out / "posterior.json", json.dumps(info, indent=2))
    write_runs_csv(out / "runs.csv", res, ev.observation_names, ev.records)
    for w in unreached_warnings(ev) + (misfit_warnings(fit) if fit is not None else []) + lines(info["tradeoffs"]):
        print(f"torchslide: warning: {w}", file=sys.stderr)
    plot_posterior_any(res, out / "posterior.png", truth=None if truth is None else [truth[n] for n in prior.names])
    files = ["posterior.json", "posterior.npz", "runs.csv", "posterior.png"]
    if res.tv_history:
        plot_tv({Path(args.config).stem: res.tv_history}, out / "tv.png")
        files.append("tv.png")
    write_text_atomic(out / FINISHED, json.dumps({"n_runs": int(res.n_runs), "files": files}))
    s = res.summary
    for n in prior.names:
        print(f"{n}: mean {s['mean'][n]:.4g}  sd {s['sd'][n]:.3g}  MAP {s['map'][n]:.4g}  "
              f"90% HDR [{s['hdr90'][n][0]:.4g}, {s['hdr90'][n][1]:.4g}]")
    print(f"log evidence {res.log_evidence:.3f}; {res.n_runs} runs; inference: {inference['path']} "
          f"({inference['why']}); results in {out}")
    return 0
