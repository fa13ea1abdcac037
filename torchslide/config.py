"""TOML run configuration: loading and validation into typed dataclasses for ``simulate``.

A configuration file (paths are relative to the file)::

    [terrain]
    dem = "dem.asc"              # or: synthetic = "bondo_like" (+ cellsize = 20.0, options = {...})
    cellsize = 20.0              # optional: resample the DEM (and release / erodible rasters) to this, m
    release = "release.asc"      # or an inline table: {centre = [x, y], radii = [rx, ry], volume = 3e6},
                                 # or polygons: "release.shp" (a thickness attribute per feature) or
                                 # {polygons = "release.gpkg", thickness = 2.0} (where a feature has none)
    erodible = "erodible.asc"    # optional erodible depth, m: a raster or polygons as for release
    thickness = "normal"         # release and erodible depths normal to the slope (the field's convention),
                                 # or "vertical" (volume per unit map area)
    nodata = "outflow"           # DEM nodata cells lie outside the domain: mass entering them leaves it
                                 # ("outflow"), or they are a wall ("wall")
    fill_nodata = false          # optional instead: fill edge nodata cells of the DEM by nearest neighbour

    [model]
    rheology = "voellmy"         # or "coulomb" (xi = inf)
    mu = [0.2, 0.25]             # a list runs a batch; lists must have equal lengths, scalars broadcast
    xi = 1000.0                  # m/s^2
    density = 2000.0             # kg/m^3, for the peak pressure density * v_max^2 (not a solver parameter)
    # any other field of torchslide.physics.Params (k_ap, kappa, curvature, ...)

    [run]
    t_end = 300.0                # s
    dtype = "float64"            # or "float32"
    device = "cpu"               # or "cuda", "cuda:1"
    cfl = 0.4                    # optional, passed to SolverConfig
    executor = "local"           # where batches run (calibrate, predict, sweep, diagnose): "local" (this process)
                                 # or "dask": chunks of max_batch members on Dask workers (pip install
    workers = 4                  # torchslide[dask]): a LocalCluster of this many processes, or the cluster
    # scheduler = "tcp://host:8786"  # at this scheduler address (torchslide.executor)
    # any other SolverConfig field is accepted here too (output_interval, stop_ke_fraction, ...)

    [[gauges]]
    name = "G1"
    x = 1700.0
    y = 1331.0

    [[paths]]                    # optional: run-out along a path (summary.json, kind runout_length)
    name = "channel"
    line = "channel.geojson"     # a line feature file, or points = [[x0, y0], [x1, y1], ...] (map m)
    max_offset = 300.0           # optional: ignore cells farther than this from the path, m

    [output]
    format = "asc"               # rasters that simulate / predict write: "asc" (ESRI ASCII) or "tif"
                                 # (GeoTIFF with the DEM's CRS; needs rasterio, the geo extra)

Every problem raises :class:`ConfigError` with a one-line message naming the file, section and key.

Extending: the calibrate/diagnose configs are the same file plus more sections. Call
``load_config(path, extra_sections={"prior": parse_prior, ...})``; each parser gets
``(table, cfg)`` -- the raw TOML value of the section and the :class:`Config` with the base sections
already validated -- and returns any object, stored in ``cfg.extra[name]``. Parsers raise
:class:`ConfigError` (use :func:`check_keys` for unknown-key checks). Sections listed in
:data:`OTHER_SECTIONS` but without a parser are accepted and left unvalidated in ``cfg.raw`` (so
``torchslide simulate`` runs a calibrate config); any other unknown section is an error.
"""
from __future__ import annotations

import math
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np

from .terrain.grid import DEM, TerrainError

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

__all__ = [
    "ConfigError",
    "TerrainConfig",
    "ModelConfig",
    "RunConfig",
    "GaugeConfig",
    "Config",
    "load_config",
    "parse_config",
    "read_toml",
    "check_keys",
    "OTHER_SECTIONS",
    "BASE_SECTIONS",
]


class ConfigError(ValueError):
    """Bad configuration or input data; the message is one line naming the file, section and key."""


BASE_SECTIONS = ("terrain", "model", "run", "gauges", "paths", "output")
CONVENTIONS = {
    "thickness": "flow thickness normal to the slope, m (h_max, h_final, gauge h)",
    "speed": "speed along the surface, m/s (v_max, gauge speed)",
    "pressure": "peak pressure density * v_max^2, kPa (p_max)",
    "area": "map (planimetric) area, m^2",
    "volume": "normal thickness times the surface area of each cell, m^3",
}
"""What the outputs measure (the conventions of r.avaflow, RAMMS and AvaFrame); written into every
summary, predictive and posterior JSON file with :meth:`Config.conventions`."""
OTHER_SECTIONS: set[str] = {"prior", "observations", "calibration", "diagnose"}
"""Sections of other commands' configs that the base loader accepts without a parser."""

