"""Raster I/O: ESRI ASCII grids (always) and GeoTIFF (when rasterio is installed).

Conventions (see :mod:`torchslide.terrain.grid`): arrays are (ny, nx) with row 0 the *southern*
row; files store the northern row first, so readers and writers flip. ``xll, yll`` is the
lower-left *corner*; an ``xllcenter``/``yllcenter`` header is converted to the corner on read.

Public functions:

* :func:`read_asc`, :func:`write_asc` -- ESRI ASCII grid.
* :func:`read_geotiff`, :func:`write_geotiff` -- GeoTIFF via rasterio (``pip install torchslide[geo]``).
* :func:`read_raster` (dispatch on extension, returns a DEM), :func:`write_raster`.
* :func:`read_dem` -- read_raster with a DEM-specific name.
* :func:`read_raster_like` -- read a raster (release, erodible depth, ...) that must share a DEM's grid.
"""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from .grid import DEM, TerrainError, same_crs

__all__ = [
    "read_asc",
    "write_asc",
    "read_geotiff",
    "write_geotiff",
    "read_raster",
    "read_dem",
    "write_raster",
    "read_raster_like",
    "read_raster_on_grid",
    "write_named_raster",
]

ASC_EXTENSIONS = (".asc", ".txt", ".grd")
TIFF_EXTENSIONS = (".tif", ".tiff", ".gtiff")

_REQUIRED = ("ncols", "nrows", "cellsize")
_KNOWN = {"ncols", "nrows", "cellsize", "xllcorner", "yllcorner", "xllcenter", "yllcenter", "nodata_value",
          "xllcentre", "yllcentre"}


# --------------------------------------------------------------------------------------------- ASC
def _fill_nearest(z: np.ndarray, bad: np.ndarray) -> np.ndarray:
    """Fill cells where ``bad`` is True with the value of the nearest good cell (Euclidean in cells)."""
    from scipy import ndimage

    _, (ii, jj) = ndimage.distance_transform_edt(bad, return_indices=True)
    return z[ii, jj]


def _edge_connected(bad: np.ndarray) -> np.ndarray:
    """Bool mask of nodata cells connected (4-neighbour) to the grid edge."""
    from scipy import ndimage

    lab, _ = ndimage.label(bad)
    edge_labels = set(np.unique(np.concatenate([lab[0], lab[-1], lab[:, 0], lab[:, -1]]))) - {0}
    return np.isin(lab, list(edge_labels)) if edge_labels else np.zeros_like(bad)


NODATA = ("error", "fill", "outside")
"""What a DEM reader does with nodata cells: refuse them, fill edge-connected ones by nearest neighbour,
or mark them outside the domain (DEM.outside; their z filled by nearest neighbour for the slopes only)."""


def _dem_with_nodata(z: np.ndarray, path, cellsize, xll, yll, crs, nodata: str) -> DEM:
    """A DEM of ``z`` (NaN at nodata) handled as ``nodata`` says (NODATA)."""
    bad = ~np.isfinite(z)
    if nodata == "outside" and bad.any():
        if bad.all():
            raise TerrainError(f"{path}: every cell is nodata")
        return DEM(z=_fill_nearest(z, bad), cellsize=cellsize, xll=xll, yll=yll, crs=crs, outside=bad)
    return DEM(z=_handle_nodata(z, path, cellsize, xll, yll, nodata == "fill"), cellsize=cellsize, xll=xll, yll=yll,
               crs=crs)


def _handle_nodata(z: np.ndarray, path, cellsize, xll, yll, fill_nodata: bool) -> np.ndarray:
    """Raise on nodata/NaN cells, or fill edge-connected ones by nearest neighbour when asked."""
    bad = ~np.isfinite(z)
    if not bad.any():
        return z
    if fill_nodata:
        edge = _edge_connected(bad)
        interior = bad & ~edge
        if interior.any():
            i, j = np.argwhere(interior)[0]
            raise TerrainError(
                f"{path}: {int(interior.sum())} nodata cells inside the domain (not connected to the edge) "
                f"cannot be filled, first at row {i} from the south, col {j} "
                f"(x={xll + (j + 0.5) * cellsize:.1f} m, y={yll + (i + 0.5) * cellsize:.1f} m)"
            )
        if bad.all():
            raise TerrainError(f"{path}: every cell is nodata")
        return _fill_nearest(z, bad)
    i, j = np.argwhere(bad)[0]
    raise TerrainError(
        f"{path}: {int(bad.sum())} nodata cells, first at row {i} from the south, col {j} "
        f"(x={xll + (j + 0.5) * cellsize:.1f} m, y={yll + (i + 0.5) * cellsize:.1f} m); "
        "fix the raster or pass fill_nodata=True to fill edge cells by nearest neighbour"
    )


