"""Write one harness case as the files a user would bring, with a config for the ``torchslide diagnose`` CLI.
``python -m experiments.hidden_physics.export_case SCENARIO SEED --out DIR [--terrain narrow|resolved|fan]
[--strength S] [--thresholds FILE]``, then ``torchslide diagnose DIR/diagnose.toml --out DIR/diagnosis``.

The harness calls torchslide.diagnose from Python. This writes the same case as files:

* ``dem.asc``, ``release.asc`` (nominal volume), ``erodible.asc``: the inversion grid's terrain
  (ESRI ASCII, 17 significant digits, so they read back bit for bit);
* ``deposit.asc``: the recorded deposit map (block-averaged from the finer recording grid, with noise);
* ``g1.csv``, ``g2.csv``: the gauge series (columns t, h, speed);
* ``diagnose.toml``: [terrain], [model], [run] (the harness solver settings), [[gauges]],
  [[observations]] (with the harness' sigmas and correlation lengths; the final volume as a scalar),
  [prior], [calibration] (the baseline's budget) and [diagnose] (harness.HARNESS_BUDGETS, the case's
  seed and the decision thresholds of ``--thresholds``, default the harness' file of the terrain);
* with ``--fine-terrain``: ``dem_fine.asc``, ``release_fine.asc``, ``erodible_fine.asc``, the terrain on the
  recording grid (no hidden term), as ``[diagnose] fine_terrain`` (the harness' ``--fine-terrain``);
* ``truth.json``: the answer (scenario, hidden term, its value, the release volume factor). The
  diagnosis does not read it.

The CLI run on these files is the harness case: the same evaluator (data, sigmas, terrain, gauges,
prior), budgets and thresholds (tests/test_harness.py checks it), so its report can be compared with
the harness' saved result of the case.
"""
from __future__ import annotations

import argparse
import json
import re
from pathlib import Path

import numpy as np

from torchslide.terrain.io import write_asc

from . import scenarios
from .harness import CANDIDATE_NAMES, HARNESS_BUDGETS, load_thresholds, out_of_range, thresholds_file as thresholds_file_of
from .scenarios import (RELEASE_VOLUME_SD, SOLVER, T_END, TERRAINS, V_NOMINAL, fine_terrain_grids, gauges,
                        make_recording, release, terrain)

EXACT = "%.17g"  # float64 round trip


def _toml_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    if isinstance(v, dict):
        key = lambda k: k if re.fullmatch(r"[A-Za-z0-9_-]+", k) else json.dumps(k)   # "g1:speed" needs quotes
        return "{ " + ", ".join(f"{key(str(k))} = {_toml_value(x)}" for k, x in v.items()) + " }"
    if isinstance(v, float):
        return repr(v)
    return str(v)


def _table(name: str, d: dict, array: bool = False) -> list[str]:
    return [f"[[{name}]]" if array else f"[{name}]"] + [f"{k} = {_toml_value(v)}" for k, v in d.items()] + [""]


