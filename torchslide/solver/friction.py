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


def desingularised_factor(h: Tensor, h_eps: float) -> Tensor:
    """r(h) = sqrt(2) h / sqrt(h^4 + max(h^4, h_eps^4)), 1/m: the desingularised velocity of a momentum q is
    u = r q (KP07 Eq. 2.17); 1 / h for h >= h_eps, -> 0 as h -> 0. One division serves both components."""
    h2 = h * h
    h4 = h2 * h2
    return (2.0**0.5) * h / torch.sqrt(h4 + torch.clamp(h4, min=h_eps**4))


def desingularised_velocity(h: Tensor, q: Tensor, h_eps: float) -> Tensor:
    """u = r(h) q (desingularised_factor, KP07 Eq. 2.17): q/h for h >= h_eps, -> 0 as h -> 0."""
    return desingularised_factor(h, h_eps) * q


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


def turbulent_coefficient(dt: Tensor, xi: Tensor, sec: Tensor, g: float) -> Tensor:
    """4 dt g / (xi cos), s, per cell: the implicit turbulent step's coefficient times h^2 (apply_friction);
    0 where xi = inf (no turbulent term). dt: (B, 1, 1) s; xi: (B, 1, 1) m/s^2; sec: 1 / cos theta per cell."""
    return ((4.0 * g) * dt * torch.reciprocal(xi)) * sec


def apply_friction(h: Tensor, qn: Tensor, dt: Tensor, coul: Tensor, turb: Tensor, h_eps: float) -> Tensor:
    """The factor of one friction fractional step on the momentum along the surface (stops, never reverses).

    Friction opposes the momentum along the surface Q (|Q| = ``qn``) and scales it, so it scales the
    horizontal momentum q by the same factor:

        keep = max(0, 1 - dt coul / |Q|)                  (Coulomb + yield, clipped)
        factor = keep 2 / (1 + sqrt(1 + a4 keep |Q|)),     a4 = turb / h^2   (turbulent, implicit)

    Args:
        h: (B, ny, nx) thickness per horizontal area, m; qn: |Q|, m^2/s; dt: (B, 1, 1) s.
        coul: resisting force per horizontal area (mu_eff g_n_eff h_n + tau_y) / cos, m^2/s^2 (broadcastable).
        turb: turbulent_coefficient, 4 dt g / (xi cos) per cell (0: no turbulent term).
    Returns:
        the factor (B, ny, nx) in [0, 1].
    """
    keep = torch.where(qn > 0, torch.clamp(1.0 - dt * coul / qn, min=0.0), torch.zeros_like(qn))
    hs = torch.clamp(h, min=h_eps)
    a4 = turb / (hs * hs)
    return keep * 2.0 / (1.0 + torch.sqrt(1.0 + a4 * (keep * qn)))
