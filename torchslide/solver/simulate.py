"""``simulate``: validate inputs, run all members with per-member time steps, fill a SimulationResult."""
from __future__ import annotations

import math
import time
import warnings
from dataclasses import dataclass
from typing import Sequence

import numpy as np
import torch

from ..physics import G, Params, earth_pressure_sh
from ..result import GaugeSeries, SimulationResult
from ..terrain.grid import DEM
from . import crop as _crop
from .config import SolverConfig
from .friction import desingularised_velocity
from .graphs import StepGraphs
from .stepping import StepFlags, make_step, static_geometry, surface_geometry
from .stop import QuietWatch

Tensor = torch.Tensor

# per-member entries of the state dict (first dimension = member); "z" only when the bed evolves
_MEMBER_KEYS = ("h", "hu", "hv", "outflow", "t", "t_next", "k_out", "active", "ke_peak", "h_max", "v_max",
                "arrival", "steps", "ke", "mass", "hit", "dt", "failed", "stopped",
                "g_h", "g_u", "g_v", "g_w", "mass_hist", "ke_hist")

THICKNESS = ("normal", "vertical")
"""Conventions of an input thickness: normal to the slope (the field's, default) or vertical."""

_STEP_CACHE: dict = {}


def _as_tensor(x, name: str, dtype, device) -> Tensor:
    try:
        t = x.detach().to(device=device, dtype=dtype) if isinstance(x, Tensor) else \
            torch.as_tensor(np.asarray(x, dtype=np.float64), dtype=dtype, device=device)
    except (TypeError, ValueError) as e:
        raise ValueError(f"{name} could not be converted to a tensor: {e}") from e
    return t


def _check_raster(t: Tensor, name: str, shape: tuple[int, int], allow_batch: bool, positive: bool = False) -> None:
    ok = (t.ndim == 2 and tuple(t.shape) == shape) or (allow_batch and t.ndim == 3 and tuple(t.shape[1:]) == shape)
    if not ok:
        want = f"{shape}" + (f" or (B, {shape[0]}, {shape[1]})" if allow_batch else "")
        raise ValueError(f"{name} has shape {tuple(t.shape)}, expected {want} (the DEM grid)")
    bad = ~torch.isfinite(t)
    if bool(bad.any()):
        idx = tuple(int(i) for i in torch.nonzero(bad)[0])
        raise ValueError(f"{name} has {int(bad.sum())} non-finite values, first at index {idx}: {float(t[idx])}")
    neg = (t <= 0) if positive else (t < 0)
    if bool(neg.any()):
        idx = tuple(int(i) for i in torch.nonzero(neg)[0])
        rule = "> 0" if positive else ">= 0"
        raise ValueError(f"{name} must be {rule} everywhere, got {float(t[idx])} at index {idx}")


def kernel_that_runs(F: StepFlags, kernel: str, device="cpu") -> str:
    """The step implementation a call with ``kernel`` (SolverConfig.kernel) runs on ``device``: "fused-cpu"
    (numba), "fused-triton", "compiled" or "eager". Asked for "fused" where neither fused step runs, it
    warns once per process, naming the slower step and how to get the fast one."""
    from . import fused_cpu, fused_triton

    if kernel != "fused":
        return kernel
    if fused_triton.supported(F, device) is None:
        return "fused-triton"
    why = fused_cpu.supported(F, device)
    if why is None:
        return "fused-cpu"
    if torch.device(device).type == "cpu" and why not in _WARNED:
        _WARNED.add(why)
        warnings.warn(f"torchslide: the fused CPU step is not available ({why}); running the torch step, "
                      "about 3 times slower (pip install numba)", RuntimeWarning, stacklevel=3)
    return "eager"


_WARNED: set = set()