_TERRAIN_KEYS = {"dem", "release", "erodible", "synthetic", "cellsize", "options", "fill_nodata", "thickness", "nodata"}
NODATA = ("outflow", "wall")
THICKNESS = ("normal", "vertical")
_RELEASE_TABLE_KEYS = {"centre", "center", "radii", "volume", "thickness", "shape"}
_POLYGON_TABLE_KEYS = {"polygons", "thickness", "attribute"}
_RUN_KEYS = {"t_end", "dtype", "device", "cfl", "executor", "scheduler", "workers"}
_GAUGE_KEYS = {"name", "x", "y"}
_PATH_KEYS = {"name", "line", "points", "max_offset"}
OUTPUT_FORMATS = ("asc", "tif")
RHEOLOGIES = ("voellmy", "coulomb")


# ------------------------------------------------------------------------------------ dataclasses
@dataclass
class TerrainConfig:
    """Validated terrain: DEM, release (ny, nx) m, optional erodible depth (ny, nx) m, both measured as
    ``thickness`` says ("normal" to the slope or "vertical")."""

    dem: DEM
    release: np.ndarray
    erodible_depth: np.ndarray | None = None
    source: str = ""
    case: Any = None  # SyntheticCase for synthetic terrains (has points, thalweg)
    thickness: str = "normal"
    nodata: str = "outflow"
    release_note: str = ""   # how the release was made when torchslide converted it (a failure depth)
    source_dem: DEM | None = None   # the DEM file's grid when [terrain] cellsize resampled it (maps lie on it)

    def cell_volume_area(self) -> np.ndarray:
        """(ny, nx) m^2 that turns an input thickness into a volume: the surface area of each cell for
        a thickness normal to the slope, the map area for a vertical one."""
        if self.thickness == "normal":
            return self.dem.surface_area()
        return np.full(self.dem.shape, self.dem.cellsize**2)

    @property
    def release_volume(self) -> float:
        """m^3."""
        return float((self.release * self.cell_volume_area()).sum())


@dataclass
class ModelConfig:
    """Rheology and per-member parameter values (name -> list of B floats); density, kg/m^3, of the
    flowing mass (for the peak pressure only)."""

    rheology: str
    values: dict[str, list[float]]
    batch_size: int
    density: float = 2000.0

    def make_params(self, dtype=None, device="cpu"):
        """torchslide.physics.Params for these values."""
        import torch

        from .physics import Params

        return Params.make(B=self.batch_size, dtype=dtype or torch.float64, device=device, **self.values)


@dataclass
class RunConfig:
    """Time and numerics: t_end (s), dtype name, device name, optional CFL number.

    ``solver`` holds any other [run] keys that are fields of ``torchslide.solver.SolverConfig``
    (e.g. output_interval, stop_ke_fraction); ``cfl`` is also passed there.
    """

    t_end: float
    dtype: str = "float64"
    device: str = "cpu"
    cfl: float | None = None
    solver: dict[str, Any] = field(default_factory=dict)
    executor: str = "local"
    scheduler: str | None = None
    workers: int | None = None

    def make_executor(self):
        """The torchslide.executor of ``executor`` / ``scheduler`` / ``workers``."""
        from .executor import make_executor

        return make_executor(self.executor, scheduler=self.scheduler, workers=self.workers)

    @property
    def torch_dtype(self):
        import torch

        return {"float32": torch.float32, "float64": torch.float64}[self.dtype]


@dataclass
class GaugeConfig:
    name: str
    x: float
    y: float


@dataclass
class PathConfig:
    """A named polyline (N, 2) in map m along which run-out is measured; cells farther than max_offset
    (m, None: any) from it are ignored."""

    name: str
    xy: np.ndarray
    max_offset: float | None = None


