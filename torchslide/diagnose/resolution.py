"""The inversion grid's resolution: choosing the grid by its own error, and the mismatches finer cells remove.

Choosing the grid (``[diagnose] cellsize = "auto"``). The candidate grids have cells 8, 4, 2 and 1 times
those of the configured grid (the finest considered: the user's DEM or ``[terrain] cellsize``), within
``max_cells`` cells. From the coarsest, each is tried as the model error measures it (torchslide.
diagnose.model_error): n parameter sets (a maximin Latin hypercube over the prior box) run on the
candidate and on cells half as large (resampled from the configured grid while they are no finer than
it, else interpolated), the difference eps seen on the candidate's grid. Per observation block the ratio

    r_b = rms(eps_b) / rms(sigma_b)          (sigma_b: the stated errors of the block's values)

compares the grid's error with the stated noise. The first (coarsest) grid with r_b <= 1 for every
block is chosen; if none is, the finest within the budget, and the report says which blocks exceed.
The chosen grid's finer runs then use the terrain resampled on cells half as large (FineTerrain) when
the configured grid holds it.

Resolution as an explanation. With the grid's error in the likelihood, a significant located mismatch
(|score| >= located_min) that the baseline shows against the recordings as given (no grid error), and
that no significant one overlaps once the grid's error is accounted, is the grid's own: runs on cells
half as large remove it. :func:`removed_by_resolution` lists those, beside the physics candidates.
"""
from __future__ import annotations

import time

import numpy as np

from ..terrain.grid import DEM
from ..terrain.resample import resample_dem, resample_map, resample_thickness

FACTORS = (8, 4, 2, 1)          # candidate cells, in multiples of the configured grid's
MIN_RELEASE_CELLS = 4           # a candidate grid must hold the release on at least this many cells


def _areas(ev, dem: DEM) -> np.ndarray:
    return dem.surface_area() if getattr(ev, "thickness", "normal") == "normal" else np.full(dem.shape, dem.cellsize ** 2)


def regrid(ev, cellsize: float):
    """The evaluator ``ev`` on square cells of ``cellsize`` m over its DEM's extent: the DEM interpolated
    (terrain.resample.resample_dem), release and erodible depth resampled with their volumes kept, the
    friction scale and every map observation averaged over the cells each new cell overlaps
    (SeriesObservation.on_grid); gauges and scalar observations as they are. ``ev`` itself when the
    cells are its own."""
    if abs(cellsize - ev.dem.cellsize) <= 1e-9 * ev.dem.cellsize:
        return ev
    if ev.covariance is not None:
        raise ValueError("a full covariance of the observations is stated for their values on the configured grid; "
                         "it cannot follow them onto another grid")
    dem = resample_dem(ev.dem, cellsize)
    for name, x, y in ev.gauges:
        if not (dem.xll <= x < dem.xll + dem.nx * cellsize and dem.yll <= y < dem.yll + dem.ny * cellsize):
            raise ValueError(f"gauge {name} at ({x:g}, {y:g}) lies outside the {cellsize:g} m grid's extent")
    a_src, a_dst = _areas(ev, ev.dem), _areas(ev, dem)
    thick = lambda a: None if a is None else resample_thickness(np.asarray(a, dtype=np.float64), ev.dem, dem,
                                                                a_src, a_dst)
    mus = None if ev.mu_scale is None else resample_map(np.asarray(ev.mu_scale, dtype=np.float64), ev.dem, dem)
    obs = [o.on_grid(ev.dem, dem) if getattr(o, "is_map", False) else o for o in ev.observations]
    return ev._copy(dem=dem, release=thick(ev.release), erodible_depth=thick(ev.erodible_depth), mu_scale=mus,
                    observations=obs, fine_terrain=None, model_error=None)


def fine_terrain_from(ev, coarse):
    """A model_error.FineTerrain for ``coarse`` (an evaluator regridded from ``ev``) on cells half as large,
    resampled from ``ev``'s grid and cut to twice ``coarse``'s shape; None when those cells are finer
    than ``ev``'s own (then the finer runs interpolate the coarse DEM) or the cut grid does not cover it."""
    from .model_error import FineTerrain

    cs = coarse.dem.cellsize / 2
    if cs < ev.dem.cellsize * (1 - 1e-9):
        return None
    fine = regrid(ev, cs)
    ny, nx = 2 * coarse.dem.ny, 2 * coarse.dem.nx
    if fine.dem.ny < ny or fine.dem.nx < nx:
        return None
    cut = lambda a: None if a is None else np.asarray(a)[:ny, :nx]
    dem = DEM(fine.dem.z[:ny, :nx], fine.dem.cellsize, xll=fine.dem.xll, yll=fine.dem.yll, crs=fine.dem.crs,
              outside=cut(fine.dem.outside))
    return FineTerrain(dem, cut(fine.release), erodible_depth=cut(fine.erodible_depth), mu_scale=cut(fine.mu_scale))