def _get_step(F: StepFlags, kernel: str, device="cpu"):
    """``advance(S, P, out_times, gidx, gin)``: one time step and its output record (_record): the torch
    step (stepping.make_step), compiled with its record when ``kernel`` is "compiled" (one compiled call
    per step), or when ``kernel`` is "fused" the Triton step (fused_triton: CUDA, or any device under
    TRITON_INTERPRET=1) or else the fused CPU step (fused_cpu), where they run."""
    from . import fused_cpu, fused_triton

    fused = {"fused-triton": "triton", "fused-cpu": "cpu"}.get(kernel_that_runs(F, kernel, device), "")
    compile_ = kernel == "compiled"
    key = (F, compile_, fused)
    fn = _STEP_CACHE.get(key)
    if fn is None:
        step = {"triton": fused_triton.triton_step, "cpu": fused_cpu.fused_step}.get(fused, make_step)(F)

        def advance(S: dict, P: dict, out_times: Tensor, gidx: Tensor, gin: Tensor) -> dict:
            return _record(step(S, P), out_times, gidx, F.h_eps, out_times.shape[0], P["rec"], gin)

        fn = _with_recompile_limit(torch.compile(advance, dynamic=True)) if compile_ else advance
        _STEP_CACHE[key] = fn
    return fn


# torch.compile keeps one cache per code object: every solver configuration (StepFlags: terms,
# stop rule) and batch size 1 vs > 1 is a separate entry of the same ``advance``; a process that runs
# several configurations would pass dynamo's default limit of 8 and silently fall back to eager.
_RECOMPILE_LIMIT = 64


def _with_recompile_limit(compiled):
    import torch._dynamo as dynamo

    name = "recompile_limit" if hasattr(dynamo.config, "recompile_limit") else "cache_size_limit"

    def call(*args):
        with dynamo.config.patch(**{name: max(_RECOMPILE_LIMIT, getattr(dynamo.config, name))}):
            return compiled(*args)

    return call


def _record(S: dict, out_times: Tensor, gidx: Tensor, h_eps: float, K: int, rec: tuple,
            gin: Tensor | None = None) -> dict:
    """Write the current state into output slot k_out of members that just reached an output time.

    gidx: (G,) flat gauge indices into the (cropped) rasters of S; rec: (z_x, z_y, cos theta) rasters
    of the same window; gin: (G,) bool, gauge inside the cropped window (outside it the flow has never
    been: the gauge reads 0); None = all inside. Gauges record the normal thickness and the velocity
    along the surface (u, v, w = z_x u + z_y v).
    """
    hit = S["hit"]
    k = S["k_out"].clamp(max=K - 1)
    S = dict(S)
    if gidx.numel() > 0:
        hf = S["h"].flatten(1)[:, gidx]
        hu = S["hu"].flatten(1)[:, gidx]
        hv = S["hv"].flatten(1)[:, gidx]
        if gin is not None:
            hf, hu, hv = (torch.where(gin, x, torch.zeros_like(x)) for x in (hf, hu, hv))
        uf = desingularised_velocity(hf, hu, h_eps)
        vf = desingularised_velocity(hf, hv, h_eps)
        zx, zy, cs = (r.expand(1, *r.shape[-2:]).flatten(1)[:, gidx] for r in rec)
        kg = k.view(-1, 1, 1).expand(-1, gidx.numel(), 1)
        for key, val in (("g_h", cs * hf), ("g_u", uf), ("g_v", vf), ("g_w", zx * uf + zy * vf)):
            cur = S[key].gather(2, kg)
            S[key] = S[key].scatter(2, kg, torch.where(hit.view(-1, 1, 1), val.unsqueeze(2), cur))
    kk = k.view(-1, 1)
    for key, val in (("mass_hist", S["mass"]), ("ke_hist", S["ke"])):
        cur = S[key].gather(1, kk)
        S[key] = S[key].scatter(1, kk, torch.where(hit.view(-1, 1), val.view(-1, 1), cur))
    S["k_out"] = S["k_out"] + hit.to(S["k_out"].dtype)
    S["t_next"] = out_times[S["k_out"].clamp(max=K - 1)]
    return S