@dataclass
class Config:
    """A validated configuration. ``raw`` is the parsed TOML; ``extra`` holds extra-section results."""

    path: Path
    terrain: TerrainConfig
    model: ModelConfig
    run: RunConfig
    gauges: list[GaugeConfig] = field(default_factory=list)
    paths: list[PathConfig] = field(default_factory=list)
    raw: dict[str, Any] = field(default_factory=dict)
    extra: dict[str, Any] = field(default_factory=dict)
    output_format: str = "asc"

    @property
    def batch_size(self) -> int:
        return self.model.batch_size

    def resolve(self, p: str | Path) -> Path:
        """A path from the config, relative to the config file's folder."""
        p = Path(p)
        return p if p.is_absolute() else self.path.parent / p

    def run_out_paths(self) -> list[PathConfig]:
        """The [[paths]], and a synthetic case's thalweg as the path "thalweg" when it has one."""
        thalweg = getattr(self.terrain.case, "thalweg", None)
        own = [] if thalweg is None or any(p.name == "thalweg" for p in self.paths) else \
            [PathConfig("thalweg", np.asarray(thalweg, dtype=np.float64))]
        return own + list(self.paths)

    def conventions(self) -> dict[str, Any]:
        """CONVENTIONS plus this run's: the input thickness convention and the density, kg/m^3."""
        out = dict(CONVENTIONS, input_thickness=self.terrain.thickness, density_kg_m3=self.model.density)
        if self.terrain.release_note:
            out["release"] = self.terrain.release_note
        return out

    def make_params(self):
        """Params on the run's dtype and device."""
        return self.model.make_params(dtype=self.run.torch_dtype, device=self.run.device)

    def solver_config(self):
        """SolverConfig with the [run] numerics (None when nothing is set)."""
        kw = dict(self.run.solver)
        if self.run.cfl is not None:
            kw["cfl"] = self.run.cfl
        if self.terrain.nodata != "outflow":
            kw["nodata"] = self.terrain.nodata
        if not kw:
            return None
        from .solver.config import SolverConfig

        return SolverConfig(**kw)

    def simulate_kwargs(self) -> dict[str, Any]:
        """Keyword arguments for ``torchslide.solver.simulate(**kwargs)`` (dem, release, params, ...)."""
        return dict(
            dem=self.terrain.dem,
            release=self.terrain.release,
            params=self.make_params(),
            t_end=self.run.t_end,
            gauges=[(g.name, g.x, g.y) for g in self.gauges],
            config=self.solver_config(),
            erodible_depth=self.terrain.erodible_depth,
            thickness=self.terrain.thickness,
            dtype=self.run.torch_dtype,
            device=self.run.device,
        )


# ------------------------------------------------------------------------------------ helpers
def check_keys(table: Any, allowed, where: str, path: Path | str) -> dict:
    """Raise ConfigError when ``table`` is not a table or has keys outside ``allowed``."""
    if not isinstance(table, dict):
        raise ConfigError(f"{path}: {where} must be a table, got {type(table).__name__}")
    unknown = [k for k in table if k not in allowed]
    if unknown:
        raise ConfigError(
            f"{path}: unknown key {unknown[0]!r} in {where} (allowed: {', '.join(sorted(allowed))})"
        )
    return table


def _number(v: Any, key: str, where: str, path) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise ConfigError(f"{path}: {where} {key} must be a number, got {v!r}")
    v = float(v)
    if math.isnan(v):
        raise ConfigError(f"{path}: {where} {key} must be a number, got nan")
    return v


MAX_OUTPUT_TIMES = 1_000_000
"""The most output times (t_end / output_interval) a run records (gauge series and histories)."""
MAX_CELLS = 50_000_000
"""The largest grid a config may ask for (about 0.4 GB per float64 raster; a run holds dozens)."""


def _check_grid_size(make, kwargs: dict, path) -> None:
    """Refuse a synthetic terrain whose cell size makes a grid larger than MAX_CELLS, before allocating
    it: the cell count is estimated from the same terrain on 100 m cells."""
    cs = kwargs.get("cellsize")
    if cs is None or cs >= 100.0:
        return
    probe = make(**dict(kwargs, cellsize=100.0))
    dem = probe.dem if hasattr(probe, "dem") else probe
    n = dem.z.size * (100.0 / cs) ** 2
    if n > MAX_CELLS:
        raise ConfigError(f"{path}: [terrain] cellsize = {cs:g} m makes a grid of about {n:.3g} cells "
                          f"({n * 8 / 2**30:.3g} GiB per float64 raster); the most is {MAX_CELLS:.0e} cells")


def _check_release_table(r: dict, centre, radii, path) -> None:
    """centre = [x, y] (m), radii = r or [rx, ry] (m, > 0), volume (m^3) or thickness (m) > 0."""
    where = "[terrain] release"
    if not isinstance(centre, (list, tuple)) or len(centre) != 2:
        raise ConfigError(f"{path}: {where} centre must be [x, y] in m, got {centre!r}")
    for v in centre:
        _number(v, "centre", where, path)
    rs = [radii] if not isinstance(radii, (list, tuple)) else list(radii)
    if len(rs) not in (1, 2):
        raise ConfigError(f"{path}: {where} radii must be r or [rx, ry] in m, got {radii!r}")
    for v in rs:
        if not _number(v, "radii", where, path) > 0:
            raise ConfigError(f"{path}: {where} radii must be > 0 m, got {radii!r}")
    for key in ("volume", "thickness"):
        if r.get(key) is not None and not _number(r[key], key, where, path) > 0:
            raise ConfigError(f"{path}: {where} {key} must be > 0, got {r[key]!r}")


