"""Coverage: the share of torchslide's 90 % intervals that hold the truth when the model is wrong.

    OMP_NUM_THREADS=1 python -m bench.coverage --out bench/results/coverage.json [--workers 2]
        [--seeds 0,1] [--terrains narrow,fan] [--kinds grid,release,...] [--discrepancy none,learnt]
        [--inference auto|emulator|local]   (one setting per --out file) [--resume]

Every case is a synthetic recording that the inversion's model cannot reproduce exactly
(experiments.hidden_physics.scenarios.make_recording: made on cells half the inversion's 40 m, with a
release 0.9-1.1 times the stated one, noise stated as drawn): a deposit map, gauge series (h and speed)
and the final volume. The case kinds (``KINDS``) add to that:

    grid          nothing else: the grid's error and the release's
    release       a release 25 % larger than stated
    entrainment   entrainment (kappa 0.0015) the calibrated Voellmy model lacks
    yield_stress  a yield stress (tau_y 3 m^2/s^2) it lacks
    patch         a low-friction patch (mu x 0.55) outside every model
    dem_smooth    the inversion's DEM smoothed (a Gaussian filter of 1.5 cells), the recording's not
    entrainment+  entrainment at 1.5x, and the calibrated model has it: (mu, xi, kappa)
    yield_stress+ a yield stress at 1.5x, and the calibrated model has it: (mu, xi, tau_y)

Each case is calibrated as ``torchslide calibrate`` does it (torchslide.calibrate on a LandslideEvaluator:
20 + 20 runs in batches of 10 for (mu, xi), 30 + 30 with a switch; the local fit on the solver where
the posterior is sharp), once per discrepancy model (``[calibration] discrepancy``), and checked:

* parameters: the 90 % interval (posterior.json's hdr90) of mu and xi against the recording's (0.25,
  500 m/s^2), and of the switch against its true value where the model has one;
* predictions: as ``torchslide predict`` gives them (32 posterior draws on the inversion grid, 4 of
  them run on cells half the size too for the grid's error: torchslide.predict.figure_intervals): the 90 %
  interval of the impact area (h_max > 0.5 m, m^2) and of the run-out from the release's crown (h_max >
  0.5 m, m) against the recording's own (on its finer grid); ``covers_draws_alone`` says whether the
  draws' interval without the grid's error would have.

The JSON gives every interval, the share that covers its truth per discrepancy model, per kind of
interval and per case kind, and each calibration's wall time. Every case runs anew and --out is rewritten
after each; ``--resume`` keeps the cases already in --out (an interrupted run, on the same code) and runs the
rest.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

KINDS = {"grid": ("null", 1.0, False), "release": ("release_volume", 1.0, False),
         "entrainment": ("entrainment", 1.0, False), "yield_stress": ("yield_stress", 1.0, False),
         "patch": ("low_friction_patch", 1.0, False), "dem_smooth": ("null", 1.0, False),
         "entrainment+": ("entrainment", 1.5, True), "yield_stress+": ("yield_stress", 1.5, True)}
"""case kind -> (the recording's scenario, its strength, whether the calibrated model has the hidden term)."""
CELLSIZE = 40.0
THRESHOLD = 0.5
N_DRAWS = 32


def _truth_figures(rec, scenarios) -> dict:
    """The recording's impact area (m^2) and run-out from its release's crown (m), on its finer grid."""
    from torchslide.survey import runout_from_crown

    dem_f, _ = scenarios.terrain(CELLSIZE / 2)
    rel_f = scenarios.release(dem_f, scenarios.V_NOMINAL * rec.volume_factor
                              * (1 + rec.truth.get("release_scale", 0.0)))
    reached = rec.fine_h_max > THRESHOLD
    return {"impact_area": float(reached.sum() * dem_f.cellsize ** 2),
            "runout": runout_from_crown(dem_f.z, rel_f, reached, dem_f.cellsize)}


def _evaluator(rec, kind: str, discrepancy: str, scenarios):
    """The case's LandslideEvaluator on 40 m cells: Voellmy (mu, xi), or with the hidden term's switch."""
    from scipy.ndimage import gaussian_filter

    from torchslide.bayes import Prior, Uniform
    from torchslide.diagnose.candidates import CANDIDATES
    from torchslide.evaluator import LandslideEvaluator
    from torchslide.solver import SolverConfig
    from torchslide.terrain.grid import DEM

    dem, erod = scenarios.terrain(CELLSIZE)
    release = scenarios.release(dem, scenarios.V_NOMINAL)
    if kind == "dem_smooth":
        dem = DEM(gaussian_filter(dem.z, 1.5, mode="nearest"), dem.cellsize, xll=dem.xll, yll=dem.yll)
    comps = {"mu": Uniform(0.12, 0.4), "xi": Uniform(150.0, 1500.0)}
    fixed = {}
    scenario, _, in_model = KINDS[kind]
    if in_model:
        c = CANDIDATES[scenario]
        comps[c.param] = Uniform(*c.prior)
        fixed.update(dict(c.fixed))
    return LandslideEvaluator(dem=dem, release=release, observations=scenarios.noise_sigmas(rec.observations),
                              prior=Prior(comps), fixed=fixed, t_end=scenarios.T_END, gauges=scenarios.gauges(),
                              erodible_depth=erod, solver_config=SolverConfig(**scenarios.SOLVER), max_batch=16,
                              discrepancy=discrepancy)


def _predictive(ev, res) -> dict:
    """The 90 % intervals of the impact area and the run-out from the crown, as ``torchslide predict`` gives
    them: over 32 posterior draws, and with the grid's error from 4 of them run on cells half the size."""
    from torchslide.predict import figure_intervals, grid_error, posterior_samples, run_predictive

    pr = run_predictive(ev, posterior_samples(res, N_DRAWS, seed=0), THRESHOLD)
    f = figure_intervals(pr.figures, grid_error(ev, pr.x[:4], THRESHOLD), seed=0, cellsize=ev.dem.cellsize)
    return {k: {"draws": [f[key]["q05"], f[key]["q95"]],
                "with_grid_error": [f[key]["with_grid_error"]["q05"], f[key]["with_grid_error"]["q95"]]}
            for k, key in (("impact_area", "impact_area_m2"), ("runout", "runout_m"))}


def run_case(terrain: str, kind: str, seed: int, discrepancy: str, inference: str = "auto") -> dict:
    """One case's calibration and its intervals against the truth (module doc)."""
    import torch

    from experiments.hidden_physics import scenarios
    from torchslide.calibration import calibrate
    from torchslide.diagnose.candidates import CANDIDATES

    torch.set_num_threads(1)
    scenario, strength, in_model = KINDS[kind]
    with scenarios.terrain_variant(terrain):
        rec = scenarios.make_recording(scenario, seed, CELLSIZE, strength=strength)
        truth_fig = _truth_figures(rec, scenarios)
        ev = _evaluator(rec, kind, discrepancy, scenarios)
        p = len(ev.names)
        t0 = time.perf_counter()
        res = calibrate(ev, ev.prior.bounds, n_initial=10 * p, n_total=20 * p, batch_size=10, seed=0,
                        progress=False, inference=inference)
        pred = _predictive(ev, res)
        wall = time.perf_counter() - t0
    truth = {"mu": scenarios.TRUE_BASE["mu"], "xi": scenarios.TRUE_BASE["xi"]}
    if in_model:
        c = CANDIDATES[scenario]
        truth[c.param] = rec.truth[c.param]
    intervals = [{"quantity": n, "type": "switch" if n not in ("mu", "xi") else "parameter",
                  "interval": res.summary["hdr90"][n], "truth": float(t)} for n, t in truth.items()]
    intervals += [{"quantity": n, "type": "prediction", "interval": pred[n]["with_grid_error"],
                   "draws_alone": pred[n]["draws"], "truth": truth_fig[n]} for n in ("impact_area", "runout")]
    for iv in intervals:
        lo, hi = iv["interval"]
        iv["covers"] = bool(lo <= iv["truth"] <= hi)
        if "draws_alone" in iv:
            iv["covers_draws_alone"] = bool(iv["draws_alone"][0] <= iv["truth"] <= iv["draws_alone"][1])
    return {"terrain": terrain, "kind": kind, "seed": seed, "discrepancy": discrepancy, "inference_asked": inference,
            "inference": res.inference.get("path"), "discrepancy_factors": res.discrepancy_factors,
            "map": res.summary["map"], "intervals": intervals, "wall_s": wall}


def _key(c: dict) -> str:
    return f"{c['terrain']}:{c['kind']}:{c['seed']}:{c['discrepancy']}"


def summarise(cases: list) -> dict:
    """Shares of intervals covering the truth: per discrepancy model, and by interval type and case kind."""
    out = {}
    for model in sorted({c["discrepancy"] for c in cases}):
        ivs = [(c, iv) for c in cases if c["discrepancy"] == model for iv in c["intervals"]]
        share = lambda sel: {"n": len(sel), "covered": int(sum(iv["covers"] for _, iv in sel)),
                             "share": float(np.mean([iv["covers"] for _, iv in sel])) if sel else None}
        out[model] = {"all": share(ivs),
                      "by_type": {t: share([(c, iv) for c, iv in ivs if iv["type"] == t])
                                  for t in ("parameter", "switch", "prediction")},
                      "median_width_over_truth": {t: float(np.median([(iv["interval"][1] - iv["interval"][0])
                                                                      / abs(iv["truth"]) for _, iv in ivs
                                                                      if iv["type"] == t]))
                                                  for t in ("parameter", "switch", "prediction")
                                                  if any(iv["type"] == t for _, iv in ivs)},
                      "by_kind": {k: share([(c, iv) for c, iv in ivs if c["kind"] == k]) for k in KINDS},
                      "n_cases": len({_key(c) for c, _ in ivs}),
                      "wall_s_median": float(np.median([c["wall_s"] for c in cases if c["discrepancy"] == model]))}
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=Path("bench/results/coverage.json"))
    ap.add_argument("--terrains", default="narrow,fan")
    ap.add_argument("--kinds", default=",".join(KINDS))
    ap.add_argument("--seeds", default="0,1")
    ap.add_argument("--discrepancy", default="none,learnt")
    ap.add_argument("--inference", default="auto", choices=("auto", "emulator", "local"),
                    help="calibrate's inference path (torchslide.calibrate; auto: local where the posterior is sharp)")
    ap.add_argument("--workers", type=int, default=int(os.environ.get("COVERAGE_WORKERS", "2")))
    ap.add_argument("--resume", action="store_true", help="keep the cases already in --out, run the others")
    a = ap.parse_args(argv)
    done = {}
    if a.resume and a.out.exists():
        done = {_key(c): c for c in json.loads(a.out.read_text()).get("cases", [])}
    jobs = [(t, k, int(s), d, a.inference) for t in a.terrains.split(",") for k in a.kinds.split(",")
            for s in a.seeds.split(",") for d in a.discrepancy.split(",")]
    for k in {j[1] for j in jobs} - set(KINDS):
        raise SystemExit(f"--kinds: unknown kind {k!r} (known: {', '.join(KINDS)})")
    todo = [j for j in jobs if f"{j[0]}:{j[1]}:{j[2]}:{j[3]}" not in done]

    def save():
        cases = sorted(done.values(), key=_key)
        a.out.parent.mkdir(parents=True, exist_ok=True)
        tmp = a.out.with_suffix(".tmp")
        tmp.write_text(json.dumps({"command": "python -m bench.coverage " + " ".join(sys.argv[1:] if argv is None else argv),
                                   "summary": summarise(cases), "cases": cases}, indent=1))
        os.replace(tmp, a.out)

    with ProcessPoolExecutor(max_workers=max(1, a.workers)) as pool:
        futures = {pool.submit(run_case, *j): j for j in todo}
        for f in futures:
            c = f.result()
            done[_key(c)] = c
            save()
            print(f"{_key(c)}: {sum(iv['covers'] for iv in c['intervals'])}/{len(c['intervals'])} covered, "
                  f"{c['wall_s']:.0f} s", flush=True)
    if not todo:
        save()
    print(json.dumps(json.loads(a.out.read_text())["summary"], indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