def _stated_sigma(ev) -> np.ndarray:
    """(k,) the stated error of every data value (a scalar observation's sigma; a series' per value)."""
    out = []
    for o in ev.observations:
        sv = getattr(o, "sigma_vector", None)
        out.append(sv() if sv is not None else np.atleast_1d(np.asarray(o.sigma, dtype=np.float64)))
    return np.concatenate(out)


def error_ratios(ev, samples: np.ndarray) -> dict:
    """{block: rms(eps) / rms(stated sigma)} of the (n, k) grid-error samples ``samples`` (module doc)."""
    s = _stated_sigma(ev)
    return {b.name: float(np.sqrt(np.mean(samples[:, b.slice] ** 2)) / np.sqrt(np.mean(s[b.slice] ** 2)))
            for b in ev.blocks}


def choose_grid(ev, max_cells: int = 20000, n_sets: int = 4, seed: int = 0, factors=FACTORS, log=print):
    """(evaluator on the chosen grid, its FineTerrain or None, report dict): the coarsest candidate grid
    whose error is below the stated noise in every block, else the finest within ``max_cells`` (module
    doc). The report lists every grid tried: cellsize, cells, per-block ratio, seconds, and why it was
    passed over."""
    from ..active import maximin_lhs
    from .model_error import approximation_error

    lo, hi = (b.numpy() for b in ev.prior.bounds)
    x = lo + maximin_lhs(n_sets, len(lo), seed=seed) * (hi - lo)
    tried, chosen = [], None
    for f in sorted(factors, reverse=True):
        cs = ev.dem.cellsize * f
        row = {"cellsize": float(cs)}
        try:
            cand = regrid(ev, cs)
        except ValueError as e:          # too few cells, a map or release lost on cells this large
            tried.append({**row, "skipped": str(e)})
            continue
        row["cells"] = int(cand.dem.ny * cand.dem.nx)
        if row["cells"] > max_cells:
            tried.append({**row, "skipped": f"over the budget of {max_cells} cells"})
            continue
        if int((np.asarray(cand.release) > 0).sum()) < MIN_RELEASE_CELLS:
            tried.append({**row, "skipped": f"the release covers fewer than {MIN_RELEASE_CELLS} cells"})
            continue
        ft = fine_terrain_from(ev, cand)
        t0 = time.perf_counter()
        me = approximation_error(cand._copy(fine_terrain=ft), x, factor=2)
        row.update(ratio=error_ratios(cand, me.samples), seconds=time.perf_counter() - t0,
                   fine="resampled" if ft is not None else "interpolated")
        row["passes"] = all(v <= 1.0 for v in row["ratio"].values())
        tried.append(row)
        log(f"[diagnose] grid {cs:g} m ({row['cells']} cells): the grid's error / stated noise " +
            ", ".join(f"{k} {v:.2g}" for k, v in row["ratio"].items()))
        chosen = (cand, ft, row)
        if row["passes"]:
            break
    if chosen is None:
        raise ValueError(f"cellsize = \"auto\": no grid of {', '.join(str(r['cellsize']) for r in tried)} m "
                         f"could be tried ({'; '.join(r.get('skipped', '') for r in tried)})")
    cand, ft, row = chosen
    over = [k for k, v in row["ratio"].items() if v > 1.0]
    why = ("the coarsest grid whose error is below the stated noise in every block" if row["passes"] else
           f"the finest grid within the budget; its error exceeds the stated noise in {', '.join(over)} "
           "(it is modelled as the grid's approximation error)")
    log(f"[diagnose] inversion grid {row['cellsize']:g} m: {why}")
    return cand, ft, {"cellsize": row["cellsize"], "reason": why, "n_sets": int(n_sets), "max_cells": int(max_cells),
                      "tried": tried}


def removed_by_resolution(located_raw: list, located: list) -> list:
    """The located mismatches of the baseline against the recordings as given (``located_raw``, no grid
    error) that share no data value with any of ``located`` (those significant once the grid's error is
    accounted): the grid's own (module doc). Items as localise's, without private keys."""
    kept = set()
    for l in located:
        kept.update(int(i) for i in l.get("_idx", ()))
    return [{k: v for k, v in l.items() if not k.startswith("_")} for l in located_raw
            if not kept.intersection(int(i) for i in l.get("_idx", ()))]