def read_toml(path) -> dict[str, Any]:
    """Parse a TOML file; missing file or syntax errors -> ConfigError."""
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"{path}: config file not found")
    try:
        with open(path, "rb") as f:
            return tomllib.load(f)
    except tomllib.TOMLDecodeError as e:
        raise ConfigError(f"{path}: invalid TOML: {e}") from None


# ------------------------------------------------------------------------------------ sections
def _parse_terrain(t: Any, path: Path) -> TerrainConfig:
    from .terrain import io, synthetic

    t = check_keys(t, _TERRAIN_KEYS, "[terrain]", path)
    base = path.parent

    def file(key: str) -> Path:
        v = t[key]
        if not isinstance(v, str) or not v:
            raise ConfigError(f"{path}: [terrain] {key} must be a file path string, got {v!r}")
        p = Path(v) if Path(v).is_absolute() else base / v
        if not p.is_file():
            raise ConfigError(f"{path}: [terrain] {key} file not found: {p}")
        return p

    has_dem, has_syn = "dem" in t, "synthetic" in t
    if has_dem == has_syn:
        raise ConfigError(f"{path}: [terrain] needs exactly one of 'dem' (a raster file) or 'synthetic' (a terrain name)")
    case = None
    nodata = t.get("nodata", "outflow")
    if nodata not in NODATA:
        raise ConfigError(f"{path}: [terrain] nodata must be one of {', '.join(map(repr, NODATA))} "
                          f"(what DEM nodata cells are), got {nodata!r}")
    convention = t.get("thickness", "normal")
    if convention not in THICKNESS:
        raise ConfigError(f"{path}: [terrain] thickness must be one of {', '.join(map(repr, THICKNESS))} "
                          f"(the convention of the release and erodible depths), got {convention!r}")
    try:
        if has_dem:
            if "options" in t:
                raise ConfigError(f"{path}: [terrain] options is only used with 'synthetic', not with 'dem'")
            src = io.read_raster(file("dem"), nodata="fill" if t.get("fill_nodata", False) else "outside")
            failure = None
            if isinstance(t.get("release"), dict) and "failure_depth" in t["release"]:
                check_keys(t["release"], {"failure_depth"}, "[terrain] release", path)
                v = t["release"]["failure_depth"]
                fp = Path(v) if isinstance(v, str) and Path(v).is_absolute() else base / str(v)
                if not isinstance(v, str) or not fp.is_file():
                    raise ConfigError(f"{path}: [terrain] release failure_depth file not found: {v!r}")
                src, failure = _failure_surface(src, fp)
            dem = src
            if "cellsize" in t:
                from .terrain.resample import resample_dem

                dem = resample_dem(src, _cellsize(t, path))
            source = str(t["dem"])
        else:
            name = t["synthetic"]
            if name not in synthetic.SYNTHETIC_TERRAINS:
                raise ConfigError(
                    f"{path}: [terrain] unknown synthetic terrain {name!r} "
                    f"(known: {', '.join(sorted(synthetic.SYNTHETIC_TERRAINS))})"
                )
            kwargs = dict(t.get("options", {}))
            if not isinstance(t.get("options", {}), dict):
                raise ConfigError(f"{path}: [terrain] options must be a table")
            if "cellsize" in t:
                kwargs["cellsize"] = _cellsize(t, path)
            try:
                _check_grid_size(synthetic.SYNTHETIC_TERRAINS[name], kwargs, path)
                out = synthetic.SYNTHETIC_TERRAINS[name](**kwargs)
            except TypeError as e:
                raise ConfigError(f"{path}: [terrain] bad options for synthetic terrain {name!r}: {e}") from None
            if isinstance(out, synthetic.SyntheticCase):
                case, dem = out, out.dem
            else:
                dem = out
            source = f"synthetic:{name}"
            src = dem
        if not np.isfinite(dem.z).all():  # DEM() already refuses this; keep the check explicit
            raise ConfigError(f"{path}: [terrain] DEM has NaN cells")

        # release
        release_note = ""
        if "release" in t:
            r = t["release"]
            if has_dem and failure is not None:
                release_v, release_note = failure
                area = src.surface_area() if convention == "normal" else np.full(src.shape, src.cellsize ** 2)
                # a vertical depth d over a map cell is the volume d cellsize^2, as a normal thickness d cos
                h = release_v * (src.cellsize ** 2 / src.surface_area()) if convention == "normal" else release_v
                release = _on_grid(h, src, dem, convention)
                release_note += (f"; as normal thickness (x cos theta of the failure surface), {float((h * area).sum()):,.0f} m^3"
                                 if convention == "normal" else "")
            elif _is_polygons(r):
                release = _polygon_thickness(r, "release", dem, base, path)
            elif isinstance(r, dict):
                r = check_keys(r, _RELEASE_TABLE_KEYS, "[terrain] release", path)
                centre = r.get("centre", r.get("center"))
                if centre is None or "radii" not in r:
                    raise ConfigError(f"{path}: [terrain] release table needs centre = [x, y] and radii = [rx, ry]")
                radii = r["radii"]
                _check_release_table(r, centre, radii, path)
                release = synthetic.release_from_shape(
                    dem, tuple(centre), radii if np.isscalar(radii) else tuple(radii),
                    volume=r.get("volume"), thickness=r.get("thickness"), shape=r.get("shape", "ellipse"),
                    normal=convention == "normal")
            else:
                release = _on_grid(synthetic.release_from_raster(file("release"), src), src, dem, convention)
        elif case is not None:
            release = case.release
        else:
            raise ConfigError(f"{path}: [terrain] release is missing (a raster file or a table with centre, radii, volume)")
        if not np.isfinite(release).all():
            raise ConfigError(f"{path}: [terrain] release has non-finite values")
        if (release < 0).any():
            raise ConfigError(f"{path}: [terrain] release thickness is negative in {int((release < 0).sum())} cells")
        if release.sum() <= 0:
            raise ConfigError(f"{path}: [terrain] release is empty (zero volume)")
        if dem.outside is not None and (release[dem.outside] > 0).any():
            i, j = np.argwhere(dem.outside & (release > 0))[0]
            x, y = dem.cell_centre(int(i), int(j))
            raise ConfigError(f"{path}: [terrain] release covers {int((dem.outside & (release > 0)).sum())} nodata "
                              f"cells of the DEM (outside its domain), first at x={x:g} m, y={y:g} m")

        erod = None
        if "erodible" in t:
            if _is_polygons(t["erodible"]):
                erod = _polygon_thickness(t["erodible"], "erodible", dem, base, path)
            else:
                erod = _on_grid(io.read_raster_like(file("erodible"), src, what="erodible depth"), src, dem, convention)
            if (erod < 0).any():
                raise ConfigError(f"{path}: [terrain] erodible depth is negative in {int((erod < 0).sum())} cells")
        elif case is not None and case.erodible_depth is not None:
            erod = case.erodible_depth
    except TerrainError as e:
        raise ConfigError(f"{path}: [terrain] {e}") from None
    if src is not None and src is not dem and src.crs and not dem.crs:    # a raster read on the DEM file's grid
        dem.crs = src.crs                                                   # gave the CRS (terrain.io)
    return TerrainConfig(dem=dem, release=np.asarray(release, dtype=np.float64), erodible_depth=erod,
                         source=source, case=case, thickness=convention, nodata=nodata, release_note=release_note,
                         source_dem=src if has_dem and src is not dem else None)


