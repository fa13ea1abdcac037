"""The solver step on Triton kernels (CUDA; on the CPU under TRITON_INTERPRET=1, for the tests).

``triton_step(F)`` returns a drop-in for ``stepping.make_step(F)``: the same SSP-RK2 step with the same
arithmetic in the same order per cell and per face (triton_ops: float64 equals the torch step to the last
bit; float32 takes the card's fast paths and is judged by physics). Only the sums over the grid (mass,
kinetic energy, outflow) add in another order. A stage is two passes over the grid of every member:

    faces    the central-upwind fluxes of every face and, per cell, the mass its faces carry out and the
             momentum change of gravity and pressure along the surface, in one of two designs (FACES):
             "march" (triton_march: one kernel, each cell's slopes and each face's flux computed once) or
             "lines" (triton_lines: velocities, x faces, y faces and cells, each face reconstructing its four
             cells)
    update   the draining limiter, the new state, the mass sources and friction (triton_update); after the
             second stage also the Heun average and the records of the step

Nothing in a step waits for the host: the CFL time step, the end times and the stop test are per-member
tensors on the device. Switches are compile-time constants (one specialisation per set of terms, cached on
disk by Triton). A bed that evolves has its geometry recomputed per stage by stepping.static_geometry.
"""
from __future__ import annotations

import functools
import math
import os

import torch

from ..physics import FR_DEP, MU_I_D, MU_I_I0
from .scheme import WAVE_SPEED_MIN
from .stepping import static_geometry
from .triton_ops import CONSTANTS, FAST_FLOAT32, FLUSH_SUBNORMALS, interpreted, triton  # noqa: F401

if triton is not None:
    from .triton_lines import _cells, _faces, _velocities
    from .triton_march import _march
    from .triton_update import _end_step, _update

PM = ("mu", "xi", "tau_y", "k_ap", "earth_pressure", "k_act", "k_pass", "curvature", "mu_i", "kappa", "deposition")
"""The per-member parameters the kernels read, in their order (columns of the (B, 11) table)."""

FACES = os.environ.get("TORCHSLIDE_TRITON_FACES", "march")
"""The faces' design (module docstring; environment TORCHSLIDE_TRITON_FACES at import): "march" or "lines". The
same bits either way. Compiled for sm_90, "march" has a third of the SASS instructions per float32 cell-update
of "lines" (bench/results/triton_profile.json); a GPU run (bench.bench_solver --device cuda --launch
128x4:lines,128x4:march) decides which is faster on the card."""

BLOCK = {"float32": 512, "float64": 128}
"""Cells (or faces) per program of the line design's kernels, per dtype: with 4 warps four cells per thread in
float32 (their scalar and address work shared) and one in float64 (whose registers four would spill;
bench.bench_solver --launch BLOCKxWARPS sets both)."""

NUM_WARPS = 4
"""Warps per program of the line design's kernels."""

MARCH = (32, 64)
"""(W, BAND) of the marching kernel: a warp over a strip of W = 32 positions (W - 4 = 28 columns owned, one
position per lane: its neighbours along a row are shuffles within the warp) marching through at most BAND = 64
rows (band: fewer where a small batch would leave the card's multiprocessors without work)."""

UPDATE = (32, 64)
"""(W, BAND) of the update: a warp over a strip of W = 32 positions (W - 2 = 30 columns updated, a draining
factor's neighbours along a row are shuffles) marching through at most BAND = 64 rows."""

PROGRAMS_PER_SM = 8
"""The least programs (one warp each) per multiprocessor a marching launch aims at before it shortens its band
(band): on a card of 132 multiprocessors (H100 SXM, H200) the 20 m Bondo-like grid's faces march through 8 rows
at 1 and 10 members, 32 at 32 and 64 at 256."""

UPDATE_UNROLL = 2
"""The update's loop over rows unrolled (1: not)."""

MARCH_UNROLL = 3
"""The marching loop unrolled three times: the rows' roles (older, newer, new) rotate with period three, so
unrolled they stay in their registers (unrolled once, 40 moves per row: 544 SASS instructions per position
against 474)."""

INTERPRETED_BLOCK = 2048
"""Cells per program of the cell-wise kernels under Triton's interpreter (the tests on the CPU), whose cost is
mostly per program; the same arithmetic per cell as any BLOCK."""

INTERPRETED_MARCH = (64, 32)
"""(W, BAND) under the interpreter (the tests on the CPU), whose cost is per program and row: a test grid of up to
60 columns and 32 rows in one program per member (tests/triton_interpret.py's bitwise case splits its grid
into several strips and bands to test their seams)."""

