"""How large is each hidden term at strength 1, in the recordings' own error units?
``python -m experiments.hidden_physics.effect_size [--out FILE]``

Noise-free recordings (experiments/hidden_physics/scenarios.make_recording with noise_scale = 0, true
release volume = nominal, TRUE_BASE mu, xi) on the recording grid (20 m) for every scenario, the null
recording, and two null recordings with mu and xi nudged (+5 %, +20 %). Everything is whitened by the
likelihood's effective sigmas (DiagnosisEvaluator.sigma: measurement sigma x correlation factor), so
|.|^2 is a chi-square in the units the diagnosis works in. For every scenario:

* ``effect``: |(y_S - y_null) / sigma|, the hidden term's whole effect on the recordings;
* ``effect_unmimicked``: the same after projecting out what re-tuning mu, xi can mimic (linearised:
  finite differences of the null recording; the screening's projection, torchslide/diagnose/screen.py);
* the floor it has to beat: ``discretisation``: the null model on the inversion grid (40 m, same
  parameters) against the null recording (20 m), also projected, i.e. the model error the inversion
  always has ("inverse crime" avoided), and the noise: E|noise / sigma|^2 = k_eff, the effective
  number of independent data (the expected chi-square of a correct model).

A term whose unmimicked effect is not clearly larger than the discretisation floor cannot be told from
the model error of the coarser inversion grid, whatever the method. Diagnostic only: the scenario
strengths are NOT tuned with it.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from .scenarios import SCENARIOS, TRUE_BASE, make_evaluator, make_recording

HERE = Path(__file__).parent


def _flat(rec, ev):
    ev2 = make_evaluator(rec)
    assert ev2.data.shape == ev.data.shape
    return ev2.data


def main(argv=None) -> int:
    a = argparse.ArgumentParser()
    a.add_argument("--out", default=str(HERE / "results" / "effect_size.json"))
    a.add_argument("--seed", type=int, default=0)
    args = a.parse_args(argv)
    kw = dict(noise_scale=0.0, volume_factor=1.0)
    null = make_recording("null", args.seed, **kw)
    ev = make_evaluator(null)
    sig = ev.sigma
    y0 = ev.data
    steps = {"mu": 0.05 * TRUE_BASE["mu"], "xi": 0.2 * TRUE_BASE["xi"]}
    J = []
    for n, h in steps.items():
        r = make_recording("null", args.seed, base={n: TRUE_BASE[n] + h}, **kw)
        J.append((_flat(r, ev) - y0) / sig / h)
    A = np.stack(J, axis=1)
    P = lambda v: v - A @ np.linalg.lstsq(A, v, rcond=None)[0]
    coarse, failed = ev.run_values({k: np.array([v]) for k, v in TRUE_BASE.items()})
    disc = (coarse[0] - y0) / sig
    k_eff = float(sum(b.obs.n_eff if hasattr(b.obs, "n_eff") else 1.0 for b in ev.blocks))
    rows = {"k": int(y0.size), "k_eff": k_eff,
            "discretisation": float(np.linalg.norm(disc)), "discretisation_unmimicked": float(np.linalg.norm(P(disc))),
            "scenarios": {}}
    for sc in SCENARIOS:
        if sc == "null":
            continue
        r = make_recording(sc, args.seed, **kw)
        d = (_flat(r, ev) - y0) / sig
        per_block = {b.name: float(np.linalg.norm(P(d)[b.slice])) for b in ev.blocks}
        rows["scenarios"][sc] = {"effect": float(np.linalg.norm(d)), "effect_unmimicked": float(np.linalg.norm(P(d))),
                                 "unmimicked_by_block": per_block}
        print(sc, json.dumps(rows["scenarios"][sc]), flush=True)
    print(json.dumps({k: v for k, v in rows.items() if k != "scenarios"}))
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
