"""Would refitting on a finer grid over the same DEM correct a biased switch? ``python -m
experiments.hidden_physics.finer_grid_profile [--cases resolved:earth_pressure_s0,narrow:yield_stress_s1:mu_i,...]
[--out FILE] [--finer-inputs dem|terrain|terrain_volume] [--grids inversion,finer] [--cellsize M]
[--ladder refit|prior] [--search-iters N] [--sweeps N] [--sigmas harness|noise] [--device cuda] [--compile]``

On the resolved terrain the earth-pressure switch comes out near 0.5 (truth 1) and tau_y near 4-5
(truth 3), even in a noise-free scan (grid_convergence.py --switch-scan). If the 40 m solver were the
cause, the same refit on cells half as large over the inversion's own DEM (interpolated bilinearly,
as the model error's finer runs do: torchslide.diagnose.model_error.fine_run) would move the switch
towards the truth, and a "finer-grid check" of the named term would be worth adding to the diagnosis.

For each saved harness case (``run:case[:candidate]``, run one of RESULTS' keys, default candidate: the
true term; the terrain, cell size and recording grid are the case's own, so the 20 m runs are profiled
on 20 m and 10 m cells): the
profile along the candidate's switch (torchslide.diagnose.profile.switch_profile: a ladder of 5 switch
values over the centre of the saved refit's 90 % interval +- 1.5 times its width (at least +- 2 % of
the prior range; extended where the profile stays high), the best ln L + ln prior over (mu, xi) at each by a
local search on the solver) with the likelihood of the measurement errors alone (no grid model error:
the finer grid is what that error stands for), once on the inversion grid and once on cells half as
large. Start points: 32 draws from a normal with the saved refit's mean and sd = (90 % interval
width) / 3.3 (the report keeps no samples), clipped to the prior box. Rows go to ``--out`` (default
results/finer_grid_profile.json); the results page reads them. ``--grids`` profiles one grid only: a row
holding one profile is completed by a later run with the other (the costly finer profiles can run on
another machine than the cheap ones). ``--cellsize M``: re-make the case's recording (same scenario,
seed and release error; its noise drawn on the new grid) for an inversion on M m cells, i.e. the
recording on M / 2 m cells, and profile there, started from the saved refit: what an inversion on those
cells would see, without its cost (rows keyed by M). ``--ladder prior``: the switch values evenly over
the switch's whole prior range instead of around the refit's interval, so that the profile holds switch
0 and so the term's rise over its nested baseline; ``--search-iters N``: N iterations of the search per
value instead of 2; ``--sweeps N``: up to N continuation sweeps after the profile, each value searched
again from its neighbours' optima (rows keyed by all three). ``--device``, ``--compile``: where the solver runs,
and compiled (not row keys). ``--sigmas noise``: the likelihood states each gauge series' and the deposit map's
sigma as the sd of the noise drawn for it (scenarios.noise_sigmas) instead of the harness' larger ones (a row
key).

The information ceiling: ``--grids finer --finer-inputs terrain --ladder prior`` profiles a case on the
recording's own cells and terrain (the nominal release, the measurement errors alone), i.e. the inversion
without any grid error: the term's gain over its nested baseline is then what the recordings themselves hold
about it; on coarser cells the grid's error only adds to what must be told apart (results/oracle_profile.json;
results page, "Could any inversion find it?").
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

import numpy as np
import torch

from torchslide.diagnose.model_error import fine_run
from torchslide.diagnose.polish import local_search
from torchslide.diagnose.profile import switch_profile
from torchslide.diagnose.refit import candidate_evaluator
from torchslide.physics import CANDIDATES

from . import scenarios
from .scenarios import SCENARIOS, SIGMAS, make_evaluator, make_recording, noise_sigmas

HERE = Path(__file__).parent
RESULTS = {"narrow": HERE / "results" / "harness", "resolved": HERE / "results" / "resolved" / "results",
           "narrow_20m": HERE / "results" / "narrow_20m" / "results",
           "resolved_20m": HERE / "results" / "resolved_20m" / "results",
           "resolved_outflow": HERE / "results" / "resolved_outflow" / "results",
           "resolved_vol": HERE / "results" / "resolved_vol" / "results"}
DEFAULT_CASES = ("resolved:earth_pressure_s0,resolved:earth_pressure_s1,resolved:yield_stress_s0,"
                 "resolved:entrainment_s4,narrow:earth_pressure_s0,narrow:entrainment_s0,narrow:yield_stress_s1")


N_STARTS = 32      # profile start points drawn around the saved refit (profile_starts)
MIN_HALF = 0.02   # the ladder's least half-width (fraction of the prior range): it follows the refit's interval


def finer_grid_evaluator(ev, factor: int = 2):
    """A copy of the DiagnosisEvaluator ``ev`` (same prior, likelihood and observations) whose runs are
    on cells ``factor`` times smaller over the same inputs (model_error.fine_run)."""
    if int(factor) != factor or factor < 2:
        raise ValueError(f"finer-grid factor must be an integer >= 2, got {factor!r}")
    base = type(ev)

    class FinerGrid(base):
        def simulate(self, x):
            return fine_run(self, x, int(factor))

    kw = {f.name: getattr(ev, f.name) for f in dataclasses.fields(ev) if f.init and f.name not in ("records", "solver_seconds")}
    return FinerGrid(**kw)


def profile_starts(parameters: dict, names, bounds: np.ndarray, n: int = N_STARTS, seed: int = 0) -> np.ndarray:
    """(n, p) start points around a refit known by its reported ``parameters`` ({name: {mean, hdr90}},
    as in report.json; the report keeps no samples): normal draws with the posterior mean and
    sd = (90 % interval width) / 3.3, clipped to ``bounds`` (2, p); ``names`` (p,) in the evaluator's
    order, the switch last."""
    missing = [k for k in names if k not in parameters or "mean" not in parameters[k] or "hdr90" not in parameters[k]]
    if missing:
        raise ValueError(f"refit parameters lack mean / hdr90 for {missing}")
    m = np.array([parameters[k]["mean"] for k in names], float)
    sd = np.array([(parameters[k]["hdr90"][1] - parameters[k]["hdr90"][0]) / 3.3 for k in names], float)
    b = np.asarray(bounds, float)
    return np.clip(m + sd * np.random.default_rng(seed).standard_normal((n, len(names))), b[0], b[1])


LADDERS = ("refit", "prior")


def neighbour_sweeps(ev_c, S, pz, px, bounds, sweeps: int, n_iter: int = 2, pop: int = 6, tol: float = 0.5,
                     seed: int = 0) -> tuple[np.ndarray, np.ndarray, list[float]]:
    """Continuation sweeps over a profile: every switch value S[k] searched again (local search over the
    other parameters, the switch held; polish.local_search) from its neighbours' optima px[k - 1], px[k + 1]
    with the switch set to S[k], keeping the better; repeated up to ``sweeps`` times, while some value
    rises by more than ``tol``. A profile's searches start from one trend line, so a value far from the
    refit it was started from (switch 0 when the refit sat at 0.3) can stop far below its optimum; its
    neighbour's optimum is a start on the ridge. ``S`` (K,) sorted, ``pz`` (K,), ``px`` (K, p).
    Returns (pz, px) updated and the largest rise of each sweep."""
    b = np.asarray(bounds, float)
    pz, px = np.array(pz, float), np.array(px, float)
    pz = np.where(np.isfinite(pz), pz, -np.inf)     # a value whose runs all failed is lifted by any finite one
    hold = np.zeros(b.shape[1], bool)
    hold[-1] = True
    rises = []
    for it in range(sweeps):
        st = np.array([np.append(px[j, :-1], S[k]) for k in range(len(S)) for j in (k - 1, k + 1)
                       if 0 <= j < len(S)])
        st = np.clip(st, b[0], b[1])
        r = ev_c(torch.as_tensor(st))
        z0 = np.where(r.failed.detach().cpu().numpy(), -np.inf, r.z.detach().cpu().numpy().astype(float))
        ls = local_search(ev_c, st, z0, b, n_iter=n_iter, pop=pop, n_starts=None, seed=seed + 211 + it, hold=hold)
        X = np.vstack([st, ls["x"]]) if len(ls["x"]) else st
        Z = np.concatenate([z0, ls["z"]])
        rise = 0.0
        for k in range(len(S)):
            on = np.isclose(X[:, -1], S[k]) & np.isfinite(Z)
            if on.any():
                i = np.flatnonzero(on)[int(np.argmax(Z[on]))]
                if Z[i] > pz[k]:
                    # a value that had no finite run counts as risen (another sweep), not as an infinite rise
                    rise = max(rise, float(Z[i] - pz[k]) if np.isfinite(pz[k]) else tol + 1.0)
                    pz[k], px[k] = Z[i], X[i]
        rises.append(rise)
        if rise <= tol:
            break
    return pz, px, rises


def grid_profile(ev_c, parameters: dict, factor: int = 1, seed: int = 0, n_values: int = 5, n_iter: int = 2,
                 pop: int = 6, ladder: str = "refit", sweeps: int = 0) -> dict:
    """Profile of one candidate along its switch (module doc) on the evaluator's grid (``factor`` 1) or
    on cells ``factor`` times smaller. ``ev_c``: the candidate's evaluator (prior: baseline parameters
    + switch last); ``parameters``: its refit's {name: {mean, hdr90}}. ``ladder``: "refit" (the switch
    values follow the refit's 90 % interval) or "prior" (``n_values`` evenly over the switch's whole
    prior range, its ends and so switch 0 included: the profile then also gives the term's rise over
    its nested baseline, wherever the refit sat). ``sweeps`` > 0: that many continuation sweeps after the
    profile (neighbour_sweeps, 2 search iterations each; the first pass's profile is kept as z_first,
    each sweep's largest rise as sweep_rises). Returns {switch (K,), z (K,), best (switch at the
    maximum), z_max, x (p,) the parameters there, runs, wall_s}."""
    if ladder not in LADDERS:
        raise ValueError(f"ladder must be one of {LADDERS}, got {ladder!r}")
    names = list(ev_c.prior.names)
    b = ev_c.prior.bounds.numpy()
    e = ev_c if factor == 1 else finer_grid_evaluator(ev_c, factor)
    # switch_ladder spans the interval's centre +- half the prior range when given the whole prior
    interval = parameters[names[-1]]["hdr90"] if ladder == "refit" else (float(b[0, -1]), float(b[1, -1]))
    t0 = time.perf_counter()
    r = switch_profile(e, profile_starts(parameters, names, b, seed=seed), interval, b,
                       n_values=n_values, n_iter=n_iter, pop=pop, min_half=MIN_HALF, seed=seed)
    extra = {}
    if sweeps > 0:
        extra["z_first"] = np.asarray(r["z"], float).tolist()
        # 2 iterations per sweep search: a sweep starts on the ridge, next to the value's optimum
        pz, px, extra["sweep_rises"] = neighbour_sweeps(e, np.asarray(r["switch"], float), r["z"], r["x"], b, sweeps,
                                                        n_iter=2, pop=pop, seed=seed)
        r = dict(r, z=pz, x=px)
    z = np.where(np.isfinite(r["z"]), r["z"], -np.inf)
    if not np.isfinite(z).any():
        raise RuntimeError(f"profile of {names[-1]}: every run failed")
    k = int(np.argmax(z))
    return {"switch": np.asarray(r["switch"], float).tolist(), "z": np.asarray(r["z"], float).tolist(),
            "best": float(r["switch"][k]), "z_max": float(z[k]), "x": np.asarray(r["x"][k], float).tolist(),
            "runs": len(e.records),
            "wall_s": time.perf_counter() - t0, **extra}


def _parse(spec: str) -> tuple[str, str, str | None]:
    parts = spec.split(":")
    if len(parts) not in (2, 3) or parts[0] not in RESULTS:
        raise SystemExit(f"--cases: {spec!r} is not run:case[:candidate] with run in {sorted(RESULTS)}")
    return parts[0], parts[1], parts[2] if len(parts) == 3 else None


FINER_INPUTS = ("dem", "terrain", "terrain_volume")


def case_evaluator(D: dict, finer_inputs: str = "dem", device: str = "cpu", compile_solver: bool = False,
                   sigmas: str = "harness"):
    """(recording, evaluator) of the saved harness case ``D`` (its terrain, cell size and recording
    grid), the evaluator's finer-grid inputs as ``finer_inputs`` says (profile_case); its runs on
    ``device``, compiled when ``compile_solver`` (scenarios.make_evaluator); ``sigmas`` "noise": the
    recording's sigmas those of scenarios.noise_sigmas."""
    if finer_inputs not in FINER_INPUTS:
        raise ValueError(f"finer_inputs must be one of {FINER_INPUTS}, got {finer_inputs!r}")
    if sigmas not in SIGMAS:
        raise ValueError(f"sigmas must be one of {SIGMAS}, got {sigmas!r}")
    cellsize = float(D.get("cellsize", 40.0))
    with scenarios.terrain_variant(D.get("terrain", "narrow")):
        rec = make_recording(D["scenario"], int(D["seed"]), cellsize=cellsize, fine_factor=D.get("fine_factor", 2))
        if sigmas == "noise":
            rec = dataclasses.replace(rec, observations=noise_sigmas(rec.observations))
        ev = make_evaluator(rec, cellsize=cellsize, fine_terrain=finer_inputs != "dem", device=device,
                            compile_solver=compile_solver)
    if finer_inputs == "terrain_volume":
        vf = rec.volume_factor
        ft = ev.fine_terrain
        ev = ev._copy(release=ev.release * vf, fine_terrain=dataclasses.replace(ft, release=ft.release * vf),
                      fixed=dict(ev.fixed))
    return rec, ev