def read_asc(path, *, fill_nodata: bool = False, allow_nodata: bool = False, nodata: str | None = None) -> DEM:
    """Read an ESRI ASCII grid into a :class:`DEM` (row 0 south).

    Header keys are case-insensitive; ``xllcorner``/``yllcorner`` or ``xllcenter``/``yllcenter``
    (converted to the corner); ``nodata_value`` optional. Cells equal to nodata (or NaN) raise a
    :class:`TerrainError` naming the file, the count and the first location, unless
    ``fill_nodata=True`` (cells connected to the grid edge are filled from the nearest valid cell).
    ``allow_nodata=True`` sets nodata cells to 0 instead (for non-DEM rasters); leave it False for DEMs.
    ``nodata="outside"`` marks them outside the domain (DEM.outside). The CRS comes from a ``.prj``
    file beside the grid, when there is one.
    """
    z, cellsize, xll, yll = read_asc_array(path)
    crs = read_prj(path)
    if allow_nodata:
        return DEM(z=np.where(np.isfinite(z), z, 0.0), cellsize=cellsize, xll=xll, yll=yll, crs=crs)
    return _dem_with_nodata(z, path, cellsize, xll, yll, crs, nodata or ("fill" if fill_nodata else "error"))


def read_prj(path) -> str | None:
    """The CRS (WKT) in the ``.prj`` file beside an ESRI ASCII grid, or None when there is none."""
    prj = Path(path).with_suffix(".prj")
    if not prj.is_file():
        return None
    text = prj.read_text().strip()
    return text or None


def read_asc_array(path) -> tuple[np.ndarray, float, float, float]:
    """Parse an ESRI ASCII grid: returns (z (ny, nx) row 0 south with NaN at nodata, cellsize, xll, yll)."""
    path = Path(path)
    if not path.exists():
        raise TerrainError(f"{path}: file not found")
    try:
        text = path.read_text()
    except UnicodeDecodeError:
        raise TerrainError(f"{path}: not a text file (expected an ESRI ASCII grid)") from None
    lines = text.splitlines()
    header: dict[str, float] = {}
    n = 0
    while n < len(lines):
        parts = lines[n].split()
        if not parts:
            n += 1
            continue
        key = parts[0].lower()
        if not _isfloat(key) and key[0].isalpha():   # a number ("nan" and "inf" too) starts the data
            if key not in _KNOWN:
                raise TerrainError(f"{path}, line {n + 1}: unknown header key {parts[0]!r}")
            if len(parts) != 2:
                raise TerrainError(f"{path}, line {n + 1}: header line must be 'key value', got {lines[n].strip()!r}")
            try:
                header[key.replace("centre", "center")] = float(parts[1])
            except ValueError:
                raise TerrainError(f"{path}, line {n + 1}: header value {parts[1]!r} for {parts[0]} is not a number") from None
            n += 1
        else:
            break
    for k in _REQUIRED:
        if k not in header:
            raise TerrainError(f"{path}: header is missing {k!r}")
    ncols, nrows = header["ncols"], header["nrows"]
    if ncols != int(ncols) or nrows != int(nrows) or ncols < 1 or nrows < 1:
        raise TerrainError(f"{path}: ncols/nrows must be positive integers, got {ncols:g}/{nrows:g}")
    ncols, nrows = int(ncols), int(nrows)
    cs = header["cellsize"]
    if not (np.isfinite(cs) and cs > 0):
        raise TerrainError(f"{path}: cellsize must be positive, got {cs:g}")
    if "xllcorner" in header:
        xll = header["xllcorner"]
    elif "xllcenter" in header:
        xll = header["xllcenter"] - 0.5 * cs
    else:
        raise TerrainError(f"{path}: header is missing 'xllcorner' or 'xllcenter'")
    if "yllcorner" in header:
        yll = header["yllcorner"]
    elif "yllcenter" in header:
        yll = header["yllcenter"] - 0.5 * cs
    else:
        raise TerrainError(f"{path}: header is missing 'yllcorner' or 'yllcenter'")
    nodata = header.get("nodata_value")

    rows = []
    for ln in range(n, len(lines)):
        parts = lines[ln].split()
        if not parts:
            continue
        if len(parts) != ncols:
            raise TerrainError(f"{path}, line {ln + 1}: expected {ncols} values (ncols), found {len(parts)}")
        try:
            rows.append([float(p) for p in parts])
        except ValueError:
            bad = next(p for p in parts if not _isfloat(p))
            raise TerrainError(f"{path}, line {ln + 1}: non-numeric value {bad!r}") from None
    if len(rows) != nrows:
        raise TerrainError(f"{path}: expected {nrows} data rows (nrows), found {len(rows)}")
    z = np.asarray(rows, dtype=np.float64)[::-1].copy()  # file is north first -> row 0 south
    # NODATA_value may be any number, nan or +-inf (com1DFA writes nan); other non-finite values are errors
    missing = np.zeros(z.shape, dtype=bool) if nodata is None else (np.isnan(z) if np.isnan(nodata) else z == nodata)
    _refuse_non_finite(np.where(missing, 0.0, z), path, allow_nan=False)
    z[missing] = np.nan
    return z, float(cs), float(xll), float(yll)


