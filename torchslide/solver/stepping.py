"""One time step for all members: SSP-RK2 (Heun) of flux + bed source + sources + friction stages.

``make_step(flags)`` returns a pure function ``step(S, P) -> S`` on dicts of tensors, free of
data-dependent Python branching (all switches are Python constants fixed per call), so that
torch.compile can fuse it. Each member b has its own dt_b (a (B, 1, 1) tensor); an ended member
gets dt_b = 0, which leaves its state bitwise unchanged.

A division by a Python number (the cell size) is written as a multiplication by its reciprocal:
torch on CUDA computes tensor / number that way and on the CPU it divides, so writing it out keeps
the step the same on both devices, and the fused kernels (fused_cpu, fused_triton) do the same.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import torch

from ..physics import FR_DEP
from .friction import apply_friction, curvature_gn, desingularised_factor, mu_effective, turbulent_coefficient
from .scheme import (bed_terms, diff, draining_factors, faces_of, frozen_faces, hold_coefficients, pad_linear,
                     pad_replicate, sweep)

Tensor = torch.Tensor


@dataclass(frozen=True)
class StepFlags:
    """Python constants of one solver call (compile-time for torch.compile)."""

    dx: float
    g: float
    cfl: float
    theta: float
    h_eps: float
    h_wet: float
    wb_ratio: float
    dt_max: float
    stop_ke_fraction: float
    arrival_threshold: float
    v_max_min_depth: float
    entrain_h_min: float
    no_creep: bool
    slope_correction: bool
    use_ep: bool
    use_curv: bool
    use_ent: bool
    use_dep: bool
    use_mu_i: bool
    use_mu_scale: bool
    use_tau: bool = True      # a member's yield stress is not 0 (without it the step leaves its zero terms out)
    inflow: bool = False      # SolverConfig.boundary == "open": boundary faces may carry mass into the domain
    domain: str = ""          # cells outside the DEM's domain: "" none, "outflow" or "wall" (SolverConfig.nodata)


def surface_geometry(z: Tensor, dx: float, slope_correction: bool, hessian: bool):
    """Metric fields of the bed surface z (B or 1, ny, nx), central differences (linear ghost cells).

    Returns (z_x, z_y, cos theta, Hessian (z_xx, z_xy, z_yy) when ``hessian`` is asked, else None).
    cos theta = 1 / sqrt(1 + |grad z|^2). Without ``slope_correction`` the metric is that of a
    horizontal plane (z_x = z_y = 0, cos = 1: the classic shallow-water equations).
    """
    ny, nx = z.shape[1], z.shape[2]
    zpx = pad_linear(z, 2)
    zpy = pad_linear(z, 1)
    zx = (zpx.narrow(2, 3, nx) - zpx.narrow(2, 1, nx)) * (1.0 / (2 * dx))
    zy = (zpy.narrow(1, 3, ny) - zpy.narrow(1, 1, ny)) * (1.0 / (2 * dx))
    hess = None
    if hessian:
        zxx = (zpx.narrow(2, 3, nx) - 2 * z + zpx.narrow(2, 1, nx)) * (1.0 / dx**2)
        zyy = (zpy.narrow(1, 3, ny) - 2 * z + zpy.narrow(1, 1, ny)) * (1.0 / dx**2)
        zp2 = pad_linear(zpx, 1)  # (.., ny+4, nx+4)
        zxy = (zp2[:, 3:ny + 3, 3:nx + 3] - zp2[:, 3:ny + 3, 1:nx + 1]
               - zp2[:, 1:ny + 1, 3:nx + 3] + zp2[:, 1:ny + 1, 1:nx + 1]) * (1.0 / (4 * dx**2))
        hess = (zxx, zxy, zyy)
    if not slope_correction:
        return torch.zeros_like(z), torch.zeros_like(z), torch.ones_like(z), hess
    return zx, zy, 1.0 / torch.sqrt(1.0 + zx * zx + zy * zy), hess


class Geometry(NamedTuple):
    """What the step reads of a bed (static_geometry): per cell (B or 1, ny, nx) z_x, z_y, cos theta, its
    reciprocal sec = 1 / cos theta and the pressure coefficient per unit k, g cos^2 theta; the Hessian
    (z_xx, z_xy, z_yy) or None; the bed terms of the x and y sweeps (scheme.bed_terms); the no-creep rule's
    coefficients at the x and y faces (scheme.hold_coefficients) or None."""

    zx: Tensor
    zy: Tensor
    cs: Tensor
    sec: Tensor
    gc2: Tensor
    hess: tuple | None
    beds: tuple
    holds: tuple | None


def static_geometry(z: Tensor, F, mu_scale: Tensor | None = None) -> Geometry:
    """Everything the step needs from a bed (B or 1, ny, nx) and the friction map ``mu_scale`` (with
    F.use_mu_scale); computed once per cropping box by the caller for a bed that does not evolve and passed
    in as ``P["geo"]`` (it is the same for every step on that box), per stage where the bed moves."""
    zx, zy, cs, hess = surface_geometry(z, F.dx, F.slope_correction, F.use_curv)
    sec = torch.reciprocal(cs)
    beds = (bed_terms(z, 2), bed_terms(z, 1))
    holds = None
    if F.no_creep:
        mcs = mu_scale * cs if F.use_mu_scale else cs
        holds = tuple(hold_coefficients(zx, zy, cs, mcs, sec, bed, F.g, F.dx, d) for bed, d in zip(beds, (2, 1)))
    return Geometry(zx, zy, cs, sec, (F.g * cs) * cs, hess, beds, holds)


def surface_speed(u: Tensor, v: Tensor, zx: Tensor, zy: Tensor) -> Tensor:
    """|V|, m/s: the speed along the surface of a flow with horizontal velocity (u, v),
    V = (u, v, z_x u + z_y v)."""
    w = zx * u + zy * v
    return torch.sqrt(u * u + v * v + w * w)


def inverse_metric(px: Tensor, py: Tensor, zx: Tensor, zy: Tensor, cs: Tensor) -> tuple[Tensor, Tensor]:
    """G^-1 p with G = I + grad z grad z^T (the surface metric in map coordinates):
    p - grad z cos^2 (grad z . p). Turns the horizontal gradient of a potential into the horizontal
    projection of its gradient along the surface."""
    a = cs * cs * (zx * px + zy * py)
    return px - zx * a, py - zy * a


def motion_stretch(u: Tensor, v: Tensor, zx: Tensor, zy: Tensor, tiny: float = 0.0) -> tuple[Tensor, Tensor, Tensor]:
    """(sigma, c, moving) of a flow with horizontal velocity u = (u, v): c = (grad z . u) / |u|^2 and
    sigma = sqrt(1 + (grad z . u) c), the length along the surface of a unit map step in the direction of
    motion (sigma |u| = |V|); at rest (|u|^2 <= ``tiny``) sigma = 1 and c = 0."""
    n2 = u * u + v * v
    w = zx * u + zy * v
    moving = n2 > tiny
    c = torch.where(moving, w / n2, torch.zeros_like(n2))
    return torch.sqrt(1.0 + w * c), c, moving


def surface_momentum_change(px: Tensor, py: Tensor, u: Tensor, v: Tensor, motion: tuple, zx: Tensor,
                            zy: Tensor) -> tuple[Tensor, Tensor]:
    """The change of the surface momentum Q = sigma q (m^2/s per unit time, times dx) that the force whose
    horizontal projection along the surface is p = (px, py) makes, for a flow with horizontal velocity u
    (motion: motion_stretch(u)): along the direction of motion e its component along the surface,
    e^T G p / sigma (G = I + grad z grad z^T), across e sigma times p's (which turns the flow without
    changing its speed), i.e. sigma p + u c ((grad z . p) - c (u . p)) / sigma. Where the flow is at rest
    the change is sigma_p p, with the stretch of p's own direction."""
    sg, c, moving = motion
    zp = zx * px + zy * py
    k = c * (zp - c * (u * px + v * py)) / sg
    sp = motion_stretch(px, py, zx, zy)[0]
    return torch.where(moving, sg * px + u * k, sp * px), torch.where(moving, sg * py + v * k, sp * py)


