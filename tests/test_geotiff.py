"""GeoTIFF input (the `geo` extra, rasterio): every read path gets the same checks and orientation.

Skipped where rasterio is not installed; the dev extra (`make test`) installs it, so CI runs these.
"""
from __future__ import annotations

import numpy as np
import pytest

rasterio = pytest.importorskip("rasterio")
from rasterio.transform import Affine  # noqa: E402

from torchslide.config import load_config  # noqa: E402
from torchslide.observe_series import read_map  # noqa: E402
from torchslide.terrain import DEM, read_raster, read_raster_like, write_raster  # noqa: E402
from torchslide.terrain.io import TerrainError  # noqa: E402

from .conftest import cfg_text, write_case  # noqa: E402

CRS = "EPSG:2056"  # Swiss LV95, as for the Bondo case


def _dem(ny=4, nx=5, cs=10.0, xll=100.0, yll=200.0):
    return DEM(z=np.random.default_rng(0).uniform(0, 100, (ny, nx)), cellsize=cs, xll=xll, yll=yll)


def _write(path, rows, transform, *, count=1, nodata=-9999.0):
    """Write ``rows`` (file order: row 0 first) with a raw transform, as another program would."""
    a = np.asarray(rows, dtype=np.float64)
    with rasterio.open(path, "w", driver="GTiff", height=a.shape[0], width=a.shape[1], count=count,
                       dtype="float64", crs=CRS, transform=transform, nodata=nodata) as dst:
        for b in range(1, count + 1):
            dst.write(a, b)


def test_round_trip_keeps_values_grid_nodata_and_crs(tmp_path):
    dem = _dem()
    dem = DEM(z=dem.z, cellsize=dem.cellsize, xll=dem.xll, yll=dem.yll, crs=rasterio.crs.CRS.from_string(CRS).to_wkt())
    a = dem.z.copy()
    a[1, 2] = np.nan  # written as nodata
    write_raster(tmp_path / "a.tif", a, dem)
    m = read_map(tmp_path / "a.tif", dem, what="deposit map")  # a map keeps nodata as NaN
    assert np.isnan(m[1, 2]) and np.isfinite(np.delete(m.ravel(), 1 * 5 + 2)).all()
    z = read_raster_like(tmp_path / "a.tif", dem, what="release")  # nodata -> 0 for a release
    assert z[1, 2] == 0.0
    np.testing.assert_array_equal(np.delete(z.ravel(), 1 * 5 + 2), np.delete(dem.z.ravel(), 1 * 5 + 2))
    write_raster(tmp_path / "d.tif", dem.z, dem)
    back = read_raster(tmp_path / "d.tif")
    assert back.same_grid(dem) and back.crs is not None and "2056" in back.crs
    np.testing.assert_array_equal(back.z, dem.z)


def test_south_up_file_reads_like_north_up(tmp_path):
    dem = _dem()
    ymax = dem.yll + dem.ny * dem.cellsize
    _write(tmp_path / "north.tif", dem.z[::-1], Affine(10.0, 0, dem.xll, 0, -10.0, ymax))
    _write(tmp_path / "south.tif", dem.z, Affine(10.0, 0, dem.xll, 0, 10.0, dem.yll))
    for name in ("north.tif", "south.tif"):
        back = read_raster(tmp_path / name)
        assert back.same_grid(dem), name
        np.testing.assert_array_equal(back.z, dem.z)
        # the same file as a release / map on the DEM's grid: same orientation (a south-up file is
        # neither flipped nor shifted)
        np.testing.assert_array_equal(read_raster_like(tmp_path / name, dem, what="release"), dem.z)
        np.testing.assert_array_equal(read_map(tmp_path / name, dem), dem.z)