def _refuse_non_finite(z: np.ndarray, path, allow_nan: bool) -> None:
    """A raster value that is infinite (or NaN, where NaN is not the format's nodata) is an error, not a
    missing cell: TerrainError naming the first one (row 0 south)."""
    bad = np.isinf(z) if allow_nan else ~np.isfinite(z)
    if bad.any():
        i, j = np.argwhere(bad)[0]
        raise TerrainError(f"{path}: {int(bad.sum())} non-finite values, first {z[i, j]} at row {i} from the south, "
                           f"col {j}; mark cells without data with the NODATA_value instead")


def _isfloat(s: str) -> bool:
    try:
        float(s)
        return True
    except ValueError:
        return False


def write_asc(path, array, dem: DEM, *, nodata_value: float | None = -9999.0, fmt: str = "%.6g") -> None:
    """Write ``array`` ((ny, nx), row 0 south, on ``dem``'s grid) as an ESRI ASCII grid.

    Non-finite cells and cells outside the DEM's domain are written as ``nodata_value``. Uses
    ``xllcorner``/``yllcorner``. ``fmt`` defaults to 6 significant digits; pass ``"%.17g"`` for an exact
    float64 round trip. The DEM's CRS goes into a ``.prj`` file beside the grid.
    """
    a = _masked(array, dem, path)[::-1]
    bad = ~np.isfinite(a)
    if bad.any():
        if nodata_value is None:
            raise TerrainError(f"{path}: array has non-finite values and nodata_value is None")
        a = np.where(bad, nodata_value, a)
    lines = [
        f"ncols {dem.nx}",
        f"nrows {dem.ny}",
        f"xllcorner {dem.xll!r}",
        f"yllcorner {dem.yll!r}",
        f"cellsize {dem.cellsize!r}",
    ]
    if nodata_value is not None:
        lines.append(f"NODATA_value {nodata_value:g}")
    body = "\n".join(" ".join(fmt % v for v in row) for row in a)
    Path(path).write_text("\n".join(lines) + "\n" + body + "\n")
    if dem.crs:
        Path(path).with_suffix(".prj").write_text(dem.crs + "\n")