def simulate(dem: DEM, release, params: Params, *, t_end: float,
             gauges: Sequence[tuple[str, float, float]] | None = None,
             config: SolverConfig | None = None, erodible_depth=None, mu_scale=None,
             dtype: torch.dtype = torch.float64, device: str | torch.device = "cpu",
             progress: bool = False, thickness: str = "normal") -> SimulationResult:
    """Run B members (one per parameter set) from a release on a DEM until t_end or until they stop.

    Args:
        dem: terrain (z (ny, nx), cellsize m).
        release: (ny, nx) shared or (B, ny, nx) initial flow thickness, m (>= 0, finite), measured
            as ``thickness`` says.
        params: B parameter sets (torchslide.physics.Params).
        t_end: end time, s (> 0).
        gauges: (name, x, y) map points sampled every ``config.output_interval`` s.
        config: numerical settings (SolverConfig()).
        erodible_depth: (ny, nx) erodible bed depth, m, for entrainment (kappa > 0), measured as
            ``thickness`` says.
        mu_scale: (ny, nx) per-cell friction multiplier (> 0) applied to mu.
        dtype, device: where the run happens (float64 default; float32 allowed).
        progress: show a tqdm bar of the slowest member's time.
        thickness: "normal" (default, the field's convention: thickness normal to the slope) or
            "vertical" (thickness along the vertical, i.e. volume per unit map area).
    Returns:
        SimulationResult (see torchslide.result); failed members are flagged, never silent.
    """
    t0_wall = time.perf_counter()
    cfg = config or SolverConfig()
    cfg.validate()
    _check_call(dem, params, dtype, t_end, thickness)
    device = torch.device(device)
    params.validate()
    P0 = params.to(device=device, dtype=dtype)
    z0 = torch.as_tensor(dem.z, dtype=dtype, device=device).unsqueeze(0)
    metric = surface_geometry(z0, float(dem.cellsize), cfg.slope_correction, False)[:3]
    inp = _inputs(dem, release, P0, erodible_depth, mu_scale, gauges, dtype, device, metric, thickness)
    F = _step_flags(cfg, P0, inp, float(dem.cellsize))
    out_times = _output_times(t_end, cfg.output_interval, dtype, device)
    S = _initial_state(inp, P0.B, dem, out_times, cfg, dtype, device)
    release_volume = S["mass"].clone()
    h_release = inp.h0.clone()      # the steps may reuse the initial state's storage
    S, exceeded = _run(S, P0, inp, F, cfg, out_times, t_end, progress)
    res = _result(S, exceeded, P0, inp, dem, out_times, release_volume, cfg, time.perf_counter() - t0_wall,
                  h_release)
    res.kernel = kernel_that_runs(F, "compiled" if cfg.compile else cfg.kernel, device)
    return res


def _check_call(dem: DEM, params: Params, dtype: torch.dtype, t_end: float, thickness: str) -> None:
    if thickness not in THICKNESS:
        raise ValueError(f"thickness must be one of {THICKNESS} (the convention of the release and "
                         f"erodible depths), got {thickness!r}")
    if not isinstance(dem, DEM):
        raise ValueError(f"dem must be a torchslide.terrain.DEM, got {type(dem).__name__}")
    if not isinstance(params, Params):
        raise ValueError(f"params must be a torchslide.physics.Params, got {type(params).__name__}")
    if dtype not in (torch.float32, torch.float64):
        raise ValueError(f"dtype must be torch.float32 or torch.float64, got {dtype}")
    if not (isinstance(t_end, (int, float)) and math.isfinite(t_end) and t_end > 0):
        raise ValueError(f"t_end must be a finite number of seconds > 0, got {t_end!r}")


