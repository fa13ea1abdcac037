"""Set the decision thresholds on null cases: ``python -m experiments.hidden_physics.calibrate_thresholds
--results DIR [--out FILE] [--apply DIR2]``.

``DIR`` holds harness cases of the *null* scenario on seeds that are not reported (e.g.
``harness --seed-list 100,101,102,103,104 --scenarios null --out DIR``). Their recordings have no
hidden term but the finer recording grid, the noise and the release error, so what the candidates gain
on them is what discretisation and noise alone buy. The rule (torchslide.diagnose.null.RULE):

* bf_min = max(6, 1.25 x the largest lower-bound 2 ln BF of any refitted candidate on the null seeds);
* located_min = max(8, 1.25 x the largest located |score| of the null baselines);
* fit_max per observable: a one-sided 95 % prediction bound of the null seeds' Z_fit (n >= 3 seeds,
  Bonferroni over the observables);
* waic_min = margin_min = 6, explain_min = 0.5, ess_min = 2, z_threshold = 3, fixed a priori.

Writes ``FILE`` (default: the null cases' design's file, experiments/hidden_physics/thresholds.json for
the narrow channel, thresholds_<terrain>.json for the others, "_fine" added for --fine-terrain cases; the
harness reads it for that design).
``--apply DIR2`` then re-decides every saved case in DIR2 with the new thresholds (the verdict is a
pure function of a case's saved statistics and the thresholds, so this equals re-running it); the
decision it was run with is kept as ``decision_as_run``.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

from torchslide.diagnose.null import RULE, thresholds_from_null

from .summary import release_sd, write_json

HERE = Path(__file__).parent


def null_statistics(results) -> dict:
    """{"bf": [...], "located": [...], "fit_rows": [{observable: Z_fit}], "cases": [...], "candidates": [...],
    "release_volume_sd": [...]} of the null cases in ``results``: per case the largest lower-bound 2 ln BF of a
    refitted candidate, the largest located |score| and the calibrated baseline's Z_fit per observable; the
    candidates and the release errors (summary.release_sd) they were diagnosed with."""
    bf, loc, fit_rows, rows, names, sds = [], [], [], [], set(), set()
    for p in sorted(Path(results).glob("null_s*.json")):
        case = json.loads(p.read_text())
        j = case["diagnosis"]
        sds.add(release_sd(case))
        names.update(c["name"] for c in j["candidates"])
        b = [c["two_ln_bf_lower"] for c in j["candidates"] if c.get("two_ln_bf_lower") is not None]
        l = [abs(x["standardised_residual"]) for x in j["located"]]
        bf.append(max(b, default=float("-inf")))
        loc.append(max(l, default=0.0))
        z = (j.get("decision") or {}).get("fit_z")
        if z:
            fit_rows.append(z)
        rows.append({"case": p.stem, "max_two_ln_bf_lower": bf[-1], "max_located": loc[-1]})
    return {"bf": bf, "located": loc, "fit_rows": fit_rows, "cases": rows, "candidates": sorted(names),
            "release_volume_sd": sorted(sds)}


def apply_thresholds(results, th: dict, force: bool = False) -> int:
    """Re-decide the saved cases in ``results`` with thresholds ``th`` and refresh their coverage check
    (harness.coverage); returns the number of cases whose verdict or named term changed. ``force``: also
    the cases already decided with ``th`` (after a change of the decision rule)."""
    from torchslide.diagnose.decide import Thresholds, decide
    from torchslide.diagnose.pipeline import DECISION_CONTEXT

    from .harness import coverage

    changed = 0
    for p in sorted(Path(results).glob("*_s*.json")):
        case = json.loads(p.read_text())
        if "diagnosis" not in case:
            continue
        j = case["diagnosis"]
        if "truth" in case:
            case["true_term_covered_hdr90"], case["true_term_covered_equal_tailed90"] = coverage(
                j, case["truth"], case.get("volume_factor", 1.0))
        if j["thresholds"] != th or force:
            cands = [c for c in j["candidates"] if c.get("log_bayes_factor") is not None]
            fit_z = (j.get("decision") or {}).get("fit_z") or {}
            d = decide(cands, j["located"], j["decision"].get("baseline_verification") or {},
                       j["fit_before"]["misfit"], Thresholds(**th), fit_z=fit_z)
            # what the pipeline added to its decision is kept
            for k in DECISION_CONTEXT:
                d[k] = j["decision"].get(k)
            changed += (d["verdict"], d["missing_physics"]) != (j["verdict"], j["missing_physics"])
            j.setdefault("decision_as_run", {"verdict": j["verdict"], "missing_physics": j["missing_physics"],
                                             "thresholds": j["thresholds"], "reason": j["decision"].get("reason")})
            j.update(verdict=d["verdict"], missing_physics=d["missing_physics"], decision=d, thresholds=dict(th))
        write_json(p, case)
    return changed


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description="decision thresholds from null harness cases")
    p.add_argument("--results", required=True, help="harness folder with null cases (null_s<seed>.json)")
    p.add_argument("--out", default=None, help="thresholds file (default: the null cases' terrain's)")
    p.add_argument("--apply", default=None, help="harness results folder to re-decide with the new thresholds")
    p.add_argument("--force", action="store_true",
                   help="with --apply: re-decide every case, also those already at these thresholds")
    a = p.parse_args(argv)
    st = null_statistics(a.results)
    if not st["cases"]:
        p.error(f"--results {a.results}: no null cases (null_s<seed>.json)")
    designs = {(c.get("terrain", "narrow"), bool(c.get("fine_terrain")))
               for c in (json.loads(f.read_text()) for f in Path(a.results).glob("null_s*.json"))}
    if len(designs) > 1:
        p.error(f"--results {a.results}: null cases of several designs (terrain, fine terrain) {sorted(designs)}")
    if len(st["release_volume_sd"]) > 1:
        p.error(f"--results {a.results}: null cases stated several release errors {st['release_volume_sd']}")
    from .harness import thresholds_file

    out = a.out or thresholds_file(*designs.pop())
    th = thresholds_from_null(st, st["fit_rows"] or None)
    write_json(out, {"rule": RULE, "candidates": st["candidates"], "release_volume_sd": st["release_volume_sd"][0],
                     "null_cases": st["cases"],
                     "fit_null_cases": len(st["fit_rows"]), "thresholds": th})
    print(json.dumps(th))
    if a.apply:
        n = apply_thresholds(a.apply, th, force=a.force)
        print(f"re-decided the cases in {a.apply} with these thresholds: {n} verdict(s) changed")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
