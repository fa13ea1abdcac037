"""How far a refit's 90 % interval moves between runs of one case: ``python -m
experiments.hidden_physics.refit_spread SCENARIO SEED --inference-seeds 0,1,2 [--model-error-seed K]
[--terrain narrow] [--out FILE]``.

The recording of harness case (SCENARIO, SEED) is the same in every run (seeded by SEED); the diagnosis is
run with only the true term as candidate and the harness budgets, each time with another inference seed (Budgets.seed: the
Latin hypercubes, the acquisition's restarts, the posterior draws, and the pilot calibration whose draws
estimate the grid's approximation error, so the likelihood's model-error covariance is re-estimated too).
``--model-error-seed K`` holds that estimate, and so the likelihood, fixed (Budgets.model_error_seed): the
remaining spread is the emulator's and the refit's alone. Per run: the true switch's 90 % HDI (the
harness' strict check), its mean and the verified 2 ln BF. If the runs' means disagree by as much as
their intervals are wide, an interval from one run claims more than the inference knows (session 36:
entrainment seed 1 gave intervals that overlap little on two machines). Rows are added to ``--out``
(JSON; runs already there are skipped), so several processes can share a file, each with its own seeds.
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from torchslide.diagnose import Budgets, diagnose

from .harness import HARNESS_BUDGETS, harness_thresholds
from .scenarios import SCENARIOS, SWITCH, TERRAINS, make_evaluator, make_recording, terrain_variant

HERE = Path(__file__).parent


def run_one(scenario: str, seed: int, inference_seed: int, model_error_seed: int | None = None,
            log=lambda *a: None) -> dict:
    """One diagnosis of case (scenario, seed) with only the true term, its inference seeded by
    ``inference_seed`` (and the grid-error estimate by ``model_error_seed``, None: the same seed): the
    true switch's interval, mean and the verified 2 ln BF."""
    term = SCENARIOS[scenario][0]
    if term not in SWITCH:
        raise SystemExit(f"scenario {scenario!r} has no library term to refit (library terms: "
                         f"{sorted(s for s, (t, _) in SCENARIOS.items() if t in SWITCH)})")
    t0 = time.perf_counter()
    rec = make_recording(scenario, seed)
    ev = make_evaluator(rec)
    bud = Budgets(**{**HARNESS_BUDGETS, "top_k": 1, "seed": inference_seed, "model_error_seed": model_error_seed})
    j = diagnose(ev, [term], bud, harness_thresholds(), log=log).to_json()
    c = next(x for x in j["candidates"] if x["name"] == term)
    p = c["parameters"][SWITCH[term]]
    return {"scenario": scenario, "seed": seed, "inference_seed": inference_seed,
            "model_error_seed": model_error_seed, "term": term,
            "truth": rec.truth[SWITCH[term]], "mean": p["mean"], "hdi90": p.get("hdi90", p["hdr90"]),
            "two_ln_bf": c.get("two_ln_bf"), "two_ln_bf_lower": c.get("two_ln_bf_lower"),
            "wall_s": time.perf_counter() - t0}