INTERPRETED_UPDATE = (64, 32)
"""The update's (W, BAND) under the interpreter."""


def supported(F, device) -> str | None:
    """None when the Triton step runs the call's settings ``F`` on ``device``, else why not: it needs
    triton and a CUDA device (or any device under TRITON_INTERPRET=1)."""
    if triton is None:
        return "triton is not installed"
    if torch.device(device).type != "cuda" and not interpreted():
        return "the Triton step runs on CUDA (or under TRITON_INTERPRET=1)"
    return None


def constants(F, dtype, device) -> torch.Tensor:
    """The kernels' constant table (triton_ops.CONSTANTS, indexed by its C_* names) in the state's dtype."""
    vals = {"g": F.g, "dx": F.dx, "theta": F.theta, "h_eps4": F.h_eps ** 4, "h_wet": F.h_wet, "wb_ratio": F.wb_ratio,
            "sqrt2": 2.0 ** 0.5, "wave_speed_min": WAVE_SPEED_MIN, "h_eps": F.h_eps, "entrain_h_min": F.entrain_h_min,
            "fr_dep": FR_DEP, "mu_i_scale": 2.5 * MU_I_D, "mu_i_i0": MU_I_I0, "tiny": 1e-12,
            "v_max_min_depth": F.v_max_min_depth, "arrival_threshold": F.arrival_threshold, "inf": math.inf,
            "inv_dx": 1.0 / F.dx, "normal": _normal(dtype), "cfl_dx": F.cfl * F.dx, "dt_max": F.dt_max,
            "stop_ke_fraction": F.stop_ke_fraction, "cell_area": F.dx * F.dx}
    return torch.tensor([vals[k] for k in CONSTANTS], dtype=dtype, device=device)


def _normal(dtype) -> float:
    """The least denominator a guarded division takes (C_NORMAL): float32's smallest normal number on the
    fast paths, whose division and square root flush subnormal operands to zero; else 0 (every positive one)."""
    return torch.finfo(torch.float32).tiny if fp_fusion(dtype) else 0.0


def fp_fusion(dtype) -> bool:
    """Whether the kernels of ``dtype`` may fuse multiply-adds: float32 on the fast paths only (FAST_FLOAT32);
    never float64, whose every operation rounds as in the torch step."""
    return bool(FAST_FLOAT32 and dtype in (torch.float32, "fp32"))


def _block(dtype) -> int:
    """BLOCK of ``dtype`` (or INTERPRETED_BLOCK under the interpreter)."""
    if interpreted():
        return INTERPRETED_BLOCK
    return BLOCK[str(dtype).replace("torch.", "")] if isinstance(BLOCK, dict) else BLOCK


def _launch(dtype) -> dict:
    """Launch options of the line design's kernels (fused multiply-add: fp_fusion)."""
    return {"BLOCK": _block(dtype), "num_warps": NUM_WARPS, "enable_fp_fusion": fp_fusion(dtype)}


def march_shape() -> tuple[int, int]:
    """(W, BAND) of the marching kernel: MARCH, or INTERPRETED_MARCH under the interpreter."""
    return INTERPRETED_MARCH if interpreted() else MARCH


def update_shape() -> tuple[int, int]:
    """(W, BAND) of the update: UPDATE, or INTERPRETED_UPDATE under the interpreter."""
    return INTERPRETED_UPDATE if interpreted() else UPDATE


@functools.lru_cache(maxsize=None)
def multiprocessors(device: torch.device) -> int | None:
    """The streaming multiprocessors of a CUDA ``device`` (read from the driver once per device: band asks at
    every stage); None on any other device."""
    if device.type != "cuda":
        return None
    return torch.cuda.get_device_properties(device).multi_processor_count


