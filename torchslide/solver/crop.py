"""Active-region cropping: step only the bounding box of the cells the flow has touched.

Why it is exact. In the central-upwind scheme a face between two dry cells carries no flux (both
reconstructed face depths are 0), so the wetted support grows by at most one cell per stage, two per
time step. The box is the bounding box of the wet cells of all members, dilated by
``margin = 2 * crop_every + 3`` cells and clipped to the DEM; it is checked every ``crop_every`` steps
and only ever grows. Inside it, the two cells next to a box edge stay dry until the next check, so
the ghost cells of the box (linear extrapolation of h: 0) see what the real neighbours would: nothing.
Outside it every field keeps its initial value (h = hu = hv = 0, h_max = v_max = 0, arrival = inf),
so cropping changes only the cost, never the result (up to the summation order of the diagnostic
totals mass and kinetic energy).
"""
from __future__ import annotations

from dataclasses import dataclass

import torch

Tensor = torch.Tensor

# state entries that are rasters (first dimension member or 1, then ny, nx)
SPATIAL = ("h", "hu", "hv", "z", "erod", "dep", "h_max", "v_max", "arrival")


@dataclass(frozen=True)
class Box:
    """Rows r0:r1 and columns c0:c1 of the DEM grid (half-open, row 0 south)."""

    r0: int
    r1: int
    c0: int
    c1: int

    @property
    def shape(self) -> tuple[int, int]:
        return self.r1 - self.r0, self.c1 - self.c0

    def covers(self, ny: int, nx: int) -> bool:
        return self.r0 == 0 and self.c0 == 0 and self.r1 == ny and self.c1 == nx


def full_box(ny: int, nx: int) -> Box:
    return Box(0, ny, 0, nx)


def grow(h: Tensor, box: Box | None, ny: int, nx: int, margin: int) -> Box:
    """The box needed for the next ``crop_every`` steps.

    Args:
        h: (B, rows, cols) thickness on the current box (the whole grid when ``box`` is None), m.
        box: current box (None: none yet); the result always contains it.
        ny, nx: DEM grid size; margin: dry cells kept between the wet support and the box edge.
    Returns:
        the (possibly unchanged) box; when it must grow it grows by an extra ``margin`` cells so that
        it is not rebuilt at every check.
    """
    off_r, off_c = (box.r0, box.c0) if box is not None else (0, 0)
    wet = h > 0
    rows = wet.any(dim=2).any(dim=0)
    cols = wet.any(dim=1).any(dim=0)
    flags = torch.cat([rows, cols]).cpu()
    r_idx = torch.nonzero(flags[: rows.numel()]).flatten()
    c_idx = torch.nonzero(flags[rows.numel():]).flatten()
    if r_idx.numel() == 0:  # nothing wet (a dry release): keep what there is
        return box if box is not None else full_box(ny, nx)
    lo_r, hi_r = off_r + int(r_idx[0]), off_r + int(r_idx[-1]) + 1
    lo_c, hi_c = off_c + int(c_idx[0]), off_c + int(c_idx[-1]) + 1
    need = Box(max(0, lo_r - margin), min(ny, hi_r + margin), max(0, lo_c - margin), min(nx, hi_c + margin))
    if box is not None and need.r0 >= box.r0 and need.r1 <= box.r1 and need.c0 >= box.c0 and need.c1 <= box.c1:
        return box
    extra = margin
    new = Box(max(0, need.r0 - extra), min(ny, need.r1 + extra), max(0, need.c0 - extra), min(nx, need.c1 + extra))
    if box is not None:
        new = Box(min(new.r0, box.r0), max(new.r1, box.r1), min(new.c0, box.c0), max(new.c1, box.c1))
    return new


def extract(S: dict, box: Box, ny: int, nx: int) -> dict:
    """The state on the box: raster entries cut (contiguous copies), others shared."""
    if box.covers(ny, nx):
        return dict(S)
    out = dict(S)
    for k in SPATIAL:
        v = S.get(k)
        if v is not None:
            out[k] = v[:, box.r0:box.r1, box.c0:box.c1].contiguous()
    return out


def write_back(S: dict, sub: dict, box: Box, ny: int, nx: int, keys) -> None:
    """Copy the box state ``sub`` into the whole-grid state ``S`` (in place): rasters in ``keys`` into
    the box window, every non-raster entry by reference."""
    for k, v in sub.items():
        if k not in SPATIAL:
            S[k] = v
    if box.covers(ny, nx):
        for k in keys:
            if k in SPATIAL and sub.get(k) is not None:
                S[k] = sub[k]
        return
    for k in keys:
        if k in SPATIAL and sub.get(k) is not None:
            S[k][:, box.r0:box.r1, box.c0:box.c1] = sub[k]


def gauge_index(rows: Tensor, cols: Tensor, box: Box) -> tuple[Tensor, Tensor]:
    """Flat indices of gauge cells (row, col on the DEM grid) in the box, and a mask of those inside
    (outside the box a gauge reads 0: the flow has never reached it)."""
    inside = (rows >= box.r0) & (rows < box.r1) & (cols >= box.c0) & (cols < box.c1)
    w = box.c1 - box.c0
    idx = torch.where(inside, (rows - box.r0) * w + (cols - box.c0), torch.zeros_like(rows))
    return idx, inside