def reference_posterior(scenario: str, seed: int, model_error_seed: int, box, n: int = 16, chunk: int = 64,
                        baseline: bool = False, points=None, log=print) -> dict:
    """The brute-force posterior of the true-term model for case (scenario, seed) with the grid-error
    estimate of ``model_error_seed`` (the likelihood the refits of ``--model-error-seed`` see): z = ln L +
    ln prior on every node of an n^p grid over ``box`` ((lo, hi) per parameter, the candidate evaluator's
    order, e.g. mu, xi, switch), one solver run per node in batches of ``chunk``. Returns the switch's mean
    and 90 % HDI from the grid's marginal (verify.hdi_from_grid, cell edges), each parameter's marginal
    mass in the box's edge cells (the box must hold the posterior: both near 0), and the log evidence
    over the box. ``box`` must lie inside the prior. ``baseline``: the baseline model (mu, xi) instead, its
    last parameter's marginal in place of the switch's (the reference for the baseline's calibration).
    ``points``: parameter vectors (e.g. a refit's best run) where z is evaluated too, to compare with the
    grid's best node."""
    import numpy as np
    import torch

    from torchslide.diagnose.refit import candidate_evaluator
    from torchslide.diagnose.verify import hdi_from_grid
    from torchslide.posterior import marginals

    term = SCENARIOS[scenario][0]
    if term not in SWITCH:
        raise ValueError(f"scenario {scenario!r} has no library term")
    rec = make_recording(scenario, seed)
    ev0 = make_evaluator(rec)
    model = (lambda e: e) if baseline else (lambda e: candidate_evaluator(e, term))
    prior = model(ev0).prior
    names = list(prior.names)
    lo_p, hi_p = prior.bounds[0].numpy(), prior.bounds[1].numpy()
    box = np.asarray(box, float)
    if box.size != 2 * len(names):
        raise ValueError(f"reference box needs lo, hi for each of {names}: {2 * len(names)} numbers, got {box.size}")
    box = box.reshape(len(names), 2)
    bad = [f"{nm} [{a:g}, {b:g}] (prior [{l:g}, {h:g}])" for nm, (a, b), l, h in zip(names, box, lo_p, hi_p)
           if not l <= a < b <= h]
    if bad:
        raise ValueError("reference box must lie inside the prior, with lo < hi: " + "; ".join(bad))
    evc = _likelihood(ev0, term, model_error_seed, baseline=baseline, log=log)
    axes = [np.linspace(a, b, n) for a, b in box]
    X = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, len(names))
    z = np.empty(len(X))
    t0 = time.perf_counter()
    for i in range(0, len(X), chunk):
        z[i:i + chunk] = evc(torch.as_tensor(X[i:i + chunk])).z.numpy()
        log(f"[reference] {min(i + chunk, len(X))}/{len(X)} runs ({time.perf_counter() - t0:.0f} s)")
    pts = np.asarray(points if points is not None else np.zeros((0, len(names))), float).reshape(-1, len(names))
    z_pts = evc(torch.as_tensor(pts)).z.numpy() if len(pts) else np.zeros(0)
    zz = z.reshape([n] * len(names))
    fin = np.isfinite(zz)
    dens = np.where(fin, np.exp(zz - zz[fin].max()), 0.0)
    marg = marginals(dens, axes)
    k = len(names) - 1
    w = marg[k] / marg[k].sum()
    cell = np.prod([(b - a) / (n - 1) for a, b in box])
    return {"scenario": scenario, "seed": seed, "model_error_seed": model_error_seed,
            "term": "baseline" if baseline else term, "names": names,
            "box": box.tolist(), "n": n, "runs": int(len(X)), "failed_runs": int((~fin).sum()),
            "truth": rec.truth[names[k]] if baseline else rec.truth[SWITCH[term]], "switch": names[k], "mean": float(np.sum(w * axes[k])),
            "hdi90": hdi_from_grid(dens, axes, k),
            "edge_mass": {nm: float((m[0] + m[-1]) / m.sum()) for nm, m in zip(names, marg)},
            "log_evidence_box": float(zz[fin].max() + np.log(dens.sum() * cell)),
            "best_x": X[int(np.nanargmax(np.where(np.isfinite(z), z, -np.inf)))].tolist(), "best_z": float(np.nanmax(z)),
            "points": [{"x": p.tolist(), "z": float(v)} for p, v in zip(pts, z_pts)],
            "wall_s": time.perf_counter() - t0}


def _likelihood(ev0, term: str, model_error_seed: int, baseline: bool = False, log=print):
    """The evaluator of the ``term`` model (or of the baseline) built on ``ev0`` (a case's baseline
    evaluator, scenarios.make_evaluator) with the grid error of ``model_error_seed``: the likelihood the
    refits of ``--model-error-seed`` see."""
    import tempfile

    from torchslide.diagnose.pipeline import grid_model_error
    from torchslide.diagnose.refit import candidate_evaluator

    with tempfile.TemporaryDirectory(prefix="refit_spread_") as tmp:
        ev, _ = grid_model_error(ev0, Budgets(**{**HARNESS_BUDGETS, "seed": model_error_seed}), tmp, log=log)
    return ev if baseline else candidate_evaluator(ev, term)


