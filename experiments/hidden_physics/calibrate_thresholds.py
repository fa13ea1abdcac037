"""Set the decision thresholds on null data: ``python -m experiments.hidden_physics.calibrate_thresholds [--results DIR]``.

Input: harness results of the *null* scenario on calibration seeds that are NOT the reported ones
(default: results/null_calib, made with ``harness --seed-list 100,101,102,103,104 --scenarios null
--out experiments/hidden_physics/results/null_calib``; v8: re-run after the refits' mode check also
starts from the screening's linearised optimum and compares the search with the refit's posterior
draws, not only its runs; v7: re-run after the grid's approximation error
became the default (Budgets.model_error_runs = 12) and every refit is followed by a local search on
the solver (pipeline._mode_search; a refit that missed its mode is refined with its runs); v6: re-run after refits with untrustworthy
evidence are refined with a local emulator (up to 4 rounds, until trustworthy and stable) instead of
continued; v4: re-run after all five library candidates
are refitted (HARNESS_BUDGETS top_k), gauge-window mismatches are re-scored with their own statistic
and refits leaning against an unsampled switch bound are probed there and refined; v3: after the
baseline refinement and the stricter acceptance of the beta = 0 slice; null_calib and null_calib_v2
are earlier versions).
The recordings there have no hidden term but do have the finer recording grid, noise and the release
error, so whatever the candidates gain on them is what model discretisation and noise alone buy.

Rule (fixed before looking at any hidden-term result):

* bf_min = max(6, 1.25 * the largest lower-bound 2 ln BF of any refitted candidate on the null seeds)
* located_min = max(8, 1.25 * the largest located |score| of the null baselines)
* waic_min = 6, margin_min = 6, explain_min = 0.5, ess_min = 2, z_threshold = 3 (fixed a priori)

Writes experiments/hidden_physics/thresholds.json (read by the harness).

``--apply DIR``: afterwards, re-decide every saved harness case in DIR with the new thresholds
(torchslide.diagnose.decide on the case's saved statistics; the verdict is a pure function of them
and the thresholds, so this equals re-running with the thresholds). The case keeps the decision it
was run with under ``decision_as_run``. This lets the evaluation seeds run at the same time as the
null calibration seeds (their statistics do not depend on the thresholds); nothing from the
evaluation seeds enters the thresholds.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

HERE = Path(__file__).parent


def null_statistics(results) -> dict:
    bf, loc, rows = [], [], []
    for p in sorted(Path(results).glob("null_s*.json")):
        j = json.loads(p.read_text())["diagnosis"]
        b = [c["two_ln_bf_lower"] for c in j["candidates"] if c.get("two_ln_bf_lower") is not None]
        l = [abs(x["standardised_residual"]) for x in j["located"]]
        bf.append(max(b, default=float("-inf")))
        loc.append(max(l, default=0.0))
        rows.append({"case": p.stem, "max_two_ln_bf_lower": bf[-1], "max_located": loc[-1]})
    return {"bf": bf, "located": loc, "cases": rows}


def thresholds_from_null(stats: dict) -> dict:
    return {"bf_min": max(6.0, 1.25 * max(stats["bf"], default=0.0)),
            "located_min": max(8.0, 1.25 * max(stats["located"], default=0.0)),
            "waic_min": 6.0, "margin_min": 6.0, "explain_min": 0.5, "ess_min": 2.0, "z_threshold": 3.0}


def apply_thresholds(results, th: dict, force: bool = False) -> int:
    """Re-decide the saved cases in ``results`` with thresholds ``th`` (see the module doc) and
    recompute their coverage check (harness.coverage); returns the number of cases whose verdict or
    named term changed. ``force``: also the cases already decided with ``th`` (after a change of the
    decision rule in torchslide/diagnose/decide.py)."""
    from torchslide.diagnose.decide import Thresholds, decide

    from .harness import coverage

    changed = 0
    for p in sorted(Path(results).glob("*.json")):
        case = json.loads(p.read_text())
        if "diagnosis" not in case:      # e.g. a thresholds.json kept next to the cases
            continue
        j = case["diagnosis"]
        # the coverage check as harness.coverage does it now (with the tolerance for a grid's last
        # cell edge); the value it was run with is kept
        cov = coverage(j, case["truth"]) if "truth" in case else None
        if cov is not None and cov != (case.get("true_term_covered_hdr90"), case.get("true_term_covered_equal_tailed90")):
            case.setdefault("coverage_as_run", [case.get("true_term_covered_hdr90"),
                                                case.get("true_term_covered_equal_tailed90")])
            case["true_term_covered_hdr90"], case["true_term_covered_equal_tailed90"] = cov
            p.write_text(json.dumps(case, indent=1))
        if j["thresholds"] == th and not force:
            continue
        cands = [c for c in j["candidates"] if c.get("log_bayes_factor") is not None]
        d = decide(cands, j["located"], j["decision"].get("baseline_verification") or {}, j["fit_before"]["misfit"],
                   Thresholds(**th))
        d["baseline_verification"] = j["decision"].get("baseline_verification")
        d["elpd_waic_baseline"] = j["decision"].get("elpd_waic_baseline")
        changed += (d["verdict"], d["missing_physics"]) != (j["verdict"], j["missing_physics"])
        j.setdefault("decision_as_run", {"verdict": j["verdict"], "missing_physics": j["missing_physics"],
                                         "thresholds": j["thresholds"], "reason": j["decision"].get("reason")})
        j.update(verdict=d["verdict"], missing_physics=d["missing_physics"], decision=d, thresholds=dict(th))
        p.write_text(json.dumps(case, indent=1))
    return changed


def main(argv=None) -> int:
    p = argparse.ArgumentParser()
    p.add_argument("--results", default=str(HERE / "results" / "null_calib"))
    p.add_argument("--out", default=str(HERE / "thresholds.json"))
    p.add_argument("--apply", default=None, help="harness results folder to re-decide with the new thresholds")
    p.add_argument("--force", action="store_true",
                   help="with --apply: re-decide every case, also those already at these thresholds (rule change)")
    a = p.parse_args(argv)
    st = null_statistics(a.results)
    if not st["cases"]:
        raise SystemExit(f"no null results in {a.results}")
    th = thresholds_from_null(st)
    Path(a.out).write_text(json.dumps({"rule": __doc__.split("Rule")[1].split("Writes")[0].strip(),
                                       "null_cases": st["cases"], "thresholds": th}, indent=1))
    print(json.dumps(th))
    if a.apply:
        n = apply_thresholds(a.apply, th, force=a.force)
        print(f"re-decided the cases in {a.apply} with these thresholds: {n} verdict(s) changed")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
