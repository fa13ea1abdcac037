"""``simulate``: validate inputs, run all members with per-member time steps, fill a SimulationResult."""
from __future__ import annotations

import math
import time
from typing import Sequence

import numpy as np
import torch

from ..physics import G, Params, earth_pressure_sh
from ..result import GaugeSeries, SimulationResult
from ..terrain.grid import DEM
from . import crop as _crop
from .config import SolverConfig
from .friction import desingularised_velocity
from .stepping import StepFlags, make_step, static_geometry

Tensor = torch.Tensor

# per-member entries of the state dict (first dimension = member); "z" only when the bed evolves
_MEMBER_KEYS = ("h", "hu", "hv", "outflow", "t", "t_next", "k_out", "active", "ke_peak", "h_max", "v_max",
                "arrival", "steps", "ke", "mass", "hit", "dt", "failed", "stopped",
                "g_h", "g_u", "g_v", "mass_hist", "ke_hist")

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


def _get_step(F: StepFlags, compile_: bool):
    """``advance(S, P, out_times, gidx, gin)``: one time step (stepping.make_step) and its output
    record (_record), compiled together when ``compile_`` (one compiled call per step)."""
    key = (F, compile_)
    fn = _STEP_CACHE.get(key)
    if fn is None:
        step = make_step(F)

        def advance(S: dict, P: dict, out_times: Tensor, gidx: Tensor, gin: Tensor) -> dict:
            return _record(step(S, P), out_times, gidx, F.h_eps, out_times.shape[0], gin)

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


