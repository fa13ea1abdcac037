"""Basal friction (paper Eq. 4) and the friction-side candidate terms.

S = u/|u| (mu_eff g_n_eff h + tau_y) + g |u| u / xi        (stress / density, m^2/s^2)

applied to the whole momentum vector q = h u as a fractional step that can stop but never reverse:

    q_c = q * max(0, 1 - dt (mu_eff g_n_eff h + tau_y) / |q|)          (Coulomb + yield, clipped)
    q   = q_c * 2 / (1 + sqrt(1 + 4 a |q_c|)),   a = dt g / (xi h^2)     (turbulent, implicit)

the second line solves q + dt g |q| q / (xi h^2) = q_c exactly, so a steady state of the step is
exactly g |u|^2 / xi = g_n h (tan(theta) - mu), i.e. the Voellmy terminal velocity
u^2 = xi h (sin(theta) - mu cos(theta)) on a plane (docs/verification.md, case 3), independent of dt.
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


def curvature_gn(gn: Tensor, scale: Tensor, u: Tensor, v: Tensor, hess: tuple[Tensor, Tensor, Tensor],
                 grad2: Tensor) -> Tensor:
    """g_n_eff = max(0, g_n + c (u^T H u) / (1 + |grad z|^2)): centrifugal normal acceleration.

    H = (z_xx, z_xy, z_yy) is the DEM Hessian (positive in hollows, so flow through a hollow presses
    harder on the bed); c is the ``curvature`` switch (0 = no curvature term).
    """
    zxx, zxy, zyy = hess
    cent = (zxx * u * u + 2.0 * zxy * u * v + zyy * v * v) / (1.0 + grad2)
    return torch.clamp(gn + scale * cent, min=0.0)


def apply_friction(h: Tensor, qx: Tensor, qy: Tensor, dt: Tensor, coul: Tensor, xi: Tensor,
                   g: float, h_eps: float) -> tuple[Tensor, Tensor]:
    """One friction fractional step on the momentum vector (stops, never reverses).

    Args:
        h: (B, ny, nx) thickness, m; qx, qy: momentum, m^2/s; dt: (B, 1, 1) s.
        coul: resisting stress mu_eff g_n_eff h + tau_y, m^2/s^2 (broadcastable).
        xi: (B, 1, 1) Voellmy coefficient, m/s^2 (inf: no turbulent term).
    """
    qn = torch.sqrt(qx * qx + qy * qy)
    moving = qn > 0
    qs = torch.where(moving, qn, torch.ones_like(qn))
    keep = torch.where(moving, torch.clamp(1.0 - dt * coul / qs, min=0.0), torch.zeros_like(qn))
    hs = torch.clamp(h, min=h_eps)
    a4 = 4.0 * dt * (g / xi) / (hs * hs)
    factor = keep * 2.0 / (1.0 + torch.sqrt(1.0 + a4 * (keep * qn)))
    return qx * factor, qy * factor