@dataclass
class _Inputs:
    """The checked rasters and gauges of a call: h0 (B, ny, nx) and erod0 (ny, nx) or None, per unit
    map area (vertical thickness), m; mu_scale (ny, nx) or None; gauges [(name, x, y)] and their flat
    cell indices; use_ent / use_dep: some member entrains / deposits (the bed then evolves);
    metric: (z_x, z_y, cos theta) of the DEM, each (1, ny, nx)."""

    h0: Tensor
    erod0: Tensor | None
    mu_scale: Tensor | None
    gauges: list
    gidx: list
    use_ent: bool
    use_dep: bool
    metric: tuple
    inside: Tensor | None = None

    @property
    def evolve(self) -> bool:
        return self.use_ent or self.use_dep


def _inputs(dem: DEM, release, P0: Params, erodible_depth, mu_scale, gauges, dtype, device, metric: tuple,
            thickness: str) -> _Inputs:
    """Convert and check the rasters and gauges (ValueError naming the input and the value); a
    thickness normal to the slope becomes the thickness per unit map area h / cos(theta)."""
    per_map_area = metric[2].squeeze(0) if thickness == "normal" else torch.ones_like(metric[2].squeeze(0))
    B = P0.B
    ny, nx = dem.shape
    rel = _as_tensor(release, "release", dtype, device)
    _check_raster(rel, "release", (ny, nx), allow_batch=True)
    if rel.ndim == 3 and rel.shape[0] != B:
        raise ValueError(f"release has {rel.shape[0]} members (shape {tuple(rel.shape)}) but params has B = {B}")
    h0 = (rel.expand(B, ny, nx) if rel.ndim == 2 else rel) / per_map_area
    if bool((P0.release_scale != 0).any()):     # Params.release_scale (0: the release as given, bitwise)
        h0 = h0 * (1.0 + P0.release_scale.to(dtype=dtype, device=device)).view(B, 1, 1)
    use_ent = bool((P0.kappa > 0).any())
    erod0 = None
    if erodible_depth is not None:
        erod0 = _as_tensor(erodible_depth, "erodible_depth", dtype, device)
        _check_raster(erod0, "erodible_depth", (ny, nx), allow_batch=False)
        erod0 = erod0 / per_map_area
    elif use_ent:
        b = int(torch.nonzero(P0.kappa > 0)[0])
        raise ValueError(f"parameter kappa[{b}] = {float(P0.kappa[b])} > 0 needs an erodible_depth raster")
    ms = None
    if mu_scale is not None:
        ms = _as_tensor(mu_scale, "mu_scale", dtype, device)
        _check_raster(ms, "mu_scale", (ny, nx), allow_batch=False, positive=True)
    gauge_list = list(gauges or [])
    gidx, names = [], []
    for gg in gauge_list:
        if len(gg) != 3:
            raise ValueError(f"gauge entries must be (name, x, y), got {gg!r}")
        name, gx, gy = gg
        i, j = dem.index(float(gx), float(gy), what=f"gauge {name!r}")
        gidx.append(i * nx + j)
        names.append(str(name))
    if len(set(names)) != len(names):
        raise ValueError(f"gauge names must be unique, got {names}")
    inside = None
    if dem.outside is not None:
        outside = torch.as_tensor(dem.outside, device=device)
        bad = outside & (h0 > 0).any(dim=0)
        if bool(bad.any()):
            i, j = (int(v) for v in torch.nonzero(bad)[0])
            x, y = dem.cell_centre(i, j)
            raise ValueError(f"release covers {int(bad.sum())} cells outside the DEM's domain (nodata), first at "
                             f"row {i} from the south, col {j} (x={x:g} m, y={y:g} m)")
        for name, k in zip(names, gidx):
            if bool(outside.flatten()[k]):
                raise ValueError(f"gauge {name!r} lies in a cell outside the DEM's domain (nodata)")
        if erod0 is not None:
            erod0 = torch.where(outside, torch.zeros_like(erod0), erod0)
        inside = (~outside).unsqueeze(0)
    return _Inputs(h0, erod0, ms, gauge_list, gidx, use_ent, bool((P0.deposition > 0).any()), metric, inside)


