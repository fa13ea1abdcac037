"""What a modeller quotes of a run against a mapped event.

For each mapped footprint among the observations (``footprint`` and ``impact_map``: the cells mapped as
reached; ``elevation_change``: the surveyed cells whose surface changed), a run's figures:

- ``footprint_jaccard``: |mapped and reached| / |mapped or reached|, reached meaning h_max > threshold;
- ``share_of_mapped_reached``: the share of the mapped cells the run reaches;
- ``share_of_reached_unmapped``: the share of the reached cells outside the mapped footprint;
- ``runout_m``: {"run", "mapped"}: the horizontal distance from the release's highest cell (the crown) to
  the farthest reached / mapped cell centre, m (``mapped_runout`` measures a map's, as the observation
  ``runout_length`` with ``map = FILE`` takes it);
- for ``elevation_change`` also ``deposition_m3`` and ``erosion_m3`` ({"run", "survey"}: volumes of the
  vertical surface rise and fall, m^3; the run's over the whole grid, the survey's over its cells) and
  ``rmse_m`` (the simulated against the surveyed change over the surveyed cells, m).
"""
from __future__ import annotations

import numpy as np

FOOTPRINT_KINDS = ("footprint", "impact_map", "elevation_change")


def mapped_footprint(obs) -> np.ndarray:
    """(ny, nx) bool: the cells a map observation marks as reached (see the module doc)."""
    grid = obs.to_grid(obs.values)
    if obs.kind == "elevation_change":
        return np.isfinite(grid) & (grid != 0.0)
    return np.nan_to_num(grid) >= 0.5


def crown_cell(z: np.ndarray, release: np.ndarray) -> tuple[int, int]:
    """(row, col) of the release's highest cell (the crown), on a grid of elevations z (ny, nx) m."""
    if not (np.asarray(release) > 0).any():
        raise ValueError("the release has no cell with a positive thickness: it has no crown")
    zr = np.where(np.asarray(release) > 0, z, -np.inf)
    r0, c0 = np.unravel_index(np.argmax(zr), zr.shape)
    return int(r0), int(c0)


def crown_point(dem, release: np.ndarray) -> tuple[float, float]:
    """Map coordinates (x, y), m, of the centre of the release's highest cell on ``dem``."""
    r0, c0 = crown_cell(dem.z, release)
    return float(dem.xll + (c0 + 0.5) * dem.cellsize), float(dem.yll + (r0 + 0.5) * dem.cellsize)


def runout_from_crown(z: np.ndarray, release: np.ndarray, mask: np.ndarray, cellsize: float) -> float:
    """Horizontal distance, m, from the release's highest cell to the farthest cell of ``mask`` (0 if empty)."""
    if not mask.any() or not (release > 0).any():
        return 0.0
    r0, c0 = crown_cell(z, release)
    rows, cols = np.nonzero(mask)
    return float(np.hypot(rows - r0, cols - c0).max() * cellsize)


def mapped_runout(mapped: np.ndarray, dem, point: tuple | None = None, thalweg=None,
                  max_offset: float | None = None) -> float:
    """The run-out of a mapped footprint (``mapped`` (ny, nx) bool on ``dem``'s grid), m: the largest horizontal
    distance of a mapped cell centre from ``point`` (x, y) (the crown), or its largest distance along
    ``thalweg`` (torchslide.observe.thalweg_distance_map; cells farther than ``max_offset`` from it left out)."""
    from .observe import point_distance_map, thalweg_distance_map

    if not mapped.any():
        raise ValueError("the map has no mapped cell (finite and non-zero)")
    if thalweg is not None:
        s, dist = thalweg_distance_map(dem, thalweg)
        keep = mapped if max_offset is None else mapped & (dist <= max_offset)
        if not keep.any():
            raise ValueError(f"no mapped cell lies within max_offset = {max_offset:g} m of the path")
        return float(s[keep].max())
    return float(point_distance_map(dem, *point)[mapped].max())