GRIDS = {"inversion": ("inversion_grid", 1), "finer": ("finer_grid", 2)}


def profile_case(run: str, case: str, candidate: str | None = None, results=None, seed: int = 0,
                 finer_inputs: str = "dem", grids=("inversion", "finer"), row: dict | None = None,
                 cellsize: float | None = None, ladder: str = "refit", n_iter: int = 2, sweeps: int = 0,
                 device: str = "cpu", compile_solver: bool = False, sigmas: str = "harness") -> dict:
    """The two profiles of one saved case (module doc); ``run``: a key of RESULTS (where the case is
    read unless ``results`` is given). ``finer_inputs``: what the finer grid runs on, "dem" (the
    inversion's DEM interpolated bilinearly, as the diagnosis' model error does), "terrain" (the
    recording grid's own surface: scenarios.make_evaluator(fine_terrain=True)) or "terrain_volume"
    (that, and on both grids the recording's own release volume instead of the nominal one: what
    remains is the noise and the grid). Row: {terrain, cellsize, case, candidate, param, truth,
    finer_inputs, refit_hdr90, profiles: {inversion_grid, finer_grid: grid_profile's dict}}. ``grids``:
    which of "inversion" and "finer" to profile; ``row``: a row of the same case to complete (its
    profiles are kept; those of ``grids`` it lacks are added). ``cellsize``: the inversion grid's cell
    size in m if not the case's own (the recording re-made on cells half as large; module doc); the row
    then has ``saved_cellsize``, the case's own. ``ladder``, ``n_iter``, ``sweeps``: grid_profile's (the
    row keeps them where they are not the defaults "refit", 2 and 0). ``device``, ``compile_solver``: where
    and how the runs go (case_evaluator; the row keeps a device other than the CPU); ``sigmas``: the likelihood's
    (case_evaluator; the row keeps "noise")."""
    if cellsize is not None and not (np.isfinite(cellsize) and cellsize > 0):
        raise ValueError(f"cellsize must be a positive number of m, got {cellsize!r}")
    bad = [g for g in grids if g not in GRIDS]
    if bad or not grids:
        raise ValueError(f"grids must be a non-empty subset of {sorted(GRIDS)}, got {list(grids)!r}")
    D = json.loads((Path(results or RESULTS[run]) / f"{case}.json").read_text())
    saved = float(D.get("cellsize", 40.0))
    if cellsize is not None:
        D = dict(D, cellsize=float(cellsize))
    terrain, cellsize = D.get("terrain", run), float(D.get("cellsize", 40.0))
    rec, ev = case_evaluator(D, finer_inputs, device=device, compile_solver=compile_solver, sigmas=sigmas)
    sc = D["scenario"]
    cand = candidate or SCENARIOS[sc][0]
    C = CANDIDATES[cand]
    ev_c = candidate_evaluator(ev, cand)
    P = next(c for c in D["diagnosis"]["candidates"] if c["name"] == cand)["parameters"]
    new = {"terrain": terrain, "cellsize": cellsize, "case": case, "candidate": cand, "param": C.param,
           "truth": rec.truth.get(C.param) if rec.truth["term"] == cand else None, "finer_inputs": finer_inputs,
           "refit_hdr90": P[C.param]["hdr90"], "profiles": {}}
    if cellsize != saved:
        new["saved_cellsize"] = saved
    if ladder != "refit":
        new["ladder"] = ladder
    if n_iter != 2:
        new["n_iter"] = int(n_iter)
    if sweeps:
        new["sweeps"] = int(sweeps)
    if device != "cpu":
        new["device"] = str(device)
    if sigmas != "harness":
        new["sigmas"] = sigmas
    row = {**new, "profiles": dict((row or {}).get("profiles", {}))}
    for label, f in (GRIDS[g] for g in GRIDS if g in grids):
        if label in row["profiles"]:
            continue
        row["profiles"][label] = grid_profile(ev_c, P, factor=f, seed=seed, n_iter=n_iter, ladder=ladder,
                                              sweeps=sweeps)
        print(terrain, cellsize, case, cand, label, "best", round(row["profiles"][label]["best"], 4), flush=True)
    return row