def _failure_surface(src: DEM, path: Path) -> tuple[DEM, tuple[np.ndarray, str]]:
    """A failure-depth raster (post- minus pre-event elevation in the source, <= 0, vertical m; a DEM of
    difference's erosion, on the DEM file's grid) as a release: the bed lowered to the failure surface and
    the vertical thickness -d of the material above it. Returns (the DEM of the failure surface, (the
    (ny, nx) vertical release thickness, m, a note saying what was done))."""
    from .terrain import io

    d = io.read_raster_like(path, src, what="failure depth")
    if (d > 0).any():
        i, j = np.argwhere(d > 0)[0]
        raise TerrainError(f"{path}: a failure depth is <= 0 (post- minus pre-event elevation); {int((d > 0).sum())} "
                           f"cells are positive, first {d[i, j]:g} m at row {i} from the south, col {j}")
    if not (d < 0).any():
        raise TerrainError(f"{path}: the failure depth has no negative value: nothing is released")
    bed = DEM(src.z + d, src.cellsize, src.xll, src.yll, crs=src.crs, outside=src.outside)
    vol = float(-d.sum()) * src.cellsize ** 2
    note = (f"release from the failure depths of {path.name}: {int((d < 0).sum())} cells, {vol:,.0f} m^3 "
            "(vertical), the bed lowered to the failure surface")
    return bed, (-d, note)


def _cellsize(t: dict, path: Path) -> float:
    cs = _number(t["cellsize"], "cellsize", "[terrain]", path)
    if not (cs > 0 and math.isfinite(cs)):
        raise ConfigError(f"{path}: [terrain] cellsize must be > 0 m, got {t['cellsize']!r}")
    return cs


def _on_grid(a: np.ndarray, src: DEM, dem: DEM, convention: str) -> np.ndarray:
    """A thickness raster of the DEM file's grid on the (resampled) inversion grid, its volume kept."""
    if dem is src:
        return a
    from .terrain.resample import resample_thickness

    area = (lambda d: d.surface_area()) if convention == "normal" else (lambda d: np.full(d.shape, d.cellsize**2))
    return resample_thickness(a, src, dem, area(src), area(dem))