def footprint_figures(reached: np.ndarray, mapped: np.ndarray) -> dict:
    """Jaccard and the two shares of a reached (ny, nx) bool mask against a mapped one."""
    both, either = int((reached & mapped).sum()), int((reached | mapped).sum())
    return {"footprint_jaccard": both / either if either else 1.0,
            "share_of_mapped_reached": both / int(mapped.sum()) if mapped.any() else float("nan"),
            "share_of_reached_unmapped": int((reached & ~mapped).sum()) / int(reached.sum()) if reached.any() else 0.0}


def change_figures(dz: np.ndarray, survey: np.ndarray, cellsize: float) -> dict:
    """Deposition / erosion volumes (m^3) of a simulated vertical change ``dz`` (ny, nx) and of the survey
    (NaN off its cells), and the rmse of dz against the survey over its cells (m)."""
    area = cellsize * cellsize
    on = np.isfinite(survey)
    s = np.where(on, survey, 0.0)
    return {"deposition_m3": {"run": float(np.clip(dz, 0, None).sum() * area), "survey": float(np.clip(s, 0, None).sum() * area)},
            "erosion_m3": {"run": float(-np.clip(dz, None, 0).sum() * area), "survey": float(-np.clip(s, None, 0).sum() * area)},
            "rmse_m": float(np.sqrt(np.mean((dz[on] - survey[on]) ** 2)))}


def run_figures(h_max: np.ndarray, dz: np.ndarray | None, observations, z: np.ndarray, release: np.ndarray,
                cellsize: float, threshold: float) -> dict:
    """{observation name: figures} of one run (h_max (ny, nx) m, dz its vertical surface change or None) against
    every mapped footprint among ``observations`` (module doc); reached means h_max > the observation's
    threshold (``threshold`` for elevation_change)."""
    out = {}
    for obs in observations:
        if getattr(obs, "kind", None) not in FOOTPRINT_KINDS:
            continue
        mapped = mapped_footprint(obs)
        t = threshold if obs.kind == "elevation_change" else obs.threshold
        reached = h_max > t
        f = {"threshold_m": t, **footprint_figures(reached, mapped),
             "runout_m": {"run": runout_from_crown(z, release, reached, cellsize),
                          "mapped": runout_from_crown(z, release, mapped, cellsize)}}
        if obs.kind == "elevation_change" and dz is not None:
            f.update(change_figures(dz, obs.to_grid(obs.values), cellsize))
        out[str(obs.name)] = f
    return out


def spread(per_run: list[dict]) -> dict:
    """{name: {figure: {"median", "q05", "q95"}}} over the runs' run_figures (nested {"run", ...} figures by
    their "run" value; the survey's and the mapped values kept as they are)."""
    out: dict = {}
    if not per_run:
        return out
    for name, first in per_run[0].items():
        out[name] = {}
        for key, v in first.items():
            if isinstance(v, dict):
                vals = np.array([r[name][key]["run"] for r in per_run])
                fixed = {k: x for k, x in v.items() if k != "run"}
            else:
                vals = np.array([r[name][key] for r in per_run], dtype=float)
                fixed = {}
            if key == "threshold_m":
                out[name][key] = v
                continue
            out[name][key] = {"median": float(np.median(vals)), "q05": float(np.quantile(vals, 0.05)),
                              "q95": float(np.quantile(vals, 0.95)), **fixed}
    return out


def mapped_path(mapped: np.ndarray, dem, release: np.ndarray) -> np.ndarray:
    """(n, 3) the mapped footprint's centre line from the release's crown: the crown, then for each ring one
    cell wide around it (as path_width) the centre of its mapped cells; columns x, y (map m) and the distance
    along the line from the crown, m."""
    r0, c0 = crown_cell(dem.z, release)
    rows, cols = np.nonzero(np.asarray(mapped, bool))
    ring = np.floor(np.hypot(rows - r0, cols - c0)).astype(int)
    n = np.bincount(ring)
    keep = n > 0
    rc = np.column_stack([np.bincount(ring, rows)[keep] / n[keep], np.bincount(ring, cols)[keep] / n[keep]])
    rc = np.vstack([[r0, c0], rc])          # rings in order of their distance from the crown
    xy = np.column_stack([dem.xll + (rc[:, 1] + 0.5) * dem.cellsize, dem.yll + (rc[:, 0] + 0.5) * dem.cellsize])
    along = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(xy, axis=0).T))])
    return np.column_stack([xy, along])