def main(argv=None) -> int:
    a = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    a.add_argument("--cases", default=DEFAULT_CASES, help="comma-separated run:case[:candidate]")
    a.add_argument("--out", default=str(HERE / "results" / "finer_grid_profile.json"),
                   help="rows file; an existing one is kept and its cases are skipped (resume)")
    a.add_argument("--finer-inputs", default="dem", choices=FINER_INPUTS,
                   help="what the finer grid runs on (profile_case): the inversion DEM interpolated (default), the "
                        "recording grid's own terrain, or that and the recording's release volume")
    a.add_argument("--grids", default="inversion,finer",
                   help="comma-separated grids to profile: inversion (the case's cells), finer (cells halved); a row "
                        "lacking one is completed by a later run")
    a.add_argument("--cellsize", type=float, default=None,
                   help="profile on cells of this size (m) against the case's recording re-made on cells half as "
                        "large, instead of on the case's own grid")
    a.add_argument("--ladder", default="refit", choices=LADDERS,
                   help="switch values around the saved refit's 90 %% interval (default), or evenly over the "
                        "switch's whole prior range, 0 included (the term's rise over its nested baseline)")
    a.add_argument("--search-iters", type=int, default=2,
                   help="local-search iterations (6 moves each) over the baseline parameters per switch value")
    a.add_argument("--sweeps", type=int, default=0,
                   help="continuation sweeps after the profile: each switch value searched again from its "
                        "neighbours' optima (neighbour_sweeps), while a value still rises by more than 0.5")
    a.add_argument("--sigmas", default="harness", choices=SIGMAS,
                   help="the likelihood's sigmas: the harness' (default) or the sd of the noise it draws")
    a.add_argument("--device", default="cpu", help="where the solver runs (cpu, cuda, ...)")
    a.add_argument("--compile", action="store_true", help="compile the solver (SolverConfig.compile)")
    args = a.parse_args(argv)
    if args.sweeps < 0:
        raise SystemExit(f"--sweeps: {args.sweeps!r} is not a number of sweeps >= 0")
    if args.search_iters < 1:
        raise SystemExit(f"--search-iters: {args.search_iters!r} is not a positive number of iterations")
    if args.cellsize is not None and not (np.isfinite(args.cellsize) and args.cellsize > 0):
        raise SystemExit(f"--cellsize: {args.cellsize!r} is not a positive number of m")
    grids = tuple(g for g in args.grids.split(",") if g)
    if not grids or any(g not in GRIDS for g in grids):
        raise SystemExit(f"--grids: {args.grids!r} is not a comma-separated subset of {', '.join(GRIDS)}")
    specs = [_parse(c) for c in args.cases.split(",") if c]
    for run, case, _ in specs:
        if not (RESULTS[run] / f"{case}.json").exists():
            raise SystemExit(f"--cases: no saved case {case!r} in {RESULTS[run]}")
    out = Path(args.out)
    rows = json.loads(out.read_text()) if out.exists() else []
    out.parent.mkdir(parents=True, exist_ok=True)
    for run, case, cand in specs:
        cs = json.loads((RESULTS[run] / f"{case}.json").read_text())
        key = (cs.get("terrain", run), args.cellsize or float(cs.get("cellsize", 40.0)), case,
               cand or SCENARIOS[cs["scenario"]][0], args.finer_inputs, args.ladder, args.search_iters,
               args.sweeps, args.sigmas)
        k = next((i for i, r in enumerate(rows) if (r["terrain"], float(r.get("cellsize", 40.0)), r["case"],
                                                     r["candidate"], r.get("finer_inputs", "dem"),
                                                     r.get("ladder", "refit"), r.get("n_iter", 2),
                                                     r.get("sweeps", 0), r.get("sigmas", "harness")) == key), None)
        have = set(rows[k].get("profiles", {"inversion_grid": 0, "finer_grid": 0})) if k is not None else set()
        if all(GRIDS[g][0] in have for g in grids):
            print("already in", out, *key)
            continue
        r = profile_case(run, case, cand, finer_inputs=args.finer_inputs, grids=grids,
                         row=rows[k] if k is not None else None, cellsize=args.cellsize, ladder=args.ladder,
                         n_iter=args.search_iters, sweeps=args.sweeps, device=args.device,
                         compile_solver=args.compile, sigmas=args.sigmas)
        if k is None:
            rows.append(r)
        else:
            rows[k] = r
        out.write_text(json.dumps(rows, indent=1))      # after every case: an interrupted run loses one
    print("wrote", out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