def horizontal_momentum(QX: Tensor, QY: Tensor, zx: Tensor, zy: Tensor, tiny: float = 0.0) -> tuple[Tensor, Tensor, Tensor]:
    """(qx, qy, |Q|): the horizontal momentum q = Q / sigma(Q) = Q |Q| / sqrt(|Q|^2 + (grad z . Q)^2) of the
    surface momentum Q (map direction, |Q| = h |V|) in a cell of slope grad z, and |Q|."""
    n2 = QX * QX + QY * QY
    w = zx * QX + zy * QY
    t = n2 + w * w
    f = torch.where(t > tiny, torch.sqrt(n2 / t), torch.ones_like(t))
    return QX * f, QY * f, torch.sqrt(n2)


def _earth_pressure(u: Tensor, v: Tensor, P: dict, F: StepFlags) -> Tensor:
    """k per cell: (1 - s) k_ap + s k_SH, k_SH active where div(u) >= 0, passive where < 0."""
    if not F.use_ep:
        return P["k_ap"]
    ny, nx = u.shape[1], u.shape[2]
    up = pad_replicate(u, 2)
    vp = pad_replicate(v, 1)
    div = (up.narrow(2, 3, nx) - up.narrow(2, 1, nx)) + (vp.narrow(1, 3, ny) - vp.narrow(1, 1, ny))
    ksh = torch.where(div >= 0, P["k_act"], P["k_pass"])
    s = P["earth_pressure"]
    return (1.0 - s) * P["k_ap"] + s * ksh