def nearest_on_path(cells: np.ndarray, dem, path: np.ndarray) -> dict:
    """Where a cluster (``cells`` (ny, nx) bool) meets the mapped path (mapped_path): of the centre-line points
    within half a cell of the cluster's nearest approach, the one nearest the crown: {"x", "y", "along_m"}."""
    rr, cc = np.nonzero(cells)
    cx, cy = dem.xll + (cc + 0.5) * dem.cellsize, dem.yll + (rr + 0.5) * dem.cellsize
    d = np.hypot(path[:, :1] - cx[None, :], path[:, 1:2] - cy[None, :]).min(axis=1)
    k = int(np.nonzero(d <= d.min() + 0.5 * dem.cellsize)[0][0])
    return {"x": float(path[k, 0]), "y": float(path[k, 1]), "along_m": float(path[k, 2])}


def mismatch_clusters(p_reached: np.ndarray, mapped: np.ndarray, dem, release: np.ndarray, *, level: float = 0.5,
                      min_cells: int = 3, h_p50: np.ndarray | None = None, survey_dz: np.ndarray | None = None) -> list:
    """Where a run set and a mapped footprint disagree, in a modeller's terms: the clusters (8-connected) of
    cells reached but not mapped ("excess": impact probability p_reached >= ``level`` off the map) and of
    cells mapped but not reached ("deficit": on the map, p_reached < ``level``), of at least ``min_cells``
    cells, the largest first. Each: {"what", "n_cells", "area_m2", "box" [xmin, ymin, xmax, ymax] m,
    "from_crown_m" [nearest, farthest] (horizontal distance of its cells from the release's crown),
    "path_point" (where it meets the mapped path: nearest_on_path, with its distance along the path), "score"
    (the cells' sum of |2 p - 1|: how many cells the runs agree on), and "volume_m3": for an excess the
    median run's flow over it (``h_p50`` (ny, nx) m of h_max, times the map area), for a deficit the
    survey's change in it (``survey_dz``, vertical m, its absolute volume)}."""
    from scipy import ndimage

    p = np.asarray(p_reached, dtype=np.float64)
    mapped = np.asarray(mapped, bool)
    r0, c0 = crown_cell(dem.z, release)
    rows, cols = np.indices(dem.shape)
    dist = np.hypot(rows - r0, cols - c0) * dem.cellsize
    area = dem.cellsize ** 2
    path = mapped_path(mapped | (np.asarray(release) > 0), dem, release)
    out = []
    for what, cells in (("excess: reached, not mapped", (p >= level) & ~mapped),
                        ("deficit: mapped, not reached", mapped & (p < level))):
        lab, n = ndimage.label(cells, structure=np.ones((3, 3)))
        for k in range(1, n + 1):
            m = lab == k
            if m.sum() < min_cells:
                continue
            rr, cc = np.nonzero(m)
            item = {"what": what, "n_cells": int(m.sum()), "area_m2": float(m.sum() * area),
                    "box": [float(dem.xll + cc.min() * dem.cellsize), float(dem.yll + rr.min() * dem.cellsize),
                            float(dem.xll + (cc.max() + 1) * dem.cellsize), float(dem.yll + (rr.max() + 1) * dem.cellsize)],
                    "from_crown_m": [float(dist[m].min()), float(dist[m].max())],
                    "path_point": nearest_on_path(m, dem, path),
                    "score": float(np.abs(2 * p[m] - 1).sum())}
            if what.startswith("excess") and h_p50 is not None:
                item["volume_m3"] = float(np.asarray(h_p50)[m].sum() * area)
            if what.startswith("deficit") and survey_dz is not None:
                item["volume_m3"] = float(np.nansum(np.abs(np.asarray(survey_dz)[m])) * area)
            out.append(item)
    return sorted(out, key=lambda i: -i["score"])


