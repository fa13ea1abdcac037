"""How large is each hidden term at strength 1, in the recordings' own error units?
``python -m experiments.hidden_physics.effect_size [--terrain narrow|resolved] [--cellsize C] [--out FILE]``

Noise-free recordings (experiments/hidden_physics/scenarios.make_recording with noise_scale = 0, true
release volume = nominal, TRUE_BASE mu, xi) on the recording grid (C / 2: 20 m for the harness' inversion
cells C = 40 m) for every scenario, the null recording, and two null recordings with mu and xi nudged
(+5 %, +20 %). Everything is whitened by the likelihood's effective sigmas (DiagnosisEvaluator.sigma:
measurement sigma x correlation factor), so |.|^2 is a chi-square in the units the diagnosis works in.
For every scenario:

* ``effect``: |(y_S - y_null) / sigma|, the hidden term's whole effect on the recordings;
* ``effect_unmimicked``: the same after projecting out what re-tuning mu, xi can mimic (linearised:
  finite differences of the null recording; the screening's projection, torchslide/diagnose/screen.py);
* the floor it has to beat: ``discretisation``: the null model on the inversion grid (C m, same
  parameters) against the null recording (C / 2 m), also projected, i.e. the model error the inversion
  always has ("inverse crime" avoided), and the noise: E|noise / sigma|^2 = k_eff, the effective
  number of independent data (the expected chi-square of a correct model).

A term whose unmimicked effect is not clearly larger than the discretisation floor cannot be told from
the model error of the coarser inversion grid, whatever the method. Diagnostic only: the scenario
strengths are NOT tuned with it.

Another terrain or cell size (``--terrain resolved``, ``--cellsize 20``: what a harness on 20 m cells
with 10 m recordings would face) writes ``results/effect_size_<terrain>_<C>m.json``; the default run
(narrow, 40 m) writes ``results/effect_size.json``.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from .scenarios import SCENARIOS, TERRAINS, TRUE_BASE, make_evaluator, make_recording, terrain, terrain_variant

HERE = Path(__file__).parent


def _flat(rec, ev, cellsize):
    ev2 = make_evaluator(rec, cellsize=cellsize)
    assert ev2.data.shape == ev.data.shape
    return ev2.data


def main(argv=None) -> int:
    a = argparse.ArgumentParser()
    a.add_argument("--out", default=None, help="default: results/effect_size.json for narrow at 40 m, "
                   "results/effect_size_<terrain>_<cellsize>m.json otherwise")
    a.add_argument("--seed", type=int, default=0)
    a.add_argument("--terrain", choices=sorted(TERRAINS), default="narrow")
    a.add_argument("--cellsize", type=float, default=40.0, help="inversion cell size, m (recordings on half of it)")
    args = a.parse_args(argv)
    if not args.cellsize > 0:
        a.error(f"--cellsize must be > 0, got {args.cellsize!r}")
    out = args.out
    if out is None:
        default = args.terrain == "narrow" and args.cellsize == 40.0
        out = HERE / "results" / ("effect_size.json" if default else f"effect_size_{args.terrain}_{args.cellsize:g}m.json")
    with terrain_variant(args.terrain):
        coarse, fine = terrain(args.cellsize)[0].shape, terrain(args.cellsize / 2)[0].shape
        if (fine[0] // 2, fine[1] // 2) != coarse:
            a.error(f"--cellsize {args.cellsize:g}: the recording grid ({fine[0]}x{fine[1]} cells of "
                    f"{args.cellsize / 2:g} m) does not block-average onto the inversion grid ({coarse[0]}x{coarse[1]}) "
                    f"on the {args.terrain} terrain; try 100, 60, 40, 20 or 10")
        rows = _measure(args.seed, args.cellsize)
    rows.update(terrain=args.terrain, cellsize=args.cellsize, recording_cellsize=args.cellsize / 2)
    print(json.dumps({k: v for k, v in rows.items() if k != "scenarios"}))
    Path(out).parent.mkdir(parents=True, exist_ok=True)
    Path(out).write_text(json.dumps(rows, indent=1))
    return 0


def _measure(seed: int, cellsize: float) -> dict:
    """Effect sizes on the current terrain (module docstring); the dict written as JSON."""
    kw = dict(noise_scale=0.0, volume_factor=1.0, cellsize=cellsize)
    null = make_recording("null", seed, **kw)
    ev = make_evaluator(null, cellsize=cellsize)
    sig = ev.sigma
    y0 = ev.data
    steps = {"mu": 0.05 * TRUE_BASE["mu"], "xi": 0.2 * TRUE_BASE["xi"]}
    J = []
    for n, h in steps.items():
        r = make_recording("null", seed, base={n: TRUE_BASE[n] + h}, **kw)
        J.append((_flat(r, ev, cellsize) - y0) / sig / h)
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
        r = make_recording(sc, seed, **kw)
        d = (_flat(r, ev, cellsize) - y0) / sig
        per_block = {b.name: float(np.linalg.norm(P(d)[b.slice])) for b in ev.blocks}
        rows["scenarios"][sc] = {"effect": float(np.linalg.norm(d)), "effect_unmimicked": float(np.linalg.norm(P(d))),
                                 "unmimicked_by_block": per_block}
        print(sc, json.dumps(rows["scenarios"][sc]), flush=True)
    return rows


if __name__ == "__main__":
    raise SystemExit(main())