def _stage(h, hu, hv, z, erod, dep, dt, dt_cap, P: dict, F: StepFlags, geo=None):
    """Forward-Euler stage: fluxes + gravity and pressure, entrainment / deposition, friction.

    h is the thickness per unit horizontal area (the vertical thickness, m), (hu, hv) the horizontal
    momentum; the normal thickness is cos h and the surface speed |V| (module docstring of the solver).
    With ``dt`` None the time step is chosen here from the CFL condition and ``dt_cap`` (B,).
    ``geo``: ``static_geometry`` of the bed when the caller already has it (a bed that does not evolve:
    both stages share it); None computes it from ``z``.
    Returns the new (h, hu, hv, z, erod, dep), the outflow volume of the stage (B,) m^3 and dt (B,).
    """
    dx, g = F.dx, F.g
    if geo is None:
        geo = static_geometry(z, F, P.get("mu_scale"))
    zx, zy, cs, sec, gc2, hess, (bx, by), holds = geo
    r = desingularised_factor(h, F.h_eps)
    u, v = r * hu, r * hv
    if F.slope_correction:
        # the momentum crosses faces as the surface momentum Q = sigma q (speed along the surface, map
        # direction), so a flow passing between cells of different slope keeps its speed (module docstring)
        motion = motion_stretch(u, v, zx, zy)
        sg = motion[0]
        cu, cv = sg * u, sg * v
        carried_x, carried_y = (cu, cv), (cv, cu)
    else:
        carried_x = carried_y = None
    kg = _earth_pressure(u, v, P, F) * gc2   # pressure k g_n hn^2 / 2 of the normal thickness hn = cos h, per horizontal length
    tau = P["tau_y"] if F.use_tau else None
    fx = fy = None
    if F.no_creep:
        fx, fy = frozen_faces(h, kg, (hu == 0) & (hv == 0), P["mu"], tau, holds, dx)
    if F.domain == "wall":
        wx, wy = _domain_walls(P["inside"])
        fx, fy = (wx, wy) if fx is None else (fx | wx, fy | wy)
    Fhx, Fqnx, Fqtx, phix, hbarx, dBx, ax = sweep(h, u, v, z, kg, fx, 2, F.theta, F.h_wet, F.wb_ratio, bx, carried_x)
    Fhy, Fqny, Fqty, phiy, hbary, dBy, ay = sweep(h, v, u, z, kg, fy, 1, F.theta, F.h_wet, F.wb_ratio, by, carried_y)
    if dt is None:
        dt = torch.minimum(F.cfl * dx / (ax + ay), dt_cap)
        dt = torch.where(dt_cap > 0, dt, torch.zeros_like(dt))
    dtb = dt.view(-1, 1, 1)
    facx, facy = draining_factors(h, Fhx, Fhy, dtb, dx, ghost=1.0 if F.inflow else 0.0)
    Fhx, Fqnx, Fqtx = Fhx * facx, Fqnx * facx, Fqtx * facx
    Fhy, Fqny, Fqty = Fhy * facy, Fqny * facy, Fqty * facy
    lam = dtb * (1.0 / dx)
    hn = h - lam * (diff(Fhx, 2) + diff(Fhy, 1))
    # gravity + pressure as horizontal gradients (times dx), then projected along the surface (Eq. 2-3)
    px = kg * diff(phix, 2) + g * hbarx * dBx
    py = kg * diff(phiy, 1) + g * hbary * dBy
    if F.slope_correction:
        # the surface momentum Q = sigma q is updated and turned back into q with the cell's own metric
        px, py = inverse_metric(px, py, zx, zy, cs)
        px, py = surface_momentum_change(px, py, u, v, motion, zx, zy)
        qx, qy, qn = horizontal_momentum(sg * hu - lam * ((diff(Fqnx, 2) + diff(Fqty, 1)) + px),
                                         sg * hv - lam * ((diff(Fqtx, 2) + diff(Fqny, 1)) + py), zx, zy)
    else:
        qx = hu - lam * ((diff(Fqnx, 2) + diff(Fqty, 1)) + px)
        qy = hv - lam * ((diff(Fqtx, 2) + diff(Fqny, 1)) + py)
        qn = torch.sqrt(qx * qx + qy * qy)
    nx, ny = h.shape[2], h.shape[1]
    bnd = ((Fhx.narrow(2, nx, 1).sum(dim=(1, 2)) - Fhx.narrow(2, 0, 1).sum(dim=(1, 2)))
           + (Fhy.narrow(1, ny, 1).sum(dim=(1, 2)) - Fhy.narrow(1, 0, 1).sum(dim=(1, 2))))
    outflow = dt * dx * bnd
    if F.domain == "outflow":   # what entered a cell outside the domain has left it
        gone = ~P["inside"]
        outflow = outflow + torch.where(gone, hn, torch.zeros_like(hn)).sum(dim=(1, 2)) * (dx * dx)
        hn, qx, qy, qn = (torch.where(gone, torch.zeros_like(a), a) for a in (hn, qx, qy, qn))
    # --- mass sources (explicit in the stage-start state; rates per unit horizontal area)
    gn = g * cs
    if F.use_ent or F.use_dep:
        speed0 = surface_speed(u, v, zx, zy)
    if F.use_ent:
        # erosion kappa |V| normal to the bed per unit bed area = kappa |V| / cos per horizontal area
        rate = P["kappa"] * speed0 * sec * (cs * h > F.entrain_h_min).to(h.dtype)
        de = torch.minimum(dtb * rate, erod)
        hn = hn + de
        erod = erod - de
        z = z - de
    if F.use_dep:
        hs = torch.clamp(cs * h, min=F.h_eps)
        froude = speed0 / torch.sqrt(torch.clamp(gn, min=1e-12) * hs)
        rate = P["deposition"] * h * torch.clamp(1.0 - froude / FR_DEP, min=0.0)
        hpos = torch.clamp(hn, min=0.0)
        dd = torch.minimum(dtb * rate, hpos)
        ratio = torch.where(hpos > 0, (hpos - dd) / hpos, torch.zeros_like(hpos))
        qx, qy, qn = qx * ratio, qy * ratio, qn * ratio
        hn = hn - dd
        dep = dep + dd
        z = z + dd
    # --- friction on the momentum along the surface (Eq. 4)
    mu_c = P["mu"] * P["mu_scale"] if F.use_mu_scale else P["mu"]
    if F.use_curv or F.use_mu_i:
        rn = desingularised_factor(hn, F.h_eps)
        un, vn = rn * qx, rn * qy
    gne = curvature_gn(gn, P["curvature"], cs * _hessian_form(hess, un, vn)) if F.use_curv else gn
    spd = surface_speed(un, vn, zx, zy) if F.use_mu_i else None
    hnp = torch.clamp(hn, min=0.0)
    mue = mu_effective(mu_c, P["mu_i"], spd, cs * hnp, gne, F.h_eps, F.use_mu_i)
    coul = mue * gne * hnp + tau * sec if F.use_tau else mue * gne * hnp
    factor = apply_friction(hn, qn, dtb, coul, turbulent_coefficient(dtb, P["xi"], sec, g), F.h_eps)
    # a layer thinner than h_eps keeps its desingularised velocity's momentum h u
    factor = factor * torch.where(hn < F.h_eps, hn * desingularised_factor(hn, F.h_eps), torch.ones_like(hn))
    qx, qy = qx * factor, qy * factor
    hn = torch.clamp(hn, min=0.0)
    return hn, qx, qy, z, erod, dep, outflow, dt


