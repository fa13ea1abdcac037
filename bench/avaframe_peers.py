"""torchslide against AvaFrame's com1DFA on AvaFrame's own cases (avaWog: the real Wolfsgruben DEM;
avaHelix), set up as a user of both does: com1DFA's DEM remeshed to 10 m (its remeshedRasters file, which
marks nodata with NaN), the case's release polygons 1 m thick normal to the slope, Voellmy mu 0.155,
xi 4000 m/s^2 (com1DFA's defaults), no entrainment, density 200 kg/m^3. Both models' peak fields are
compared cell by cell on that grid: v_max (peak, 99th percentile over cells with h_max > 0.5 m), p_max,
the footprint h_max > 0.5 m (area, Jaccard), the areas reached by 1 mm to 1 m (the lateral spread of thin
layers), the run-out along the case's AIMEC path, the cells above the
energy line from the release (docs/verification.md, case 7; outside the release and the cells beside
it) and above free fall, and each run's simulated time and wall time.

    git clone https://github.com/avaframe/AvaFrame; mkdir peers; cp -r AvaFrame/avaframe/data/avaWog peers/
    python -m bench.com1dfa_run peers/avaWog          # in a Python with avaframe==2.1
    python -m bench.avaframe_peers --peers peers --out bench/results/avaframe_peers.json
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
from scipy.ndimage import binary_dilation

CASES = {"avaWog": "REL/relWog.shp", "avaHelix": "REL/release1HX.shp"}
MU, XI, DENSITY, THRESHOLD = 0.155, 4000.0, 200.0, 0.5


def _peak(folder: Path, kind: str) -> np.ndarray:
    from torchslide.terrain.io import read_asc_array

    (path,) = sorted(folder.glob(f"*_{kind}.asc"))
    return np.nan_to_num(read_asc_array(path)[0])


def _figures(dem, release_v, h, v, path_xy, mu) -> dict:
    from torchslide.bounds import energy_line_speed, free_fall_speed
    from torchslide.observe import thalweg_distance_map

    outside = (h > 0.05) & ~binary_dilation(release_v > 0)
    eb = energy_line_speed(dem.z, dem.cellsize, release_v, mu, h)
    ff = free_fall_speed(dem.z, release_v)
    s, _ = thalweg_distance_map(dem, path_xy)
    foot = h > THRESHOLD
    return {"v_max_peak": float(v.max()), "v_max_p99_h>0.5": float(np.percentile(v[foot], 99)),
            "p_max_peak_kpa": float(DENSITY * v.max() ** 2 / 1000.0),
            "impact_area_m2_h>0.5": float(foot.sum() * dem.cellsize ** 2),
            "area_m2_by_h_max": {f"{t:g}": float((h > t).sum() * dem.cellsize ** 2) for t in (0.001, 0.01, 0.1, 0.5, 1.0)},
            "runout_m_along_path": float(s[foot].max()),
            "cells_above_energy_line": int((outside & (v > eb)).sum()),
            "largest_v_over_energy_line": float((v[outside] / np.maximum(eb[outside], 1e-12)).max()),
            "cells_above_free_fall": int((outside & (v > ff)).sum())}


def run_case(peers: Path, case: str) -> dict:
    from torchslide.config import load_config
    from torchslide.physics import Params
    from torchslide.solver import simulate
    from torchslide.terrain.vector import read_polyline

    ava = peers / case
    (dem_file,) = sorted((ava / "Inputs" / "remeshedRasters").glob("*.asc"))
    rel = ava / "Inputs" / CASES[case]
    cfg_file = ava / "torchslide.toml"
    cfg_file.write_text(f'[terrain]\ndem = "{dem_file.relative_to(ava)}"\nrelease = {{ polygons = '
                        f'"{rel.relative_to(ava)}", thickness = 1.0 }}\nthickness = "normal"\nnodata = "outflow"\n'
                        f'[model]\nmu = {MU}\nxi = {XI}\n[run]\nt_end = 400.0\n')
    cfg = load_config(cfg_file)
    dem, release = cfg.terrain.dem, cfg.terrain.release
    t0 = time.perf_counter()
    r = simulate(dem, release, Params.make(mu=MU, xi=XI), t_end=400.0, config=cfg.solver_config())
    wall = time.perf_counter() - t0
    release_v = release * np.sqrt(1.0 + sum(g ** 2 for g in np.gradient(dem.z, dem.cellsize)))
    path = read_polyline(ava / "Inputs" / "LINES" / "path_aimec.shp", dem)
    ts = {"kernel": r.kernel, "runtime_s": wall, "t_final_s": float(r.t_final[0]),
          "release_volume_m3": float(r.release_volume[0]), "final_volume_m3": float(r.final_volume[0]),
          **_figures(dem, release_v, r.h_max[0].numpy(), r.v_max[0].numpy(), path, MU)}
    out = {"grid": {"cellsize_m": dem.cellsize, "shape": list(dem.shape)}, "torchslide": ts}
    peak = ava / "Outputs" / "com1DFA" / "peakFiles"
    h_c, v_c = _peak(peak, "pft"), _peak(peak, "pfv")
    if h_c.shape == dem.shape:
        out["com1DFA"] = _figures(dem, release_v, h_c, v_c, path, MU)
        a, b = r.h_max[0].numpy() > THRESHOLD, h_c > THRESHOLD
        out["footprint_jaccard_h>0.5"] = float((a & b).sum() / (a | b).sum())
        out["area_ratio_by_h_max"] = {t: ts["area_m2_by_h_max"][t] / out["com1DFA"]["area_m2_by_h_max"][t]
                                      for t in ts["area_m2_by_h_max"]}
        out["ratio_torchslide_to_com1DFA"] = {k: ts[k] / out["com1DFA"][k] for k in
                                             ("v_max_peak", "v_max_p99_h>0.5", "p_max_peak_kpa",
                                              "impact_area_m2_h>0.5", "runout_m_along_path")}
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--peers", required=True, type=Path, help="folder with the cases com1dfa_run ran (avaWog, ...)")
    ap.add_argument("--cases", default="avaWog,avaHelix")
    ap.add_argument("--out", type=Path, default=Path("bench/results/avaframe_peers.json"))
    a = ap.parse_args(argv)
    res = {}
    for case in a.cases.split(","):
        res[case] = run_case(a.peers, case)
        print(case, json.dumps(res[case], indent=1))
    a.out.parent.mkdir(parents=True, exist_ok=True)
    a.out.write_text(json.dumps({"mu": MU, "xi": XI, "density": DENSITY, "threshold_m": THRESHOLD, "cases": res},
                                indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