def _masked(array, dem: DEM, path) -> np.ndarray:
    """``array`` as float64 (ny, nx), NaN outside the DEM's domain; TerrainError when the shape differs."""
    a = np.asarray(array, dtype=np.float64)
    if a.shape != dem.shape:
        raise TerrainError(f"{path}: array shape {a.shape} does not match the DEM grid {dem.shape}")
    return np.where(dem.outside, np.nan, a) if dem.outside is not None else a


# ----------------------------------------------------------------------------------------- GeoTIFF
def _rasterio():
    try:
        import rasterio  # noqa: F401
    except ImportError:
        raise TerrainError(
            "GeoTIFF support needs rasterio, which is not installed: `pip install torchslide[geo]` "
            "(or convert the raster to ESRI ASCII .asc)"
        ) from None
    return rasterio


def _geotiff(path, band: int = 1):
    """(z (ny, nx) row 0 south with NaN at nodata, cellsize, xll, yll, crs WKT or None) of one band.

    Every GeoTIFF read goes through here, so a DEM and a map or release raster get the same checks:
    north-up or south-up, unrotated, square pixels, an existing band. Raises TerrainError naming the
    file and what is wrong.
    """
    rasterio = _rasterio()
    path = Path(path)
    if not path.exists():
        raise TerrainError(f"{path}: file not found")
    with rasterio.open(path) as src:
        t = src.transform
        if abs(t.b) > 0 or abs(t.d) > 0:
            raise TerrainError(f"{path}: rotated rasters are not supported (transform {tuple(t)[:6]})")
        if not np.isclose(abs(t.a), abs(t.e), rtol=1e-9):
            raise TerrainError(f"{path}: pixels are not square ({abs(t.a):g} x {abs(t.e):g} m)")
        if t.a < 0:
            raise TerrainError(f"{path}: columns run east to west (pixel width {t.a:g}); not supported")
        if not 1 <= band <= src.count:
            raise TerrainError(f"{path}: band {band} does not exist (the file has {src.count})")
        z = src.read(band).astype(np.float64)
        nodata = src.nodata
        cs = abs(t.a)
        xll = t.c
        if t.e < 0:  # north-up: row 0 is the north edge
            yll = t.f - src.height * cs
            z = z[::-1]
        else:  # south-up: row 0 is already the south edge
            yll = t.f
        crs = src.crs.to_wkt() if src.crs else None
    z = z.copy()
    _refuse_non_finite(z, path, allow_nan=True)     # NaN is a GeoTIFF's usual nodata
    if nodata is not None:
        z[z == nodata] = np.nan
    return z, cs, xll, yll, crs


def read_geotiff(path, *, fill_nodata: bool = False, band: int = 1, nodata: str | None = None) -> DEM:
    """Read one band of a GeoTIFF into a :class:`DEM` (needs rasterio). Square, unrotated pixels only;
    nodata as for :func:`read_asc`."""
    z, cs, xll, yll, crs = _geotiff(path, band)
    return _dem_with_nodata(z, path, cs, xll, yll, crs, nodata or ("fill" if fill_nodata else "error"))


def write_geotiff(path, array, dem: DEM, *, nodata_value: float = -9999.0) -> None:
    """Write ``array`` ((ny, nx), row 0 south) as a single-band float64 GeoTIFF (needs rasterio)."""
    rasterio = _rasterio()
    from rasterio.transform import from_origin

    a = _masked(array, dem, path)
    a = np.where(np.isfinite(a), a, nodata_value)[::-1]
    _, _, _, ymax = dem.extent
    transform = from_origin(dem.xll, ymax, dem.cellsize, dem.cellsize)
    with rasterio.open(
        path, "w", driver="GTiff", height=dem.ny, width=dem.nx, count=1, dtype="float64",
        crs=dem.crs, transform=transform, nodata=nodata_value,
    ) as dst:
        dst.write(a, 1)


# ----------------------------------------------------------------------------------------- dispatch
def _kind(path) -> str:
    ext = os.path.splitext(str(path))[1].lower()
    if ext in ASC_EXTENSIONS:
        return "asc"
    if ext in TIFF_EXTENSIONS:
        return "tif"
    raise TerrainError(
        f"{path}: unknown raster extension {ext!r} (expected one of {', '.join(ASC_EXTENSIONS + TIFF_EXTENSIONS)})"
    )


