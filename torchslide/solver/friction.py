"""Basal friction (paper Eq. 4) and the friction-side candidate terms.

S = V/|V| (mu_eff g_n_eff h_n + tau_y + g |V|^2 / xi)        (stress / density per unit bed area, m^2/s^2)

with h_n the normal thickness and V the velocity along the surface, applied per unit horizontal area
(bed area per horizontal area 1 / cos) to the momentum along the surface Q = h V (h the thickness per
horizontal area, |Q| = sqrt(|q|^2 + (grad z . q)^2) for the horizontal momentum q) as a fractional
step that can stop but never reverse:

    Q_c = Q * max(0, 1 - dt (mu_eff g_n_eff h_n + tau_y) / (cos |Q|))     (Coulomb + yield, clipped)
    Q   = Q_c * 2 / (1 + sqrt(1 + 4 a |Q_c|)),   a = dt g / (xi cos h^2)     (turbulent, implicit)

the second line solves Q + dt g |Q| Q / (xi cos h^2) = Q_c exactly, so a steady state on a plane is
exactly g |V|^2 / (xi cos) = g h (sin(theta) - mu cos(theta)), i.e. the Voellmy terminal velocity
|V|^2 = xi h_n (sin(theta) - mu cos(theta)) along the surface (docs/verification.md, case 3),
independent of dt.
"""
from __future__ import annotations

import torch

from ..physics import MU_I_D, MU_I_I0

Tensor = torch.Tensor


def desingularised_velocity(h: Tensor, q: Tensor, h_eps: float) -> Tensor:
    """u = sqrt(2) h q / sqrt(h^4 + max(h^4, h_eps^4)) (KP07 Eq. 2.17): q/h for h >= h_eps, -> 0 as h -> 0."""
    h4 = h * h * h * h
    den = torch.sqrt(h4 + torch.clamp(h4, min=h_eps**4))
    return (2.0**0.5) * h * q / den


def mu_effective(mu_c: Tensor, mu_i: Tensor, speed: Tensor, h: Tensor, gn: Tensor, h_eps: float,
                 use_mu_i: bool) -> Tensor:
    """mu_eff = mu + mu_i I / (I0 + I), I = 5 d |u| / (2 h sqrt(g_n h)) (Pouliquen & Forterre 2002 form).

    Thin cells use h = max(h, h_eps) in I, so I stays finite.
    """
    if not use_mu_i:
        return mu_c
    hs = torch.clamp(h, min=h_eps)
    inertial = 2.5 * MU_I_D * speed / (hs * torch.sqrt(torch.clamp(gn, min=1e-12) * hs))
    return mu_c + mu_i * inertial / (MU_I_I0 + inertial)


def curvature_gn(gn: Tensor, scale: Tensor, cent: Tensor) -> Tensor:
    """g_n_eff = max(0, g_n + c cent): the normal acceleration with the centrifugal part.

    cent = cos(theta) u^T H u is the normal acceleration a point needs to follow the surface (H the DEM
    Hessian, positive in hollows, so flow through a hollow presses harder on the bed; u horizontal);
    c is the ``curvature`` switch (0 = no curvature term).
    """
    return torch.clamp(gn + scale * cent, min=0.0)


def apply_friction(h: Tensor, qx: Tensor, qy: Tensor, dt: Tensor, coul: Tensor, xi: Tensor,
                   g: float, h_eps: float, slope: tuple[Tensor, Tensor]) -> tuple[Tensor, Tensor]:
    """One friction fractional step on the momentum along the surface (stops, never reverses).

    The momentum along the surface of the horizontal momentum q = (qx, qy) is Q = (qx, qy, z_x qx +
    z_y qy); friction opposes Q and scales it, so it scales q by the same factor.

    Args:
        h: (B, ny, nx) thickness per horizontal area, m; qx, qy: horizontal momentum, m^2/s; dt: (B, 1, 1) s.
        coul: resisting force per horizontal area (mu_eff g_n_eff h_n + tau_y) / cos, m^2/s^2 (broadcastable).
        xi: (B, 1, 1) or per cell Voellmy coefficient times cos theta, m/s^2 (inf: no turbulent term);
            the turbulent force per horizontal area is g |Q|^2 / (xi cos h^2).
        slope: (z_x, z_y) of the bed.
    """
    zx, zy = slope
    w = zx * qx + zy * qy
    qn = torch.sqrt(qx * qx + qy * qy + w * w)
    moving = qn > 0
    qs = torch.where(moving, qn, torch.ones_like(qn))
    keep = torch.where(moving, torch.clamp(1.0 - dt * coul / qs, min=0.0), torch.zeros_like(qn))
    hs = torch.clamp(h, min=h_eps)
    a4 = 4.0 * dt * (g / xi) / (hs * hs)
    factor = keep * 2.0 / (1.0 + torch.sqrt(1.0 + a4 * (keep * qn)))
    return qx * factor, qy * factor
