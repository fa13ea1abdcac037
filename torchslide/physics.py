"""Rheology and source-term parameters of the run-out model, batched over parameter sets.

One ``Params`` object holds B parameter sets (every field a (B,) tensor), so that one solver call
runs B members. The baseline model is Voellmy friction (paper Eq. 4),

    S = V/|V| (mu_eff g_n h + g |V|^2 / xi + tau_y),      mu_eff = mu + mu_i I / (I0 + I),

with h the flow thickness normal to the slope, V the velocity along the surface and g_n = g cos(theta)
(+ an optional centrifugal part), and the candidate terms of the diagnosis
(entrainment, curvature, Savage-Hutter earth pressure, yield stress, mu(I), deposition) each nested:
its switch parameter at 0 gives plain Voellmy *bitwise* (the solver multiplies by the switch, never
branches on it per member).

Fields (units; default; allowed values):

=============== ======== ========= ================================================================
name            unit     default   meaning
=============== ======== ========= ================================================================
mu              -        required  Coulomb friction coefficient tan(delta), > 0
xi              m/s^2    inf       Voellmy turbulent coefficient, > 0; inf = Coulomb (no turbulent term)
k_ap            -        1         constant earth-pressure coefficient, > 0 (Eq. 2-3: k g_n h^2 / 2)
phi_int         deg      NaN       internal friction angle for Savage-Hutter k; NaN = not given.
                                   Needs atan(mu) <= phi_int < 90.
earth_pressure  -        0         switch in [0, 1]: k = (1 - s) k_ap + s k_SH(phi_int, delta),
                                   k_SH = k_act where div(u) >= 0 (diverging), k_pass where converging,
                                   k_act/pass = 2 (1 -/+ sqrt(1 - cos^2 phi (1 + tan^2 delta))) / cos^2 phi - 1
curvature       -        0         scale c of the centrifugal normal stress:
                                   g_n_eff = max(0, g_n + c cos(theta) (u^T H u)), u the horizontal
                                   velocity, H the Hessian of the DEM (positive in hollows), used in
                                   the friction
kappa           1/m      0         entrainment: erosion rate E = kappa |V| (m/s, normal to the bed)
                                   where h > h_flow, capped by the remaining erodible depth raster;
                                   the bed is lowered
tau_y           m^2/s^2  0         yield stress / density: constant resisting stress added to friction
mu_i            -        0         mu(I) (Pouliquen): mu_eff = mu + mu_i I/(I0 + I),
                                   I = 5 d |V| / (2 h sqrt(g_n h)), d = MU_I_D, I0 = MU_I_I0
deposition      1/s      0         deposition rate D: mass leaves the flow onto the bed at rate
                                   D h max(0, 1 - Fr / FR_DEP), Fr = |V| / sqrt(g_n h)
                                   (slow / thin flow deposits; the deposit is part of h_final)
release_scale   -        0         relative change of the release: each member starts from the release
                                   thickness x (1 + release_scale), > -1 (an uncertain release volume,
                                   calibrated or diagnosed like the terms)
=============== ======== ========= ================================================================

The per-cell friction multiplier raster ``mu_scale`` (ny, nx) is not a batched parameter: it is an
argument of ``simulate`` (used to make "out-of-library" synthetic data).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, fields
from typing import Any

import torch

G = 9.81
"""Gravity, m/s^2."""
MU_I_D = 0.1
"""Grain diameter d (m) in the inertial number of the mu(I) term."""
MU_I_I0 = 0.3
"""Reference inertial number I0 of the mu(I) term."""
FR_DEP = 1.0
"""Froude number below which the deposition term removes mass from the flow."""

_DEFAULTS: dict[str, float | None] = {
    "mu": None,
    "xi": math.inf,
    "k_ap": 1.0,
    "phi_int": math.nan,
    "earth_pressure": 0.0,
    "curvature": 0.0,
    "kappa": 0.0,
    "tau_y": 0.0,
    "mu_i": 0.0,
    "deposition": 0.0,
    "release_scale": 0.0,
}


def default_value(name: str) -> float:
    """The value of parameter ``name`` when it is not given (its term off); KeyError for an unknown name."""
    v = _DEFAULTS[name]
    if v is None:
        raise KeyError(f"parameter {name!r} has no default (it is required)")
    return float(v)


# The values each parameter may take (low, high, low_open, high_open): the rules of Params.validate as
# intervals, so that a prior's range can be checked before any run (check_range). phi_int's second rule
# (phi_int >= atan(mu)) couples two parameters and is checked per member by Params.validate.
DOMAINS: dict[str, tuple[float, float, bool, bool]] = {
    "mu": (0.0, math.inf, True, True),
    "xi": (0.0, math.inf, True, False),
    "k_ap": (0.0, math.inf, True, True),
    "phi_int": (0.0, 90.0, True, True),
    "earth_pressure": (0.0, 1.0, False, False),
    "curvature": (0.0, math.inf, False, True),
    "kappa": (0.0, math.inf, False, True),
    "tau_y": (0.0, math.inf, False, True),
    "mu_i": (0.0, math.inf, False, True),
    "deposition": (0.0, math.inf, False, True),
    "release_scale": (-1.0, math.inf, True, True),
}


def check_range(name: str, low: float, high: float) -> None:
    """Raise ValueError naming the parameter and the bound when [low, high] leaves its allowed values.

    ``name`` must be a :class:`Params` field; the allowed values are :data:`DOMAINS` (the module table).
    Used on prior ranges, so that a prior reaching e.g. mu <= 0 is refused before any solver run.
    """
    if name not in DOMAINS:
        raise ValueError(f"unknown parameter {name!r}; known: {list(DOMAINS)}")
    lo, hi, lo_open, hi_open = DOMAINS[name]
    allowed = f"{'(' if lo_open else '['}{lo:g}, {hi:g}{')' if hi_open else ']'}"
    if low < lo or (lo_open and low == lo):
        raise ValueError(f"parameter {name}: range low = {low!r} is outside the allowed values {allowed}")
    if high > hi or (hi_open and high == hi):
        raise ValueError(f"parameter {name}: range high = {high!r} is outside the allowed values {allowed}")


@dataclass
class Params:
    """B parameter sets of the run-out model; every field is a (B,) tensor (see the module table).

    Build with :meth:`Params.make`, which validates and broadcasts.
    """

    mu: torch.Tensor
    xi: torch.Tensor
    k_ap: torch.Tensor
    phi_int: torch.Tensor
    earth_pressure: torch.Tensor
    curvature: torch.Tensor
    kappa: torch.Tensor
    tau_y: torch.Tensor
    mu_i: torch.Tensor
    deposition: torch.Tensor
    release_scale: torch.Tensor

    # ------------------------------------------------------------------ construction
    @classmethod
    def names(cls) -> list[str]:
        return [f.name for f in fields(cls)]

    @classmethod
    def make(cls, B: int | None = None, dtype: torch.dtype = torch.float64,
             device: str | torch.device = "cpu", **values: Any) -> "Params":
        """Build B parameter sets from floats, lists, numpy arrays or tensors.

        A scalar broadcasts to B; B defaults to the length of the longest given sequence (1 if all
        are scalars). Raises ValueError naming the field and the value for unknown names, shape
        mismatches, non-finite or out-of-range values (mu <= 0, xi <= 0, negative kappa, ...).
        """
        unknown = sorted(set(values) - set(_DEFAULTS))
        if unknown:
            raise ValueError(f"unknown parameter(s) {unknown}; known: {list(_DEFAULTS)}")
        if values.get("mu") is None:
            raise ValueError("parameter mu (Coulomb friction coefficient) is required")
        tens: dict[str, torch.Tensor] = {}
        for name, default in _DEFAULTS.items():
            v = values.get(name, default)
            if v is None:
                v = default
            t = torch.as_tensor(v, dtype=dtype).to(device=device).reshape(-1) if not isinstance(v, torch.Tensor) \
                else v.detach().to(device=device, dtype=dtype).reshape(-1)
            tens[name] = t
        lengths = {n: t.numel() for n, t in tens.items() if t.numel() != 1}
        if B is None:
            B = max(lengths.values()) if lengths else 1
        if B < 1:
            raise ValueError(f"B must be >= 1, got {B}")
        for n, L in lengths.items():
            if L != B:
                raise ValueError(f"parameter {n} has {L} values but B = {B}")
        tens = {n: (t.expand(B).clone() if t.numel() == 1 else t.clone()) for n, t in tens.items()}
        p = cls(**tens)
        p.validate()
        return p

    def validate(self) -> None:
        """Raise ValueError naming the field, member and value of the first bad entry."""
        def bad(name: str, mask: torch.Tensor, rule: str) -> None:
            if bool(mask.any()):
                b = int(torch.nonzero(mask)[0])
                raise ValueError(f"parameter {name}[{b}] = {float(getattr(self, name)[b])!r} is invalid: {rule}")

        B = self.mu.numel()
        for n in self.names():
            t = getattr(self, n)
            if t.shape != (B,):
                raise ValueError(f"parameter {n} has shape {tuple(t.shape)}, expected ({B},)")
        bad("mu", ~(torch.isfinite(self.mu) & (self.mu > 0)), "need a finite mu > 0")
        bad("xi", torch.isnan(self.xi) | ~(self.xi > 0), "need xi > 0 (inf for Coulomb)")
        bad("k_ap", ~(torch.isfinite(self.k_ap) & (self.k_ap > 0)), "need a finite k_ap > 0")
        phi = self.phi_int
        given = ~torch.isnan(phi)
        bad("phi_int", given & ~((phi > 0) & (phi < 90)), "need 0 < phi_int < 90 deg (or NaN = not given)")
        delta = torch.rad2deg(torch.atan(self.mu))
        bad("phi_int", given & (phi < delta), "need phi_int >= atan(mu) (deg) for real Savage-Hutter k")
        s = self.earth_pressure
        bad("earth_pressure", ~((s >= 0) & (s <= 1)), "need 0 <= earth_pressure <= 1")
        bad("earth_pressure", (s > 0) & ~given, "earth_pressure > 0 needs phi_int")
        for n in ("curvature", "kappa", "tau_y", "mu_i", "deposition"):
            t = getattr(self, n)
            bad(n, ~(torch.isfinite(t) & (t >= 0)), f"need a finite {n} >= 0")
        bad("release_scale", ~(torch.isfinite(self.release_scale) & (self.release_scale > -1)),
            "need a finite release_scale > -1")

    # ------------------------------------------------------------------ helpers
    @property
    def B(self) -> int:
        return int(self.mu.numel())

    def as_dict(self) -> dict[str, torch.Tensor]:
        return {n: getattr(self, n) for n in self.names()}

    def to(self, device=None, dtype=None) -> "Params":
        return Params(**{n: t.to(device=device, dtype=dtype) for n, t in self.as_dict().items()})

    def select(self, idx) -> "Params":
        """The members ``idx`` (an index tensor, list or slice) as a new Params."""
        return Params(**{n: t[idx] for n, t in self.as_dict().items()})

    @staticmethod
    def cat(items: list["Params"]) -> "Params":
        return Params(**{n: torch.cat([getattr(p, n) for p in items]) for n in Params.names()})


def earth_pressure_sh(phi_int_deg: torch.Tensor, mu: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Savage-Hutter (1989) active and passive earth-pressure coefficients.

    k_act/pass = 2 (1 -/+ sqrt(1 - cos^2 phi (1 + tan^2 delta))) / cos^2 phi - 1, tan(delta) = mu.
    The square-root argument is clipped at 0 (delta > phi). Works on any broadcastable shapes.
    """
    c2 = torch.cos(torch.deg2rad(phi_int_deg)) ** 2
    r = torch.sqrt(torch.clamp(1 - c2 * (1 + mu * mu), min=0.0))
    return 2 * (1 - r) / c2 - 1, 2 * (1 + r) / c2 - 1


LABELS: dict[str, str] = {
    "mu": r"$\mu$ (-)",
    "xi": r"$\xi$ (m/s$^2$)",
    "k_ap": r"$k_{a/p}$ (-)",
    "phi_int": r"$\phi_{int}$ (deg)",
    "earth_pressure": "earth-pressure switch (-)",
    "curvature": "curvature switch (-)",
    "kappa": r"$\kappa$ (1/m)",
    "tau_y": r"$\tau_y$ (m$^2$/s$^2$)",
    "mu_i": r"$\mu_I$ (-)",
    "deposition": "deposition rate (1/s)",
}
"""Axis labels of the parameters, with their units (matplotlib mathtext)."""


def label(name: str) -> str:
    """The axis label of parameter ``name`` (the name itself when it is not a Params field)."""
    return LABELS.get(name, name)