def _is_polygons(v: Any) -> bool:
    """A [terrain] release / erodible value that names polygons: a vector file or a {polygons = ...} table."""
    from .terrain.vector import is_vector

    return (isinstance(v, str) and is_vector(v)) or (isinstance(v, dict) and "polygons" in v)


def _polygon_thickness(v: Any, key: str, dem: DEM, base: Path, path: Path) -> np.ndarray:
    """(ny, nx) thickness, m, of [terrain] ``key`` given as polygons (the attribute, or the table's
    thickness where a feature has none)."""
    from .terrain.vector import rasterize_thickness

    if isinstance(v, dict):
        check_keys(v, _POLYGON_TABLE_KEYS, f"[terrain] {key}", path)
        f, default, attr = v["polygons"], v.get("thickness"), v.get("attribute", "thickness")
        if default is not None and not (_number(default, "thickness", f"[terrain] {key}", path) > 0):
            raise ConfigError(f"{path}: [terrain] {key} thickness must be > 0 m, got {default!r}")
        if not isinstance(attr, str) or not attr:
            raise ConfigError(f"{path}: [terrain] {key} attribute must be a field name, got {attr!r}")
    else:
        f, default, attr = v, None, "thickness"
    if not isinstance(f, str) or not f:
        raise ConfigError(f"{path}: [terrain] {key} polygons must be a file path string, got {f!r}")
    p = Path(f) if Path(f).is_absolute() else base / f
    if not p.is_file():
        raise ConfigError(f"{path}: [terrain] {key} file not found: {p}")
    return rasterize_thickness(p, dem, attribute=attr, default=None if default is None else float(default), what=key)


def _parse_model(m: Any, path: Path) -> ModelConfig:
    from .physics import Params

    names = Params.names()
    m = check_keys(m, {"rheology", "density", *names}, "[model]", path)
    density = _number(m.get("density", 2000.0), "density", "[model]", path)
    if not (density > 0 and math.isfinite(density)):
        raise ConfigError(f"{path}: [model] density must be a finite number of kg/m^3 > 0, got {m['density']!r}")
    rheology = m.get("rheology", "voellmy")
    if rheology not in RHEOLOGIES:
        raise ConfigError(f"{path}: [model] unknown rheology {rheology!r} (known: {', '.join(RHEOLOGIES)})")
    if "mu" not in m:
        raise ConfigError(f"{path}: [model] mu is missing")
    if rheology == "voellmy" and "xi" not in m:
        raise ConfigError(f"{path}: [model] xi is missing (required for rheology 'voellmy'; use rheology = 'coulomb' for none)")
    if rheology == "coulomb" and "xi" in m:
        raise ConfigError(f"{path}: [model] xi is not used by rheology 'coulomb' (remove it or use 'voellmy')")
    values: dict[str, list[float]] = {}
    for k in names:
        if k not in m:
            continue
        v = m[k]
        seq = v if isinstance(v, list) else [v]
        if not seq:
            raise ConfigError(f"{path}: [model] {k} is an empty list")
        vals = [_number(x, k, "[model]", path) for x in seq]
        if k == "mu" and any(not x > 0 for x in vals):
            raise ConfigError(f"{path}: [model] mu must be > 0, got {v!r}")
        if k == "xi" and any(not x > 0 for x in vals):
            raise ConfigError(f"{path}: [model] xi must be > 0 m/s^2, got {v!r}")
        values[k] = vals
    if rheology == "coulomb":
        values["xi"] = [math.inf]
    lengths = {k: len(v) for k, v in values.items() if len(v) > 1}
    if len(set(lengths.values())) > 1:
        raise ConfigError(
            f"{path}: [model] parameter lists must have equal lengths (or be scalars), got "
            + ", ".join(f"{k}: {n}" for k, n in lengths.items())
        )
    B = max(lengths.values()) if lengths else 1
    mc = ModelConfig(rheology=rheology, values=values, batch_size=B, density=density)
    try:
        mc.make_params()
    except ValueError as e:
        raise ConfigError(f"{path}: [model] {e}") from None
    return mc


def _solver_fields() -> dict[str, Any]:
    """name -> default of SolverConfig fields (empty when the solver is not importable)."""
    import dataclasses

    try:
        from .solver.config import SolverConfig
    except ImportError:
        return {}
    return {f.name: f.default for f in dataclasses.fields(SolverConfig)}


