"""Is the refitted switch biased by the recording grid or by the method?
``python -m experiments.hidden_physics.switch_bias [--scenarios earth_pressure,curvature] [--seeds 0,1] [--out FILE]``

For each scenario / seed the true candidate alone is refitted (the harness budgets) on two recordings
that differ only in the grid they were made on: ``fine_factor`` = 2 (the harness: 20 m recording,
40 m inversion) and ``fine_factor`` = 1 (recording on the inversion grid itself; same noise, same
release error). If the switch's 90 % HDI covers the truth with fine_factor = 1 but not with 2, the
bias comes from the discretisation difference (model error), not from the calibration / HDI method.
``--method new`` (default) is exactly the pipeline's refit of one candidate
(torchslide.diagnose.pipeline.refit_candidate: bound probe, refinement of untrustworthy evidence);
``old`` the refit of two versions ago (MCMC posterior of the emulator, continued to n_total_max when
untrusted). Rows are appended to --out (default results/switch_bias_v2.json; results/switch_bias.json
holds the rows of the earlier versions) with their method and version; a (scenario, seed, grid,
method) row already there is not recomputed.
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from torchslide.diagnose import Budgets
from torchslide.diagnose.pipeline import _params, grid_model_error, refit_candidate
from torchslide.diagnose.predictive import posterior_predictive, posterior_samples
from torchslide.diagnose.refit import calibrate_evaluator, refit
from torchslide.diagnose.verify import verified_evidence

from .harness import HARNESS_BUDGETS
from .scenarios import SCENARIOS, SWITCH, make_evaluator, make_recording

HERE = Path(__file__).parent


def one(scenario: str, seed: int, fine_factor: int, workdir: Path, method: str = "new", model_error: int = 0) -> dict:
    t0 = time.perf_counter()
    term = SCENARIOS[scenario][0]
    rec = make_recording(scenario, seed, fine_factor=fine_factor)
    ev = make_evaluator(rec)
    tag = f"{scenario}_s{seed}_f{fine_factor}_{method}" + (f"_me{model_error}" if model_error else "")
    ck = workdir / f"{tag}.pt"
    ck.unlink(missing_ok=True)
    (workdir / tag).mkdir(exist_ok=True)
    (workdir / tag / "pilot.pt").unlink(missing_ok=True)
    if method == "new":
        # exactly the pipeline's refit of one candidate (torchslide.diagnose.pipeline.refit_candidate),
        # with the grid's approximation error in the likelihood when model_error > 0 (grid_model_error)
        bud = Budgets(**{**HARNESS_BUDGETS, "seed": seed, "model_error_runs": model_error})
        if model_error:
            ev, _ = grid_model_error(ev, bud, workdir / tag, log=lambda s: None)
        _, cal, _, _, hist = refit_candidate(ev, term, bud, ck, log=lambda s: None)
        version = ("refined (local emulator, zoomed grid posterior)" if any("trusted" in h for h in hist)
                   else "MCMC posterior (trustworthy at the first verification)")
    else:
        B = HARNESS_BUDGETS
        ev_c, cal = refit(ev, term, B["n_initial"], B["n_total"], batch_size=B["batch_size"], seed=seed, checkpoint=ck)
        p = posterior_predictive(ev_c, posterior_samples(cal, B["n_posterior_samples_after"], seed=seed + 1))
        ver = verified_evidence(ev_c, cal, p.x, p.draws, seed=seed)
        version = "MCMC posterior (previous method)"
        if ver["ess"] < 0.3 * ver["n_draws"] or ver["se"] > 1.0:
            cal = calibrate_evaluator(ev_c, B["n_initial"], B["n_total_max"], batch_size=B["batch_size"], seed=seed,
                                      checkpoint=ck)
    par = _params(cal)[SWITCH[term]]
    truth = rec.truth[SWITCH[term]]
    ok = ~np.asarray(cal.failed)
    best = int(np.argmax(np.where(ok, cal.z, -np.inf)))
    return {"scenario": scenario, "seed": seed, "fine_factor": fine_factor, "version": version,
            "volume_factor": rec.volume_factor, "truth": truth, "mean": par["mean"],
            "map": par["map"], "hdi90": par["hdi90"], "covered": bool(par["hdi90"][0] <= truth <= par["hdi90"][1]),
            "best_run_x": np.asarray(cal.x[best]).tolist(), "n_runs": int(cal.n_runs),
            "wall_s": time.perf_counter() - t0}


def main(argv=None) -> int:
    a = argparse.ArgumentParser()
    a.add_argument("--scenarios", default="earth_pressure,curvature")
    a.add_argument("--seeds", default="0,1")
    a.add_argument("--out", default=str(HERE / "results" / "switch_bias_v2.json"))
    a.add_argument("--grids", default="1,2", help="recording grid factors (fine_factor) to run")
    a.add_argument("--model-error", type=int, default=0,
                   help="new method only: approximation error of the grid from this many run pairs (0: off)")
    a.add_argument("--method", choices=("new", "old"), default="new",
                   help="new: refits leaning against an unsampled bound are probed and refined (pipeline "
                        "default); old: the MCMC posterior of the refit, continued to n_total_max when untrusted")
    args = a.parse_args(argv)
    out = Path(args.out)
    work = out.parent / "switch_bias_ck"
    work.mkdir(parents=True, exist_ok=True)
    rows = json.loads(out.read_text()) if out.exists() else []
    rounds = Budgets().refit_refine_rounds
    have = {(r["scenario"], r["seed"], r["fine_factor"]) for r in rows
            if r.get("method") == args.method and r.get("model_error", 0) == args.model_error
            and r.get("refit_refine_rounds", rounds) == rounds}
    for sc in args.scenarios.split(","):
        for s in [int(v) for v in args.seeds.split(",")]:
            for ff in [int(g) for g in args.grids.split(",")]:
                if (sc, s, ff) in have:
                    continue
                r = dict(one(sc, s, ff, work, args.method, args.model_error), method=args.method,
                         model_error=args.model_error, refit_refine_rounds=rounds)
                print(json.dumps(r), flush=True)
                rows.append(r)
                out.write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
