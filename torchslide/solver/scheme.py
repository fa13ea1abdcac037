"""Kurganov-Petrova (2007) central-upwind fluxes on the DEM grid, one direction at a time.

Every function here works along a tensor dimension ``d`` (2 = x, columns; 1 = y, rows) of (B, ny, nx)
fields, so the x and y sweeps run the same code (rotations and mirrors of the grid are exact).

Ghost cells (2 per side): the bed and the thickness are extrapolated linearly (the thickness clipped at
0), so the surface w = h + z is too: a lake at rest and a uniform layer on a plane continue unchanged
through the boundary. Velocities and per-cell coefficients are replicated (zero gradient, transmissive).
What a boundary face may carry into the domain is set by ``draining_factors``' ``ghost`` factor
(SolverConfig.boundary): "outflow" lets mass leave and nothing enter, "open" is fully transmissive.
"""
from __future__ import annotations

from typing import NamedTuple

import torch

Tensor = torch.Tensor

# Faces whose one-sided wave speeds span less than this (m/s) carry no flux. Without it a face between
# a dry cell and a near-empty one (h ~ 1e-80 m, u ~ 1e-317 m/s, a subnormal) had a+ - a- so small that
# 1 / (a+ - a-) overflowed to inf and a+ a- / (a+ - a-) = 0 * inf made the state NaN (a run with
# limiter_theta = 2 on 10 m cells failed so at t = 15.5 s). Such a face moves at most 1e-10 m/s * h
# per unit time, far below round-off of any real flow, and a zero flux conserves mass exactly.
WAVE_SPEED_MIN = 1e-10


def pad_replicate(q: Tensor, d: int) -> Tensor:
    """Two ghost cells per side along ``d`` holding the edge value (zero-gradient)."""
    n = q.shape[d]
    lo, hi = q.narrow(d, 0, 1), q.narrow(d, n - 1, 1)
    return torch.cat([lo, lo, q, hi, hi], dim=d)


def pad_linear(z: Tensor, d: int) -> Tensor:
    """Two ghost cells per side along ``d`` by linear extrapolation (exact for a plane): g1 = 2 z0 - z1 next to
    the edge cell z0, then g2 = 2 g1 - z0 (each ghost continues the line through the two cells inside it)."""
    n = z.shape[d]
    l0, l1 = z.narrow(d, 0, 1), z.narrow(d, 1, 1)
    r0, r1 = z.narrow(d, n - 1, 1), z.narrow(d, n - 2, 1)
    gl, gr = 2 * l0 - l1, 2 * r0 - r1
    return torch.cat([2 * gl - l0, gl, z, gr, 2 * gr - r0], dim=d)


def pad_const(q: Tensor, d: int, value: float) -> Tensor:
    """One ghost cell per side along ``d`` holding ``value``."""
    shape = list(q.shape)
    shape[d] = 1
    c = torch.full(shape, value, dtype=q.dtype, device=q.device)
    return torch.cat([c, q, c], dim=d)


def minmod3(a: Tensor, b: Tensor, c: Tensor) -> Tensor:
    """minmod(a, b, c): the smallest magnitude when all have one sign, else 0, written as
    max(min(a, b, c), 0) + min(max(a, b, c), 0) (at most one of the two terms is not 0)."""
    zero = torch.zeros_like(a)
    return (torch.maximum(torch.minimum(torch.minimum(a, b), c), zero)
            + torch.minimum(torch.maximum(torch.maximum(a, b), c), zero))


def reconstruct(qp: Tensor, d: int, n: int, theta: float) -> tuple[Tensor, Tensor]:
    """Piecewise-linear generalised-minmod reconstruction (KP07 Eq. 2.12).

    The slope of cell c is minmod(theta dq_c, dq_c / 2 + dq_c+1 / 2, theta dq_c+1) of the differences
    dq_c = q_c - q_c-1 between neighbours, each difference (and its theta dq and dq / 2) computed once for the
    two cells it serves.

    Args:
        qp: field padded with 2 ghost cells along ``d`` (length n + 4).
    Returns:
        (left, right) states at the n + 1 faces along ``d`` (face i lies between cells i-1 and i;
        face 0 and face n are the boundary faces).
    """
    dq = qp.narrow(d, 1, n + 3) - qp.narrow(d, 0, n + 3)
    tdq, hdq = theta * dq, 0.5 * dq
    s = minmod3(tdq.narrow(d, 0, n + 2), hdq.narrow(d, 0, n + 2) + hdq.narrow(d, 1, n + 2), tdq.narrow(d, 1, n + 2))
    qc = qp.narrow(d, 1, n + 2)
    east = qc + 0.5 * s
    west = qc - 0.5 * s
    return east.narrow(d, 0, n + 1), west.narrow(d, 1, n + 1)