def _parse_run(r: Any, path: Path) -> RunConfig:
    sf = _solver_fields()
    r = check_keys(r, _RUN_KEYS | set(sf), "[run]", path)
    if "t_end" not in r:
        raise ConfigError(f"{path}: [run] t_end (s) is missing")
    t_end = _number(r["t_end"], "t_end", "[run]", path)
    if not (math.isfinite(t_end) and t_end > 0):
        raise ConfigError(f"{path}: [run] t_end must be > 0 s, got {r['t_end']!r}")
    dtype = r.get("dtype", "float64")
    if dtype not in ("float32", "float64"):
        raise ConfigError(f"{path}: [run] dtype must be 'float32' or 'float64', got {dtype!r}")
    device = r.get("device", "cpu")
    if not isinstance(device, str) or not (device == "cpu" or device == "cuda" or device.startswith("cuda:")):
        raise ConfigError(f"{path}: [run] device must be 'cpu' or 'cuda' (or 'cuda:N'), got {device!r}")
    if device.startswith("cuda"):
        import torch

        if not torch.cuda.is_available():
            raise ConfigError(f"{path}: [run] device {device!r} requested but CUDA is not available")
    cfl = None
    if "cfl" in r:
        cfl = _number(r["cfl"], "cfl", "[run]", path)
        if not 0 < cfl <= 1:
            raise ConfigError(f"{path}: [run] cfl must be in (0, 1], got {r['cfl']!r}")
    executor, scheduler, workers = parse_executor(r, path)
    solver = {k: v for k, v in r.items() if k not in _RUN_KEYS}
    for k, v in solver.items():
        default = sf[k]
        if isinstance(default, bool) and not isinstance(v, bool):
            raise ConfigError(f"{path}: [run] {k} must be true or false, got {v!r}")
        if isinstance(default, (int, float)) and not isinstance(default, bool):
            _number(v, k, "[run]", path)
    if solver:
        from .solver.config import SolverConfig

        try:
            sc = SolverConfig(**solver)
            if hasattr(sc, "validate"):
                sc.validate()
        except (TypeError, ValueError) as e:
            raise ConfigError(f"{path}: [run] {e}") from None
    interval = float(solver.get("output_interval", sf.get("output_interval", 1.0)))
    if t_end / interval > MAX_OUTPUT_TIMES:
        raise ConfigError(f"{path}: [run] t_end / output_interval = {t_end:g} / {interval:g} s gives "
                          f"{t_end / interval:.3g} output times (at most {MAX_OUTPUT_TIMES:.0e}): shorten t_end or "
                          "lengthen output_interval")
    return RunConfig(t_end=t_end, dtype=dtype, device=device, cfl=cfl, solver=solver, executor=executor,
                     scheduler=scheduler, workers=workers)


def parse_executor(r: dict, path: Path) -> tuple[str, str | None, int | None]:
    """[run] executor, scheduler, workers (checked: one-line ConfigError naming the key and value)."""
    executor = r.get("executor", "local")
    if executor not in ("local", "dask"):
        raise ConfigError(f"{path}: [run] executor must be \"local\" or \"dask\", got {executor!r}")
    scheduler = r.get("scheduler")
    if scheduler is not None and (not isinstance(scheduler, str) or "://" not in scheduler):
        raise ConfigError(f"{path}: [run] scheduler must be an address like \"tcp://host:8786\", got {scheduler!r}")
    workers = r.get("workers")
    if workers is not None and (not isinstance(workers, int) or isinstance(workers, bool) or workers < 1):
        raise ConfigError(f"{path}: [run] workers must be an integer >= 1, got {workers!r}")
    if executor == "local" and (scheduler is not None or workers is not None):
        raise ConfigError(f"{path}: [run] scheduler / workers need executor = \"dask\"")
    if scheduler is not None and workers is not None:
        raise ConfigError(f"{path}: [run] give scheduler (a running cluster) or workers (a local one), not both")
    return executor, scheduler, workers


def _parse_gauges(g: Any, dem: DEM, path: Path) -> list[GaugeConfig]:
    if not isinstance(g, list):
        raise ConfigError(f"{path}: gauges must be an array of tables ([[gauges]])")
    out, seen = [], set()
    for n, item in enumerate(g):
        where = f"[[gauges]] #{n + 1}"
        check_keys(item, _GAUGE_KEYS, where, path)
        for k in ("name", "x", "y"):
            if k not in item:
                raise ConfigError(f"{path}: {where} {k} is missing")
        name = item["name"]
        if not isinstance(name, str) or not name:
            raise ConfigError(f"{path}: {where} name must be a non-empty string")
        if name in seen:
            raise ConfigError(f"{path}: {where} duplicate gauge name {name!r}")
        seen.add(name)
        x, y = _number(item["x"], "x", where, path), _number(item["y"], "y", where, path)
        if not dem.contains(x, y):
            xmin, ymin, xmax, ymax = dem.extent
            raise ConfigError(
                f"{path}: gauge {name!r} at x={x:g}, y={y:g} is outside the DEM "
                f"(x in [{xmin:g}, {xmax:g}), y in [{ymin:g}, {ymax:g}))"
            )
        out.append(GaugeConfig(name, x, y))
    return out


