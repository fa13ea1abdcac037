"""torchslide and landlab's MassWastingRunout against the surveyed elevation change of the msh2021 event.

Each model's change of the surface (torchslide: SimulationResult.elevation_change of a run at the given
mu, xi; MassWastingRunout: bench.mwr_run's mwr_dod.asc) against the survey's DoD: the footprint of the
change (|dz| > 0.1 m) against the 224 mapped cells (Jaccard, the shares of mapped cells reached and of
changed cells outside the map), deposition and erosion volumes (vertical m^3), the run-out (horizontal
distance from the highest source cell to the farthest changed cell) and the DoD rmse over the mapped cells.

    torchslide example msh2021 --out case
    python -m bench.mwr_run case                       # in a Python with landlab
    python -m bench.msh2021_peers case --out bench/results/msh2021_peers.json [--mu M --xi X]

mu, xi default to the posterior median run of experiments/msh2021 (its _work/summary.json).
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from bench import write_result

CHANGED = 0.1   # m: a cell whose surface moved by more is in a model's footprint


def compare(dod: np.ndarray, dz: np.ndarray, source: np.ndarray, cellsize: float) -> dict:
    """Figures of a modelled change ``dz`` against the survey ``dod`` (NaN off the mapped cells)."""
    mapped, changed = np.isfinite(dod), np.abs(dz) > CHANGED
    area = cellsize ** 2
    rows, cols = np.indices(dod.shape)
    r0, c0 = np.argwhere(source)[0] if source.any() else (0, 0)

    def runout(mask):
        return float(np.hypot(rows[mask] - r0, cols[mask] - c0).max() * cellsize) if mask.any() else 0.0

    return {"footprint_jaccard": float((mapped & changed).sum() / (mapped | changed).sum()),
            "share_of_mapped_cells_changed": float((mapped & changed).sum() / mapped.sum()),
            "share_of_changed_cells_unmapped": float((changed & ~mapped).sum() / max(changed.sum(), 1)),
            "deposition_m3": float(np.where(dz > 0, dz, 0).sum() * area),
            "erosion_m3": float(-np.where(dz < 0, dz, 0).sum() * area),
            "runout_m": runout(changed), "dod_rmse_on_mapped_cells_m": float(np.sqrt(np.mean((dz[mapped] - dod[mapped]) ** 2)))}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("case", type=Path, help="the msh2021 example folder, with mwr_dod.asc from bench.mwr_run")
    ap.add_argument("--mu", type=float, default=None)
    ap.add_argument("--xi", type=float, default=None)
    ap.add_argument("--out", type=Path, default=Path("bench/results/msh2021_peers.json"))
    a = ap.parse_args(argv)
    from torchslide.config import load_config
    from torchslide.physics import Params
    from torchslide.solver import simulate
    from torchslide.terrain.io import read_asc_array

    if a.mu is None or a.xi is None:
        summary = Path(__file__).resolve().parents[1] / "experiments" / "msh2021" / "_work" / "summary.json"
        x = json.loads(summary.read_text())["median_run"]
        a.mu, a.xi = a.mu or x["mu"], a.xi or x["xi"]
    cfg = load_config(a.case / "simulate.toml")
    dem = cfg.terrain.dem
    dod = read_asc_array(a.case / "dod.asc")[0]
    source = np.nan_to_num(read_asc_array(a.case / "failure_depth.asc")[0]) < 0
    z0 = np.where(source, dem.z, -np.inf)
    source_top = z0 == z0.max()
    r = simulate(dem, cfg.terrain.release, Params.make(mu=a.mu, xi=a.xi), t_end=cfg.run.t_end)
    mwr = np.nan_to_num(read_asc_array(a.case / "mwr_dod.asc")[0])
    survey = np.where(np.isfinite(dod), dod, 0.0)
    out = {"torchslide": {"mu": a.mu, "xi": a.xi, **compare(dod, r.elevation_change[0].numpy(), source_top, dem.cellsize)},
           "MassWastingRunout": {"parameters": "landlab tutorial's (bench.mwr_run)", **compare(dod, mwr, source_top, dem.cellsize)},
           "survey": compare(dod, survey, source_top, dem.cellsize)}
    write_result(a.out, out, indent=1)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