def _step_flags(cfg: SolverConfig, P0: Params, inp: _Inputs, dx: float) -> StepFlags:
    """The step's static settings: the numerical ones and which terms any member switches on."""
    return StepFlags(
        dx=dx, g=G, cfl=cfg.cfl, theta=cfg.limiter_theta, h_eps=cfg.h_eps, h_wet=cfg.h_wet, wb_ratio=cfg.wb_depth_ratio,
        dt_max=cfg.dt_max, stop_ke_fraction=cfg.stop_ke_fraction,
        arrival_threshold=cfg.arrival_threshold, v_max_min_depth=cfg.v_max_min_depth, entrain_h_min=cfg.entrain_h_min,
        no_creep=cfg.no_creep, slope_correction=cfg.slope_correction,
        use_ep=bool((P0.earth_pressure > 0).any()), use_curv=bool((P0.curvature > 0).any()),
        use_tau=bool((P0.tau_y != 0).any()),
        use_ent=inp.use_ent, use_dep=inp.use_dep, use_mu_i=bool((P0.mu_i > 0).any()),
        use_mu_scale=inp.mu_scale is not None, inflow=cfg.boundary == "open",
        domain="" if inp.inside is None else cfg.nodata)


def _output_times(t_end: float, interval: float, dtype, device) -> Tensor:
    """(K,) output times 0, interval, ..., t_end (the last one exactly t_end), s."""
    times = list(np.arange(0.0, t_end, interval))
    if not times or t_end - times[-1] > 1e-9 * max(1.0, t_end):
        times.append(float(t_end))
    else:
        times[-1] = float(t_end)
    return torch.tensor(times, dtype=dtype, device=device)


def _initial_state(inp: _Inputs, B: int, dem: DEM, out_times: Tensor, cfg: SolverConfig, dtype, device) -> dict:
    """The state dict at t = 0 (per-member entries first-dimension B), output slot 0 recorded."""
    h0 = inp.h0
    ny, nx = dem.shape
    evolve = inp.evolve
    K, G_ = out_times.shape[0], len(inp.gidx)
    z0 = torch.as_tensor(dem.z, dtype=dtype, device=device).unsqueeze(0)
    zeros_b = torch.zeros(B, dtype=dtype, device=device)
    cell_area = float(dem.cellsize) ** 2
    S = {
        "h": h0, "hu": torch.zeros_like(h0), "hv": torch.zeros_like(h0),
        "z": z0.expand(B, ny, nx).clone() if evolve else z0,
        "erod": inp.erod0.expand(B, ny, nx).clone() if inp.use_ent else None,
        "dep": torch.zeros_like(h0) if inp.use_dep else None,
        "outflow": zeros_b.clone(), "t": zeros_b.clone(),
        "t_next": out_times[min(1, K - 1)].expand(B).clone(),
        "k_out": torch.zeros(B, dtype=torch.long, device=device),
        "active": torch.ones(B, dtype=torch.bool, device=device),
        "ke_peak": zeros_b.clone(),
        "h_max": h0 * inp.metric[2], "v_max": torch.zeros_like(h0),
        "arrival": torch.where(h0 * inp.metric[2] > cfg.arrival_threshold, torch.zeros_like(h0),
                               torch.full_like(h0, math.inf)),
        "steps": torch.zeros(B, dtype=torch.long, device=device),
        "ke": zeros_b.clone(), "mass": h0.sum(dim=(1, 2)) * cell_area,
        "hit": torch.ones(B, dtype=torch.bool, device=device), "dt": zeros_b.clone(),
        "failed": torch.zeros(B, dtype=torch.bool, device=device),
        "stopped": torch.zeros(B, dtype=torch.bool, device=device),
        "g_h": torch.zeros(B, G_, K, dtype=dtype, device=device),
        "g_u": torch.zeros(B, G_, K, dtype=dtype, device=device),
        "g_v": torch.zeros(B, G_, K, dtype=dtype, device=device),
        "g_w": torch.zeros(B, G_, K, dtype=dtype, device=device),
        "mass_hist": torch.zeros(B, K, dtype=dtype, device=device),
        "ke_hist": torch.zeros(B, K, dtype=dtype, device=device),
    }
    # slot 0 = the initial state
    S = _record(S, out_times, torch.tensor(inp.gidx, dtype=torch.long, device=device), cfg.h_eps, K, inp.metric)
    S["hit"] = torch.zeros(B, dtype=torch.bool, device=device)
    return S