def read_raster(path, *, fill_nodata: bool = False, nodata: str | None = None) -> DEM:
    """Read an .asc or .tif raster into a :class:`DEM` (dispatch on the extension); ``nodata``: NODATA."""
    if _kind(path) == "asc":
        return read_asc(path, fill_nodata=fill_nodata, nodata=nodata)
    return read_geotiff(path, fill_nodata=fill_nodata, nodata=nodata)


read_dem = read_raster


def write_raster(path, array, dem: DEM, **kwargs) -> None:
    """Write ``array`` ((ny, nx) numpy or torch, row 0 south) on ``dem``'s grid; format from the extension."""
    try:
        import torch

        if isinstance(array, torch.Tensor):
            array = array.detach().cpu().double().numpy()
    except ImportError:  # pragma: no cover
        pass
    if _kind(path) == "asc":
        write_asc(path, array, dem, **kwargs)
    else:
        write_geotiff(path, array, dem, **kwargs)


def write_named_raster(folder, name: str, array, dem: DEM, output_format: str = "asc",
                       number_format: str = "%.6g") -> Path:
    """Write ``array`` ((ny, nx), row 0 south) as ``folder/name.asc`` (ESRI ASCII, values as
    ``number_format``) or ``folder/name.tif`` (float64 GeoTIFF with the DEM's CRS); returns the path."""
    if output_format not in ("asc", "tif"):
        raise TerrainError(f"unknown raster output format {output_format!r} (asc or tif)")
    path = Path(folder) / f"{name}.{output_format}"
    if output_format == "asc":
        write_raster(path, array, dem, fmt=number_format)
    else:
        write_raster(path, array, dem)
    return path


def _grid_str(dem: DEM) -> str:
    return f"{dem.ny}x{dem.nx} cells of {dem.cellsize:g} m at xll={dem.xll:g}, yll={dem.yll:g}"


def read_raster_on_grid(path, dem: DEM, what: str = "map") -> np.ndarray:
    """A raster (.asc or .tif) that must lie on ``dem``'s grid: its (ny, nx) array, row 0 south, nodata as NaN.

    Raises :class:`TerrainError` naming the file, ``what`` it is, and both grids when shape, cell size
    or origin differ, or the CRSs when both are known and differ; a DEM without a CRS takes the raster's.
    """
    if _kind(path) == "asc":
        z, cs, xll, yll = read_asc_array(path)
        crs = read_prj(path)
    else:
        z, cs, xll, yll, crs = _geotiff(path)
    if not same_crs(crs, dem.crs):
        raise TerrainError(f"{path}: {what} CRS differs from the DEM's; reproject it onto the DEM's grid and CRS")
    if crs and not dem.crs:     # a DEM without a CRS takes the first one its inputs carry
        dem.crs = crs
    ny, nx = z.shape
    same = (
        (ny, nx) == dem.shape
        and abs(cs - dem.cellsize) <= 1e-9 * dem.cellsize
        and abs(xll - dem.xll) <= 1e-6 * dem.cellsize
        and abs(yll - dem.yll) <= 1e-6 * dem.cellsize
    )
    if not same:
        raise TerrainError(
            f"{path}: {what} grid ({ny}x{nx} cells of {cs:g} m at xll={xll:g}, yll={yll:g}) "
            f"does not match the DEM grid ({_grid_str(dem)})"
        )
    return np.asarray(z, dtype=np.float64)


def read_raster_like(path, dem: DEM, what: str = "release", *, nodata_as_zero: bool = True) -> np.ndarray:
    """Read a raster that must lie on ``dem``'s grid (:func:`read_raster_on_grid`); returns its (ny, nx)
    array (row 0 south). Nodata cells become 0 (``nodata_as_zero``; usual for release and erodible-depth
    rasters) or raise.
    """
    z = read_raster_on_grid(path, dem, what)
    bad = ~np.isfinite(z)
    if bad.any():
        if nodata_as_zero:
            z = np.where(bad, 0.0, z)
        else:
            _handle_nodata(z, path, dem.cellsize, dem.xll, dem.yll, False)
    return z
