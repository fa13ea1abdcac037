"""Set the decision thresholds on null data: ``python -m experiments.hidden_physics.calibrate_thresholds [--results DIR]``.

Input: harness results of the *null* scenario on calibration seeds that are NOT the reported ones
(default: _work/null_calib_v4, made with ``harness --seed-list 100,101,102,103,104 --scenarios null
--out experiments/hidden_physics/_work/null_calib_v4``; v4: re-run after all five library candidates
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


def main(argv=None) -> int:
    p = argparse.ArgumentParser()
    p.add_argument("--results", default=str(HERE / "_work" / "null_calib_v4"))
    p.add_argument("--out", default=str(HERE / "thresholds.json"))
    a = p.parse_args(argv)
    st = null_statistics(a.results)
    if not st["cases"]:
        raise SystemExit(f"no null results in {a.results}")
    th = thresholds_from_null(st)
    Path(a.out).write_text(json.dumps({"rule": __doc__.split("Rule")[1].split("Writes")[0].strip(),
                                       "null_cases": st["cases"], "thresholds": th}, indent=1))
    print(json.dumps(th))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