def _domain_walls(inside: Tensor) -> tuple[Tensor, Tensor]:
    """Faces between a cell of the domain and one outside it: (x faces (1, ny, nx + 1), y faces (1, ny + 1, nx))."""
    out = []
    for d in (2, 1):
        a, b = faces_of(pad_replicate(inside, d), d, inside.shape[d])
        out.append(a != b)
    return out[0], out[1]


def _hessian_form(hess, u: Tensor, v: Tensor) -> Tensor:
    """u^T H u, m/s^2, for the bed Hessian H = (z_xx, z_xy, z_yy): the vertical acceleration of a
    point moving with horizontal velocity (u, v) along the surface."""
    zxx, zxy, zyy = hess
    return zxx * u * u + 2.0 * zxy * u * v + zyy * v * v


def make_step(F: StepFlags):
    """The step function for one call's constants ``F``: ``step(S, P) -> S`` (dicts of tensors).

    S holds h, hu, hv (B, ny, nx); z (B or 1, ny, nx); erod, dep (B, ny, nx) or placeholders;
    outflow, t, t_next, ke_peak (B,); active (B,) bool; h_max, v_max, arrival (B, ny, nx);
    steps (B,) int64; h, hu, hv per unit horizontal area, h_max (normal thickness) and v_max (speed
    along the surface) as the outputs. P holds the member parameters as (B, 1, 1) tensors, "rec":
    (z_x, z_y, cos theta) of the initial bed, and, optionally, "geo": ``static_geometry(z, F)`` of the
    (static) bed of S.
    """

    def step(S: dict, P: dict) -> dict:
        h, hu, hv, z, erod, dep = S["h"], S["hu"], S["hv"], S["z"], S["erod"], S["dep"]
        active = S["active"]
        t, t_next = S["t"], S["t_next"]
        rem = t_next - t
        dt_cap = torch.where(active, torch.clamp(rem, max=F.dt_max), torch.zeros_like(rem))
        # a bed that does not evolve (no entrainment / deposition) has one geometry for both stages,
        # given by the caller as P["geo"] (static_geometry) or else computed here once per step
        if F.use_ent or F.use_dep:
            geo = None
        else:
            geo = P["geo"] if "geo" in P else static_geometry(z, F, P.get("mu_scale"))
        h1, hu1, hv1, z1, e1, d1, o1, dt = _stage(h, hu, hv, z, erod, dep, None, dt_cap, P, F, geo)
        h2, hu2, hv2, z2, e2, d2, o2, _ = _stage(h1, hu1, hv1, z1, e1, d1, dt, dt_cap, P, F, geo)
        stop = (hu1 == 0) & (hv1 == 0) & (hu2 == 0) & (hv2 == 0)
        zero = torch.zeros_like(hu)
        out = dict(S)
        out["h"] = 0.5 * (h + h2)
        out["hu"] = torch.where(stop, zero, 0.5 * (hu + hu2))
        out["hv"] = torch.where(stop, zero, 0.5 * (hv + hv2))
        if F.use_ent or F.use_dep:
            out["z"] = 0.5 * (z + z2)
        if F.use_ent:
            out["erod"] = 0.5 * (erod + e2)
        if F.use_dep:
            out["dep"] = 0.5 * (dep + d2)
        out["outflow"] = S["outflow"] + 0.5 * (o1 + o2)
        hit = active & (dt >= rem)
        t_new = torch.where(hit, t_next, t + dt)
        out["t"] = t_new
        out["dt"] = dt
        out["hit"] = hit
        out["steps"] = S["steps"] + active.to(S["steps"].dtype)
        # --- per-step records (normal thickness, speed along the surface; P["rec"]: the initial bed's
        # z_x, z_y, cos theta on this box)
        rzx, rzy, rcs = P["rec"]
        hN = out["h"]
        spd = desingularised_factor(hN, F.h_eps) * surface_speed(out["hu"], out["hv"], rzx, rzy)
        spd2 = spd * spd
        hfin = hN + out["dep"] if F.use_dep else hN
        hnorm = rcs * hN
        out["h_max"] = torch.maximum(S["h_max"], rcs * hfin)
        out["v_max"] = torch.maximum(S["v_max"], torch.where(hnorm >= F.v_max_min_depth, spd, torch.zeros_like(spd)))
        arrived = torch.isinf(S["arrival"]) & (hnorm > F.arrival_threshold)
        out["arrival"] = torch.where(arrived, t_new.view(-1, 1, 1).expand_as(hN), S["arrival"])
        cell_area = F.dx * F.dx
        ke = 0.5 * (hN * spd2).sum(dim=(1, 2)) * cell_area
        mass = hfin.sum(dim=(1, 2)) * cell_area
        return end_of_step(S, out, P, F, ke, mass)

    return step


