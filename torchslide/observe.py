"""Observation operators: map a batched :class:`SimulationResult` to quantities comparable with field data.

Every operator returns a (B,) tensor on the result's device and dtype (one value per batch member).
Thickness thresholds are in m (default 0.5 m), areas in m^2, volumes in m^3, lengths in m, speeds m/s.

Definitions:

Conventions (those of the field's tools): thicknesses (h_max, h_final, gauge h) are normal to the slope,
speeds (v_max, gauge speed) along the surface, areas are map (planimetric) areas, as a mapped outline's,
and volumes are normal thickness times the surface area of each cell.

* impact_area:    map area of the cells with h_max > threshold (area ever reached by the flow).
* deposit_area:   map area of the cells with h_final > threshold.
* deposit_volume: sum of h_final * cell_area (surface area) over cells with h_final > threshold (the
                  mapped deposit; thin films below the threshold are excluded).
* final_volume:   ``result.final_volume``: all material in the domain at the end (no threshold).
* max_velocity, max_height, deposit_height at a point (x, y): v_max, h_max or h_final of the cell that
  contains the point (``method="cell"``, the default: the finite-volume value is a cell average), or
  bilinear interpolation between the four nearest cell centres (``method="bilinear"``; clamped at the
  grid edge).
* runout_length:  the largest distance d of a reached cell, d either along a thalweg polyline (N, 2) in
  map m (every cell centre projected onto the nearest point of the polyline, d the distance along it
  from its first vertex; ``max_offset`` (m) optionally ignores cells farther than that from the
  polyline) or, without a polyline, the horizontal distance from a point (x, y), the release's crown
  (a mapped run-out measured from the crown, torchslide.survey). As an observation it is continuous in
  the parameters (``runout_reach``): a cell counts 2 r d while its reach r = h_max^4 / (h_max^4 +
  threshold^4) is below 1/2 and d + cellsize (r - 1/2) above, so the farthest cell with h_max at the
  threshold gives d, as the sharp ``runout_length`` does, and the value moves with the front instead of
  stepping a cell at a time (for the local fits' finite differences and the emulator alike).
* gauge_series:   the (B, T) series of a named gauge (h, u, v or speed).

Observations (:class:`Observation`) tie a kind to a measured value and its standard deviation; the
registry :data:`KINDS` maps kind names to operators. Add a kind with :func:`register_kind` (for
example gauge-series or map observations) without editing this module.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np
import torch

from .result import SimulationResult
from .terrain.grid import DEM

__all__ = [
    "impact_area",
    "deposit_area",
    "deposit_volume",
    "final_volume",
    "max_velocity",
    "max_height",
    "deposit_height",
    "point_value",
    "runout_length",
    "runout_reach",
    "thalweg_distance_map",
    "point_distance_map",
    "gauge_series",
    "Observation",
    "ObservationKind",
    "KINDS",
    "register_kind",
    "DEFAULT_THRESHOLD",
]

DEFAULT_THRESHOLD = 0.5  # m


# ------------------------------------------------------------------------------------- area / volume
def _area(result: SimulationResult) -> torch.Tensor:
    return result.cell_area.to(result.h_max)


def impact_area(result: SimulationResult, threshold: float = DEFAULT_THRESHOLD) -> torch.Tensor:
    """(B,) map area ever covered by more than ``threshold`` m of flow (normal thickness):
    map_cell_area * #[h_max > threshold], m^2."""
    return (result.h_max > threshold).to(result.h_max).sum(dim=(-2, -1)) * result.map_cell_area


def deposit_area(result: SimulationResult, threshold: float = DEFAULT_THRESHOLD) -> torch.Tensor:
    """(B,) deposit map area: map_cell_area * #[h_final > threshold], m^2."""
    return (result.h_final > threshold).to(result.h_final).sum(dim=(-2, -1)) * result.map_cell_area


def deposit_volume(result: SimulationResult, threshold: float = DEFAULT_THRESHOLD) -> torch.Tensor:
    """(B,) deposit volume: sum h_final * cell_area over cells with h_final > threshold, m^3."""
    h = result.h_final
    return torch.where(h > threshold, h, torch.zeros_like(h)).mul(_area(result)).sum(dim=(-2, -1))


