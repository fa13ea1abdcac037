"""Would a finer-grid check tell yield stress from mu(I)? ``python -m experiments.hidden_physics.finer_check
[--results DIR] [--profiles FILE,...] [--out FILE] [--truth] [--converge [INPUTS]]
[--cases NAME,...]``

On the resolved terrain inverted on 20 m cells, yield stress and mu(I) both gain strong evidence from a
yield-stress recording, and mu(I) came out ahead in 2 ln BF in seeds 0 and 1 (named). Profiled along
their switches on cells half as large (finer_grid_profile.py), yield stress led in both, which
suggested a check for the diagnosis: when two candidates pass the evidence check and one of them every
check (finer_pair: else no order between them can change the verdict), take their order and their
separation (2 ln profile ratio against margin_min) from the maxima of their profiles on cells half as
large, with the measurement errors alone in the likelihood, instead of from their Bayes factors.

This script re-decides saved harness cases as that check would (torchslide.diagnose.decide on the
saved statistics, the pair's log Bayes factors replaced so that the leader keeps the larger of the two
and the other lies the profile ratio below it; every other check stays the candidates' own), from
finer_grid_profile.py's rows. The saved cases are not changed. Per case: the pair (or none), whether
both profiles are in ``--profiles`` (a missing one is listed and the case stays as it was), the leader
and the 2 ln profile ratio, the verdict and name before and after, and two strict-success checks after:
``strict_after`` (the page's rule, with the Bayes factors' margin: a name they rank second fails it)
and ``strict_after_finer`` (the margin from the finer grid, as the check decides). Rows go to ``--out``
(default results/finer_check_resolved_20m.json); the results page reads it. ``--truth``: also z at
the true parameters on the finer grid, against the profiles' maxima (is the profile's local search
converged there?). ``--converge [dem|terrain|terrain_volume]``: also both maxima after a longer search over every
parameter from the profiles' optima and the truth (converged_maxima), and the verdict the check would
give from them; with the finer grid over the inversion DEM, as the check would run it (dem, the
default), over the recording's own terrain, or that and its release volume (the noise alone left).
``--cases``: re-decide only these saved cases, keeping the other rows of an existing ``--out`` (an
existing row's converged searches are kept in any run, unless the same inputs are searched again). The
check was not put in the diagnosis: see the page's section for why.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

from torchslide.diagnose.decide import Thresholds, checks, decide

from .calibrate_thresholds import case_fit_z
from .make_page import found_label, strict_success, true_label

HERE = Path(__file__).parent
DEFAULT_RESULTS = HERE / "results" / "resolved_20m" / "results"
DEFAULT_PROFILES = HERE / "results" / "finer_grid_profile_20m.json"


def profile_maxima(rows: list, terrain: str, cellsize: float, case: str) -> dict:
    """{candidate: max finer-grid profile z} of ``case`` in finer_grid_profile.py's ``rows`` (finer grid over the
    inversion DEM, as the check would run it; rows without a finer-grid profile, or whose recording was re-made
    for other cells (finer_grid_profile --cellsize), are left out)."""
    return {r["candidate"]: max(z for z in r["profiles"]["finer_grid"]["z"] if z is not None)
            for r in rows if r["case"] == case and r["terrain"] == terrain and float(r.get("cellsize", 40.0)) == cellsize
            and r.get("finer_inputs", "dem") == "dem" and "finer_grid" in r["profiles"] and "saved_cellsize" not in r}


def finer_pair(candidates: list, baseline: dict, misfit_before: float, th: Thresholds) -> list | None:
    """The pair the check compares: the two candidates with the largest Bayes factors among those that
    pass ``evidence``, when at least one of the two passes every check; None otherwise."""
    ok = sorted([c for c in candidates if c.get("log_bayes_factor") is not None
                 and checks(c, baseline, misfit_before, th)["evidence"]], key=lambda c: -c["log_bayes_factor"])
    if len(ok) < 2 or not any(all(checks(c, baseline, misfit_before, th).values()) for c in ok[:2]):
        return None
    return [ok[0]["name"], ok[1]["name"]]


def finer_order(candidates: list, pair, z_max: dict) -> tuple[list, dict]:
    """(copies of ``candidates`` with the pair's log Bayes factors set to the finer grid's order and
    separation, the check's {pair, z_max, leader, two_ln_ratio}): the leader keeps the larger of the
    pair's two log BF, the other gets it minus the ln profile ratio."""
    a, b = pair
    d = float(z_max[a]) - float(z_max[b])
    lead, other = (a, b) if d >= 0 else (b, a)
    lbf = {c["name"]: c["log_bayes_factor"] for c in candidates}
    top = max(lbf[a], lbf[b])
    new = {lead: top, other: top - abs(d)}
    out = [dict(c, log_bayes_factor=new[c["name"]]) if c["name"] in new else c for c in candidates]
    return out, {"pair": [a, b], "z_max": {a: float(z_max[a]), b: float(z_max[b])}, "leader": lead,
                 "two_ln_ratio": 2 * abs(d)}


def _candidate_evaluator(case: dict, name: str, finer_inputs: str = "dem"):
    """The evaluator of candidate ``name`` for the saved case (torchslide.diagnose.refit.candidate_evaluator:
    the scenario's prior on mu, xi, the switch last), on the inversion grid; its finer grid's inputs as
    ``finer_inputs`` says (finer_grid_profile.case_evaluator: "dem", the inversion DEM, as the check
    would run it; "terrain", "terrain_volume")."""
    from torchslide.diagnose.refit import candidate_evaluator

    from .finer_grid_profile import case_evaluator

    return candidate_evaluator(case_evaluator(case, finer_inputs)[1], name)


def _truth_x(case: dict) -> list:
    """The true term's (mu, xi, switch) of the case, in its evaluator's order."""
    from torchslide.physics import CANDIDATES

    t = case["truth"]
    return [t["mu"], t["xi"], t[CANDIDATES[t["term"]].param]]


def truth_on_finer_grid(case: dict) -> float:
    """z = ln L + ln prior of the true term at the true parameters (the case's truth) on cells half as
    large over the inversion DEM (the finer grid of the check's profiles), measurement errors alone:
    what the true term's finer-grid profile should reach at least, if its local search converged."""
    import torch

    from .finer_grid_profile import finer_grid_evaluator

    ev_c = _candidate_evaluator(case, case["truth"]["term"])
    r = finer_grid_evaluator(ev_c).evaluate(torch.tensor([_truth_x(case)], dtype=torch.float64))[0]
    return float("nan") if bool(r.failed[0]) else float(r.z[0])


N_ITER_CONVERGED, POP_CONVERGED = 8, 12     # the longer search of converged_maxima (the check's profile: 2 x 6)


def converged_maxima(case: dict, pair, n_iter: int = N_ITER_CONVERGED, pop: int = POP_CONVERGED,
                     seed: int = 0, profile: dict | None = None, finer_inputs: str = "dem") -> dict:
    """Is the check's lead the search's? For each candidate of ``pair``: its profile on the finer grid
    as the check runs it (finer_grid_profile.grid_profile, factor 2), then a local search over all
    its parameters, switch included (torchslide.diagnose.polish.local_search, ``n_iter`` iterations
    of ``pop`` moves per start), from the profile's optimum and, for the case's true term, also from
    the true parameters. ``profile``: keyword arguments for grid_profile (default: the check's budget).
    ``finer_inputs``: what the finer grid runs on (_candidate_evaluator; "terrain_volume" leaves the
    noise as the only difference between the recording and the true term there).
    Returns {name: {profile_z, truth_z (true term only, else None), z, x (3,),
    runs}}: z, the best ln L + ln prior found, is the maximum the check would compare if its search
    converged."""
    import numpy as np
    import torch

    from torchslide.diagnose.polish import local_search

    from .finer_grid_profile import finer_grid_evaluator, grid_profile

    out = {}
    for name in pair:
        ev_c = _candidate_evaluator(case, name, finer_inputs)
        P = next(c for c in case["diagnosis"]["candidates"] if c["name"] == name)["parameters"]
        prof = grid_profile(ev_c, P, factor=2, seed=seed, **(profile or {}))
        e = finer_grid_evaluator(ev_c)
        X, Z = [prof["x"]], [prof["z_max"]]
        truth_z = None
        if case["truth"].get("term") == name:
            r = e.evaluate(torch.tensor([_truth_x(case)], dtype=torch.float64))[0]
            truth_z = float("nan") if bool(r.failed[0]) else float(r.z[0])
            X.append(_truth_x(case))
            Z.append(truth_z if np.isfinite(truth_z) else -np.inf)
        ls = local_search(e, np.array(X, float), np.array(Z, float), e.prior.bounds.numpy(), n_iter=n_iter, pop=pop,
                          n_starts=None, seed=seed)
        k = int(np.argmax(Z))
        z, x = (float(ls["best_z"]), list(map(float, ls["best_x"]))) if ls["best_z"] > Z[k] else (Z[k], list(X[k]))
        out[name] = {"profile_z": prof["z_max"], "truth_z": truth_z, "z": z, "x": x, "runs": len(e.records)}
    return out


def redecide_case(case: dict, name: str, rows: list, truth: bool = False, converge=()) -> dict:
    """The row of one saved harness case (module doc); ``truth``: also truth_on_finer_grid for a case
    whose true term is in the pair (one finer-grid run); ``converge``: finer-grid inputs ("dem",
    "terrain", "terrain_volume") for each of which such a case also gets converged_maxima and the
    verdict the check would give from them (row["converged"][inputs]: {z_max, profile_z, truth_z, x,
    runs, leader, two_ln_ratio, verdict, named})."""
    j = case["diagnosis"]
    th = Thresholds(**j["thresholds"])
    cands = [c for c in j["candidates"] if c.get("log_bayes_factor") is not None]
    base = j["decision"].get("baseline_verification") or {}
    misfit = j["fit_before"]["misfit"]
    pair = finer_pair(cands, base, misfit, th)
    row = {"case": name, "scenario": case["scenario"], "seed": case["seed"], "truth": true_label(case),
           "pair": pair, "verdict_before": j["verdict"], "named_before": j["missing_physics"],
           "strict_before": strict_success(case), "covered": case.get("true_term_covered_hdr90")}
    zmax = profile_maxima(rows, case.get("terrain", "narrow"), float(case.get("cellsize", 40.0)), name)
    row["missing_profiles"] = [n for n in pair or [] if n not in zmax]
    fit_z, _ = case_fit_z(case)
    # the saved statistics without the check give the saved verdict (else the rows would compare two rules)
    d0 = decide(cands, j["located"], base, misfit, th, fit_z=fit_z or None)
    row["reproduced"] = (d0["verdict"], d0["missing_physics"]) == (j["verdict"], j["missing_physics"])
    fc = None
    if pair and not row["missing_profiles"]:
        cands_f, fc = finer_order(cands, pair, zmax)
        d = decide(cands_f, j["located"], base, misfit, th, fit_z=fit_z or None)
        # the page's margin for a strict success: the named candidate over the best other by Bayes factors
        lbf = {c["name"]: c["log_bayes_factor"] for c in cands}
        if d["missing_physics"] is not None:
            d["two_ln_bf_over_runner_up_finer"] = d["two_ln_bf_over_runner_up"]
            d["two_ln_bf_over_runner_up"] = 2 * (lbf[d["missing_physics"]] -
                                                 max([v for k, v in lbf.items() if k != d["missing_physics"]] + [0.0]))
    else:
        d = dict(j["decision"], verdict=j["verdict"], missing_physics=j["missing_physics"])
    after = dict(case, diagnosis=dict(j, verdict=d["verdict"], missing_physics=d["missing_physics"], decision=d))
    row.update(applied=fc is not None, leader=(fc or {}).get("leader"), two_ln_ratio=(fc or {}).get("two_ln_ratio"),
               z_max=(fc or {}).get("z_max"), verdict_after=d["verdict"], named_after=d["missing_physics"],
               found_after=found_label(after), strict_after=strict_success(after), reason_after=d["reason"])
    if fc is not None and d["missing_physics"] is not None:
        d2 = dict(d, two_ln_bf_over_runner_up=d["two_ln_bf_over_runner_up_finer"])
        row["strict_after_finer"] = strict_success(dict(after, diagnosis=dict(after["diagnosis"], decision=d2)))
    else:
        row["strict_after_finer"] = row["strict_after"]
    if truth and fc is not None and case["truth"].get("term") in fc["pair"]:
        t = case["truth"]["term"]
        other = next(n for n in fc["pair"] if n != t)
        row["z_truth_finer"] = z = truth_on_finer_grid(case)
        row["truth_minus_profile_max"] = {t: z - fc["z_max"][t], other: z - fc["z_max"][other]}
    for inputs in converge if fc is not None and case["truth"].get("term") in fc["pair"] else ():
        cm = converged_maxima(case, fc["pair"], finer_inputs=inputs)
        zc = {n: v["z"] for n, v in cm.items()}
        cands_c, fcc = finer_order(cands, fc["pair"], zc)
        dc = decide(cands_c, j["located"], base, misfit, th, fit_z=fit_z or None)
        row.setdefault("converged", {})[inputs] = {
            "z_max": zc, **{k: {n: v[k] for n, v in cm.items()} for k in ("profile_z", "truth_z", "x", "runs")},
            "leader": fcc["leader"], "two_ln_ratio": fcc["two_ln_ratio"], "verdict": dc["verdict"],
            "named": dc["missing_physics"]}
    return row


def main(argv=None) -> int:
    a = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    a.add_argument("--results", default=str(DEFAULT_RESULTS), help="a harness results folder")
    a.add_argument("--profiles", default=str(DEFAULT_PROFILES), help="comma-separated finer_grid_profile.py row files")
    a.add_argument("--out", default=str(HERE / "results" / "finer_check_resolved_20m.json"))
    a.add_argument("--truth", action="store_true",
                   help="also z at the true parameters on the finer grid (truth_on_finer_grid: one run per case whose "
                        "true term is in the pair), against both profiles' maxima")
    from .finer_grid_profile import FINER_INPUTS

    a.add_argument("--converge", nargs="?", const="dem", choices=FINER_INPUTS, default=None,
                   help="also each pair's maxima after a longer local search over every parameter (converged_maxima: the "
                        "profiles again, then 8 x 12 moves from their optima and from the truth) and the verdict from them; "
                        "its value: the finer grid's inputs (default dem, as the check; terrain; terrain_volume)")
    a.add_argument("--cases", default="",
                   help="comma-separated case names (file stems) to re-decide; the other rows of an existing --out are kept")
    args = a.parse_args(argv)
    res = Path(args.results).resolve()
    files = [Path(f) for f in args.profiles.split(",") if f]
    bad = [str(f) for f in files if not f.exists()]
    if not res.is_dir() or bad:
        raise SystemExit(f"finer_check: no results folder {res}" if not res.is_dir() else f"finer_check: no profile file(s) {bad}")
    rows = [r for f in files for r in json.loads(f.read_text())]
    only = [c for c in args.cases.split(",") if c]
    unknown = [c for c in only if not (res / f"{c}.json").exists()]
    if unknown:
        raise SystemExit(f"finer_check --cases: no saved case(s) {unknown} in {res}")
    kept = {}       # an existing --out's rows: other cases' rows (with --cases) and earlier converged searches
    if Path(args.out).exists():
        kept = {r["case"]: r for r in json.loads(Path(args.out).read_text())["rows"]}
    out = []
    for p in sorted(res.glob("*.json")):
        case = json.loads(p.read_text())
        if "diagnosis" not in case:
            continue
        if only and p.stem not in only:
            if p.stem in kept:
                out.append(kept[p.stem])
            continue
        r = redecide_case(case, p.stem, rows, truth=args.truth, converge=(args.converge,) if args.converge else ())
        for inputs, c in kept.get(p.stem, {}).get("converged", {}).items():   # earlier inputs' searches are kept
            r.setdefault("converged", {}).setdefault(inputs, c)
        out.append(r)
        if r["pair"]:
            print(f"{p.stem}: pair {r['pair']}" + (f", missing profiles {r['missing_profiles']}" if r["missing_profiles"]
                                                   else f", {r['leader']} ahead by {r['two_ln_ratio']:.1f}")
                  + f"; {r['verdict_before']} ({r['named_before']}) -> {r['verdict_after']} ({r['named_after']})"
                  + (f"; truth on the finer grid minus the profiles' maxima {r['truth_minus_profile_max']}"
                     if "truth_minus_profile_max" in r else "")
                  + "".join(f"; converged over {k}: {c['leader']} ahead by {c['two_ln_ratio']:.1f} -> {c['verdict']} "
                            f"({c['named']})" for k, c in r.get("converged", {}).items()), flush=True)
    Path(args.out).write_text(json.dumps({"results": str(res.relative_to(HERE)) if res.is_relative_to(HERE) else str(res),
                                          "profiles": [f.name for f in files], "rows": out}, indent=1))
    bad = [r["case"] for r in out if not r["reproduced"]]
    if bad:
        print(f"warning: the saved statistics do not reproduce the saved verdict of {bad}")
    n_missing = sum(bool(r["missing_profiles"]) for r in out)
    print(f"wrote {args.out}: {len(out)} cases, {sum(r['pair'] is not None for r in out)} with a pair, "
          f"{n_missing} lacking a profile")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