def faces_of(qp: Tensor, d: int, n: int) -> tuple[Tensor, Tensor]:
    """Cell values on the left and right of each of the n + 1 faces, from a 2-ghost padded field."""
    return qp.narrow(d, 1, n + 1), qp.narrow(d, 2, n + 1)


def bed_terms(z: Tensor, d: int) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """Bed-only quantities of a sweep along ``d`` (computed once per step when the bed does not evolve).

    Args:
        z: (B or 1, ny, nx) bed, m.
    Returns:
        zp: bed padded with 2 ghost cells (n + 4 along ``d``); zL, zR: cell beds left / right of the
        n + 1 faces; Bf: face bed (mean of the two); bias: (z+ - 2 z + z-) / 4 magnitude of the n + 2
        cells with a neighbour on each side (the bed-curvature offset of the face beds).
    """
    n = z.shape[d]
    zp = pad_linear(z, d)
    zL, zR = faces_of(zp, d, n)
    Bf = 0.5 * (zL + zR)
    zm, zc, zq = zp.narrow(d, 0, n + 2), zp.narrow(d, 1, n + 2), zp.narrow(d, 2, n + 2)
    bias = torch.abs(zq - 2.0 * zc + zm) * 0.25
    return zp, zL, zR, Bf, bias


def central_upwind(hL: Tensor, hR: Tensor, uL: Tensor, uR: Tensor, UL: Tensor, UR: Tensor, tL: Tensor, tR: Tensor,
                   kgL: Tensor, kgR: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """The central-upwind fluxes at faces (KP07 Eq. 3.11) from the left and right thickness h, normal velocity
    u, carried normal and tangential velocities U, t and pressure coefficients kg (all broadcastable).

    With the one-sided speeds a+ >= 0 >= a- (a = u -+ sqrt(kg h)) and d = a+ - a-, the mass flux
    (a+ h- u- - a- h+ u+) / d + a+ a- (h+ - h-) / d is the sum of a left part L = h- a+ (u- - a-) / d and a
    right part R = h+ a- (a+ - u+) / d; the momentum fluxes carry the same parts, L U- + R U+ and L t- + R t+,
    and the pressure potential is phi = (a+ h-^2 - a- h+^2) / (2 d). A face whose speeds span less than
    WAVE_SPEED_MIN carries nothing. Returns (Fh, Fqn, Fqt, phi, max(a+, -a-)).
    """
    cL = torch.sqrt(kgL * hL)
    cR = torch.sqrt(kgR * hR)
    zero = torch.zeros_like(hL)
    ap = torch.maximum(torch.maximum(uR + cR, uL + cL), zero)
    am = torch.minimum(torch.minimum(uR - cR, uL - cL), zero)
    den = ap - am
    pos = den > WAVE_SPEED_MIN
    inv = torch.where(pos, torch.reciprocal(den), zero)
    aL = hL * (ap * inv)
    aR = hR * (am * inv)
    left = aL * (uL - am)
    right = aR * (ap - uR)
    return (left + right, left * UL + right * UR, left * tL + right * tR, 0.5 * (aL * hL - aR * hR),
            torch.maximum(ap, -am))


def sweep(h: Tensor, un: Tensor, ut: Tensor, z: Tensor, kg: Tensor, frozen: Tensor | None, d: int,
          theta: float, h_wet: float, wb_ratio: float = 0.25, bed=None, carried=None):
    """Central-upwind fluxes along direction ``d``.

    Args:
        h: (B, ny, nx) thickness per unit horizontal area, m; un, ut: horizontal velocity normal /
        tangential to the faces, m/s (it transports). z: (B or 1, ny, nx) bed, m. kg: pressure coefficient
        per cell, m/s^2 (the pressure is kg h^2 / 2). frozen: (B, ...) bool at the n + 1 faces (no flux),
        or None. bed: ``bed_terms(z, d)`` when the caller has it (None: computed here). carried: the
        velocity the momentum flux carries, (normal, tangential) per cell (None: (un, ut), the classic
        flux of h u; the solver passes the surface velocity in map directions, stepping._stage).
    Returns:
        Fh, Fqn, Fqt: mass and momentum fluxes (normal, tangential) at the n + 1 faces (per unit width);
        phi: the face pressure potential (a+ h-^2/2 - a- h+^2/2)/(a+ - a-) (times kg of the cell it
        enters); hbar, dB: per cell mean face thickness and bed difference (east - west) for the
        well-balanced bed source g hbar dB/dx (KP07 Eq. 3.13); amax: (B,) largest one-sided speed.
    """
    n = h.shape[d]
    hp = torch.clamp(pad_linear(h, d), min=0.0)
    # bed at faces (mean of the two cells; exact for a plane) and its curvature offset
    zp, zL, zR, Bf, bias = bed if bed is not None else bed_terms(z, d)
    wp = hp + zp
    # surface reconstruction where wet, thickness reconstruction at wet/dry fronts
    wL, wR = reconstruct(wp, d, n, theta)
    hLh, hRh = reconstruct(hp, d, n, theta)
    hm, hc, hq = hp.narrow(d, 0, n + 2), hp.narrow(d, 1, n + 2), hp.narrow(d, 2, n + 2)
    # w-reconstruction only where the layer is thick compared with the bed-curvature bias of the face
    # beds ((z+ - 2 z + z-) / 4): on a curved bed a thin layer would otherwise see face thickness 0 and
    # lose its gravity drive; there h is reconstructed (the face mean then equals the cell's h).
    wet = (torch.minimum(torch.minimum(hm, hc), hq) > h_wet) & (bias <= wb_ratio * hc)
    wetL, wetR = wet.narrow(d, 0, n + 1), wet.narrow(d, 1, n + 1)
    hL = torch.where(wetL, torch.clamp(wL - Bf, min=0.0), hLh)
    hR = torch.where(wetR, torch.clamp(wR - Bf, min=0.0), hRh)
    uL, uR = reconstruct(pad_replicate(un, d), d, n, theta)
    if carried is None:
        UL, UR = uL, uR
        tL, tR = reconstruct(pad_replicate(ut, d), d, n, theta)
    else:
        UL, UR = reconstruct(pad_replicate(carried[0], d), d, n, theta)
        tL, tR = reconstruct(pad_replicate(carried[1], d), d, n, theta)
    kgp = pad_replicate(kg.expand_as(h) if kg.shape != h.shape else kg, d)
    kgL, kgR = faces_of(kgp, d, n)
    Fh, Fqn, Fqt, phi, speed = central_upwind(hL, hR, uL, uR, UL, UR, tL, tR, kgL, kgR)
    if frozen is not None:
        Fh, Fqn, Fqt = (torch.where(frozen, torch.zeros_like(a), a) for a in (Fh, Fqn, Fqt))
    hbar = 0.5 * (hR.narrow(d, 0, n) + hL.narrow(d, 1, n))
    dB = Bf.narrow(d, 1, n) - Bf.narrow(d, 0, n)
    return Fh, Fqn, Fqt, phi, hbar, dB, speed.amax(dim=(1, 2))


def _face_mean(q: Tensor, d: int) -> Tensor:
    """Mean of the two cells beside each of the n + 1 faces along ``d`` (edge value replicated)."""
    n = q.shape[d]
    qL, qR = faces_of(pad_replicate(q, d), d, n)
    return 0.5 * (qL + qR)


class FaceHold(NamedTuple):
    """The bed's part of the no-creep rule at the faces along one axis (hold_coefficients): with A the drive
    per unit thickness normal to the face, the squared drive along the surface per unit thickness is
    (alpha A + beta) A + gamma; m0 = g cos (times the friction map), gdz = g dz / dx (the bed step across the
    face), secf = 1 / cos, all face means of the two cells."""

    alpha: Tensor
    beta: Tensor
    gamma: Tensor
    m0: Tensor
    gdz: Tensor
    secf: Tensor


def hold_coefficients(zx: Tensor, zy: Tensor, cs: Tensor, mcs: Tensor, sec: Tensor, bed, g: float, dx: float,
                      d: int) -> FaceHold:
    """The no-creep rule's coefficients at the faces along ``d`` of a bed (frozen_faces; once per bed).

    The horizontal drive per unit map area at a face is f = hbar (A n + T t): A = -(kg dh / dx + g dz / dx)
    along the face normal n, T = -g dz/dt along the face (the cells' mean slope), and its squared norm
    along the surface is |f|^2 - cos^2 (grad z . f)^2 (the metric's inverse) = hbar^2 ((alpha A + beta) A +
    gamma) with alpha = 1 - cos^2 z_n^2, beta = -2 cos^2 z_n z_t T, gamma = T^2 (1 - cos^2 z_t^2).

    Args:
        zx, zy, cs, mcs, sec: per cell z_x, z_y, cos theta, cos theta times the friction map (cos theta
        without one) and 1 / cos theta, (B or 1, ny, nx); bed: bed_terms(z, d).
    """
    zxf, zyf, csf, secf = (_face_mean(q, d) for q in (zx, zy, cs, sec))
    mcf = csf if mcs is cs else _face_mean(mcs, d)
    zn, zt = (zxf, zyf) if d == 2 else (zyf, zxf)
    T = -g * zt
    c2 = csf * csf
    _, zL, zR, _, _ = bed
    return FaceHold(1.0 - c2 * (zn * zn), -2.0 * c2 * zn * zt * T, T * T * (1.0 - c2 * (zt * zt)), g * mcf,
                    g * (zR - zL) * (1.0 / dx), secf)


def frozen_faces(h: Tensor, kg: Tensor, rest: Tensor, mu: Tensor, tau: Tensor | None, holds: tuple, dx: float
                 ) -> tuple[Tensor, Tensor]:
    """Faces that pass no flux (no creep; the D-Claw "no failure" rule on a sloping surface).

    A face is frozen when both cells beside it are at rest and friction can hold the driving force
    there: the horizontal drive per unit map area, -(kg dh + g dz) hbar / dx across the face from the face
    itself and -g hbar dz/dt along it from the bed (hold_coefficients), measured along the surface, against
    hold = mu g cos hbar + tau_y / cos. On a plane the test is the same in any plan orientation.

    Args:
        h: (B, ny, nx) thickness per map area, m; kg: pressure coefficient per cell, m/s^2;
        rest: (B, ny, nx) bool, momentum exactly zero; mu, tau: per member (B, 1, 1) (tau None: no yield
        stress); holds: (hold_coefficients along x, along y).
    Returns:
        (frozen x faces (B, ny, nx + 1), frozen y faces (B, ny + 1, nx)).
    """
    out = []
    for d, H in ((2, holds[0]), (1, holds[1])):
        n = h.shape[d]
        hcL, hcR = faces_of(torch.clamp(pad_linear(h, d), min=0.0), d, n)
        kgL, kgR = faces_of(pad_replicate(kg.expand_as(h) if kg.shape != h.shape else kg, d), d, n)
        hf = 0.5 * (hcL + hcR)
        A = -(0.5 * (kgL + kgR) * (hcR - hcL) * (1.0 / dx) + H.gdz)
        drive2 = (hf * hf) * ((H.alpha * A + H.beta) * A + H.gamma)
        lim = hf * (mu * H.m0) + tau * H.secf if tau is not None else hf * (mu * H.m0)
        restL, restR = faces_of(pad_replicate(rest, d), d, n)
        out.append(restL & restR & (drive2 <= lim * lim))
    return out[0], out[1]


def diff(F: Tensor, d: int) -> Tensor:
    """East minus west face value per cell, from n + 1 face values along ``d``."""
    n = F.shape[d] - 1
    return F.narrow(d, 1, n) - F.narrow(d, 0, n)


def draining_factors(h: Tensor, Fx: Tensor, Fy: Tensor, dt: Tensor, dx: float,
                     ghost: float = 0.0) -> tuple[Tensor, Tensor]:
    """Draining-flux limiter (Bollermann et al. 2013): keeps h >= 0 for any time step.

    A cell whose outgoing mass in one step would exceed its content scales all its outgoing fluxes by
    content / outgoing. Returns the factors for the x faces (B, ny, nx+1) and y faces (B, ny+1, nx);
    each face is scaled by the factor of its upwind cell. ``ghost`` is the factor of the ghost cells,
    i.e. of a boundary face whose flux points into the domain: 0 (outflow boundary: nothing enters; the
    face keeps only its pressure, like a wall) or 1 (open: the ghost cells supply without limit).
    """
    nx, ny = h.shape[2], h.shape[1]
    outx = torch.relu(Fx.narrow(2, 1, nx)) + torch.relu(-Fx.narrow(2, 0, nx))
    outy = torch.relu(Fy.narrow(1, 1, ny)) + torch.relu(-Fy.narrow(1, 0, ny))
    out = (outx + outy) * (dt * (1.0 / dx))
    fac = torch.where(out > h, h / out, torch.ones_like(out))
    fx = pad_const(fac, 2, ghost)
    fy = pad_const(fac, 1, ghost)
    facx = torch.where(Fx > 0, fx.narrow(2, 0, nx + 1), fx.narrow(2, 1, nx + 1))
    facy = torch.where(Fy > 0, fy.narrow(1, 0, ny + 1), fy.narrow(1, 1, ny + 1))
    return facx, facy
