"""Deterministic synthetic terrains and releases.

Every terrain is an analytic surface z(x, y) sampled at cell centres, so any ``cellsize`` gives the
same geometry (the domain extent is fixed in metres; the cell count is ``round(extent / cellsize)``).
Flow goes towards +x unless stated; the grid origin is (0, 0).

* :func:`inclined_plane` -- plane of angle theta with a flat run-out.
* :func:`parabola` -- z = C (1 - x/L)^2 for x < L, 0 beyond (C = 1000 m, L = C / tan 34 deg).
* :func:`bowl` -- a paraboloid bowl.
* :func:`channel_with_bends` -- an inclined channel with two bends and a flat run-out.
* :func:`bondo_like` -- a Bondo-like case (rock face, bending channel, fan) as a :class:`SyntheticCase`.
* :func:`bend_to_fan` -- a steep channel with one 60 deg bend onto a fan, with an erodible reach.
* :func:`release_from_shape` -- an elliptic paraboloid-cap (or cylinder) release of a given volume.
* :func:`release_from_raster` -- a release thickness raster on a DEM's grid.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from .grid import DEM, TerrainError

__all__ = [
    "SyntheticCase",
    "inclined_plane",
    "parabola",
    "bowl",
    "channel_with_bends",
    "bondo_like",
    "bend_to_fan",
    "release_from_shape",
    "release_from_raster",
    "SYNTHETIC_TERRAINS",
    "thalweg_length",
]


@dataclass
class SyntheticCase:
    """A synthetic test case.

    Attributes:
        name: case name.
        dem: the terrain.
        release: (ny, nx) release thickness, m (vertical), >= 0.
        points: name -> (x, y) map points, m (e.g. "L1", "L2", "L3").
        thalweg: (N, 2) x, y along the flow path (downhill order), m.
        erodible_depth: (ny, nx) erodible bed depth, m (zeros where none).
        info: geometry numbers (release volume m^3, drop m, path length m, ...).
    """

    name: str
    dem: DEM
    release: np.ndarray
    points: dict[str, tuple[float, float]] = field(default_factory=dict)
    thalweg: np.ndarray | None = None
    erodible_depth: np.ndarray | None = None
    info: dict[str, float] = field(default_factory=dict)

    @property
    def release_volume(self) -> float:
        """Release volume, m^3 (the thickness, normal to the slope, times the surface area of each cell)."""
        return float((self.release * self.dem.surface_area()).sum())


def _grid(extent_x: float, extent_y: float, cellsize: float):
    if not (np.isfinite(cellsize) and cellsize > 0):
        raise TerrainError(f"cellsize must be a positive number of metres, got {cellsize!r}")
    nx = max(3, int(round(extent_x / cellsize)))
    ny = max(3, int(round(extent_y / cellsize)))
    x = (np.arange(nx) + 0.5) * cellsize
    y = (np.arange(ny) + 0.5) * cellsize
    X, Y = np.meshgrid(x, y)  # (ny, nx), row 0 south
    return X, Y


def _smoothstep(x, a: float, b: float):
    """0 for x <= a, 1 for x >= b, C1 cubic in between."""
    t = np.clip((np.asarray(x, dtype=np.float64) - a) / (b - a), 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def thalweg_length(thalweg: np.ndarray) -> float:
    """Length of an (N, 2) polyline, m."""
    d = np.diff(np.asarray(thalweg, dtype=np.float64), axis=0)
    return float(np.hypot(d[:, 0], d[:, 1]).sum())


# ------------------------------------------------------------------------------------ simple terrains
def inclined_plane(theta_deg: float = 30.0, cellsize: float = 10.0, *, slope_length: float = 1000.0,
                   runout_length: float = 1000.0, width: float = 500.0, transition: float = 0.0) -> DEM:
    """Plane of angle ``theta_deg`` falling towards +x over ``slope_length`` (horizontal, m), then flat.

    z = tan(theta) (slope_length - x) for x < slope_length, 0 beyond; with ``transition`` > 0 (m) the
    kink is replaced by a parabolic blend of that horizontal length centred on the kink (C1 surface).
    Domain: x in [0, slope_length + runout_length], y in [0, width].
    """
    X, _ = _grid(slope_length + runout_length, width, cellsize)
    return DEM(z=_slope_then_flat(X, slope_length, theta_deg, transition), cellsize=cellsize)


def _slope_then_flat(X: np.ndarray, slope_length: float, theta_deg: float, transition: float) -> np.ndarray:
    """z = tan(theta) (slope_length - x) for x < slope_length, 0 beyond (m); ``transition`` > 0 (m) replaces
    the kink by a parabolic blend of that horizontal length centred on it (C1; bed curvature
    tan(theta) / transition, 1/m, over the blend)."""
    if not (math.isfinite(transition) and 0.0 <= transition <= 2.0 * slope_length):
        raise ValueError(f"transition: need 0 <= transition <= 2 * slope_length ({2.0 * slope_length:g} m), "
                         f"got {transition!r}")
    tan = math.tan(math.radians(theta_deg))
    s = slope_length - X
    z = tan * np.maximum(s, 0.0)
    if transition > 0:
        a = 0.5 * transition
        z = np.where(np.abs(s) < a, tan * (s + a) ** 2 / (4 * a), z)
    return z


PARABOLA_C = 1000.0
PARABOLA_L = PARABOLA_C / math.tan(math.radians(34.0))


def parabola(cellsize: float = 10.0, *, C: float = PARABOLA_C, L: float | None = None,
             runout_length: float = 1000.0, width: float = 1000.0, lateral_curvature: float = 0.0) -> DEM:
    """Parabolic slope: z = C (1 - x/L)^2 for x < L, 0 beyond (C = 1000 m, L = C / tan 34 deg = 1482.6 m).

    The slope at x is 2 C / L (1 - x/L), tangent to the flat run-out at x = L. Optional lateral
    shape: ``lateral_curvature`` k (1/m) adds k (y - width/2)^2 (k > 0 a channel, k < 0 a ridge).
    Domain: x in [0, L + runout_length], y in [0, width].
    """
    L = PARABOLA_L if L is None else float(L)
    X, Y = _grid(L + runout_length, width, cellsize)
    z = C * np.clip(1.0 - X / L, 0.0, None) ** 2 + lateral_curvature * (Y - 0.5 * width) ** 2
    return DEM(z=z, cellsize=cellsize)


def bowl(cellsize: float = 10.0, *, radius: float = 500.0, depth: float = 100.0, margin: float = 100.0) -> DEM:
    """Paraboloid bowl z = depth (r / radius)^2 centred in a square of side 2 (radius + margin), m."""
    side = 2.0 * (radius + margin)
    X, Y = _grid(side, side, cellsize)
    r2 = (X - 0.5 * side) ** 2 + (Y - 0.5 * side) ** 2
    return DEM(z=depth * r2 / radius**2, cellsize=cellsize)


def _bends(x, x0: float, x1: float, amplitude: float):
    """Lateral offset of a two-bend (S) centreline: A (sin 2 pi u - sin 4 pi u / 2), u in [0, 1].

    C2 at both ends (zero offset, slope and curvature); extremes +-1.299 A at u = 1/3 and 2/3.
    """
    u = np.clip((np.asarray(x, dtype=np.float64) - x0) / (x1 - x0), 0.0, 1.0)
    return amplitude * (np.sin(2 * np.pi * u) - 0.5 * np.sin(4 * np.pi * u))


def channel_with_bends(cellsize: float = 10.0, *, theta_deg: float = 25.0, slope_length: float = 2000.0,
                       runout_length: float = 800.0, width: float = 1200.0, channel_depth: float = 20.0,
                       channel_halfwidth: float = 40.0, amplitude: float = 150.0,
                       side_slope_deg: float = 10.0, transition: float = 0.0) -> DEM:
    """An inclined channel with two bends (an S) falling towards +x, then a flat run-out.

    Thalweg: y_c(x) = width/2 + _bends(x, 0.15 L, 0.85 L, amplitude), elevation tan(theta) (L - x) for
    x < L (L = slope_length), 0 beyond. Cross-section at distance d = y - y_c: a Gaussian channel
    ``channel_depth (1 - exp(-(d/w)^2))`` plus valley sides ``tan(side_slope) |d|`` (smoothed).
    The channel fades out over the last 10 % of the slope. ``transition`` > 0 (m): the slope-to-run-out
    kink becomes a parabolic blend of that horizontal length (as in :func:`inclined_plane`), so that
    the bed curvature there does not grow as the cells shrink.
    """
    X, Y = _grid(slope_length + runout_length, width, cellsize)
    L = slope_length
    yc = 0.5 * width + _bends(X, 0.15 * L, 0.85 * L, amplitude)
    d = Y - yc
    z0 = _slope_then_flat(X, L, theta_deg, transition)
    depth = channel_depth * (1.0 - _smoothstep(X, 0.9 * L, L))
    c = 50.0
    z = z0 + depth * (1.0 - np.exp(-((d / channel_halfwidth) ** 2))) \
        + math.tan(math.radians(side_slope_deg)) * (np.sqrt(d**2 + c**2) - c)
    return DEM(z=z, cellsize=cellsize)


# ----------------------------------------------------------------------------------------- releases
def release_from_shape(dem: DEM, centre: tuple[float, float], radii: tuple[float, float] | float, *,
                       volume: float | None = None, thickness: float | None = None,
                       shape: str = "ellipse", normal: bool = True) -> np.ndarray:
    """Release thickness (ny, nx), m, of an elliptic body sampled at cell centres: normal to the slope
    (``normal``, the field's convention) or vertical.

    shape "ellipse": paraboloid cap h = h0 (1 - rho^2) for rho < 1, rho^2 = ((x-xc)/rx)^2 + ((y-yc)/ry)^2;
    shape "cylinder": h = h0 inside the ellipse. Give ``volume`` (m^3; the sampled field is scaled so
    that sum(h * area) equals it exactly at every resolution, area the surface area of each cell for a
    normal thickness (DEM.surface_area), the map area for a vertical one) or the peak ``thickness`` h0 (m).
    """
    if shape not in ("ellipse", "cylinder"):
        raise TerrainError(f"release shape must be 'ellipse' or 'cylinder', got {shape!r}")
    if (volume is None) == (thickness is None):
        raise TerrainError("release_from_shape needs exactly one of volume (m^3) or thickness (m)")
    rx, ry = (radii, radii) if np.isscalar(radii) else radii
    if not (rx > 0 and ry > 0):
        raise TerrainError(f"release radii must be positive, got {radii!r}")
    xc, yc = centre
    if not dem.contains(xc, yc):
        dem.index(xc, yc, what="release centre")
    xmin, ymin, xmax, ymax = dem.extent
    if xc - rx < xmin or xc + rx > xmax or yc - ry < ymin or yc + ry > ymax:
        # a cut ellipse would silently be a thicker release of another shape (its volume kept)
        raise TerrainError(
            f"release ellipse at ({xc:g}, {yc:g}) with radii ({rx:g}, {ry:g}) m extends beyond the DEM "
            f"(x in [{xmin:g}, {xmax:g}], y in [{ymin:g}, {ymax:g}]); move it inside or make it smaller")
    X, Y = np.meshgrid(dem.x_centres(), dem.y_centres())
    rho2 = ((X - xc) / rx) ** 2 + ((Y - yc) / ry) ** 2
    base = np.clip(1.0 - rho2, 0.0, None) if shape == "ellipse" else (rho2 < 1.0).astype(np.float64)
    if base.sum() <= 0:
        raise TerrainError(
            f"release ellipse at ({xc}, {yc}) with radii ({rx}, {ry}) m covers no cell centre of the "
            f"{dem.cellsize:g} m grid; enlarge it"
        )
    if volume is not None:
        if not volume > 0:
            raise TerrainError(f"release volume must be positive, got {volume!r}")
        area = dem.surface_area() if normal else dem.cellsize**2
        return base * (volume / (base * area).sum())
    if not thickness > 0:
        raise TerrainError(f"release thickness must be positive, got {thickness!r}")
    return base * float(thickness)


def release_from_raster(path, dem: DEM) -> np.ndarray:
    """Release thickness (ny, nx), m, from a raster on ``dem``'s grid; nodata -> 0; negative values raise."""
    from .io import read_raster_like

    h = read_raster_like(path, dem, what="release")
    if (h < 0).any():
        i, j = np.argwhere(h < 0)[0]
        raise TerrainError(
            f"{path}: release thickness must be >= 0; {int((h < 0).sum())} negative cells, "
            f"first {h[i, j]:g} m at row {i}, col {j}"
        )
    return h


# ---------------------------------------------------------------------------------------- Bondo-like
# Geometry constants (m, degrees). x runs down-valley, y across; thalweg at y = BONDO_Y0 + bends.
BONDO_EXTENT = (6500.0, 2000.0)
BONDO_Y0 = 1000.0
BONDO_BENDS = (1100.0, 4700.0, 200.0)  # x0, x1, amplitude A -> lateral excursion +-1.3 A = +-260 m
# Thalweg slope angle (deg) at knots along x; tan(angle) is piecewise linear in x, so z is piecewise quadratic.
BONDO_PROFILE = (
    (0.0, 40.0), (750.0, 40.0), (1200.0, 24.0), (2800.0, 19.0), (4500.0, 15.0),
    (4900.0, 7.0), (5300.0, 3.0), (5700.0, 2.0), (6500.0, 1.5),
)
BONDO_Z_BOTTOM = 800.0  # thalweg elevation at the down-valley edge, m
BONDO_CHANNEL = dict(depth=45.0, halfwidth=70.0, start=(700.0, 1100.0), end=(4600.0, 5100.0))
BONDO_RELEASE = dict(centre=(400.0, BONDO_Y0), radii=(300.0, 220.0), volume=3.0e6)
BONDO_POINTS_X = {"L1": 1700.0, "L2": 3200.0, "L3": 4900.0}


def _bondo_profile(x):
    """Thalweg elevation z0(x), m: integral of the piecewise-linear gradient tan(angle(x))."""
    xs = np.array([k[0] for k in BONDO_PROFILE])
    gs = np.tan(np.radians([k[1] for k in BONDO_PROFILE]))
    x = np.clip(np.asarray(x, dtype=np.float64), xs[0], xs[-1])
    seg_drop = 0.5 * (gs[1:] + gs[:-1]) * np.diff(xs)
    cum = np.concatenate([[0.0], np.cumsum(seg_drop)])  # drop from x=0 to each knot
    k = np.clip(np.searchsorted(xs, x, side="right") - 1, 0, len(xs) - 2)
    dx = x - xs[k]
    slope_k = (gs[k + 1] - gs[k]) / (xs[k + 1] - xs[k])
    drop = cum[k] + gs[k] * dx + 0.5 * slope_k * dx**2
    return BONDO_Z_BOTTOM + cum[-1] - drop


def _bondo_centreline(x):
    x0, x1, a = BONDO_BENDS
    return BONDO_Y0 + _bends(x, x0, x1, a)


def _bondo_surface(X, Y):
    """Bondo-like surface z(x, y), m: thalweg profile + channel + valley sides + valley walls."""
    d = Y - _bondo_centreline(X)
    z0 = _bondo_profile(X)
    ch = BONDO_CHANNEL
    depth = ch["depth"] * _smoothstep(X, *ch["start"]) * (1.0 - _smoothstep(X, *ch["end"]))
    channel = depth * (1.0 - np.exp(-((d / ch["halfwidth"]) ** 2)))
    # valley-side slope: 12 deg on the rock face, 20 deg along the channel, 2 deg on the fan
    side = np.tan(np.radians(12.0 + 8.0 * _smoothstep(X, 700.0, 1200.0) - 18.0 * _smoothstep(X, 4600.0, 5200.0)))
    c = 100.0
    valley = side * (np.sqrt(d**2 + c**2) - c)
    # steep valley walls beyond 650 m from the thalweg keep the fan inside the domain
    lam, w0 = 50.0, 650.0
    walls = math.tan(math.radians(30.0)) * lam * np.logaddexp(0.0, (np.abs(d) - w0) / lam)
    return z0 + channel + valley + walls


def bondo_like(cellsize: float = 20.0) -> SyntheticCase:
    """A Bondo-like rock avalanche case (after the 2017 Piz Cengalo-Bondo event), analytic and deterministic.

    Domain 6500 m (x, down-valley) x 2000 m (y), origin (0, 0); 325 x 100 cells at 20 m.
    * Rock face x in [0, 750] m at 40 deg along the thalweg (40-41 deg over the release), concave sides.
    * Release: paraboloid-cap ellipse centred (400, 1000) m, radii 300 m x 220 m, volume 3.0e6 m^3
      (scaled exactly at every cell size), peak ~29 m.
    * Channel: 45 m deep, Gaussian half-width 70 m, from x ~ 700 m to ~5000 m, with two bends
      (S-curve, +-260 m lateral, x in [1100, 4700] m) inside a valley with 20 deg sides.
    * Thalweg angle 24 -> 19 -> 15 deg down to x = 4500 m, 7 deg at 4900 m, fan / valley floor at
      3 -> 1.5 deg beyond 5300 m (side slopes 2 deg), walls 650 m either side of the thalweg.
    * Drop from the release top (x = 100 m, z = 2942 m) to L3 2065 m; path release top -> L3 5.0 km,
      thalweg 6.7 km (x 0 -> 6500 m). With mu = 0.23, xi = 1000 the deposit lies on the fan at
      x ~ 4500-5300 m (front ~5.5 km along the path); some overspill on the outer bank of the first bend.
    * Points on the thalweg: L1 upper channel (x = 1700 m), L2 mid path (x = 3200 m), L3 fan, in the
      mu = 0.23 / xi = 1000 deposit (x = 4900 m).
    * erodible_depth: up to 5 m along the channel floor (Gaussian across, x in ~[1100, 4700] m).
    * ``info`` holds these numbers as computed.
    """
    X, Y = _grid(*BONDO_EXTENT, cellsize)
    dem = DEM(z=_bondo_surface(X, Y), cellsize=cellsize)
    rel = BONDO_RELEASE
    release = release_from_shape(dem, rel["centre"], rel["radii"], volume=rel["volume"])
    # thalweg sampled every 10 m in x, independent of the cell size
    xt = np.arange(0.0, BONDO_EXTENT[0] + 1e-9, 10.0)
    thalweg = np.stack([xt, _bondo_centreline(xt)], axis=1)
    points = {k: (float(x), float(_bondo_centreline(x))) for k, x in BONDO_POINTS_X.items()}
    d = Y - _bondo_centreline(X)
    erod = 5.0 * np.exp(-((d / BONDO_CHANNEL["halfwidth"]) ** 2)) * _smoothstep(X, 900.0, 1300.0) \
        * (1.0 - _smoothstep(X, 4500.0, 4900.0))
    # geometry numbers
    x_rel_top = rel["centre"][0] - rel["radii"][0]
    z_rel_top = float(_bondo_profile(x_rel_top))
    z_l3 = float(_bondo_profile(points["L3"][0]))
    on_path = thalweg[:, 0] >= x_rel_top
    info = {
        "release_volume_m3": float((release * dem.surface_area()).sum()),
        "release_top_x_m": x_rel_top,
        "z_release_top_m": z_rel_top,
        "z_L3_m": z_l3,
        "drop_release_top_to_L3_m": z_rel_top - z_l3,
        "drop_total_m": float(_bondo_profile(0.0) - _bondo_profile(BONDO_EXTENT[0])),
        "path_length_release_top_to_L3_m": thalweg_length(thalweg[on_path & (thalweg[:, 0] <= points["L3"][0])]),
        "thalweg_length_m": thalweg_length(thalweg),
    }
    return SyntheticCase(name="bondo_like", dem=dem, release=release, points=points, thalweg=thalweg,
                         erodible_depth=erod, info=info)


# ------------------------------------------------------------------------------------- bend to fan
# x runs down-slope, y across. The thalweg heads 30 deg to the right of +x, turns 60 deg left over the
# bend and reaches the fan's apex heading 30 deg to the left of +x.
FAN_EXTENT = (1600.0, 1000.0)
FAN_Y0 = 600.0                                   # thalweg y at x = 0, m
FAN_BEND = (450.0, 750.0, 30.0)                  # x where the bend starts and ends, m; heading +-deg
FAN_ANGLES = ((0.0, 35.0), (400.0, 35.0), (700.0, 28.0), (950.0, 24.0), (1050.0, 6.0), (1600.0, 6.0))
FAN_APEX_X = 1000.0
FAN_CHANNEL = dict(depth=15.0, halfwidth=50.0, side_deg=15.0)
FAN_RELEASE = dict(centre_x=150.0, radius=100.0, volume=2.0e5)
FAN_ERODIBLE = (350.0, 800.0, 2.0)               # x range of the erodible reach, m; its depth, m
FAN_POINTS = {"g1": (400.0, 0.0), "g2": (800.0, 0.0), "g3": (1050.0, -80.0)}   # x, offset from the thalweg in y, m


def _fan_heading(x):
    """Thalweg heading (rad, from +x, positive to +y): -30 deg, turning C1 to +30 deg over the bend."""
    x0, x1, a = FAN_BEND
    return np.radians(a) * (2.0 * _smoothstep(x, x0, x1) - 1.0)


_FAN_XS = np.arange(0.0, FAN_EXTENT[0] + 1.0, 1.0)


def _fan_lookup():
    """(y_c, z_thalweg) on _FAN_XS: the centreline and the elevation along it, integrated on 1 m steps so
    that the slope along the path (not along x) is FAN_ANGLES' angle."""
    xs = _FAN_XS
    dy = np.tan(_fan_heading(xs))
    ang = np.radians(np.interp(xs, [k[0] for k in FAN_ANGLES], [k[1] for k in FAN_ANGLES]))
    dz = np.tan(ang) * np.sqrt(1.0 + dy ** 2)
    cum = lambda g: np.concatenate([[0.0], np.cumsum(0.5 * (g[1:] + g[:-1]) * np.diff(xs))])
    z = cum(dz)
    return FAN_Y0 + cum(dy), z[-1] - z


def _fan_centreline(x):
    yc, _ = _fan_lookup()
    return np.interp(x, _FAN_XS, yc)


def _fan_surface(X, Y):
    """z(x, y), m: a channel (Gaussian section in a valley of 15 deg sides) down to the apex, blended over
    x in [apex - 150, apex + 50] m into a cone of FAN_ANGLES' last angle around the apex."""
    yc_t, z_t = _fan_lookup()
    yc = np.interp(X, _FAN_XS, yc_t)
    d = Y - yc
    ch = FAN_CHANNEL
    c = 50.0
    z_ch = np.interp(X, _FAN_XS, z_t) + ch["depth"] * (1.0 - np.exp(-((d / ch["halfwidth"]) ** 2))) \
        + math.tan(math.radians(ch["side_deg"])) * (np.sqrt(d ** 2 + c ** 2) - c)
    xa = FAN_APEX_X
    za, ya = float(np.interp(xa, _FAN_XS, z_t)), float(np.interp(xa, _FAN_XS, yc_t))
    z_fan = za - math.tan(math.radians(FAN_ANGLES[-1][1])) * np.hypot(X - xa, Y - ya)
    w = _smoothstep(X, xa - 150.0, xa + 50.0)
    return z_ch - w * np.maximum(z_ch - z_fan, 0.0)


def bend_to_fan(cellsize: float = 20.0) -> SyntheticCase:
    """A steep channel with one 60 deg bend that opens onto a fan, with an erodible reach.

    Domain 1600 m (x, down-slope) x 1000 m (y), origin (0, 0); 40 x 25 cells at 40 m.
    * Thalweg y_c(x): heading 30 deg to -y down to x = 450 m, turning 60 deg (C1) to 30 deg to +y by
      x = 750 m (bend radius about 330 m), the fan's apex at x = 1000 m.
    * Slope along the path 35 deg down to x = 400 m, 22 deg at 700 m, 18 deg at 950 m, 7 deg on the fan.
    * Channel: 15 m deep, Gaussian half-width 50 m, in a valley of 15 deg sides, blended over x in
      [850, 1050] m into a cone of 7 deg around the apex: the fan.
    * Release: paraboloid cap of radius 100 m on the thalweg at x = 150 m, 2.0e5 m^3.
    * erodible_depth: 2 m within 100 m of the thalweg for x in [350, 800] m (the steep reach and the bend).
    * Points: g1 on the thalweg above the bend (x = 400 m), g2 on it just below the bend (800 m), g3 on
      the fan's head 80 m to the outer side of the thalweg (x = 1050 m), where mu = 0.25, xi = 500 deposits.
    """
    X, Y = _grid(*FAN_EXTENT, cellsize)
    dem = DEM(z=_fan_surface(X, Y), cellsize=cellsize)
    rel = FAN_RELEASE
    cx = rel["centre_x"]
    release = release_from_shape(dem, (cx, float(_fan_centreline(cx))), rel["radius"], volume=rel["volume"])
    x0, x1, depth = FAN_ERODIBLE
    erod = np.where((X >= x0) & (X <= x1) & (np.abs(Y - _fan_centreline(X)) <= 100.0), depth, 0.0)
    xt = np.arange(0.0, FAN_EXTENT[0] + 1e-9, 10.0)
    thalweg = np.stack([xt, _fan_centreline(xt)], axis=1)
    points = {k: (float(x), float(_fan_centreline(x)) + dy) for k, (x, dy) in FAN_POINTS.items()}
    z_t = _fan_lookup()[1]
    info = {"release_volume_m3": float((release * dem.surface_area()).sum()),
            "drop_release_to_apex_m": float(np.interp(cx, _FAN_XS, z_t) - np.interp(FAN_APEX_X, _FAN_XS, z_t)),
            "thalweg_length_m": thalweg_length(thalweg)}
    return SyntheticCase(name="bend_to_fan", dem=dem, release=release, points=points, thalweg=thalweg,
                         erodible_depth=erod, info=info)


SYNTHETIC_TERRAINS = {
    "inclined_plane": inclined_plane,
    "parabola": parabola,
    "bowl": bowl,
    "channel_with_bends": channel_with_bends,
    "bondo_like": bondo_like,
    "bend_to_fan": bend_to_fan,
}
