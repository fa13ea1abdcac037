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
* fit_max (session 17, only with ``--fit-probe``; unlike the rules above, chosen after session 16 had
  seen the Z_fit of the null and patch seeds 0-4, so seeds 5-9 are its held-out check), per observable
  b with Z_fit on n >= 3 null seeds:
  mean_b + t_{n-1}(1 - 0.05 / B) * sd_b * sqrt(1 + 1 / n), B the number of such observables (a
  one-sided 95 % prediction bound for a new null case, Bonferroni over the observables). The Z_fit
  (the calibrated baseline's) come from the null calibration cases' decisions, else from a
  block_fit_probe file (its null rows with seeds >= 100: more seeds than the harness' five, at ~35 s a
  case).

The rule's functions (thresholds_from_null, fit_max_from_null) live in torchslide.diagnose.null, where
the CLI's ``torchslide diagnose --null-runs N`` applies them to null simulations of a user's own design.

Writes experiments/hidden_physics/thresholds.json (read by the harness).

``--fit-probe FILE`` (a block_fit_probe.py result for the same terrain and design): sets fit_max from its
null calibration rows, and ``--apply`` takes each case's calibrated-baseline Z_fit from the probe's row of
the same scenario and seed when the case's decision has none (cases run before session 17; the probe
re-runs the diagnosis up to the calibrated baseline's localisation exactly; the values and their source
are kept in the decision as ``fit_z`` and ``fit_z_source``).

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

from torchslide.diagnose.null import fit_max_from_null, thresholds_from_null

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


def null_fit_rows(results, probe: dict | None) -> list:
    """[{observable: Z_fit}] (the calibrated baseline's) of the null calibration seeds: from the cases in
    ``results`` whose decision has them, else (and for every further seed >= 100) from the probe's null rows."""
    rows, seeds = [], set()
    for p in sorted(Path(results).glob("null_s*.json")):
        case = json.loads(p.read_text())
        z = (case["diagnosis"].get("decision") or {}).get("fit_z")
        if z:
            rows.append(z)
            seeds.add(case["seed"])
    for r in (probe or {}).get("cases", []):
        if r["scenario"] == "null" and r["seed"] >= 100 and r["seed"] not in seeds:
            rows.append({k: v["Z_fit"] for k, v in r["blocks"].items() if "Z_fit" in v})
    return rows


def probe_fit_z(probe: dict | None) -> dict:
    """{(terrain, scenario, seed, strength): {observable: Z_fit}} of a block_fit_probe result (the harness'
    design: 40 m cells, recordings on cells half that size, the harness' sigmas and gauges)."""
    return {(r.get("terrain", "narrow"), r["scenario"], r["seed"], float(r.get("strength", 1.0))):
            {k: v["Z_fit"] for k, v in r["blocks"].items() if "Z_fit" in v} for r in (probe or {}).get("cases", [])}


def _probe_design(case: dict) -> bool:
    """Whether a saved case has the design block_fit_probe re-runs (so that its row stands for the case;
    the strength is part of the row's key)."""
    return (case.get("cellsize", 40.0) == 40.0
            and case.get("fine_factor", 2) == 2 and (case.get("sigma_scale") or 1.0) == 1.0
            and case.get("sigmas", "harness") == "harness"
            and not case.get("extra_gauges"))


def case_fit_z(case: dict, probe_z: dict | None = None) -> tuple[dict, str | None]:
    """(the calibrated baseline's {observable: Z_fit} of a saved case, its source): the decision's own
    (``fit_z``: written by the pipeline since session 17, "calibrated baseline", or by an earlier --apply,
    "block_fit_probe"), else the probe's row for the case, else nothing ({}, None). Not fit_before's Z_fit:
    that is the final baseline's, which the refits may have refined (the levels are set on the first)."""
    j = case["diagnosis"]
    z = (j.get("decision") or {}).get("fit_z")
    if z:
        return z, j["decision"].get("fit_z_source")
    z = (probe_z or {}).get((case.get("terrain", "narrow"), case.get("scenario"), case.get("seed"),
                             float(case.get("strength", 1.0))))
    return (z, "block_fit_probe") if z and _probe_design(case) else ({}, None)


def apply_thresholds(results, th: dict, force: bool = False, probe: dict | None = None) -> int:
    """Re-decide the saved cases in ``results`` with thresholds ``th`` (see the module doc) and
    recompute their coverage check (harness.coverage); returns the number of cases whose verdict or
    named term changed. ``force``: also the cases already decided with ``th`` (after a change of the
    decision rule in torchslide/diagnose/decide.py). ``probe``: a block_fit_probe result giving the baseline
    Z_fit of cases whose report predates it (see the module doc)."""
    from torchslide.diagnose.decide import Thresholds, decide

    from .harness import coverage

    changed = 0
    probe_z = probe_fit_z(probe)
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
        fit_z, src = case_fit_z(case, probe_z)
        d = decide(cands, j["located"], j["decision"].get("baseline_verification") or {}, j["fit_before"]["misfit"],
                   Thresholds(**th), fit_z=fit_z)
        if src is not None:
            d.update(fit_z=fit_z, fit_z_source=src)
        # what the pipeline added to its decision (baseline verification and mode check, WAIC) is kept
        for k in ("baseline_verification", "baseline_mode_check", "elpd_waic_baseline"):
            d[k] = j["decision"].get(k)
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
    p.add_argument("--fit-probe", default=None,
                   help="block_fit_probe result: sets fit_max from its null seeds >= 100 and gives --apply the Z_fit")
    p.add_argument("--force", action="store_true",
                   help="with --apply: re-decide every case, also those already at these thresholds (rule change)")
    a = p.parse_args(argv)
    st = null_statistics(a.results)
    if not st["cases"]:
        raise SystemExit(f"no null results in {a.results}")
    probe = json.loads(Path(a.fit_probe).read_text()) if a.fit_probe else None
    fit_rows = null_fit_rows(a.results, probe) if probe else None
    th = thresholds_from_null(st, fit_rows)
    Path(a.out).write_text(json.dumps({"rule": __doc__.split("Rule")[1].split("Writes")[0].strip(),
                                       "null_cases": st["cases"], "fit_null_cases": len(fit_rows or []),
                                       "thresholds": th}, indent=1))
    print(json.dumps(th))
    if a.apply:
        n = apply_thresholds(a.apply, th, force=a.force, probe=probe)
        print(f"re-decided the cases in {a.apply} with these thresholds: {n} verdict(s) changed")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