def search_from(scenario: str, seed: int, model_error_seed: int, starts, iters: int, step: float,
                log=print) -> dict:
    """polish.local_search (the refits' mode search, 6 moves per start and iteration) on the true-term model's
    z from ``starts`` (e.g. a refit's best runs) with initial step ``step`` per axis (unit-cube units):
    how far the search gets along the posterior's ridge. The pipeline's mode search starts with twice the
    refit posterior's sd per axis (at least 0.01), the search's own default is 0.05."""
    import numpy as np
    import torch

    from torchslide.diagnose.polish import local_search

    evc = _likelihood(make_evaluator(make_recording(scenario, seed)), SCENARIOS[scenario][0], model_error_seed,
                      log=log)
    X0 = np.asarray(starts, float).reshape(-1, len(evc.prior.names))
    z0 = evc(torch.as_tensor(X0)).z.numpy()
    ls = local_search(evc, X0, z0, evc.prior.bounds.numpy(), n_iter=iters, pop=6, step0=[step] * X0.shape[1], seed=11)
    return {"scenario": scenario, "seed": seed, "model_error_seed": model_error_seed, "names": list(evc.prior.names),
            "starts": X0.tolist(), "start_z": z0.tolist(), "iters": iters, "step": step, "runs": int(len(ls["z"])),
            "best_x": np.asarray(ls["best_x"]).tolist(), "best_z": float(ls["best_z"])}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("scenario", choices=sorted(SCENARIOS))
    ap.add_argument("seed", type=int)
    ap.add_argument("--inference-seeds", default="0,1,2", help="comma-separated Budgets seeds")
    ap.add_argument("--model-error-seed", type=int, default=None,
                    help="hold the grid-error estimate (and so the likelihood) fixed at this seed while the "
                         "inference seeds vary (default: each run re-estimates it with its own seed)")
    ap.add_argument("--reference", type=int, default=0, metavar="N",
                    help="instead of refits: the brute-force posterior on an N^p grid over --box with the grid "
                         "error of --model-error-seed (reference_posterior), written to --out")
    ap.add_argument("--box", default=None, help="with --reference: lo,hi per parameter (e.g. mu, xi, switch)")
    ap.add_argument("--baseline", action="store_true", help="with --reference: the baseline model (mu, xi)")
    ap.add_argument("--points", default="", help="with --reference: ';'-separated parameter vectors "
                                                 "('0.27,630,0.0019;...') where z is evaluated too")
    ap.add_argument("--search-from", default="", help="';'-separated start vectors: instead of refits, the mode "
                                                      "search from them (search_from), printed and added to --out")
    ap.add_argument("--search-iters", type=int, default=4)
    ap.add_argument("--search-step", type=float, default=0.05, help="initial step per axis, unit-cube units")
    ap.add_argument("--terrain", default="narrow", choices=sorted(TERRAINS))
    ap.add_argument("--out", default=None, help="JSON file (default results/refit_spread_<terrain>_<case>.json, "
                                                "with _me<seed> before .json under --model-error-seed)")
    a = ap.parse_args(argv)
    try:
        seeds = [int(v) for v in a.inference_seeds.split(",")]
    except ValueError:
        ap.error(f"--inference-seeds must be comma-separated integers, got {a.inference_seeds!r}")
    me = "" if a.model_error_seed is None else f"_me{a.model_error_seed}"
    if a.search_from:
        if a.model_error_seed is None:
            ap.error("--search-from needs --model-error-seed")
        try:
            starts = [[float(v) for v in q.split(",")] for q in a.search_from.split(";") if q.strip()]
        except ValueError:
            ap.error(f"--search-from must be ';'-separated vectors of comma-separated numbers, got {a.search_from!r}")
        out = Path(a.out) if a.out else HERE / "results" / f"refit_search_{a.terrain}_{a.scenario}_s{a.seed}{me}.json"
        with terrain_variant(a.terrain):
            r = search_from(a.scenario, a.seed, a.model_error_seed, starts, a.search_iters, a.search_step)
        rows = json.loads(out.read_text())["searches"] if out.exists() else []
        out.write_text(json.dumps({"searches": rows + [r]}, indent=1))
        print(f"search from {len(starts)} starts (best z {max(r['start_z']):.1f}), {a.search_iters} iterations, "
              f"step {a.search_step:g}: best z {r['best_z']:.1f} at {[round(v, 5) for v in r['best_x']]} "
              f"({r['runs']} runs)")
        return 0
    if a.reference:
        if a.model_error_seed is None or not a.box:
            ap.error("--reference needs --model-error-seed and --box")
        try:
            box = [float(v) for v in a.box.split(",")]
            pts = [[float(v) for v in q.split(",")] for q in a.points.split(";") if q.strip()]
        except ValueError:
            ap.error(f"--box and --points must be comma-separated numbers, got {a.box!r} and {a.points!r}")
        if any(len(q) != len(box) // 2 for q in pts):
            ap.error(f"--points: each vector needs {len(box) // 2} numbers (one per parameter of --box), got {a.points!r}")
        tag = f"{a.scenario}_s{a.seed}{me}" + ("_baseline" if a.baseline else "")
        out = Path(a.out) if a.out else HERE / "results" / f"refit_reference_{a.terrain}_{tag}.json"
        try:
            with terrain_variant(a.terrain):
                r = reference_posterior(a.scenario, a.seed, a.model_error_seed, box, a.reference, baseline=a.baseline,
                                        points=pts)
        except ValueError as e:
            ap.error(str(e))
        r["terrain"] = a.terrain
        out.write_text(json.dumps(r, indent=1))
        print(f"{r['switch']}: mean {r['mean']:.4g}, 90 % HDI [{r['hdi90'][0]:.4g}, {r['hdi90'][1]:.4g}] "
              f"(truth {r['truth']:g}); edge mass {r['edge_mass']}; {r['runs']} runs in {r['wall_s']:.0f} s")
        return 0
    out = Path(a.out) if a.out else HERE / "results" / f"refit_spread_{a.terrain}_{a.scenario}_s{a.seed}{me}.json"
    with terrain_variant(a.terrain):
        for s in seeds:
            rows = json.loads(out.read_text())["runs"] if out.exists() else []
            if any(r["inference_seed"] == s for r in rows):
                continue
            r = run_one(a.scenario, a.seed, s, a.model_error_seed)
            r["terrain"] = a.terrain
            print(f"{a.scenario}_s{a.seed} inference seed {s}: {r['term']} mean {r['mean']:.4g}, 90 % HDI "
                  f"[{r['hdi90'][0]:.4g}, {r['hdi90'][1]:.4g}] (truth {r['truth']:g}), 2 ln BF "
                  + ("-" if r["two_ln_bf"] is None else f"{r['two_ln_bf']:.1f}") + f" ({r['wall_s']:.0f} s)",
                  flush=True)
            rows = json.loads(out.read_text())["runs"] if out.exists() else []   # another process may have added
            out.parent.mkdir(parents=True, exist_ok=True)
            out.write_text(json.dumps({"runs": sorted(rows + [r], key=lambda x: x["inference_seed"])}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
