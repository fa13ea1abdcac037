"""Does the solver converge on the harness terrain, and where does the inversion grid's error come from?
``python -m experiments.hidden_physics.grid_convergence [--sizes 40,20,10,5] [--scenarios ...] [--terrain T] [--out FILE]``

Noise-free runs (true mu, xi; each scenario's hidden term at strength 1; nominal release volume) of
experiments/hidden_physics/scenarios.py on cells of every size in ``--sizes``. For every scenario and
cell size: the gauges' peak flow height and speed, the run-out (largest x with a deposit > 0.1 m), and
the rms difference from the finest size of every gauge series and of the deposit map (block-averaged
onto 40 m cells). Then the split of the 40 m grid's error against the 20 m recording grid (null
scenario) into terrain and numerics: a 20 m run on the 40 m DEM interpolated bilinearly (what the
pipeline's model error uses, torchslide.diagnose.model_error.refine_dem) against the 20 m run on the
terrain itself.

``--switch-scan``: for each library scenario, the noise-free recording on cells half the inversion
size against inversion runs at the true mu, xi and on a 3 x 3 box around them (mu +-0.02, xi 350-700)
for a ladder of the true term's switch; the whitened misfit (the likelihood's sigmas, no model error)
of the best (mu, xi) per switch value. When the best switch is far from the truth even without noise,
no inference method on that grid can recover it: the grid decides.
Results go to ``--out`` (default results/grid_convergence.json); the results page reads them.
"""
from __future__ import annotations

import argparse
import itertools
import json
import time
from pathlib import Path

import numpy as np
import torch

from torchslide.diagnose.model_error import refine_dem, repeat_cells
from torchslide.observe_series import interp_series
from torchslide.physics import Params
from torchslide.solver import SolverConfig, simulate

from . import scenarios
from .scenarios import (DT_OBS, SCENARIOS, SOLVER, SWITCH, T_END, TRUE_BASE, V_NOMINAL, block_average, gauges,
                        make_evaluator, make_recording, mu_scale_patch, release, terrain)

HERE = Path(__file__).parent
SCAN = {"entrainment": [0.0, 0.00075, 0.0015, 0.003], "curvature": [0.0, 0.25, 0.5, 0.75, 1.0],
        "earth_pressure": [0.0, 0.25, 0.5, 0.75, 1.0], "yield_stress": [0.0, 1.0, 2.0, 3.0, 4.0, 5.0],
        "mu_i": [0.0, 0.1, 0.2, 0.3, 0.4]}


def _run(dem, rel, erod, vals: dict, mu_scale=None) -> dict:
    """One noise-free run: {"h_final": (ny, nx), "gauges": {name:q: (T,) on the recording times}, "wall_s"}."""
    t = np.arange(DT_OBS, T_END + 1e-9, DT_OBS)
    t0 = time.perf_counter()
    r = simulate(dem, rel, Params.make(**vals), t_end=T_END, gauges=gauges(), config=SolverConfig(**SOLVER),
                 erodible_depth=erod, mu_scale=mu_scale)
    g = {f"{n}:{q}": interp_series(G.t, G.h if q == "h" else G.speed, torch.as_tensor(t))[0].numpy()
         for n, G in r.gauges.items() for q in ("h", "speed")}
    return {"h_final": r.h_final[0].numpy(), "gauges": g, "wall_s": time.perf_counter() - t0, "dem": dem}


def _on_40(h: np.ndarray, cellsize: float) -> np.ndarray:
    f = int(round(40.0 / cellsize))
    return h if f == 1 else block_average(h, f)


def _rms(a, b) -> float:
    n = min(a.shape[-1], b.shape[-1])
    return float(np.sqrt(np.mean((a[..., :n] - b[..., :n]) ** 2)))


def _differences(a: dict, b: dict, ca: float, cb: float) -> dict:
    da, db = _on_40(a["h_final"], ca), _on_40(b["h_final"], cb)
    ny, nx = min(da.shape[0], db.shape[0]), min(da.shape[1], db.shape[1])
    out = {"deposit": _rms(da[:ny, :nx], db[:ny, :nx])}
    out.update({k: _rms(a["gauges"][k], b["gauges"][k]) for k in a["gauges"]})
    return out


def convergence(scenarios, sizes) -> dict:
    rows = {}
    for sc in scenarios:
        term, hidden = SCENARIOS[sc]
        vals = dict(TRUE_BASE, **hidden)
        runs = {}
        for cs in sizes:
            dem, erod = terrain(cs)
            ms = mu_scale_patch(dem) if term == "outside" else None
            runs[cs] = _run(dem, release(dem, V_NOMINAL), erod, vals, ms)
        finest = sizes[-1]
        rows[sc] = {str(cs): {"peak": {k: float(v.max()) for k, v in r["gauges"].items()},
                              "runout_x": float(r["dem"].x_centres()[(r["h_final"] > 0.1).any(axis=0)].max()),
                              "wall_s": r["wall_s"],
                              "rms_vs_finest": _differences(r, runs[finest], cs, finest) if cs != finest else None}
                    for cs, r in runs.items()}
        print(sc, json.dumps({cs: (v["peak"], v["runout_x"]) for cs, v in rows[sc].items()}), flush=True)
    return rows


