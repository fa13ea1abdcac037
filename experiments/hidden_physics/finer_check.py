"""The finer-grid check on saved harness cases: ``python -m experiments.hidden_physics.finer_check
[--results DIR] [--profiles FILE,...] [--out FILE]``

torchslide.diagnose.finer (Budgets.finer_check, off by default) orders the two candidates that pass
the evidence check, when one of them could be named (decide.finer_pair), by their profiles along the
switch on cells half as large, with the measurement errors alone in the likelihood. A saved case holds
everything the decision needs except those profiles; finer_grid_profile.py computes them with the same
function (finer.finer_profile, start seed 0 = Budgets.finer_seed) from the case's saved refit, so each
case is re-decided here exactly as a run with ``finer_check = True`` would decide it after the same
earlier stages. The saved cases are not changed.

For every case in ``--results``: the pair (or none), whether both profiles are in ``--profiles``
(rows of finer_grid_profile.py; a missing one is listed and the case stays as it was), the check's
leader and 2 ln profile ratio, the verdict and name before and after, and two strict-success checks
after it: ``strict_after`` (the page's rule: named, 2 ln BF >= 6 over the runner-up, 90 % interval
covering the truth, misfit reduced; a name the Bayes factors rank second fails its margin) and
``strict_after_finer`` (the same with the separation of the pair taken from the finer grid, as the
decision does). Rows go to ``--out`` (default results/finer_check_resolved_20m.json); the results page
reads it.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

from torchslide.diagnose.decide import Thresholds, decide, finer_pair

from .calibrate_thresholds import case_fit_z
from .make_page import found_label, strict_success, true_label

HERE = Path(__file__).parent
DEFAULT_RESULTS = HERE / "results" / "resolved_20m" / "results"
DEFAULT_PROFILES = HERE / "results" / "finer_grid_profile_20m.json"


def profile_maxima(rows: list, terrain: str, cellsize: float, case: str) -> dict:
    """{candidate: max finer-grid profile z} of ``case`` in finer_grid_profile.py's ``rows``."""
    return {r["candidate"]: max(z for z in r["profiles"]["finer_grid"]["z"] if z is not None)
            for r in rows if r["case"] == case and r["terrain"] == terrain and float(r.get("cellsize", 40.0)) == cellsize}


def redecide_case(case: dict, name: str, rows: list) -> dict:
    """The row of one saved harness case (module doc)."""
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
    d = decide(cands, j["located"], base, misfit, th, fit_z=fit_z or None,
               finer={n: zmax[n] for n in pair or [] if n in zmax} if pair else None)
    fc = d.get("finer_check") or {}
    after = dict(case, diagnosis=dict(j, verdict=d["verdict"], missing_physics=d["missing_physics"], decision=d))
    row.update(applied=bool(fc.get("applied")), leader=fc.get("leader"), two_ln_ratio=fc.get("two_ln_ratio"),
               z_max=fc.get("z_max"), verdict_after=d["verdict"], named_after=d["missing_physics"],
               found_after=found_label(after), strict_after=strict_success(after), reason_after=d["reason"])
    if fc.get("applied") and d["missing_physics"] == fc["leader"] and d.get("runner_up") in fc["pair"]:
        d2 = dict(d, two_ln_bf_over_runner_up=fc["two_ln_ratio"])
        row["strict_after_finer"] = strict_success(dict(after, diagnosis=dict(after["diagnosis"], decision=d2)))
    else:
        row["strict_after_finer"] = row["strict_after"]
    return row


def main(argv=None) -> int:
    a = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    a.add_argument("--results", default=str(DEFAULT_RESULTS), help="a harness results folder")
    a.add_argument("--profiles", default=str(DEFAULT_PROFILES), help="comma-separated finer_grid_profile.py row files")
    a.add_argument("--out", default=str(HERE / "results" / "finer_check_resolved_20m.json"))
    args = a.parse_args(argv)
    res = Path(args.results)
    files = [Path(f) for f in args.profiles.split(",") if f]
    bad = [str(f) for f in files if not f.exists()]
    if not res.is_dir() or bad:
        raise SystemExit(f"finer_check: no results folder {res}" if not res.is_dir() else f"finer_check: no profile file(s) {bad}")
    rows = [r for f in files for r in json.loads(f.read_text())]
    out = []
    for p in sorted(res.glob("*.json")):
        case = json.loads(p.read_text())
        if "diagnosis" not in case:
            continue
        r = redecide_case(case, p.stem, rows)
        out.append(r)
        if r["pair"]:
            print(f"{p.stem}: pair {r['pair']}" + (f", missing profiles {r['missing_profiles']}" if r["missing_profiles"]
                                                   else f", {r['leader']} ahead by {r['two_ln_ratio']:.1f}")
                  + f"; {r['verdict_before']} ({r['named_before']}) -> {r['verdict_after']} ({r['named_after']})")
    Path(args.out).write_text(json.dumps({"results": str(res.relative_to(HERE)) if res.is_relative_to(HERE) else str(res),
                                          "profiles": [f.name for f in files], "rows": out}, indent=1))
    n_missing = sum(bool(r["missing_profiles"]) for r in out)
    print(f"wrote {args.out}: {len(out)} cases, {sum(r['pair'] is not None for r in out)} with a pair, "
          f"{n_missing} lacking a profile")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