def _record(S: dict, out_times: Tensor, gidx: Tensor, h_eps: float, K: int, gin: Tensor | None = None) -> dict:
    """Write the current state into output slot k_out of members that just reached an output time.

    gidx: (G,) flat gauge indices into the (cropped) rasters of S; gin: (G,) bool, gauge inside the
    cropped window (outside it the flow has never been: the gauge reads 0); None = all inside.
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
        kg = k.view(-1, 1, 1).expand(-1, gidx.numel(), 1)
        for key, val in (("g_h", hf), ("g_u", uf), ("g_v", vf)):
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
             progress: bool = False) -> SimulationResult:
    """Run B members (one per parameter set) from a release on a DEM until t_end or until they stop.

    Args:
        dem: terrain (z (ny, nx), cellsize m).
        release: (ny, nx) shared or (B, ny, nx) initial flow thickness, m (>= 0, finite).
        params: B parameter sets (torchslide.physics.Params).
        t_end: end time, s (> 0).
        gauges: (name, x, y) map points sampled every ``config.output_interval`` s.
        config: numerical settings (SolverConfig()).
        erodible_depth: (ny, nx) erodible bed depth, m, for entrainment (kappa > 0).
        mu_scale: (ny, nx) per-cell friction multiplier (> 0) applied to mu.
        dtype, device: where the run happens (float64 default; float32 allowed).
        progress: show a tqdm bar of the slowest member's time.
    Returns:
        SimulationResult (see torchslide.result); failed members are flagged, never silent.
    """
    t0_wall = time.perf_counter()
    cfg = config or SolverConfig()
    cfg.validate()
    if not isinstance(dem, DEM):
        raise ValueError(f"dem must be a torchslide.terrain.DEM, got {type(dem).__name__}")
    if not isinstance(params, Params):
        raise ValueError(f"params must be a torchslide.physics.Params, got {type(params).__name__}")
    if dtype not in (torch.float32, torch.float64):
        raise ValueError(f"dtype must be torch.float32 or torch.float64, got {dtype}")
    if not (isinstance(t_end, (int, float)) and math.isfinite(t_end) and t_end > 0):
        raise ValueError(f"t_end must be a finite number of seconds > 0, got {t_end!r}")
    device = torch.device(device)
    params.validate()
    P0 = params.to(device=device, dtype=dtype)
    B = P0.B
    ny, nx = dem.shape
    dx = float(dem.cellsize)

    rel = _as_tensor(release, "release", dtype, device)
    _check_raster(rel, "release", (ny, nx), allow_batch=True)
    if rel.ndim == 3 and rel.shape[0] != B:
        raise ValueError(f"release has {rel.shape[0]} members (shape {tuple(rel.shape)}) but params has B = {B}")
    h0 = rel.expand(B, ny, nx).clone() if rel.ndim == 2 else rel.clone()

    use_ent = bool((P0.kappa > 0).any())
    if erodible_depth is not None:
        erod0 = _as_tensor(erodible_depth, "erodible_depth", dtype, device)
        _check_raster(erod0, "erodible_depth", (ny, nx), allow_batch=False)
    elif use_ent:
        b = int(torch.nonzero(P0.kappa > 0)[0])
        raise ValueError(f"parameter kappa[{b}] = {float(P0.kappa[b])} > 0 needs an erodible_depth raster")
    else:
        erod0 = None
    if mu_scale is not None:
        ms = _as_tensor(mu_scale, "mu_scale", dtype, device)
        _check_raster(ms, "mu_scale", (ny, nx), allow_batch=False, positive=True)
    else:
        ms = None
    gauge_list = list(gauges or [])
    gidx_l, gnames = [], []
    for gg in gauge_list:
        if len(gg) != 3:
            raise ValueError(f"gauge entries must be (name, x, y), got {gg!r}")
        name, gx, gy = gg
        i, j = dem.index(float(gx), float(gy), what=f"gauge {name!r}")
        gidx_l.append(i * nx + j)
        gnames.append(str(name))
    if len(set(gnames)) != len(gnames):
        raise ValueError(f"gauge names must be unique, got {gnames}")
    gidx = torch.tensor(gidx_l, dtype=torch.long, device=device)

    use_dep = bool((P0.deposition > 0).any())
    evolve = use_ent or use_dep
    F = StepFlags(
        dx=dx, g=G, cfl=cfg.cfl, theta=cfg.limiter_theta, h_eps=cfg.h_eps, h_wet=cfg.h_wet, wb_ratio=cfg.wb_depth_ratio,
        dt_max=cfg.dt_max, stop_ke_fraction=cfg.stop_ke_fraction,
        arrival_threshold=cfg.arrival_threshold, entrain_h_min=cfg.entrain_h_min,
        no_creep=cfg.no_creep, slope_correction=cfg.slope_correction,
        use_ep=bool((P0.earth_pressure > 0).any()), use_curv=bool((P0.curvature > 0).any()),
        use_ent=use_ent, use_dep=use_dep, use_mu_i=bool((P0.mu_i > 0).any()), use_mu_scale=ms is not None,
        inflow=cfg.boundary == "open")
    step = _get_step(F, cfg.compile)

    # member parameters as (B, 1, 1)
    Pm = {n: t.view(B, 1, 1) for n, t in P0.as_dict().items()}
    phi = torch.where(torch.isnan(P0.phi_int), torch.full_like(P0.phi_int, 45.0), P0.phi_int)
    k_act, k_pass = earth_pressure_sh(phi, P0.mu)
    Pm["k_act"], Pm["k_pass"] = k_act.view(B, 1, 1), k_pass.view(B, 1, 1)
    # shared (non-member) inputs; t_end is a tensor so a compiled step is reused for any end time
    shared = {"mu_scale": ms.unsqueeze(0) if ms is not None else None,
              "t_end": torch.tensor(float(t_end), dtype=dtype, device=device)}

    out_times_l = list(np.arange(0.0, t_end, cfg.output_interval))
    if not out_times_l or t_end - out_times_l[-1] > 1e-9 * max(1.0, t_end):
        out_times_l.append(float(t_end))
    else:
        out_times_l[-1] = float(t_end)
    out_times = torch.tensor(out_times_l, dtype=dtype, device=device)
    K = len(out_times_l)
    G_ = len(gidx_l)

    z0 = torch.as_tensor(dem.z, dtype=dtype, device=device).unsqueeze(0)
    zeros_b = torch.zeros(B, dtype=dtype, device=device)
    cell_area = dx * dx
    S = {
        "h": h0, "hu": torch.zeros_like(h0), "hv": torch.zeros_like(h0),
        "z": z0.expand(B, ny, nx).clone() if evolve else z0,
        "erod": erod0.expand(B, ny, nx).clone() if use_ent else None,
        "dep": torch.zeros_like(h0) if use_dep else None,
        "outflow": zeros_b.clone(), "t": zeros_b.clone(),
        "t_next": out_times[min(1, K - 1)].expand(B).clone(),
        "k_out": torch.ones(B, dtype=torch.long, device=device),
        "active": torch.ones(B, dtype=torch.bool, device=device),
        "ke_peak": zeros_b.clone(),
        "h_max": h0.clone(), "v_max": torch.zeros_like(h0),
        "arrival": torch.where(h0 > cfg.arrival_threshold, torch.zeros_like(h0), torch.full_like(h0, math.inf)),
        "steps": torch.zeros(B, dtype=torch.long, device=device),
        "ke": zeros_b.clone(), "mass": h0.sum(dim=(1, 2)) * cell_area,
        "hit": torch.zeros(B, dtype=torch.bool, device=device), "dt": zeros_b.clone(),
        "failed": torch.zeros(B, dtype=torch.bool, device=device),
        "stopped": torch.zeros(B, dtype=torch.bool, device=device),
        "g_h": torch.zeros(B, G_, K, dtype=dtype, device=device),
        "g_u": torch.zeros(B, G_, K, dtype=dtype, device=device),
        "g_v": torch.zeros(B, G_, K, dtype=dtype, device=device),
        "mass_hist": torch.zeros(B, K, dtype=dtype, device=device),
        "ke_hist": torch.zeros(B, K, dtype=dtype, device=device),
    }
    # slot 0 = the initial state
    S["hit"] = torch.ones(B, dtype=torch.bool, device=device)
    S["k_out"] = torch.zeros(B, dtype=torch.long, device=device)
    S = _record(S, out_times, gidx, cfg.h_eps, K)
    S["hit"] = torch.zeros(B, dtype=torch.bool, device=device)
    release_volume = S["mass"].clone()

    member_keys = [k for k in _MEMBER_KEYS] + (["z"] if evolve else []) + (["erod"] if use_ent else []) \
        + (["dep"] if use_dep else [])
    full = S
    idx = torch.arange(B, device=device)
    work = dict(S)
    Pw = dict(Pm)
    Pw.update(shared)
    exceeded = torch.zeros(B, dtype=torch.bool, device=device)

    bar = None
    if progress:
        from tqdm.auto import tqdm
        bar = tqdm(total=float(t_end), unit="s", desc="simulate")
    n_iter = 0
    # active-region cropping (torchslide.solver.crop): the steps run on `sub`, the state cut to `box`
    g_rows = torch.div(gidx, nx, rounding_mode="floor")
    g_cols = gidx - g_rows * nx
    margin = 2 * cfg.crop_every + 3
    box = _crop.full_box(ny, nx) if not cfg.crop else None

    def _enter(state: dict, b: _crop.Box):
        sub_ = _crop.extract(state, b, ny, nx)
        P_ = dict(Pw)
        if P_.get("mu_scale") is not None and not b.covers(ny, nx):
            P_["mu_scale"] = P_["mu_scale"][:, b.r0:b.r1, b.c0:b.c1].contiguous()
        if not evolve:  # the bed terms of this box, once (not once per step)
            P_["geo"] = static_geometry(sub_["z"], F)
        gi_, gin_ = _crop.gauge_index(g_rows, g_cols, b)
        return sub_, P_, gi_, gin_

    if box is None:
        box = _crop.grow(work["h"], None, ny, nx, margin)
    sub, Psub, gsub, gin = _enter(work, box)
    while True:
        for s_ in range(cfg.check_every):
            if cfg.crop and s_ % cfg.crop_every == 0 and not box.covers(ny, nx):
                nbox = _crop.grow(sub["h"], box, ny, nx, margin)
                if nbox != box:
                    _crop.write_back(work, sub, box, ny, nx, member_keys)
                    box = nbox
                    sub, Psub, gsub, gin = _enter(work, box)
            sub = step(sub, Psub, out_times, gsub, gin)
        # the checks below need only the per-member scalars; rasters go back at compaction / the end
        work.update({k: v for k, v in sub.items() if k not in _crop.SPATIAL})
        n_iter += cfg.check_every
        act = work["active"]
        over = act & (work["steps"] >= cfg.max_steps)
        if bool(over.any()):
            exceeded[idx[over]] = True
            work["active"] = act & ~over
            sub["active"] = work["active"]
            act = work["active"]
        n_act = int(act.sum())
        if bar is not None:
            tmin = float(work["t"][act].min()) if n_act else float(t_end)
            bar.n = round(tmin, 3)
            bar.set_postfix(active=n_act)
            bar.refresh()
        if n_act == 0:
            _crop.write_back(work, sub, box, ny, nx, member_keys)
            break
        if cfg.compact and n_act < idx.numel():
            _crop.write_back(work, sub, box, ny, nx, member_keys)
            for k in member_keys:
                if work[k] is not full[k] and full[k].numel():  # empty (no gauges): nothing to copy
                    full[k][idx] = work[k]
            idx = idx[act]
            work = {k: (v[act] if k in member_keys else v) for k, v in work.items()}
            Pw = {k: (v[idx] if k in Pm else v) for k, v in Pm.items()}
            Pw.update(shared)
            sub, Psub, gsub, gin = _enter(work, box)
    for k in member_keys:
        if work[k] is not full[k] and full[k].numel():
            full[k][idx] = work[k]
    if bar is not None:
        bar.n = float(t_end)
        bar.close()
    S = full

    # samples after a member ended repeat its final state
    slot = torch.arange(K, device=device)
    after = slot.view(1, K) >= S["k_out"].view(B, 1)
    hfinal_flow = S["h"]
    uF = desingularised_velocity(hfinal_flow, S["hu"], cfg.h_eps)
    vF = desingularised_velocity(hfinal_flow, S["hv"], cfg.h_eps)
    S["mass_hist"] = torch.where(after, S["mass"].view(B, 1), S["mass_hist"])
    S["ke_hist"] = torch.where(after, S["ke"].view(B, 1), S["ke_hist"])
    gauges_out: dict[str, GaugeSeries] = {}
    for gi, (name, gx, gy) in enumerate(gauge_list):
        fi = gidx_l[gi]
        a3 = after
        gh = torch.where(a3, hfinal_flow.flatten(1)[:, fi].view(B, 1), S["g_h"][:, gi])
        gu = torch.where(a3, uF.flatten(1)[:, fi].view(B, 1), S["g_u"][:, gi])
        gv = torch.where(a3, vF.flatten(1)[:, fi].view(B, 1), S["g_v"][:, gi])
        gauges_out[str(name)] = GaugeSeries(str(name), float(gx), float(gy), out_times, gh, gu, gv)

    h_final = S["h"] + S["dep"] if use_dep else S["h"]
    final_volume = h_final.sum(dim=(1, 2)) * cell_area
    if use_ent:
        entrained = (erod0.unsqueeze(0) - S["erod"]).sum(dim=(1, 2)) * cell_area
    else:
        entrained = torch.zeros(B, dtype=dtype, device=device)
    if evolve:
        bed_change = S["z"] - z0
    elif erod0 is not None:
        bed_change = torch.zeros_like(h0)
    else:
        bed_change = None
    failed = S["failed"] | exceeded
    reasons: list[str | None] = []
    for b in range(B):
        if bool(S["failed"][b]):
            reasons.append(f"non-finite state (NaN/inf) at t={float(S['t'][b]):.4g} s after "
                           f"{int(S['steps'][b])} steps (mu={float(P0.mu[b]):.4g}, xi={float(P0.xi[b]):.4g})")
        elif bool(exceeded[b]):
            reasons.append(f"exceeded max_steps={cfg.max_steps} at t={float(S['t'][b]):.4g} s")
        else:
            reasons.append(None)
    return SimulationResult(
        dem=dem, h_max=S["h_max"], v_max=S["v_max"], h_final=h_final, arrival_time=S["arrival"],
        cell_area=torch.full((ny, nx), cell_area, dtype=dtype, device=device),
        release_volume=release_volume, final_volume=final_volume, outflow_volume=S["outflow"],
        entrained_volume=entrained, steps=S["steps"], t_final=S["t"], stopped=S["stopped"],
        history_t=out_times, mass_history=S["mass_hist"], ke_history=S["ke_hist"], gauges=gauges_out,
        bed_change=bed_change, runtime_s=time.perf_counter() - t0_wall,
        params={n: t for n, t in P0.as_dict().items()}, failed=failed, failure_reason=reasons,
    )