def terrain_split() -> dict:
    """The 40 m grid's error against the 20 m recording grid (null, true mu, xi), split in two."""
    vals = dict(TRUE_BASE)
    d40, e40 = terrain(40.0)
    d20, e20 = terrain(20.0)
    rel40 = release(d40, V_NOMINAL)
    coarse = _run(d40, rel40, e40, vals)
    bilinear = _run(refine_dem(d40, 2), repeat_cells(rel40, 2), repeat_cells(e40, 2), vals)
    fine = _run(d20, release(d20, V_NOMINAL), e20, vals)
    return {"40m_vs_20m_terrain": _differences(coarse, fine, 40.0, 20.0),
            "20m_on_bilinear_40m_dem_vs_20m_terrain": _differences(bilinear, fine, 20.0, 20.0),
            "peak": {"40m": {k: float(v.max()) for k, v in coarse["gauges"].items()},
                     "20m_bilinear": {k: float(v.max()) for k, v in bilinear["gauges"].items()},
                     "20m_terrain": {k: float(v.max()) for k, v in fine["gauges"].items()}}}


def switch_scan(cellsize: float, scenarios) -> dict:
    """Noise-free best misfit per switch value on ``cellsize`` m cells (see the module doc)."""
    out = {}
    mus = [TRUE_BASE["mu"] - 0.02, TRUE_BASE["mu"], TRUE_BASE["mu"] + 0.02]
    xis = [350.0, TRUE_BASE["xi"], 700.0]
    for sc in scenarios:
        term, hidden = SCENARIOS[sc]
        if term not in SWITCH:
            continue
        rec = make_recording(sc, 0, cellsize=cellsize, noise_scale=0.0, volume_factor=1.0)
        ev = make_evaluator(rec, cellsize=cellsize)
        sw = SWITCH[term]
        rows = list(itertools.product(SCAN[term], mus, xis))
        vals = {"mu": np.array([r[1] for r in rows]), "xi": np.array([r[2] for r in rows]),
                sw: np.array([float(r[0]) for r in rows])}
        vals.update({k: np.full(len(rows), v) for k, v in hidden.items() if k != sw})
        preds, failed = ev.run_values(vals)
        mis = np.array([ev.misfit(p) if not f else np.inf for p, f in zip(preds, failed)])
        per = []
        for s in SCAN[term]:
            idx = [i for i, r in enumerate(rows) if r[0] == s]
            j = idx[int(np.argmin(mis[idx]))]
            at = next(i for i in idx if rows[i][1] == TRUE_BASE["mu"] and rows[i][2] == TRUE_BASE["xi"])
            per.append({"switch": s, "best_misfit": float(mis[j]), "best_mu": rows[j][1], "best_xi": rows[j][2],
                        "misfit_at_true_mu_xi": float(mis[at])})
        best = min(per, key=lambda r: r["best_misfit"])
        out[sc] = {"switch": sw, "truth": hidden[sw], "rows": per, "best_switch": best["switch"], "k_eff": float(
            sum(b.obs.n_eff if hasattr(b.obs, "n_eff") else 1.0 for b in ev.blocks))}
        print(cellsize, sc, "best switch", best["switch"], "truth", hidden[sw], flush=True)
    return out


def main(argv=None) -> int:
    a = argparse.ArgumentParser()
    a.add_argument("--sizes", default="40,20,10,5", help="cell sizes, m, coarse to fine (each divides 40)")
    a.add_argument("--scenarios", default=",".join(SCENARIOS))
    a.add_argument("--switch-scan", default="", help="comma-separated inversion cell sizes for the switch scan")
    a.add_argument("--terrain", default="narrow", choices=sorted(scenarios.TERRAINS), help="scenarios.TERRAINS variant")
    a.add_argument("--out", default=None, help="default results/grid_convergence.json (narrow), "
                   "results/grid_convergence_<terrain>.json otherwise")
    args = a.parse_args(argv)
    if args.out is None:
        args.out = str(HERE / "results" / ("grid_convergence.json" if args.terrain == "narrow"
                                         else f"grid_convergence_{args.terrain}.json"))
    sizes = [float(s) for s in args.sizes.split(",") if s]
    if any(abs(40.0 / s - round(40.0 / s)) > 1e-9 for s in sizes):
        raise SystemExit(f"--sizes: every size must divide 40 m, got {args.sizes}")
    scen = [s for s in args.scenarios.split(",") if s]
    bad = [s for s in scen if s not in SCENARIOS]
    if bad:
        raise SystemExit(f"--scenarios: unknown {bad} (known: {', '.join(SCENARIOS)})")
    with scenarios.terrain_variant(args.terrain):
        res = {"terrain": args.terrain, "sizes": sizes,
               "convergence": convergence(scen, sizes) if len(sizes) > 1 else {},
               "terrain_split": terrain_split(),
               "switch_scan": {s: switch_scan(float(s), scen) for s in args.switch_scan.split(",") if s}}
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(res, indent=1))
    print("wrote", args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