def _member_params(P0: Params, inp: _Inputs, t_end: float) -> tuple[dict, dict]:
    """(per-member parameters as (B, 1, 1) tensors with the Savage-Hutter k_act, k_pass; the shared
    inputs: mu_scale (1, ny, nx) or None and t_end as a tensor, so a compiled step serves any end time)."""
    B = P0.B
    Pm = {n: t.view(B, 1, 1) for n, t in P0.as_dict().items()}
    phi = torch.where(torch.isnan(P0.phi_int), torch.full_like(P0.phi_int, 45.0), P0.phi_int)
    k_act, k_pass = earth_pressure_sh(phi, P0.mu)
    Pm["k_act"], Pm["k_pass"] = k_act.view(B, 1, 1), k_pass.view(B, 1, 1)
    shared = {"mu_scale": inp.mu_scale.unsqueeze(0) if inp.mu_scale is not None else None,
              "t_end": torch.tensor(float(t_end), dtype=P0.mu.dtype, device=P0.mu.device)}
    return Pm, shared


def _run(S: dict, P0: Params, inp: _Inputs, F: StepFlags, cfg: SolverConfig, out_times: Tensor, t_end: float,
         progress: bool) -> tuple[dict, Tensor]:
    """Step every member until it ends: the steps run on the bounding box of the cells the flow has
    touched (torchslide.solver.crop), members that ended leave the batch (``cfg.compact``), the host
    checks every ``cfg.check_every`` steps. Returns (the final state, (B,) bool: max_steps exceeded)."""
    B = P0.B
    ny, nx = S["h"].shape[1:]
    device = S["h"].device
    step = _get_step(F, "compiled" if cfg.compile else cfg.kernel, device)
    Pm, shared = _member_params(P0, inp, t_end)
    gidx = torch.tensor(inp.gidx, dtype=torch.long, device=device)
    member_keys = list(_MEMBER_KEYS) + (["z"] if inp.evolve else []) + (["erod"] if inp.use_ent else []) \
        + (["dep"] if inp.use_dep else [])
    full = S
    idx = torch.arange(B, device=device)
    work = dict(S)
    Pw = dict(Pm, **shared)
    exceeded = torch.zeros(B, dtype=torch.bool, device=device)
    g_rows = torch.div(gidx, nx, rounding_mode="floor")
    g_cols = gidx - g_rows * nx
    margin = 2 * cfg.crop_every + 3

    def enter(state: dict, b: _crop.Box):
        sub_ = _crop.extract(state, b, ny, nx)
        P_ = dict(Pw)
        if P_.get("mu_scale") is not None and not b.covers(ny, nx):
            P_["mu_scale"] = P_["mu_scale"][:, b.r0:b.r1, b.c0:b.c1].contiguous()
        P_["rec"] = tuple(m[:, b.r0:b.r1, b.c0:b.c1].contiguous() for m in inp.metric)
        if inp.inside is not None:
            P_["inside"] = inp.inside[:, b.r0:b.r1, b.c0:b.c1].contiguous()
        if not inp.evolve:  # the bed terms of this box, once (not once per step)
            P_["geo"] = static_geometry(sub_["z"], F, P_.get("mu_scale"))
        gi_, gin_ = _crop.gauge_index(g_rows, g_cols, b)
        return sub_, P_, gi_, gin_

    graphs = cfg.cuda_graphs and device.type == "cuda" and not cfg.compile and cfg.kernel != "compiled"

    def new_chunks():
        """CUDA graphs for the current working set (None: steps launched one by one)."""
        return StepGraphs(step, (Psub, out_times, gsub, gin)) if graphs else None

    def advance(state: dict, n: int) -> dict:
        """n steps of the working set (replayed as a CUDA graph where ``graphs``)."""
        if chunks is not None:
            return chunks.run(state, n)
        for _ in range(n):
            state = step(state, Psub, out_times, gsub, gin)
        return state

    bar = None
    if progress:
        from tqdm.auto import tqdm
        bar = tqdm(total=float(t_end), unit="s", desc=f"simulate {B} member{'s' if B > 1 else ''}", leave=False,
                   bar_format="{desc}: {percentage:3.0f}%|{bar}| {n:.0f}/{total:.0f} s simulated [{elapsed}{postfix}]")
    box = _crop.grow(work["h"], None, ny, nx, margin) if cfg.crop else _crop.full_box(ny, nx)
    sub, Psub, gsub, gin = enter(work, box)
    chunks = new_chunks()
    watch = QuietWatch(cfg, work["h"])
    while True:
        s_ = 0
        while s_ < cfg.check_every:     # chunks of steps between the host's looks at the box
            n = cfg.check_every - s_
            if cfg.crop and not box.covers(ny, nx):
                n = min(n, cfg.crop_every)
                nbox = _crop.grow(sub["h"], box, ny, nx, margin)
                if nbox != box:
                    _crop.write_back(work, sub, box, ny, nx, member_keys)
                    box = nbox
                    sub, Psub, gsub, gin = enter(work, box)
                    chunks = new_chunks()
            sub = advance(sub, n)
            s_ += n
        # the checks below need only the per-member scalars; rasters go back at compaction / the end
        work.update({k: v for k, v in sub.items() if k not in _crop.SPATIAL})
        act = work["active"]
        over = act & (work["steps"] >= cfg.max_steps)
        if bool(over.any()):
            exceeded[idx[over]] = True
            work["active"] = act & ~over
            sub["active"] = work["active"]
            act = work["active"]
        quiet = watch.quiet(work, sub, box) & act
        if bool(quiet.any()):
            work["stopped"] = work["stopped"] | quiet
            work["active"] = act & ~quiet
            sub["active"], sub["stopped"] = work["active"], work["stopped"]
            act = work["active"]
        n_act = int(act.sum())
        if bar is not None:
            bar.n = round(float(work["t"][act].min()) if n_act else float(t_end), 3)
            bar.set_postfix(active=n_act, refresh=False)
            bar.refresh()
        if n_act == 0:
            _crop.write_back(work, sub, box, ny, nx, member_keys)
            break
        if cfg.compact and n_act < idx.numel():
            _crop.write_back(work, sub, box, ny, nx, member_keys)
            _scatter(full, work, idx, member_keys)
            idx = idx[act]
            watch.keep(act)
            work = {k: (v[act] if k in member_keys else v) for k, v in work.items()}
            Pw = dict({k: v[idx] for k, v in Pm.items()}, **shared)
            sub, Psub, gsub, gin = enter(work, box)
            chunks = new_chunks()
    _scatter(full, work, idx, member_keys)
    if bar is not None:
        bar.n = float(t_end)
        bar.close()
    return full, exceeded