def end_of_step(S: dict, out: dict, P: dict, F: StepFlags, ke: Tensor, mass: Tensor) -> dict:
    """The per-member end test of a step: ``out`` (the new state, with "hit") gets the kinetic energy
    ``ke`` and mass ``mass`` (B,) of its records, the peak kinetic energy, and which members failed
    (non-finite), stopped (calm) or stay active; ``S`` is the state the step started from."""
    out["ke"] = ke
    out["mass"] = mass
    peak = torch.maximum(S["ke_peak"], ke)
    out["ke_peak"] = peak
    finite = torch.isfinite(ke) & torch.isfinite(mass)
    # calm: motion fell below a fraction of its peak, or nothing has moved at all (a release that
    # friction holds at rest ends at once instead of idling to t_end)
    # (stop_ke_fraction = 0 switches stopping off altogether)
    calm = (peak > 0) & (ke < F.stop_ke_fraction * peak)
    if F.stop_ke_fraction > 0:
        calm = calm | (peak == 0)
    active = S["active"]
    at_end = out["hit"] & (S["t_next"] >= P["t_end"])
    out["failed"] = S["failed"] | (active & ~finite)
    out["stopped"] = S["stopped"] | (active & finite & calm & ~at_end)
    out["active"] = active & finite & ~calm & ~at_end
    return out