def final_volume(result: SimulationResult) -> torch.Tensor:
    """(B,) all material in the domain at the end, m^3 (``result.final_volume``)."""
    return result.final_volume


# ------------------------------------------------------------------------------------------- points
def point_value(field_: torch.Tensor, dem: DEM, x: float, y: float, method: str = "cell",
                what: str = "point") -> torch.Tensor:
    """(B,) value of a (B, ny, nx) field at map point (x, y): containing cell or bilinear (see module doc)."""
    if method == "cell":
        i, j = dem.index(x, y, what=what)
        return field_[..., i, j]
    if method != "bilinear":
        raise ValueError(f"point method must be 'cell' or 'bilinear', got {method!r}")
    dem.index(x, y, what=what)  # range check
    fx = (x - dem.xll) / dem.cellsize - 0.5
    fy = (y - dem.yll) / dem.cellsize - 0.5
    fx = min(max(fx, 0.0), dem.nx - 1.0)
    fy = min(max(fy, 0.0), dem.ny - 1.0)
    j0, i0 = min(int(math.floor(fx)), dem.nx - 2), min(int(math.floor(fy)), dem.ny - 2)
    wx, wy = fx - j0, fy - i0
    f = field_
    return ((1 - wy) * ((1 - wx) * f[..., i0, j0] + wx * f[..., i0, j0 + 1])
            + wy * ((1 - wx) * f[..., i0 + 1, j0] + wx * f[..., i0 + 1, j0 + 1]))


def max_velocity(result: SimulationResult, x: float, y: float, method: str = "cell") -> torch.Tensor:
    """(B,) maximum speed over time at (x, y), m/s (v_max of the containing cell, or bilinear)."""
    return point_value(result.v_max, result.dem, x, y, method, what="max_velocity point")


def max_height(result: SimulationResult, x: float, y: float, method: str = "cell") -> torch.Tensor:
    """(B,) maximum flow thickness over time at (x, y), m."""
    return point_value(result.h_max, result.dem, x, y, method, what="max_height point")


def deposit_height(result: SimulationResult, x: float, y: float, method: str = "cell") -> torch.Tensor:
    """(B,) final (deposit) thickness at (x, y), m."""
    return point_value(result.h_final, result.dem, x, y, method, what="deposit_height point")


# ------------------------------------------------------------------------------------------- run-out
_THALWEG_CACHE: dict[Any, tuple[np.ndarray, np.ndarray]] = {}


def thalweg_distance_map(dem: DEM, thalweg) -> tuple[np.ndarray, np.ndarray]:
    """Project every cell centre onto a polyline.

    Returns (s, dist), each (ny, nx) numpy float64: s the distance along the polyline (from its first
    vertex, m) of the nearest point on it, dist the distance from the cell centre to that point (m).
    Cached per (grid, polyline).
    """
    P = np.asarray(thalweg, dtype=np.float64)
    if P.ndim != 2 or P.shape[1] != 2 or P.shape[0] < 2:
        raise ValueError(f"thalweg must be an (N >= 2, 2) array of x, y in m, got shape {P.shape}")
    key = (dem.shape, dem.cellsize, dem.xll, dem.yll, P.tobytes())
    if key in _THALWEG_CACHE:
        return _THALWEG_CACHE[key]
    X, Y = np.meshgrid(dem.x_centres(), dem.y_centres())
    best_d2 = np.full(X.shape, np.inf)
    best_s = np.zeros(X.shape)
    seg = np.diff(P, axis=0)
    seglen = np.hypot(seg[:, 0], seg[:, 1])
    s0 = np.concatenate([[0.0], np.cumsum(seglen)])
    for k in range(len(seg)):
        L2 = seglen[k] ** 2
        if L2 == 0:
            continue
        t = ((X - P[k, 0]) * seg[k, 0] + (Y - P[k, 1]) * seg[k, 1]) / L2
        t = np.clip(t, 0.0, 1.0)
        px, py = P[k, 0] + t * seg[k, 0], P[k, 1] + t * seg[k, 1]
        d2 = (X - px) ** 2 + (Y - py) ** 2
        better = d2 < best_d2
        best_d2 = np.where(better, d2, best_d2)
        best_s = np.where(better, s0[k] + t * seglen[k], best_s)
    out = (best_s, np.sqrt(best_d2))
    if len(_THALWEG_CACHE) > 16:
        _THALWEG_CACHE.clear()
    _THALWEG_CACHE[key] = out
    return out


