"""Run the blind harness: ``python -m experiments.hidden_physics.harness [--out DIR] [--seeds N | --seed-list 100,101] [--scenarios a,b]
[--model-error N] [--mode-search-iters N] [--mode-search-max-iters N] [--profile-top N] [--release-volume-sd S] [--thresholds FILE] [--cellsize M] [--fine-terrain] [--terrain narrow|resolved] [--device cuda]
[--max-batch N] [--extra-gauges 300,1200] [--sigma-scale A]``.

Each case: make a recording (hidden term, finer grid, noise, release error), run torchslide.diagnose
without telling it the scenario, save DIR/<scenario>_s<seed>.json (+ .npz with before/after maps and
gauge series). Cases already saved are skipped, so the run can be resumed, and a case being run is marked
DIR/<case>.running, so several processes can share one DIR; make_page.py builds the results page
from whatever finished.

Decision thresholds: read from ``thresholds.json`` next to this file when it exists (written by
calibrate_thresholds.py from *separate* null seeds 100-104), else torchslide.diagnose.Thresholds().
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

import numpy as np

from torchslide.diagnose import Budgets, Thresholds, diagnose
from torchslide.physics import CANDIDATES

from . import scenarios
from .scenarios import SCENARIOS, SIGMAS, SWITCH, TERRAINS, make_evaluator, make_recording, noise_sigmas, terrain_variant

LIBRARY = ["entrainment", "curvature", "earth_pressure", "yield_stress", "mu_i"]
HARNESS_BUDGETS = dict(n_posterior_samples=16, n_posterior_samples_after=12, n_initial=12, n_total=24, n_total_max=36,
                       baseline_n_initial=10, baseline_n_total=16, baseline_refine_rounds=3, batch_size=8, top_k=len(LIBRARY),
                       n_perm=49)
THRESHOLDS_FILE = Path(__file__).parent / "thresholds.json"


def harness_thresholds() -> Thresholds:
    if THRESHOLDS_FILE.exists():
        d = json.loads(THRESHOLDS_FILE.read_text())
        return Thresholds(**d["thresholds"])
    return Thresholds()


def out_of_range(scenario: str, strength: float) -> str | None:
    """Why ``scenario`` cannot be recorded at ``strength`` (its scaled switch beyond the switch's range,
    e.g. earth pressure or curvature above 1), else None."""
    term, hidden = SCENARIOS[scenario]
    if term not in SWITCH:
        return None
    v = hidden[SWITCH[term]] * strength
    lo, hi = CANDIDATES[term].prior
    if not lo <= v <= hi:
        return f"switch {SWITCH[term]} = {v:g} beyond its range [{lo:g}, {hi:g}]"
    return None


def coverage(diag: dict, truth: dict) -> tuple:
    """(true switch in the 90 % HDI, in the refit's 'hdr90') of the true term's refit in a
    report.json-style ``diag``; (None, None) when the scenario has no library term or it was not
    refitted. "Covers": the highest-density interval on the prior range (it may include a prior bound,
    e.g. earth pressure = 1), with a tolerance of 1e-9 of the prior width for the floating-point end
    of a grid's last cell (0.9999999999999999 for a bound at 1). Saved cases keep the keys of older
    runs: 'true_term_covered_hdr90' holds the first value (the HDI), 'true_term_covered_equal_tailed90'
    the second ('hdr90': the equal-tailed interval of MCMC samples but, on the grid posterior a
    refinement leaves, the extent along the axis of the joint 90 % region, usually wider than a marginal
    interval; shown, never used for the targets)."""
    term = truth["term"]
    if term not in SWITCH:
        return None, None
    c = next((c for c in diag["candidates"] if c["name"] == term), None)
    par = c["parameters"].get(SWITCH[term]) if c else None
    if not par:
        return None, None
    lo_p, hi_p = CANDIDATES[term].prior
    tol = 1e-9 * (hi_p - lo_p)
    v = truth[SWITCH[term]]
    lo, hi = par.get("hdi90", par["hdr90"])
    lo_e, hi_e = par["hdr90"]
    return bool(lo - tol <= v <= hi + tol), bool(lo_e - tol <= v <= hi_e + tol)


def run_case(scenario: str, seed: int, out, cellsize: float = 40.0, strength: float = 1.0,
             budgets: dict | None = None, candidates=None, log=print, thresholds: Thresholds | None = None,
             fine_terrain: bool = False, device: str = "cpu", max_batch: int = 16, fine_factor: int = 2,
             sigma_scale: float = 1.0, compile_solver: bool = False, sigmas: str = "harness") -> dict:
    """One blind case: the recording, the diagnosis, the case JSON (and its maps) in ``out``. ``sigmas``
    "noise": the likelihood's sigmas are the noise drawn (scenarios.noise_sigmas; ``sigma_scale`` must be 1)."""
    if sigmas not in SIGMAS:
        raise ValueError(f"sigmas must be one of {SIGMAS}, got {sigmas!r}")
    if sigmas == "noise" and sigma_scale != 1.0:
        raise ValueError(f"sigmas 'noise' states the noise drawn: sigma_scale must be 1, got {sigma_scale!r}")
    t0 = time.perf_counter()
    out = Path(out)
    rec = make_recording(scenario, seed, cellsize=cellsize, strength=strength, fine_factor=fine_factor,
                         sigma_scale=sigma_scale)
    if sigmas == "noise":
        rec = dataclasses.replace(rec, observations=noise_sigmas(rec.observations))
    ev = make_evaluator(rec, cellsize=cellsize, fine_terrain=fine_terrain, device=device, max_batch=max_batch,
                        compile_solver=compile_solver)
    bud = Budgets(**{**HARNESS_BUDGETS, **(budgets or {}), "seed": seed})
    d = diagnose(ev, candidates or LIBRARY, bud, thresholds or harness_thresholds(), log=log)
    j = d.to_json()
    cover, cover_eq = coverage(j, rec.truth)
    case = {"scenario": scenario, "seed": seed, "strength": strength, "cellsize": cellsize, "terrain": scenarios.TERRAIN,
            "fine_terrain": fine_terrain, "fine_factor": fine_factor, "extra_gauges": list(scenarios.EXTRA_GAUGES),
            "sigma_scale": sigma_scale, "sigmas": sigmas, "device": str(device), "compile_solver": compile_solver, "truth": rec.truth,
            "volume_factor": rec.volume_factor, "true_term_covered_hdr90": cover,
            "true_term_covered_equal_tailed90": cover_eq,
            "wall_s": time.perf_counter() - t0, "diagnosis": j}
    tag = f"{scenario}_s{seed}" + ("" if strength == 1.0 else f"_x{strength:g}")
    out.mkdir(parents=True, exist_ok=True)
    (out / f"{tag}.json").write_text(json.dumps(case, indent=1))
    arrays = {}
    for name, m in d.localisation.maps.items():
        for k, v in m.items():
            arrays[f"before/{name}/{k}"] = np.asarray(v)
    if d.after_localisation is not None:
        for name, m in d.after_localisation.maps.items():
            for k, v in m.items():
                arrays[f"after/{name}/{k}"] = np.asarray(v)
    np.savez_compressed(out / f"{tag}.npz", **arrays)
    return case


def main(argv=None) -> int:
    p = argparse.ArgumentParser()
    p.add_argument("--out", default=str(Path(__file__).parent / "results" / "harness"))
    p.add_argument("--seeds", type=int, default=5)
    p.add_argument("--seed-list", default=None, help="comma-separated seeds (overrides --seeds)")
    p.add_argument("--scenarios", default=",".join(SCENARIOS))
    p.add_argument("--strengths", default="1")
    p.add_argument("--model-error", type=int, default=None,
                   help="Budgets.model_error_runs: the grid's approximation error from this many run pairs "
                        "(0: off; default: Budgets' default, 12)")
    p.add_argument("--mode-search-iters", type=int, default=None,
                   help="Budgets.mode_search_iters: iterations of each refit's local search on the solver (default: "
                        "Budgets' default); another value needs its own null seeds and --out")
    p.add_argument("--mode-search-max-iters", type=int, default=None,
                   help="Budgets.mode_search_max_iters: every mode search goes on while it climbs (by more than "
                        "Budgets.mode_search_tol in z over 4 iterations), up to this many iterations (default: "
                        "Budgets' default, 0: off); another value needs its own null seeds and --out")
    p.add_argument("--profile-top", type=int, default=None,
                   help="Budgets.profile_top: refits profiled along their switch (default: Budgets' default); "
                        "another value needs its own null seeds and --out")
    p.add_argument("--release-volume-sd", type=float, default=None,
                   help="Budgets.release_volume_sd: the release volume's relative sd given to the diagnosis (the "
                        "recordings' release error U(0.9, 1.1) has sd 0.1/sqrt(3) = 0.0577; default: Budgets' "
                        "default, 0); another value needs its own null seeds and --out")
    p.add_argument("--thresholds", default=str(THRESHOLDS_FILE), help="decision thresholds file")
    p.add_argument("--cellsize", type=float, default=40.0,
                   help="inversion cell size, m (the recordings use half of it); thresholds.json was set at 40 m, "
                        "so another cell size needs its own null seeds (calibrate_thresholds --results) and --out")
    p.add_argument("--fine-terrain", action="store_true",
                   help="give the diagnosis the terrain on the recording grid for the model error's finer runs "
                        "(scenarios.make_evaluator(fine_terrain=True)); needs its own null seeds and --out")
    p.add_argument("--terrain", default="narrow", choices=sorted(TERRAINS),
                   help="terrain variant (scenarios.TERRAINS); another than narrow needs its own null seeds and --out")
    p.add_argument("--fine-factor", type=int, default=2,
                   help="recording grid = inversion cells / this (the issue's harness: 2). 1 is the control without "
                        "discretisation error (the 'inverse crime': use it with --model-error 0, its own null seeds "
                        "and --out)")
    p.add_argument("--extra-gauges", default="",
                   help="comma-separated x (m) of extra gauges g3, ... on the thalweg (scenarios.extra_gauges; "
                        "design_check.py); another design needs its own null seeds and --out")
    p.add_argument("--sigma-scale", type=float, default=1.0,
                   help="multiplies the likelihood sigmas of the gauge series and the deposit map (not the noise "
                        "drawn; scenarios.make_recording); another value needs its own null seeds and --out")
    p.add_argument("--sigmas", default="harness", choices=SIGMAS,
                   help="the likelihood's sigmas: the harness' (default; 1.7-4 times the noise drawn) or the sd of the "
                        "noise drawn (scenarios.noise_sigmas); noise needs its own null seeds and --out")
    p.add_argument("--device", default="cpu", help="solver device of the diagnosis (cpu, cuda, ...)")
    p.add_argument("--max-batch", type=int, default=16, help="most members per solver call")
    p.add_argument("--compile", action="store_true",
                   help="torch.compile the diagnosis' solver steps (pays off on a GPU with a large --max-batch: "
                        "README, 'On a GPU'; the recordings are made eager on the CPU either way)")
    a = p.parse_args(argv)
    if a.max_batch < 1:
        p.error(f"--max-batch must be >= 1, got {a.max_batch}")
    if a.fine_factor < 1:
        p.error(f"--fine-factor must be >= 1, got {a.fine_factor}")
    if not 0 < a.sigma_scale <= 10:
        p.error(f"--sigma-scale must be in (0, 10], got {a.sigma_scale}")
    if a.sigmas == "noise" and a.sigma_scale != 1.0:
        p.error(f"--sigmas noise states the noise drawn: --sigma-scale must be 1, got {a.sigma_scale}")
    if a.mode_search_iters is not None and a.mode_search_iters < 0:
        p.error(f"--mode-search-iters must be >= 0, got {a.mode_search_iters}")
    if a.mode_search_max_iters is not None and a.mode_search_max_iters < 0:
        p.error(f"--mode-search-max-iters must be >= 0, got {a.mode_search_max_iters}")
    if a.release_volume_sd is not None and not 0 <= a.release_volume_sd < 0.5:
        p.error(f"--release-volume-sd must be in [0, 0.5), got {a.release_volume_sd}")
    if a.profile_top is not None and a.profile_top < 0:
        p.error(f"--profile-top must be >= 0, got {a.profile_top}")
    try:
        xs = [float(x) for x in a.extra_gauges.split(",") if x.strip()]
    except ValueError:
        p.error(f"--extra-gauges must be comma-separated numbers (x in m), got {a.extra_gauges!r}")
    with terrain_variant(a.terrain), scenarios.extra_gauges(xs):
        return _run_all(a)


def _claim(out: Path, tag: str) -> Path | None:
    """Mark case ``tag`` as taken by this process (``out/<tag>.running``, created atomically) so that
    several harness processes on one ``out`` share the cases; None when another process holds it."""
    out.mkdir(parents=True, exist_ok=True)
    f = out / f"{tag}.running"
    try:
        f.open("x").close()
    except FileExistsError:
        return None
    return f


def _run_all(a) -> int:
    th_file = Path(a.thresholds)
    th = Thresholds(**json.loads(th_file.read_text())["thresholds"]) if th_file.exists() else Thresholds()
    bud = {k: v for k, v in (("model_error_runs", a.model_error), ("mode_search_iters", a.mode_search_iters),
                             ("mode_search_max_iters", a.mode_search_max_iters), ("profile_top", a.profile_top), ("release_volume_sd", a.release_volume_sd))
           if v is not None} or None
    out = Path(a.out)
    seeds = [int(v) for v in a.seed_list.split(",")] if a.seed_list else list(range(a.seeds))
    for seed in seeds:
        for strength in [float(s) for s in a.strengths.split(",")]:
            for sc in a.scenarios.split(","):
                tag = f"{sc}_s{seed}" + ("" if strength == 1.0 else f"_x{strength:g}")
                if (out / f"{tag}.json").exists():
                    continue
                beyond = out_of_range(sc, strength)
                if beyond:
                    print(f"=== {tag}: skipped, {beyond}", flush=True)
                    continue
                claim = _claim(out, tag)
                if claim is None:
                    print(f"=== {tag}: skipped, another process holds {out / (tag + '.running')} "
                          "(delete it if that process is gone)", flush=True)
                    continue
                print(f"=== {tag}", flush=True)
                try:
                    c = run_case(sc, seed, out, cellsize=a.cellsize, strength=strength, budgets=bud, thresholds=th,
                                 fine_terrain=a.fine_terrain, device=a.device, max_batch=a.max_batch,
                                 fine_factor=a.fine_factor, sigma_scale=a.sigma_scale, compile_solver=a.compile,
                                 sigmas=a.sigmas,
                                 log=lambda s: print(s, flush=True))
                finally:
                    claim.unlink(missing_ok=True)
                print(f"=== {tag}: {c['diagnosis']['verdict']} {c['diagnosis']['missing_physics']} "
                      f"({c['wall_s']:.0f} s)", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