def _scatter(full: dict, work: dict, idx: Tensor, member_keys: list) -> None:
    """Write the members ``idx`` of the compacted state ``work`` back into ``full``."""
    for k in member_keys:
        if work[k] is not full[k] and full[k].numel():  # empty (no gauges): nothing to copy
            full[k][idx] = work[k]


def _result(S: dict, exceeded: Tensor, P0: Params, inp: _Inputs, dem: DEM, out_times: Tensor,
            release_volume: Tensor, cfg: SolverConfig, runtime_s: float, h_release: Tensor) -> SimulationResult:
    """The SimulationResult of the final state: samples after a member ended repeat its final state."""
    B, ny, nx = S["h"].shape
    K = out_times.shape[0]
    map_area = float(dem.cellsize) ** 2
    zx, zy, cs = (m.squeeze(0) for m in inp.metric)
    after = torch.arange(K, device=out_times.device).view(1, K) >= S["k_out"].view(B, 1)
    uF = desingularised_velocity(S["h"], S["hu"], cfg.h_eps)
    vF = desingularised_velocity(S["h"], S["hv"], cfg.h_eps)
    wF = zx * uF + zy * vF
    S["mass_hist"] = torch.where(after, S["mass"].view(B, 1), S["mass_hist"])
    S["ke_hist"] = torch.where(after, S["ke"].view(B, 1), S["ke_hist"])
    gauges_out: dict[str, GaugeSeries] = {}
    for gi, (name, gx, gy) in enumerate(inp.gauges):
        fi = inp.gidx[gi]
        final = {"g_h": (cs * S["h"]).flatten(1), "g_u": uF.flatten(1), "g_v": vF.flatten(1), "g_w": wF.flatten(1)}
        gh, gu, gv, gw = (torch.where(after, final[k][:, fi].view(B, 1), S[k][:, gi]) for k in ("g_h", "g_u", "g_v", "g_w"))
        gauges_out[str(name)] = GaugeSeries(str(name), float(gx), float(gy), out_times, gh, gu, gv, gw)
    per_map = S["h"] + S["dep"] if inp.use_dep else S["h"]
    h_final = cs * per_map
    if inp.use_ent:
        entrained = (inp.erod0.unsqueeze(0) - S["erod"]).sum(dim=(1, 2)) * map_area
    else:
        entrained = torch.zeros_like(release_volume)
    z0 = torch.as_tensor(dem.z, dtype=S["h"].dtype, device=S["h"].device).unsqueeze(0)
    bed_change = S["z"] - z0 if inp.evolve else (torch.zeros_like(inp.h0) if inp.erod0 is not None else None)
    return SimulationResult(
        dem=dem, h_max=S["h_max"], v_max=S["v_max"], h_final=h_final, arrival_time=S["arrival"],
        cell_area=map_area / cs, map_cell_area=map_area,
        release_volume=release_volume, final_volume=per_map.sum(dim=(1, 2)) * map_area, outflow_volume=S["outflow"],
        entrained_volume=entrained, steps=S["steps"], t_final=S["t"], stopped=S["stopped"],
        history_t=out_times, mass_history=S["mass_hist"], ke_history=S["ke_hist"], gauges=gauges_out,
        bed_change=bed_change, runtime_s=runtime_s, params=P0.as_dict(),
        failed=S["failed"] | exceeded, failure_reason=_failure_reasons(S, exceeded, P0, cfg),
        elevation_change=(S["z"] - z0 if inp.evolve else 0.0) + S["h"] - h_release)


def _failure_reasons(S: dict, exceeded: Tensor, P0: Params, cfg: SolverConfig) -> list:
    reasons: list[str | None] = []
    for b in range(P0.B):
        if bool(S["failed"][b]):
            reasons.append(f"non-finite state (NaN/inf) at t={float(S['t'][b]):.4g} s after "
                           f"{int(S['steps'][b])} steps (mu={float(P0.mu[b]):.4g}, xi={float(P0.xi[b]):.4g})")
        elif bool(exceeded[b]):
            reasons.append(f"exceeded max_steps={cfg.max_steps} at t={float(S['t'][b]):.4g} s")
        else:
            reasons.append(None)
    return reasons