def runout_length(result: SimulationResult, thalweg, threshold: float = DEFAULT_THRESHOLD,
                  max_offset: float | None = None) -> torch.Tensor:
    """(B,) run-out along a thalweg polyline, m: the largest along-path distance (from the first vertex)
    of cells with h_max > threshold, each cell centre projected onto the polyline (0 when none)."""
    s, dist = thalweg_distance_map(result.dem, thalweg)
    h = result.h_max
    s_t = torch.as_tensor(s, dtype=h.dtype, device=h.device)
    mask = h > threshold
    if max_offset is not None:
        mask = mask & torch.as_tensor(dist <= max_offset, device=h.device)
    vals = torch.where(mask, s_t.expand_as(h), torch.full_like(h, -1.0))
    return vals.amax(dim=(-2, -1)).clamp_min(0.0)


def point_distance_map(dem: DEM, x: float, y: float) -> np.ndarray:
    """(ny, nx) horizontal distance, m, of every cell centre from the map point (x, y)."""
    X, Y = np.meshgrid(dem.x_centres(), dem.y_centres())
    return np.hypot(X - x, Y - y)


def runout_reach(result: SimulationResult, distance: np.ndarray, threshold: float = DEFAULT_THRESHOLD,
                 mask: np.ndarray | None = None) -> torch.Tensor:
    """(B,) the run-out, m, continuous in the parameters (module doc): max over the cells (of ``mask``
    (ny, nx) bool, all if None) of 2 r d where r <= 1/2, d + cellsize (r - 1/2) above, r = h_max^4 /
    (h_max^4 + threshold^4), d = ``distance`` (ny, nx) m; 0 where no cell is reached at all."""
    h = result.h_max
    d = torch.as_tensor(distance, dtype=h.dtype, device=h.device)
    h4, t4 = h**4, float(threshold) ** 4
    r = h4 / (h4 + t4) if t4 > 0 else (h > 0).to(h)
    c = torch.where(r <= 0.5, 2.0 * r * d, d + result.dem.cellsize * (r - 0.5))
    if mask is not None:
        c = torch.where(torch.as_tensor(mask, device=h.device), c, torch.zeros_like(c))
    return c.amax(dim=(-2, -1)).clamp_min(0.0)


def _runout_observed(r: SimulationResult, o: "Observation") -> torch.Tensor:
    """runout_length of an observation: along its thalweg, or from its point (x, y) (module doc)."""
    if o.thalweg is not None:
        s, dist = thalweg_distance_map(r.dem, o.thalweg)
        off = o.options.get("max_offset")
        return runout_reach(r, s, o.threshold, None if off is None else dist <= off)
    return runout_reach(r, point_distance_map(r.dem, float(o.x), float(o.y)), o.threshold)


def _check_runout(o: "Observation", dem: DEM | None) -> None:
    if o.thalweg is None and (o.x is None or o.y is None):
        raise ValueError(f"observation {o.name!r}: kind 'runout_length' needs a thalweg polyline (path = \"name\" "
                         "of a [[paths]] entry) or the point it is measured from (x, y: the release's crown)")
    if o.thalweg is None and dem is not None and not dem.contains(float(o.x), float(o.y)):
        raise ValueError(f"observation {o.name!r}: its run-out is measured from x={o.x}, y={o.y}, outside the DEM")


def gauge_series(result: SimulationResult, name: str, quantity: str = "h") -> torch.Tensor:
    """(B, T) series of gauge ``name``: quantity "h" (m), "u", "v" or "speed" (m/s); times in result.gauges[name].t."""
    if name not in result.gauges:
        raise KeyError(f"no gauge named {name!r}; gauges: {sorted(result.gauges)}")
    g = result.gauges[name]
    if quantity == "speed":
        return g.speed
    if quantity not in ("h", "u", "v"):
        raise ValueError(f"gauge quantity must be h, u, v or speed, got {quantity!r}")
    return getattr(g, quantity)