@pytest.mark.parametrize(
    "transform,count,band,match",
    [
        (Affine(10.0, 0, 100.0, 0, -12.0, 248.0), 1, 1, r"pixels are not square \(10 x 12 m\)"),
        (Affine(10.0, 0.5, 100.0, 0.5, -10.0, 240.0), 1, 1, "rotated rasters are not supported"),
        (Affine(-10.0, 0, 150.0, 0, -10.0, 240.0), 1, 1, "columns run east to west"),
        (Affine(10.0, 0, 100.0, 0, -10.0, 240.0), 1, 2, r"band 2 does not exist \(the file has 1\)"),
    ],
)
def test_unsupported_layouts_are_refused_on_every_path(tmp_path, transform, count, band, match):
    from torchslide.terrain.io import _geotiff, read_geotiff

    p = tmp_path / "x.tif"
    _write(p, _dem().z[::-1], transform, count=count)
    with pytest.raises(TerrainError, match=match):
        read_geotiff(p, band=band)
    with pytest.raises(TerrainError, match=match):
        _geotiff(p, band=band)
    if band == 1:  # what a release or map raster goes through
        with pytest.raises(TerrainError, match=match):
            read_raster_like(p, _dem(), what="release")
        with pytest.raises(TerrainError, match=match):
            read_map(p, _dem())


def test_a_case_given_as_geotiffs_loads_like_the_asc_case(tmp_path):
    dem, rel = write_case(tmp_path)
    write_raster(tmp_path / "dem.tif", dem.z, dem)
    write_raster(tmp_path / "release.tif", rel, dem)
    (tmp_path / "asc.toml").write_text(cfg_text())
    (tmp_path / "tif.toml").write_text(cfg_text().replace('"dem.asc"', '"dem.tif"').replace('"release.asc"', '"release.tif"'))
    a, t = load_config(tmp_path / "asc.toml"), load_config(tmp_path / "tif.toml")
    assert t.terrain.dem.same_grid(a.terrain.dem)
    np.testing.assert_allclose(t.terrain.dem.z, a.terrain.dem.z, rtol=0, atol=1e-9)
    np.testing.assert_allclose(t.terrain.release, a.terrain.release, rtol=0, atol=1e-12)


def test_simulate_writes_geotiffs_with_the_dems_crs(tmp_path, capsys):
    """`[output] format = "tif"`: simulate writes .tif rasters on the DEM's grid with its CRS, equal to the
    .asc run's values."""
    from torchslide.cli import main

    dem, rel = write_case(tmp_path)
    crs = rasterio.crs.CRS.from_string(CRS).to_wkt()
    write_raster(tmp_path / "dem.tif", dem.z, DEM(z=dem.z, cellsize=dem.cellsize, xll=dem.xll, yll=dem.yll, crs=crs))
    write_raster(tmp_path / "release.tif", rel, dem)
    text = cfg_text().replace('"dem.asc"', '"dem.tif"').replace('"release.asc"', '"release.tif"')
    (tmp_path / "tif.toml").write_text(text.replace("t_end = 20.0", "t_end = 6.0") + '\n[output]\nformat = "tif"\n')
    (tmp_path / "asc.toml").write_text(cfg_text().replace("t_end = 20.0", "t_end = 6.0"))
    assert main(["simulate", str(tmp_path / "tif.toml"), "--out", str(tmp_path / "t"), "-q"]) == 0
    assert main(["simulate", str(tmp_path / "asc.toml"), "--out", str(tmp_path / "a"), "-q"]) == 0
    tifs = sorted(p.name for p in (tmp_path / "t").glob("*.tif"))
    assert tifs == ["arrival_time.tif", "h_final.tif", "h_max.tif", "p_max.tif", "v_max.tif"]
    assert not list((tmp_path / "t").glob("*.asc"))
    h = read_raster(tmp_path / "t" / "h_max.tif")
    assert h.same_grid(dem) and h.crs is not None and "2056" in h.crs
    np.testing.assert_allclose(h.z, read_raster(tmp_path / "a" / "h_max.asc").z, rtol=1e-12, atol=1e-12)
