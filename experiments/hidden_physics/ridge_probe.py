"""Did a refit stop short on a ridge? A longer local search on the solver from its best run.

For a saved harness case: the recording and the candidate's evaluator are rebuilt (its fine factor;
the grid's approximation error off, as in the control ``harness --fine-factor 1 --model-error 0``),
z = ln L + ln prior is evaluated at the truth, at the refit's posterior mean and at its best run, and
polish.local_search runs ``--iters`` iterations of 6 moves from the best run (initial step 0.05 of the
prior box per axis).

    python -m experiments.hidden_physics.ridge_probe --case experiments/hidden_physics/results/control_ff1/results/mu_i_s1.json --candidate mu_i
"""
from __future__ import annotations

import argparse
import json

import numpy as np
import torch

from torchslide.diagnose.polish import local_search
from torchslide.diagnose.refit import candidate_evaluator

from .scenarios import SWITCH, TRUE_BASE, make_evaluator, make_recording, terrain_variant


def probe(case: dict, candidate: str, iters: int = 16, seed: int = 1) -> dict:
    """{z_truth, z_mean, z_best_run, search_best_z, search_best_x, running_best} (see the module doc);
    search_best_*: the best of the start and the search's runs."""
    with terrain_variant(case.get("terrain", "narrow")):
        rec = make_recording(case["scenario"], case["seed"], cellsize=case["cellsize"],
                             fine_factor=case.get("fine_factor", 2))
        evc = candidate_evaluator(make_evaluator(rec, cellsize=case["cellsize"]), candidate)
        c = next(x for x in case["diagnosis"]["candidates"] if x["name"] == candidate)
        names = list(evc.prior.names)
        truth = [TRUE_BASE["mu"], TRUE_BASE["xi"], case["truth"].get(SWITCH.get(candidate, ""), 0.0)]
        X = np.array([truth, [c["parameters"][n]["mean"] for n in names], c["best_x"]], float)
        z = evc(torch.as_tensor(X)).z.numpy().astype(float)
        b = evc.prior.bounds.numpy()
        ls = local_search(evc, X[2:], z[2:], b, n_iter=iters, pop=6, n_starts=1, step0=[0.05] * len(names), seed=seed)
    best_z, best_x = (ls["best_z"], ls["best_x"]) if ls["best_z"] > z[2] else (float(z[2]), X[2])
    return {"names": names, "truth": truth, "z_truth": float(z[0]), "z_mean": float(z[1]), "z_best_run": float(z[2]),
            "search_best_z": float(best_z), "search_best_x": np.asarray(best_x).tolist(),
            "running_best": [float(np.max(ls["z"][:6 * (k + 1)])) for k in range(iters)]}


def main(argv=None) -> int:
    p = argparse.ArgumentParser()
    p.add_argument("--case", required=True, help="a saved harness case (.json)")
    p.add_argument("--candidate", required=True)
    p.add_argument("--iters", type=int, default=16)
    a = p.parse_args(argv)
    r = probe(json.loads(open(a.case).read()), a.candidate, a.iters)
    print(json.dumps(r, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