# -------------------------------------------------------------------------------------- registry
@dataclass(frozen=True)
class ObservationKind:
    """An observation kind: ``fn(result, obs) -> (B,)``, its unit and what it needs."""

    name: str
    fn: Callable[[SimulationResult, "Observation"], torch.Tensor]
    unit: str
    needs_point: bool = False
    needs_thalweg: bool = False
    uses_threshold: bool = False
    description: str = ""
    validate: Callable[["Observation", DEM], None] | None = None
    nonnegative: bool = False
    """A recorded value of this kind is >= 0 (an area, a volume, a length, a speed, a thickness)."""


KINDS: dict[str, ObservationKind] = {}


def register_kind(name: str, fn: Callable[[SimulationResult, "Observation"], torch.Tensor], *, unit: str,
                  needs_point: bool = False, needs_thalweg: bool = False, uses_threshold: bool = False,
                  description: str = "", validate: Callable[["Observation", DEM], None] | None = None,
                  overwrite: bool = False, nonnegative: bool = False) -> ObservationKind:
    """Add an observation kind to :data:`KINDS`. ``fn(result, obs)`` must return a (B,) tensor.

    ``validate(obs, dem)`` (optional) runs after the generic checks and raises ValueError.
    ``nonnegative``: a recorded value must be >= 0 (:meth:`Observation.check_recorded`).
    """
    if name in KINDS and not overwrite:
        raise ValueError(f"observation kind {name!r} is already registered")
    kind = ObservationKind(name, fn, unit, needs_point, needs_thalweg, uses_threshold, description, validate,
                           nonnegative)
    KINDS[name] = kind
    return kind


register_kind("impact_area", lambda r, o: impact_area(r, o.threshold), unit="m^2", uses_threshold=True,
              nonnegative=True, description="area with h_max > threshold")
register_kind("deposit_area", lambda r, o: deposit_area(r, o.threshold), unit="m^2", uses_threshold=True,
              nonnegative=True, description="area with h_final > threshold")
register_kind("deposit_volume", lambda r, o: deposit_volume(r, o.threshold), unit="m^3", uses_threshold=True,
              nonnegative=True, description="volume of h_final over cells with h_final > threshold")
register_kind("final_volume", lambda r, o: final_volume(r), unit="m^3",
              nonnegative=True, description="all material in the domain at the end")
register_kind("max_velocity", lambda r, o: max_velocity(r, o.x, o.y, o.method), unit="m/s", needs_point=True,
              nonnegative=True, description="v_max at a point")
register_kind("max_height", lambda r, o: max_height(r, o.x, o.y, o.method), unit="m", needs_point=True,
              nonnegative=True, description="h_max at a point")
register_kind("deposit_height", lambda r, o: deposit_height(r, o.x, o.y, o.method), unit="m", needs_point=True,
              nonnegative=True, description="h_final at a point")
register_kind("runout_length", _runout_observed, unit="m", uses_threshold=True, nonnegative=True,
              validate=_check_runout,
              description="distance of the farthest reached cell along a thalweg or from a point (the crown)")


# ---------------------------------------------------------------------------------------- Observation
def _numbers(*vals) -> bool:
    return all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in vals)