def band(shape: tuple[int, int], B: int, ny: int, nx: int, owned: int, device) -> int:
    """The rows a marching program walks: BAND of ``shape`` (W, BAND), halved (down to 8) while the launch would
    have fewer than PROGRAMS_PER_SM programs per multiprocessor of the CUDA device (a longer band shares its
    start-up over more rows; more bands give a small batch programs for the whole card); BAND itself off CUDA.
    ``owned``: columns per strip."""
    rows = shape[1]
    sms = multiprocessors(torch.device(device))
    if sms is None:
        return rows
    strips = (nx + 1 + owned - 1) // owned
    while rows > 8 and B * strips * ((ny + rows - 1) // rows) < PROGRAMS_PER_SM * sms:
        rows //= 2
    return rows


def _stride(t: torch.Tensor) -> int:
    """Member stride of a (1 or B, ...) field: 0 when one field serves every member."""
    return 0 if t.shape[0] == 1 else t[0].numel()


def geometry_record(geo, g: float) -> torch.Tensor:
    """Per cell (z_x, z_y, cos, g cos^2, 1 / cos, g cos, 0, 0) of the geometry ``geo``, (1 or B, ny, nx, 8): what
    the kernels read of a cell's bed, one address for all of it (g cos is the torch step's g_n, the same bits)."""
    zero = torch.zeros_like(geo.cs)
    return torch.stack([geo.zx, geo.zy, geo.cs, geo.gc2, geo.sec, g * geo.cs, zero, zero], dim=-1).contiguous()


def _faces_stride(t: torch.Tensor) -> int:
    """Member stride in faces (or cells) of a (1 or B, ..., k) field interleaved in k: 0 for one field of every member."""
    return 0 if t.shape[0] == 1 else t[0].numel() // t.shape[-1]


def padded_bed(geo) -> torch.Tensor:
    """The bed padded with two ghost cells on each side of both axes, (1 or B, ny + 4, nx + 4): the ghost
    columns of the rows as the x sweep pads them, the ghost rows of the columns as the y sweep does
    (scheme.bed_terms); the four corners, which no face reads, 0."""
    zpx, zpy = geo.beds[0][0], geo.beds[1][0]
    n, ny, nx = zpy.shape[0], zpy.shape[1] - 4, zpx.shape[2] - 4
    zpp = torch.zeros((n, ny + 4, nx + 4), dtype=zpx.dtype, device=zpx.device)
    zpp[:, 2:ny + 2, :] = zpx
    zpp[:, :, 2:nx + 2] = zpy
    return zpp


def _outputs(h):
    """The faces' outputs of a stage: x faces (B, ny, nx + 1, 4) and y faces (B, ny + 1, nx, 4), each (Fh, Fqn,
    Fqt, phi), and per cell (B, ny, nx, 4) (out, mx, my, sigma), interleaved."""
    B, ny, nx = h.shape
    return (torch.empty((B, ny, nx + 1, 4), dtype=h.dtype, device=h.device),
            torch.empty((B, ny + 1, nx, 4), dtype=h.dtype, device=h.device),
            torch.empty((B, ny, nx, 4), dtype=h.dtype, device=h.device))


def _faces_march(h, hu, hv, geo, fields, inside, pm, c, F, cfl: bool):
    """The faces of a stage on the marching kernel: (x faces, y faces, cells (_outputs), the largest one-sided
    speeds per program (B, programs, 2), filled with ``cfl``)."""
    B, ny, nx = h.shape
    W = march_shape()[0]
    rows = band(march_shape(), B, ny, nx, W - 4, h.device)
    zpp, gq, hold_x, hold_y = fields
    fx, fy, cell = _outputs(h)
    grid = (triton.cdiv(nx + 1, W - 4), triton.cdiv(ny, rows), B)
    amax = torch.empty((B, grid[0] * grid[1], 2), dtype=h.dtype, device=h.device)
    _march[grid](h, hu, hv, zpp, gq, hold_x, hold_y, inside, pm, c, fx, fy, cell, amax,
                 ny, nx, _stride(geo.cs), _stride(zpp), _faces_stride(hold_x), _faces_stride(hold_y),
                 NO_CREEP=F.no_creep, WALLS=F.domain == "wall", USE_EP=F.use_ep, USE_TAU=F.use_tau,
                 SLOPE=F.slope_correction, CFL=cfl, W=W, BAND=rows, UNROLL=MARCH_UNROLL, num_warps=max(1, W // 32),
                 enable_fp_fusion=fp_fusion(h.dtype))
    return fx, fy, cell, amax


def _faces_lines(h, hu, hv, geo, fields, inside, pm, c, F, cfl: bool):
    """The faces of a stage on the line kernels: as _faces_march."""
    B, ny, nx = h.shape
    zpp, gq, holds = fields[0], fields[1], fields[2:]
    launch = _launch(h.dtype)
    cells = (triton.cdiv(ny * nx, launch["BLOCK"]), B)
    u, v = torch.empty_like(h), torch.empty_like(h)
    cu, cv, sg = (torch.empty_like(h) for _ in range(3)) if F.slope_correction else (u, v, h)
    _velocities[cells](h, hu, hv, gq, c, u, v, cu, cv, sg, ny, nx, _stride(geo.cs),
                       SLOPE=F.slope_correction, **launch)
    quads = _outputs(h)
    programs = [triton.cdiv(n * m, launch["BLOCK"]) for n, m in ((ny, nx + 1), (ny + 1, nx))]
    amax = torch.zeros((B, max(programs), 2), dtype=h.dtype, device=h.device)
    halves = []
    for axis, nf in enumerate(((ny, nx + 1), (ny + 1, nx))):
        hl, hr = (torch.empty((B, *nf), dtype=h.dtype, device=h.device) for _ in range(2))
        _faces[(programs[axis], B)](h, hu, hv, u, v, cu, cv, zpp, geo.gc2, holds[axis], inside, pm, c, quads[axis], hl,
                                    hr, amax, amax.shape[1], ny, nx, _stride(zpp), _stride(geo.cs),
                                    _faces_stride(holds[axis]), AXIS=axis, NO_CREEP=F.no_creep,
                                    WALLS=F.domain == "wall", USE_EP=F.use_ep, USE_TAU=F.use_tau,
                                    SLOPE=F.slope_correction, CFL=cfl, **launch)
        halves.append((hl, hr))
    (hlx, hrx), (hly, hry) = halves
    _cells[cells](u, v, sg, zpp, gq, geo.gc2, pm, c, quads[0], hlx, hrx, quads[1], hly, hry,
                  quads[2], ny, nx, _stride(zpp), _stride(geo.cs), USE_EP=F.use_ep, SLOPE=F.slope_correction, **launch)
    return (*quads, amax)


def triton_step(F):
    """``step(S, P) -> S`` for the settings ``F`` (StepFlags; supported(F, device) must be None):
    stepping.make_step's step on the Triton kernels (same inputs and outputs), five launches: the faces and
    update of each stage and the end of the step (triton_update._end_step), nothing on the host but
    allocations."""
    moving = F.use_ent or F.use_dep
    tables: dict = {}
    held: list = [None]     # (the geometry of the last static bed, its kernels' fields), replaced whole
    held_rec: list = [None]  # (the last box's records' metric, interleaved)
    held_pm: list = [None]  # (the last working set's parameters, their (B, 11) table)

    def consts(dtype, device):
        key = (dtype, str(device))
        if key not in tables:
            tables[key] = constants(F, dtype, device)
        return tables[key]

    def params_of(P: dict, B: int) -> torch.Tensor:
        """The members' parameters (PM) as a (B, 11) table, once per working set (P is replaced with it)."""
        key = tuple(P[k] for k in PM)
        last = held_pm[0]
        if last is not None and last[1].shape[0] == B and all(a is b for a, b in zip(last[0], key)):
            return last[1]
        pm = torch.stack([P[k].reshape(-1).expand(B) for k in PM], dim=1).contiguous()
        held_pm[0] = (key, pm)
        return pm

    def rec_of(rec):
        """The records' metric (z_x, z_y, cos of the initial bed, P["rec"]) interleaved in fours, once per box."""
        last = held_rec[0]
        if last is not None and all(a is b for a, b in zip(last[0], rec)):
            return last[1]
        quad = torch.stack(list(rec) + [torch.zeros_like(rec[0])], dim=-1).contiguous()
        held_rec[0] = (rec, quad)
        return quad

    def fields_of(geo):
        """The kernels' fields of the geometry ``geo``, once per static bed (held): the padded bed zpp, the
        geometry_record, and the no-creep rule's coefficients at the x and y faces in eights (the record itself
        where the rule is off)."""
        last = held[0]
        if last is not None and last[0] is geo:
            return last[1]
        record = geometry_record(geo, F.g)
        if geo.holds is None:
            holds = (record, record)
        else:
            holds = tuple(torch.stack(list(H) + [torch.zeros_like(H.alpha)] * 2, dim=-1).contiguous()
                          for H in geo.holds)
        fields = (padded_bed(geo).contiguous(), record, *holds)
        if not moving:
            held[0] = (geo, fields)
        return fields

    def stage(state, clock, dt, pm, c, P, geo, start=None):
        """stepping._stage on the kernels: the new (h, hu, hv, z, erod, dep) and the update's sums per program (B,
        programs, 4). ``clock``: (t, t_next, active, t_end); ``dt``: (B,), written by the first stage's update
        (``start`` None), read by the second's; ``start``: for the second stage, (h, hu, hv, z, erod, dep) of
        the step's start, the records' metric and the records (h_max, v_max, arrival) and their outputs: the
        update then averages and records (COMBINE)."""
        h, hu, hv, z, erod, dep = state
        B, ny, nx = h.shape
        geo = static_geometry(z, F, P.get("mu_scale")) if geo is None else geo
        fields = fields_of(geo)
        hess = tuple(a.contiguous() for a in geo.hess) if geo.hess is not None else (fields[1],) * 3
        mus = P["mu_scale"].contiguous() if F.use_mu_scale else h
        inside = P["inside"].contiguous() if F.domain else h
        faces = _faces_march if FACES == "march" else _faces_lines
        fx, fy, cell, amax = faces(h, hu, hv, geo, fields, inside, pm, c, F, start is None)
        new = [torch.empty_like(h) for _ in range(3)]
        z_o = torch.empty_like(h) if moving else h
        e_o = torch.empty_like(h) if F.use_ent else h
        d_o = torch.empty_like(h) if F.use_dep else h
        W = update_shape()[0]
        rows = band(update_shape(), B, ny, nx, W - 2, h.device)
        grid = (triton.cdiv(nx, W - 2), triton.cdiv(ny, rows), B)
        part = torch.empty((B, grid[0] * grid[1], 4), dtype=h.dtype, device=h.device)
        some = lambda a: h if a is None else a
        if start is None:
            combine, rec, records, rec_out = (h,) * 6, h, (h,) * 3, (h,) * 3
        else:
            combine, rec, records, rec_out = start
        _update[grid](h, hu, hv, cell, some(z) if moving else h, some(erod) if F.use_ent else h,
                      some(dep) if F.use_dep else h, fx, fy, fields[1], *hess, mus, inside, pm, c, dt, amax,
                      amax.shape[1], *clock[:3], *(some(a) for a in combine), rec, *records, *new, z_o, e_o, d_o,
                      *rec_out, part, ny, nx, _stride(geo.cs), SLOPE=F.slope_correction, USE_CURV=F.use_curv,
                      USE_MU_I=F.use_mu_i, USE_ENT=F.use_ent, USE_DEP=F.use_dep, USE_MUS=F.use_mu_scale,
                      USE_TAU=F.use_tau, GONE_OUT=F.domain == "outflow", INFLOW=F.inflow, FIRST=start is None,
                      COMBINE=start is not None, W=W, BAND=rows, UNROLL=UPDATE_UNROLL, num_warps=max(1, W // 32),
                      enable_fp_fusion=fp_fusion(h.dtype))
        return (*new, z_o if moving else z, e_o if F.use_ent else erod, d_o if F.use_dep else dep), part

    def step(S: dict, P: dict) -> dict:
        state = tuple(S[k] if S[k] is None else S[k].contiguous() for k in ("h", "hu", "hv", "z", "erod", "dep"))
        h = state[0]
        B = h.shape[0]
        c = consts(h.dtype, h.device)
        pm = params_of(P, B)
        clock = (S["t"].contiguous(), S["t_next"].contiguous(), S["active"].contiguous(), P["t_end"])
        geo = None if moving else (P["geo"] if "geo" in P else static_geometry(state[3], F, P.get("mu_scale")))
        dt = torch.empty_like(clock[0])
        first, part1 = stage(state, clock, dt, pm, c, P, geo)
        records = tuple(S[k].contiguous() for k in ("h_max", "v_max", "arrival"))
        rec_out = tuple(torch.empty_like(h) for _ in range(3))
        final, part2 = stage(first, clock, dt, pm, c, P, geo, start=(state, rec_of(P["rec"]), records, rec_out))
        ends = {k: torch.empty_like(S[k]) for k in ("t", "outflow", "ke_peak", "active", "failed", "stopped", "steps")}
        ends.update(ke=torch.empty_like(dt), mass=torch.empty_like(dt), hit=torch.empty_like(S["active"]))
        _end_step[(B,)](part1, part2, part1.shape[1], dt, *clock, S["outflow"].contiguous(),
                        S["ke_peak"].contiguous(), S["failed"].contiguous(), S["stopped"].contiguous(),
                        S["steps"].contiguous(), c, ends["t"], ends["outflow"], ends["ke"], ends["mass"],
                        ends["ke_peak"], ends["hit"], ends["active"], ends["failed"], ends["stopped"], ends["steps"],
                        GONE_OUT=F.domain == "outflow", STOP_AT_REST=F.stop_ke_fraction > 0, W=32, num_warps=1)
        out = dict(S)
        out.update(h=final[0], hu=final[1], hv=final[2], h_max=rec_out[0], v_max=rec_out[1], arrival=rec_out[2],
                   dt=dt, **ends)
        if moving:
            out["z"] = final[3]
        if F.use_ent:
            out["erod"] = final[4]
        if F.use_dep:
            out["dep"] = final[5]
        return out

    return step
