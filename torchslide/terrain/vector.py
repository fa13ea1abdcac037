"""Polygon and polyline inputs: release and erodible areas, observed outlines, paths.

Vector files (ESRI shapefile, GeoJSON, GeoPackage, anything GDAL reads) are read with pyogrio and
shapely (``pip install torchslide[geo]``) and burnt onto a DEM's grid with rasterio.features: a cell
belongs to a polygon when its centre lies inside it. Where polygons overlap, the later feature wins.

The CRS of a vector file must be the DEM's when both are known (a GeoJSON file without a "crs" member
is WGS 84 by its standard); a DEM without a CRS takes the vector file's. torchslide does not reproject
(use ``ogr2ogr -t_srs`` or QGIS).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .grid import DEM, TerrainError, same_crs

__all__ = ["VECTOR_EXTENSIONS", "is_vector", "Feature", "read_features", "rasterize_thickness",
           "rasterize_outline", "read_polyline"]

VECTOR_EXTENSIONS = (".shp", ".geojson", ".json", ".gpkg", ".fgb", ".kml", ".gml")


def is_vector(path) -> bool:
    """True when ``path`` names a vector file (by extension)."""
    return Path(path).suffix.lower() in VECTOR_EXTENSIONS


@dataclass
class Feature:
    """One feature of a vector file: its shapely geometry, its attributes and its number (1-based)."""

    geometry: object
    attributes: dict
    number: int


def _libs():
    try:
        import pyogrio.raw  # noqa: F401
        import shapely
    except ImportError:  # pragma: no cover - the geo extra is installed with dev
        raise TerrainError("reading polygon or line files needs pyogrio and shapely: pip install torchslide[geo]") from None
    import pyogrio.raw as raw
    return raw, shapely


def read_features(path, geometry: str = "polygon") -> tuple[list[Feature], str | None]:
    """(features, CRS string or None) of a vector file whose geometries are all polygons (``geometry``
    "polygon") or all lines ("line"). TerrainError naming the file (and the feature) otherwise."""
    raw, shapely = _libs()
    path = Path(path)
    if not path.is_file():
        raise TerrainError(f"{path}: file not found")
    try:
        meta, _, geoms, fields = raw.read(str(path))
    except Exception as e:  # pyogrio raises DataSourceError and friends; name the file in one line
        raise TerrainError(f"{path}: not a readable vector file ({type(e).__name__}: {str(e).splitlines()[0]})") from None
    names = list(meta.get("fields", []))
    if geoms is None or len(geoms) == 0:
        raise TerrainError(f"{path}: the file holds no features")
    want = ("Polygon", "MultiPolygon") if geometry == "polygon" else ("LineString", "MultiLineString")
    out = []
    for i, wkb in enumerate(geoms):
        g = shapely.from_wkb(wkb) if wkb is not None else None
        if g is None or g.is_empty:
            raise TerrainError(f"{path}: feature {i + 1} has no geometry")
        if g.geom_type not in want:
            raise TerrainError(f"{path}: feature {i + 1} is a {g.geom_type}, expected a {' or '.join(want)}")
        if geometry == "polygon" and not g.is_valid:
            raise TerrainError(f"{path}: feature {i + 1} is not a valid polygon ({shapely.is_valid_reason(g)})")
        attrs = {n: fields[k][i] for k, n in enumerate(names)}
        out.append(Feature(g, attrs, i + 1))
    return out, meta.get("crs")


def _check_crs(path, crs, dem: DEM) -> None:
    """A CRS unlike the DEM's is an error; a DEM without one takes the file's (so the outputs carry it)."""
    if crs and not dem.crs:
        dem.crs = crs
    if not same_crs(crs, dem.crs):
        raise TerrainError(f"{path}: its CRS ({_short(crs)}) differs from the DEM's ({_short(dem.crs)}); "
                           f"reproject the file to the DEM's CRS (e.g. ogr2ogr -t_srs)")


def _short(crs: str | None) -> str:
    try:
        from rasterio.crs import CRS

        c = CRS.from_user_input(crs)
        return c.to_string() or crs
    except Exception:
        return str(crs)[:60]


def _burn(shapes, dem: DEM) -> np.ndarray:
    """(ny, nx) row 0 south: each (geometry, value) burnt on the cells whose centre it holds, later wins."""
    from rasterio import features, transform

    ny, nx = dem.shape
    tr = transform.from_origin(dem.xll, dem.yll + ny * dem.cellsize, dem.cellsize, dem.cellsize)
    a = features.rasterize(list(shapes), out_shape=(ny, nx), transform=tr, fill=np.nan, dtype="float64",
                           all_touched=False)
    return a[::-1].copy()


def rasterize_thickness(path, dem: DEM, attribute: str = "thickness", default: float | None = None,
                        what: str = "release") -> np.ndarray:
    """(ny, nx) thickness, m, of the polygons in ``path`` on ``dem``'s grid (0 outside every polygon).

    Each feature's thickness is its ``attribute`` or, where it has none, ``default``; a feature
    without either, a thickness that is not a finite number > 0, a polygon that covers no cell centre
    of the DEM and a CRS unlike the DEM's are one-line TerrainErrors naming the file and the feature."""
    feats, crs = read_features(path, "polygon")
    _check_crs(path, crs, dem)
    shapes = []
    for f in feats:
        v = f.attributes.get(attribute)
        if v is None or (isinstance(v, float) and math.isnan(v)):
            if default is None:
                raise TerrainError(f"{path}: feature {f.number} has no {attribute!r} attribute and no {what} "
                                   f"thickness is configured for it")
            v = default
        try:
            v = float(v)
        except (TypeError, ValueError):
            raise TerrainError(f"{path}: feature {f.number}: {attribute} = {v!r} is not a number") from None
        if not (math.isfinite(v) and v > 0):
            raise TerrainError(f"{path}: feature {f.number}: {attribute} must be a number of m > 0, got {v!r}")
        covered = _burn([(f.geometry, 1.0)], dem)
        if not np.isfinite(covered).any():
            x0, y0, x1, y1 = f.geometry.bounds
            raise TerrainError(f"{path}: feature {f.number} (x {x0:g}..{x1:g}, y {y0:g}..{y1:g} m) covers no cell "
                               f"centre of the DEM (x {dem.extent[0]:g}..{dem.extent[2]:g}, "
                               f"y {dem.extent[1]:g}..{dem.extent[3]:g} m)")
        shapes.append((f.geometry, v))
    a = _burn(shapes, dem)
    return np.where(np.isfinite(a), a, 0.0)


def rasterize_outline(path, dem: DEM) -> np.ndarray:
    """(ny, nx) impact map of an observed outline: 1 inside the polygons of ``path``, 0 elsewhere."""
    feats, crs = read_features(path, "polygon")
    _check_crs(path, crs, dem)
    a = _burn([(f.geometry, 1.0) for f in feats], dem)
    if not np.isfinite(a).any():
        raise TerrainError(f"{path}: the outline covers no cell centre of the DEM")
    return np.where(np.isfinite(a), 1.0, 0.0)


def read_polyline(path, dem: DEM) -> np.ndarray:
    """(N, 2) vertices, map m, of the single line feature in ``path`` (its parts joined in order)."""
    feats, crs = read_features(path, "line")
    _check_crs(path, crs, dem)
    if len(feats) != 1:
        raise TerrainError(f"{path}: a path is one line feature, the file holds {len(feats)}")
    g = feats[0].geometry
    parts = list(g.geoms) if g.geom_type == "MultiLineString" else [g]
    xy = np.concatenate([np.asarray(p.coords)[:, :2] for p in parts])
    return xy