def export_case(scenario: str, seed: int, out, strength: float = 1.0, thresholds_file=None,
                cellsize: float = 40.0, fine_terrain: bool = False,
                release_volume_sd: float = RELEASE_VOLUME_SD) -> Path:
    """Write the case (module doc) for the current terrain variant (scenarios.use_terrain) to ``out``;
    returns the config's path. ``thresholds_file``: a thresholds JSON as calibrate_thresholds writes
    it (default: the harness file of the current terrain; the default thresholds where it has none). ``fine_terrain``: also write the terrain on the recording
    grid (``*_fine.asc``, scenarios.fine_terrain_grids) as ``[diagnose] fine_terrain``, as the harness'
    ``--fine-terrain``; ``release_volume_sd``: the release's relative sd under [diagnose] (default the harness'
    HARNESS_BUDGETS, the error its recordings draw; 0: the release taken as exact)."""
    from torchslide.observe import Observation
    from torchslide.observe_series import SeriesObservation

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    rec = make_recording(scenario, seed, cellsize=cellsize, strength=strength)
    dem, erod = terrain(cellsize)
    write_asc(out / "dem.asc", dem.z, dem, fmt=EXACT)
    write_asc(out / "release.asc", release(dem, V_NOMINAL), dem, fmt=EXACT)
    write_asc(out / "erodible.asc", erod, dem, fmt=EXACT)
    obs_tables, series = [], {}
    for o in rec.observations:
        if isinstance(o, SeriesObservation) and o.kind == "deposit_map":
            a = np.full(dem.shape, np.nan)
            a.ravel()[np.asarray(o.cell_index)] = np.asarray(o.values)
            write_asc(out / "deposit.asc", a, dem, fmt=EXACT)
            obs_tables.append({"kind": "deposit_map", "file": "deposit.asc", "name": str(o.name),
                               "sigma": float(np.asarray(o.sigma)), "corr_length": float(o.corr_length)})
        elif isinstance(o, SeriesObservation) and o.kind == "gauge_series":
            series.setdefault(o.gauge, {"t": np.asarray(o.times), "sigma": {}, "corr": float(o.corr_length)})
            series[o.gauge][o.quantity] = np.asarray(o.values)
            series[o.gauge]["sigma"][o.quantity] = float(np.asarray(o.sigma))
        elif isinstance(o, Observation):
            obs_tables.append({"kind": o.kind, "name": str(o.name), "value": float(o.value), "sigma": float(o.sigma)})
        else:  # a kind this writer does not know would silently drop data
            raise ValueError(f"export_case: observation {o.name!r} of kind {o.kind!r} has no file format here")
    for g, s in series.items():
        qs = [q for q in ("h", "speed") if q in s]
        rows = ["t," + ",".join(qs)] + [",".join(EXACT % v for v in (s["t"][i], *(s[q][i] for q in qs)))
                                        for i in range(len(s["t"]))]
        (out / f"{g}.csv").write_text("\n".join(rows) + "\n")
        obs_tables.append({"kind": "gauge_series", "file": f"{g}.csv", "gauge": g, "sigma": s["sigma"],
                           "corr_time": s["corr"]})
    # the harness' order: deposit map, gauge series, scalars (the data vector's order)
    order = {"deposit_map": 0, "gauge_series": 1}
    obs_tables.sort(key=lambda d: order.get(d["kind"], 2))
    th = load_thresholds(thresholds_file or thresholds_file_of(scenarios.TERRAIN, fine_terrain)).to_json()
    bud = dict(HARNESS_BUDGETS)
    if fine_terrain:
        dem_f, rel_f, erod_f = fine_terrain_grids(cellsize)
        for name, a in (("dem", dem_f.z), ("release", rel_f), ("erodible", erod_f)):
            write_asc(out / f"{name}_fine.asc", a, dem_f, fmt=EXACT)
        bud["fine_terrain"] = {k: f"{k}_fine.asc" for k in ("dem", "release", "erodible")}
    bud["release_volume_sd"] = float(release_volume_sd)
    cal = {"n_initial": bud.pop("baseline_n_initial"), "n_total": bud.pop("baseline_n_total"),
           "batch_size": bud["batch_size"], "max_batch": 16}
    L = ["# A blind hidden-physics harness case (the answer is in truth.json, which the diagnosis does not read),",
         "# written by experiments/hidden_physics/export_case.py. Run:",
         "#   torchslide diagnose diagnose.toml --out diagnosis", ""]
    L += _table("terrain", {"dem": "dem.asc", "release": "release.asc", "erodible": "erodible.asc"})
    L += _table("model", {"rheology": "voellmy", "mu": scenarios.TRUE_BASE["mu"], "xi": scenarios.TRUE_BASE["xi"]})
    L += _table("run", {"t_end": T_END, "dtype": "float64", **SOLVER})
    for name, x, y in gauges():
        L += _table("gauges", {"name": name, "x": float(x), "y": float(y)}, array=True)
    for d in obs_tables:
        L += _table("observations", d, array=True)
    L += _table("prior", {"mu": [0.12, 0.4], "xi": [150.0, 1500.0]})
    L += _table("calibration", cal)
    L += _table("diagnose", {"candidates": list(CANDIDATE_NAMES), "seed": int(seed), **bud,
                             **{k: ({n: float(x) for n, x in v.items()} if isinstance(v, dict) else float(v))
                                for k, v in th.items() if v is not None}})
    cfg = out / "diagnose.toml"
    cfg.write_text("\n".join(L))
    (out / "truth.json").write_text(json.dumps({"scenario": scenario, "seed": seed, "terrain": scenarios.TERRAIN,
                                                "strength": strength, "truth": rec.truth,
                                                "volume_factor": rec.volume_factor}, indent=1))
    return cfg


def main(argv=None) -> int:
    a = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    a.add_argument("scenario", choices=sorted(scenarios.SCENARIOS))
    a.add_argument("seed", type=int)
    a.add_argument("--out", required=True, help="folder for the files and diagnose.toml")
    a.add_argument("--terrain", default="narrow", choices=sorted(TERRAINS))
    a.add_argument("--strength", type=float, default=1.0)
    a.add_argument("--thresholds", default=None, help="thresholds JSON (default: the harness' file of --terrain)")
    a.add_argument("--fine-terrain", action="store_true",
                   help="also write the recording grid's terrain (dem_fine.asc, release_fine.asc, erodible_fine.asc) "
                        "as [diagnose] fine_terrain, as the harness' --fine-terrain")
    a.add_argument("--release-volume-sd", type=float, default=RELEASE_VOLUME_SD,
                   help=f"[diagnose] release_volume_sd, as the harness' --budget release_volume_sd=... (default "
                        f"{RELEASE_VOLUME_SD:g}, the error the recordings draw; 0: the release taken as exact)")
    args = a.parse_args(argv)
    if not (0.0 <= args.release_volume_sd < 0.5):   # as [diagnose] release_volume_sd
        raise SystemExit(f"--release-volume-sd {args.release_volume_sd:g}: must be a relative sd in [0, 0.5)")
    why = out_of_range(args.scenario, args.strength)
    if why:
        raise SystemExit(f"--strength {args.strength:g}: {args.scenario}'s {why}")
    with scenarios.terrain_variant(args.terrain):
        cfg = export_case(args.scenario, args.seed, args.out, strength=args.strength, thresholds_file=args.thresholds,
                          fine_terrain=args.fine_terrain, release_volume_sd=args.release_volume_sd)
    print(f"wrote {cfg}; run: torchslide diagnose {cfg} --out {Path(args.out) / 'diagnosis'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