def _parse_paths(p: Any, dem: DEM, path: Path) -> list[PathConfig]:
    """[[paths]]: name, a line file or inline points (>= 2 vertices inside the DEM), optional max_offset."""
    from .terrain.vector import read_polyline

    if not isinstance(p, list):
        raise ConfigError(f"{path}: paths must be an array of tables ([[paths]])")
    out: list[PathConfig] = []
    for n, item in enumerate(p):
        where = f"[[paths]] #{n + 1}"
        check_keys(item, _PATH_KEYS, where, path)
        name = item.get("name")
        if not isinstance(name, str) or not name:
            raise ConfigError(f"{path}: {where} name must be a non-empty string")
        if any(q.name == name for q in out):
            raise ConfigError(f"{path}: {where} duplicate path name {name!r}")
        if ("line" in item) == ("points" in item):
            raise ConfigError(f"{path}: {where} needs exactly one of line (a line file) or points ([[x, y], ...])")
        if "line" in item:
            f = item["line"]
            fp = Path(f) if Path(str(f)).is_absolute() else path.parent / str(f)
            if not fp.is_file():
                raise ConfigError(f"{path}: {where} line file not found: {fp}")
            try:
                xy = read_polyline(fp, dem)
            except TerrainError as e:
                raise ConfigError(f"{path}: {where}: {e}") from None
        else:
            try:
                xy = np.asarray(item["points"], dtype=np.float64)
            except (TypeError, ValueError):
                raise ConfigError(f"{path}: {where} points must be [[x, y], ...] in m, got {item['points']!r}") from None
            if xy.ndim != 2 or xy.shape[1] != 2 or xy.shape[0] < 2 or not np.isfinite(xy).all():
                raise ConfigError(f"{path}: {where} points must be two or more [x, y] pairs in m, got {item['points']!r}")
        first = xy[0]
        if not dem.contains(float(first[0]), float(first[1])):
            raise ConfigError(f"{path}: {where} ({name!r}) starts at x={first[0]:g}, y={first[1]:g}, outside the DEM")
        off = item.get("max_offset")
        if off is not None and not (_number(off, "max_offset", where, path) > 0):
            raise ConfigError(f"{path}: {where} max_offset must be > 0 m, got {off!r}")
        out.append(PathConfig(name, xy, None if off is None else float(off)))
    return out


# ------------------------------------------------------------------------------------ entry points
def _parse_output(o: Any, path: Path) -> str:
    """[output] -> the raster format ("asc" or "tif"); "tif" is refused here when rasterio is missing."""
    o = check_keys(o, {"format"}, "[output]", path)
    fmt = str(o.get("format", "asc")).lower()
    if fmt not in OUTPUT_FORMATS:
        raise ConfigError(f"{path}: [output] format must be one of {', '.join(OUTPUT_FORMATS)}, got {o['format']!r}")
    if fmt == "tif":
        try:
            import rasterio  # noqa: F401
        except ImportError:
            raise ConfigError(f"{path}: [output] format = \"tif\" needs rasterio, which is not installed: "
                              f"`pip install torchslide[geo]`") from None
    return fmt


def parse_config(raw: dict[str, Any], path, extra_sections: dict[str, Callable[[Any, Config], Any]] | None = None) -> Config:
    """Validate an already-parsed TOML dict (``path`` anchors relative file paths and messages)."""
    path = Path(path)
    extra_sections = dict(extra_sections or {})
    known = set(BASE_SECTIONS) | set(OTHER_SECTIONS) | set(extra_sections)
    for k in raw:
        if k not in known:
            raise ConfigError(f"{path}: unknown section [{k}] (known: {', '.join(sorted(known))})")
    for k in ("terrain", "model", "run"):
        if k not in raw:
            raise ConfigError(f"{path}: section [{k}] is missing")
    terrain = _parse_terrain(raw["terrain"], path)
    model = _parse_model(raw["model"], path)
    run = _parse_run(raw["run"], path)
    gauges = _parse_gauges(raw.get("gauges", []), terrain.dem, path)
    paths = _parse_paths(raw.get("paths", []), terrain.dem, path)
    fmt = _parse_output(raw.get("output", {}), path)
    cfg = Config(path=path, terrain=terrain, model=model, run=run, gauges=gauges, paths=paths, raw=raw,
                 output_format=fmt)
    for name, parser in extra_sections.items():
        if name in raw:
            cfg.extra[name] = parser(raw[name], cfg)
    return cfg


def load_config(path, extra_sections: dict[str, Callable[[Any, Config], Any]] | None = None) -> Config:
    """Read and validate a TOML config (see the module docstring); raises :class:`ConfigError`.

    ``extra_sections`` maps section names to parsers ``(table, cfg) -> object`` (stored in ``cfg.extra``).
    """
    path = Path(path)
    return parse_config(read_toml(path), path, extra_sections)