def runout_mismatch(runouts: np.ndarray, mapped_runout: float, level: float = 0.9) -> dict:
    """The run-out's shortfall (< 0) or overshoot (> 0) against the mapped one, m: the runs' median minus the
    mapped run-out and its ``level`` interval over the runs."""
    r = np.asarray(runouts, dtype=np.float64)
    q = (1 - level) / 2
    return {"what": "run-out " + ("shortfall" if np.median(r) < mapped_runout else "overshoot"),
            "difference_m": float(np.median(r) - mapped_runout), "mapped_m": float(mapped_runout),
            "interval_m": [float(np.quantile(r, q) - mapped_runout), float(np.quantile(r, 1 - q) - mapped_runout)]}


def mismatch_line(m: dict) -> str:
    """One mismatch_clusters item or runout_mismatch result as a modeller reads it."""
    if "difference_m" in m:
        lo, hi = m["interval_m"]
        return (f"{m['what']} {m['difference_m']:+,.0f} m (90 % of the runs [{lo:+,.0f}, {hi:+,.0f}] m) of the mapped "
                f"{m['mapped_m']:,.0f} m")
    vol = f", {m['volume_m3']:,.0f} m^3" if m.get("volume_m3") is not None else ""
    x0, y0, x1, y1 = m["box"]
    pp = m.get("path_point")
    at = f", meets the mapped path {pp['along_m']:,.0f} m along it (x {pp['x']:,.0f}, y {pp['y']:,.0f})" if pp else ""
    return (f"{m['what']}: {m['n_cells']} cells ({m['area_m2']:,.0f} m^2{vol}), {m['from_crown_m'][0]:,.0f}-"
            f"{m['from_crown_m'][1]:,.0f} m from the crown{at}, x {x0:,.0f}-{x1:,.0f}, y {y0:,.0f}-{y1:,.0f} m "
            f"(score {m['score']:.1f})")


def cluster_labels(clusters: list, n: int = 9) -> list:
    """[(x, y, "i")]: the first ``n`` mismatch_clusters numbered at their boxes' centres (mapplots.plot_outlines)."""
    return [(0.5 * (c["box"][0] + c["box"][2]), 0.5 * (c["box"][1] + c["box"][3]), str(i + 1))
            for i, c in enumerate(clusters[:n])]


NARROW_CELLS = 3.0
"""The fewest cells across which a finite-volume grid holds a channel (its bed and two banks)."""


def path_width(mapped: np.ndarray, dem, release: np.ndarray) -> dict:
    """How many cells across the mapped path is, below the release: the mapped cells outside the release in
    rings one cell wide around the crown, each ring's count of cells (its area over its width: the path's
    width where it crosses the ring, in cells). {"median_cells", "share_narrower" (of the rings, narrower than NARROW_CELLS cells),
    "n_rings", "cellsize_m"}; where most of the path is narrower, the grid does not hold the channel that
    confined the flow."""
    mapped = np.asarray(mapped, bool) & ~(np.asarray(release) > 0)
    if not mapped.any():
        return {"median_cells": float("nan"), "share_narrower": float("nan"), "n_rings": 0,
                "cellsize_m": float(dem.cellsize)}
    r0, c0 = crown_cell(dem.z, release)
    rows, cols = np.nonzero(mapped)
    ring = np.floor(np.hypot(rows - r0, cols - c0)).astype(int)
    cells = np.bincount(ring)
    cells = cells[cells > 0]               # each ring's mapped cells = its area / cell area = its width in cells
    return {"median_cells": float(np.median(cells)), "share_narrower": float(np.mean(cells < NARROW_CELLS)),
            "n_rings": int(len(cells)), "cellsize_m": float(dem.cellsize)}


def width_line(w: dict) -> str:
    """path_width as a modeller reads it."""
    s = (f"the mapped path below the release is {w['median_cells']:.1f} cells of {w['cellsize_m']:g} m across (median "
         f"over {w['n_rings']} rings around the crown), narrower than {NARROW_CELLS:g} cells over "
         f"{100 * w['share_narrower']:.0f} % of its length")
    return s + (": the DEM does not resolve the channel that confined the flow" if w["share_narrower"] > 0.5 else "")