@dataclass
class Observation:
    """One measured quantity with its Gaussian standard deviation.

    Attributes:
        kind: a key of :data:`KINDS`.
        value: the measured value (unit of the kind).
        sigma: standard deviation of the measurement error (> 0, same unit).
        x, y: map point in m (point kinds).
        name: label (defaults to the kind, plus the point).
        threshold: thickness threshold in m for area/volume/run-out kinds.
        thalweg: (N, 2) polyline x, y in m (runout_length).
        method: "cell" or "bilinear" for point kinds.
        options: extra per-kind settings (e.g. max_offset for runout_length, gauge names for new kinds).
    """

    kind: str
    value: float
    sigma: float | None = None
    x: float | None = None
    y: float | None = None
    name: str | None = None
    threshold: float = DEFAULT_THRESHOLD
    thalweg: Any = None
    method: str = "cell"
    options: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.name is None:
            point = self.x is not None and self.y is not None
            self.name = f"{self.kind}@({self.x:g},{self.y:g})" if point and _numbers(self.x, self.y) else self.kind

    @property
    def spec(self) -> ObservationKind:
        if self.kind not in KINDS:
            raise ValueError(f"unknown observation kind {self.kind!r}; known kinds: {', '.join(sorted(KINDS))}")
        return KINDS[self.kind]

    def validate(self, dem: DEM | None = None) -> "Observation":
        """Check kind, value, sigma, threshold, point and thalweg; raise ValueError naming the problem."""
        spec = self.spec
        label = f"observation {self.name!r}"
        try:
            v = float(self.value)
        except (TypeError, ValueError):
            raise ValueError(f"{label}: value must be a number, got {self.value!r}") from None
        if not math.isfinite(v):
            raise ValueError(f"{label}: value must be finite, got {self.value!r}")
        if self.sigma is None:
            raise ValueError(f"{label}: sigma (standard deviation, {spec.unit}) is missing")
        try:
            s = float(self.sigma)
        except (TypeError, ValueError):
            raise ValueError(f"{label}: sigma must be a number, got {self.sigma!r}") from None
        if not (math.isfinite(s) and s > 0):
            raise ValueError(f"{label}: sigma must be > 0, got {self.sigma!r}")
        if spec.uses_threshold and not (math.isfinite(self.threshold) and self.threshold >= 0):
            raise ValueError(f"{label}: threshold must be >= 0 m, got {self.threshold!r}")
        if spec.needs_point:
            if self.x is None or self.y is None:
                raise ValueError(f"{label}: kind {self.kind!r} needs a point x, y (m)")
            if self.method not in ("cell", "bilinear"):
                raise ValueError(f"{label}: method must be 'cell' or 'bilinear', got {self.method!r}")
            if dem is not None and not dem.contains(float(self.x), float(self.y)):
                xmin, ymin, xmax, ymax = dem.extent
                raise ValueError(
                    f"{label}: point x={self.x}, y={self.y} is outside the DEM "
                    f"(x in [{xmin:g}, {xmax:g}), y in [{ymin:g}, {ymax:g}))"
                )
        if spec.needs_thalweg and self.thalweg is None:
            raise ValueError(f"{label}: kind {self.kind!r} needs a thalweg polyline ((N, 2) x, y in m)")
        if self.thalweg is not None:
            P = np.asarray(self.thalweg, dtype=np.float64)
            if P.ndim != 2 or P.shape[1] != 2 or P.shape[0] < 2 or not np.isfinite(P).all():
                raise ValueError(f"{label}: thalweg must be an (N >= 2, 2) array of finite x, y, got shape {P.shape}")
        if spec.validate is not None:
            spec.validate(self, dem)
        return self

    def check_recorded(self) -> "Observation":
        """Checks a value a user recorded must pass beyond :meth:`validate`: ValueError for a negative value
        of a kind that cannot be negative (an area, a volume, a length, a speed, a thickness). Not part of
        validate, since simulated recordings with noise (e.g. the null runs of torchslide.diagnose.null) may
        fall below zero."""
        if self.spec.nonnegative and float(self.value) < 0:
            raise ValueError(f"observation {self.name!r}: a recorded {self.kind} cannot be negative, got "
                             f"{self.value!r} {self.spec.unit}")
        return self

    def predict(self, result: SimulationResult) -> torch.Tensor:
        """(B,) model prediction of this observation from a batched result."""
        out = self.spec.fn(result, self)
        if out.shape != (result.batch_size,):
            raise RuntimeError(f"observation kind {self.kind!r} returned shape {tuple(out.shape)}, expected (B,)")
        return out

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "Observation":
        """Build from a TOML/JSON table; unknown keys raise ValueError (extra per-kind keys go in ``options``)."""
        known = {"kind", "value", "sigma", "x", "y", "name", "threshold", "thalweg", "method", "options"}
        unknown = set(d) - known
        if unknown:
            raise ValueError(f"observation {d.get('name', d.get('kind'))!r}: unknown keys {sorted(unknown)} "
                             f"(known: {', '.join(sorted(known))})")
        if "kind" not in d:
            raise ValueError(f"observation {d.get('name')!r}: 'kind' is missing; known kinds: {', '.join(sorted(KINDS))}")
        if "value" not in d:
            raise ValueError(f"observation {d.get('name', d['kind'])!r}: 'value' is missing")
        return cls(**d)
