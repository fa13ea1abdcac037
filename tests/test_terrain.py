"""Terrain: ESRI ASCII I/O, fields, synthetic terrains, releases."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from torchslide.terrain import (
    DEM,
    TerrainError,
    bondo_like,
    bowl,
    channel_with_bends,
    curvature,
    gradient,
    hillshade,
    inclined_plane,
    parabola,
    read_asc,
    read_raster,
    read_raster_like,
    release_from_raster,
    release_from_shape,
    slope_deg,
    thalweg_length,
    unit_normal,
    write_asc,
    write_raster,
)
from torchslide.terrain.io import read_geotiff


def _dem(ny=4, nx=5, cs=10.0, xll=100.0, yll=200.0):
    rng = np.random.default_rng(0)
    return DEM(z=rng.uniform(0, 100, (ny, nx)), cellsize=cs, xll=xll, yll=yll)


# ------------------------------------------------------------------------------------------ ASC I/O
def test_asc_round_trip_exact(tmp_path):
    dem = _dem()
    p = tmp_path / "dem.asc"
    write_asc(p, dem.z, dem, fmt="%.17g")
    back = read_asc(p)
    assert back.same_grid(dem)
    np.testing.assert_array_equal(back.z, dem.z)


def test_asc_row_order_and_corner(tmp_path):
    p = tmp_path / "a.asc"
    p.write_text("NCOLS 3\nnrows 3\nXLLCENTER 5\nyllcenter 15\nCellSize 10\nnodata_value -9999\n"
                 "7 8 9\n4 5 6\n1 2 3\n")
    dem = read_asc(p)
    assert (dem.xll, dem.yll, dem.cellsize) == (0.0, 10.0, 10.0)
    # first file row is the northern row -> last array row
    np.testing.assert_array_equal(dem.z[0], [1, 2, 3])
    np.testing.assert_array_equal(dem.z[-1], [7, 8, 9])
    assert dem.index(25.0, 35.0) == (2, 2) and dem.z[2, 2] == 9


def test_asc_nodata_error_and_fill(tmp_path):
    p = tmp_path / "nd.asc"
    p.write_text("ncols 3\nnrows 3\nxllcorner 0\nyllcorner 0\ncellsize 1\nNODATA_value -9999\n"
                 "-9999 8 9\n4 5 6\n1 2 3\n")
    with pytest.raises(TerrainError, match=r"nd\.asc: 1 nodata cells, first at row 2 .*col 0"):
        read_asc(p)
    dem = read_asc(p, fill_nodata=True)
    assert dem.z[2, 0] in (4.0, 8.0)  # a nearest neighbour
    # interior nodata cannot be filled
    p2 = tmp_path / "nd2.asc"
    p2.write_text("ncols 3\nnrows 3\nxllcorner 0\nyllcorner 0\ncellsize 1\nNODATA_value -9999\n"
                  "7 8 9\n4 -9999 6\n1 2 3\n")
    with pytest.raises(TerrainError, match="inside the domain"):
        read_asc(p2, fill_nodata=True)


def test_asc_write_nodata_round_trip(tmp_path):
    dem = _dem()
    a = dem.z.copy()
    a[1, 2] = np.inf
    p = tmp_path / "w.asc"
    write_asc(p, a, dem)
    assert "NODATA_value -9999" in p.read_text()
    with pytest.raises(TerrainError, match="1 nodata cells"):
        read_asc(p)
    z = read_raster_like(p, dem)
    assert z[1, 2] == 0.0


@pytest.mark.parametrize(
    "text,match",
    [
        ("ncols 3\nnrows 2\nxllcorner 0\ncellsize 1\n1 2 3\n4 5 6\n", "missing 'yllcorner'"),
        ("ncols 3\nnrows 2\nxllcorner 0\nyllcorner 0\ncellsize abc\n1 2 3\n4 5 6\n", r"line 5: header value 'abc'"),
        ("ncols 3\nnrows 2\nxllcorner 0\nyllcorner 0\nfoo 1\n1 2 3\n4 5 6\n", r"line 5: unknown header key 'foo'"),
        ("ncols 3\nnrows 3\nxllcorner 0\nyllcorner 0\ncellsize 1\n1 2 3\n4 5 6\n", "expected 3 data rows"),
        ("ncols 3\nnrows 2\nxllcorner 0\nyllcorner 0\ncellsize 1\n1 2 3\n4 5\n", r"line 7: expected 3 values"),
        ("ncols 3\nnrows 2\nxllcorner 0\nyllcorner 0\ncellsize 1\n1 2 3\n4 x 6\n", r"line 7: non-numeric value 'x'"),
    ],
)
def test_asc_malformed(tmp_path, text, match):
    p = tmp_path / "bad.asc"
    p.write_text(text)
    with pytest.raises(TerrainError, match=match) as e:
        read_asc(p)
    assert "bad.asc" in str(e.value)


def test_read_raster_dispatch_and_missing(tmp_path):
    dem = _dem()
    write_raster(tmp_path / "t.asc", torch.as_tensor(dem.z), dem, fmt="%.17g")
    np.testing.assert_array_equal(read_raster(tmp_path / "t.asc").z, dem.z)
    with pytest.raises(TerrainError, match="unknown raster extension"):
        read_raster(tmp_path / "t.xyz")
    with pytest.raises(TerrainError, match="file not found"):
        read_raster(tmp_path / "none.asc")


def test_geotiff_without_rasterio_message(tmp_path, monkeypatch):
    """Without the geo extra a .tif gets the install hint, on the DEM and the map path alike (rasterio is
    hidden here, so this runs where it is installed too; tests/test_geotiff.py covers reading)."""
    import sys

    from torchslide.terrain.io import read_raster_on_grid

    monkeypatch.setitem(sys.modules, "rasterio", None)  # `import rasterio` raises ImportError
    (tmp_path / "x.tif").write_bytes(b"")
    with pytest.raises(TerrainError, match=r"pip install torchslide\[geo\]"):
        read_geotiff(tmp_path / "x.tif")
    with pytest.raises(TerrainError, match=r"pip install torchslide\[geo\]"):
        read_raster_on_grid(tmp_path / "x.tif", _dem())


def test_read_raster_like_grid_mismatch(tmp_path):
    dem = _dem()
    other = DEM(z=np.zeros((4, 5)), cellsize=10.0, xll=110.0, yll=200.0)
    p = tmp_path / "rel.asc"
    write_asc(p, other.z, other)
    with pytest.raises(TerrainError, match=r"rel\.asc: release grid \(4x5 cells of 10 m at xll=110.*DEM grid \(4x5 cells of 10 m at xll=100"):
        read_raster_like(p, dem, what="release")
    neg = DEM(z=-np.ones((4, 5)), cellsize=10.0, xll=100.0, yll=200.0)
    write_asc(p, neg.z, neg)
    with pytest.raises(TerrainError, match="must be >= 0"):
        release_from_raster(p, dem)


# ------------------------------------------------------------------------------------------ fields
def test_fields_plane_numpy_and_torch():
    dem = inclined_plane(30.0, cellsize=10.0, slope_length=500, runout_length=200, width=200)
    s = slope_deg(dem)
    assert np.allclose(s[:, 2:45], 30.0)  # interior of the slope
    assert np.allclose(s[:, 55:-2], 0.0)
    nx_, ny_, nz = unit_normal(dem)
    assert np.allclose(nz[:, 5], math.cos(math.radians(30)))
    assert np.allclose(nx_[:, 5], math.sin(math.radians(30)))  # normal tilts downhill (+x)
    zt = torch.as_tensor(dem.z, dtype=torch.float32)
    p, q = gradient(zt, 10.0)
    assert isinstance(p, torch.Tensor) and p.dtype == torch.float32
    assert torch.allclose(p[:, 5], torch.tensor(-math.tan(math.radians(30))))
    hs = hillshade(dem)
    assert hs.shape == dem.shape and hs.min() >= 0 and hs.max() <= 1


def test_curvature_signs_and_values():
    # sphere-like cap z = -(x^2 + y^2) / (2 R): convex, |k| ~ 1/R near the top at small slope
    cs, R = 5.0, 1000.0
    x = (np.arange(81) - 40) * cs
    X, Y = np.meshgrid(x, x)
    hill = DEM(z=-(X**2 + Y**2) / (2 * R), cellsize=cs)
    kp, kh = curvature(hill)
    c = slice(30, 51)
    assert np.all(kp[c, c][np.hypot(X, Y)[c, c] > 0] > 0)
    assert np.allclose(kp[35, 40], 1 / R, rtol=0.01)
    assert np.allclose(kh[35, 40], 1 / 25.0, rtol=0.01)  # contour: circle of radius 25 m (5 cells)
    bowl_dem = bowl(cellsize=10.0)
    kp2, _ = curvature(bowl_dem)
    assert kp2[10, 30] < 0  # concave


# ------------------------------------------------------------------------------------------ synthetic
def test_inclined_plane_and_parabola_formulas():
    dem = inclined_plane(25.0, cellsize=20.0, slope_length=1000, runout_length=500, width=400)
    assert dem.shape == (20, 75)
    x = dem.x_centres()
    np.testing.assert_allclose(dem.z[3], math.tan(math.radians(25)) * np.maximum(1000 - x, 0))
    para = parabola(cellsize=10.0)
    L = 1000.0 / math.tan(math.radians(34.0))
    x = para.x_centres()
    np.testing.assert_allclose(para.z[0], 1000.0 * np.clip(1 - x / L, 0, None) ** 2)
    assert para.z[0, 0] == pytest.approx(1000 * (1 - 5 / L) ** 2)
    assert np.all(para.z[:, x > L] == 0)
    lat = parabola(cellsize=10.0, lateral_curvature=1e-3)
    assert lat.z[0, -1] > 0  # channel: edges higher than the centre
    ch = channel_with_bends(cellsize=20.0)
    assert np.isfinite(ch.z).all() and ch.z[:, 0].min() > ch.z[:, -1].max()


def test_channel_transition_keeps_the_bed_curvature_bounded_as_cells_shrink():
    """channel_with_bends(transition=T): the slope-to-run-out kink becomes a C1 blend whose bed
    curvature along the thalweg is tan(theta) / T on every grid; without it the kink's discrete
    curvature grows as 1 / cellsize. Away from the blend both surfaces are the same."""
    tan = math.tan(math.radians(25.0))
    geom = dict(slope_length=1200.0, runout_length=500.0, width=600.0, amplitude=80.0)
    peak = {}
    for cs in (40.0, 20.0, 10.0):
        for T in (0.0, 300.0):
            dem = channel_with_bends(cs, transition=T, **geom)
            row = dem.z[dem.ny // 2]
            curv = np.diff(row, 2) / cs**2  # along x, past the bends and the channel's fade-out
            x = dem.x_centres()[1:-1]
            window = (x > 1230) & (x < 1340) if T else (x > 1170) & (x < 1230)
            peak[cs, T] = float(curv[window].max())
            far = (np.abs(dem.x_centres() - 1200.0) > 160.0 + cs)
            np.testing.assert_allclose(dem.z[:, far], channel_with_bends(cs, **geom).z[:, far], atol=1e-9)
    for cs in (40.0, 20.0, 10.0):
        assert peak[cs, 300.0] == pytest.approx(tan / 300.0, rel=0.05)
    assert peak[10.0, 0.0] > 3.5 * peak[40.0, 0.0] > 3.5 * tan / 300.0
    for bad in (-10.0, float("nan"), 5000.0):
        with pytest.raises(ValueError, match="transition"):
            channel_with_bends(40.0, transition=bad, **geom)


def test_release_from_shape_volume_any_resolution():
    for cs in (5.0, 10.0, 25.0):
        dem = inclined_plane(30.0, cellsize=cs, slope_length=600, runout_length=200, width=400)
        h = release_from_shape(dem, (300.0, 200.0), (80.0, 50.0), volume=1e5)   # normal to the slope
        assert (h * dem.surface_area()).sum() == pytest.approx(1e5, rel=1e-12)
        assert h.min() >= 0
        hv = release_from_shape(dem, (300.0, 200.0), (80.0, 50.0), volume=1e5, normal=False)
        assert hv.sum() * cs**2 == pytest.approx(1e5, rel=1e-12)
    h = release_from_shape(dem, (300.0, 200.0), 50.0, thickness=4.0, shape="cylinder")
    assert set(np.unique(h)) <= {0.0, 4.0}
    with pytest.raises(TerrainError, match="outside the DEM"):
        release_from_shape(dem, (-10.0, 0.0), 50.0, volume=1.0)
    # centre inside, ellipse cut by the edge: refused (the volume would be kept in a thicker cut body)
    with pytest.raises(TerrainError, match=r"radii \(80, 50\) m extends beyond the DEM \(x in \[0, 800\], y in \[0, 400\]\)"):
        release_from_shape(dem, (300.0, 380.0), (80.0, 50.0), volume=1e5)


@pytest.mark.parametrize("cs", [20.0, 40.0])
def test_bondo_like_geometry(cs):
    case = bondo_like(cs)
    dem = case.dem
    assert dem.extent[2] == pytest.approx(6500.0, abs=cs) and dem.extent[3] == pytest.approx(2000.0, abs=cs)
    # release ~3e6 m^3 within 2 %
    assert case.release_volume == pytest.approx(3.0e6, rel=0.02)
    assert case.release.min() >= 0
    # release face 35-45 deg
    s = slope_deg(dem)[case.release > 0]
    assert 35.0 <= np.percentile(s, 2) and np.percentile(s, 98) <= 45.0
    # drop ~2000 m from the release top to the fan (L3), path ~6 km
    zi = lambda p: dem.z[dem.index(*p)]  # noqa: E731
    i_rel = np.argwhere(case.release > 0)
    z_top = dem.z[tuple(i_rel[np.argmax(dem.z[case.release > 0])])]
    drop = z_top - zi(case.points["L3"])
    assert 1800.0 < drop < 2300.0
    assert 5500.0 < thalweg_length(case.thalweg) < 7500.0
    assert 4500.0 < case.info["path_length_release_top_to_L3_m"] < 6500.0
    # L1-L3 on the thalweg, in order downhill, each the lowest cell across its column
    zs = [zi(case.points[k]) for k in ("L1", "L2", "L3")]
    assert zs[0] > zs[1] > zs[2]
    for k in ("L1", "L2", "L3"):
        i, j = dem.index(*case.points[k])
        assert abs(int(np.argmin(dem.z[:, j])) - i) <= 1  # within a cell of the valley bottom
    # a confining channel: banks some tens of m above the thalweg at L2
    i, j = dem.index(*case.points["L2"])
    assert dem.z[i + int(150 / cs), j] - dem.z[i, j] > 25.0
    assert case.erodible_depth.shape == dem.shape and case.erodible_depth.max() > 1.0


def test_bondo_like_resolution_independent():
    # 60 m cell centres (30 + 60 k) coincide with 20 m centres (10 + 20 (3k + 1)): same analytic surface
    a, b = bondo_like(20.0), bondo_like(60.0)
    np.testing.assert_allclose(b.dem.z, a.dem.z[1::3, 1::3][: b.dem.ny, : b.dem.nx], rtol=0, atol=1e-9)
    assert b.points == a.points
    np.testing.assert_allclose(b.thalweg, a.thalweg)
    assert b.release_volume == pytest.approx(a.release_volume, rel=1e-12)


def test_config_cellsize_resamples_a_dem_file_and_keeps_the_release_volume(tmp_path):
    """[terrain] cellsize with a DEM file: the grid is resampled inside torchslide (a plane stays the
    plane), and a release raster of the file's grid keeps its volume on the new grid."""
    from torchslide.config import load_config
    from torchslide.terrain.io import write_asc

    x = (np.arange(60) + 0.5) * 5.0
    z = np.tile(500.0 - 0.7 * x, (40, 1)) + 0.2 * (np.arange(40)[:, None] * 5.0)
    src = DEM(z, 5.0, xll=1000.0, yll=2000.0, crs="EPSG:2056")
    write_asc(tmp_path / "dem.asc", src.z, src, fmt="%.17g")
    rel = release_from_shape(src, (1080.0, 2100.0), (30.0, 25.0), volume=2e4)
    write_asc(tmp_path / "rel.asc", rel, src, fmt="%.17g")
    (tmp_path / "c.toml").write_text('[terrain]\ndem = "dem.asc"\nrelease = "rel.asc"\ncellsize = 20.0\n'
                                     '[model]\nmu = 0.3\nxi = 500.0\n[run]\nt_end = 1.0\n')
    cfg = load_config(tmp_path / "c.toml")
    dem = cfg.terrain.dem
    assert dem.shape == (10, 15) and dem.cellsize == 20.0 and (dem.xll, dem.yll) == (1000.0, 2000.0)
    X, Y = np.meshgrid(dem.x_centres(), dem.y_centres())
    np.testing.assert_allclose(dem.z, 500.0 - 0.7 * (X - 1000.0) + 0.2 * (Y - 2002.5), atol=1e-9)
    assert dem.crs == "EPSG:2056"
    assert cfg.terrain.release_volume == pytest.approx(2e4, rel=1e-9)
    # a raster on another CRS than the DEM's is refused
    (tmp_path / "rel.prj").write_text("EPSG:21781\n")
    with pytest.raises(Exception, match=r"rel.asc: release CRS differs from the DEM's"):
        load_config(tmp_path / "c.toml")


def test_a_non_finite_nodata_value_marks_nodata_cells(tmp_path):
    """NODATA_value nan (as com1DFA writes its remeshed DEMs) or -inf marks those cells as nodata; a NaN in
    a grid whose NODATA_value is a number is still refused, naming the cell."""
    from torchslide.terrain.io import read_asc, read_asc_array

    def grid(name, nodata, first):
        p = tmp_path / name
        p.write_text(f"ncols 3\nnrows 3\nxllcorner 0\nyllcorner 0\ncellsize 10\nNODATA_value {nodata}\n"
                     f"{first} 9 8\n7 6 5\n4 3 2\n")
        return p

    for nodata in ("nan", "NaN", "-inf"):
        z = read_asc_array(grid("a.asc", nodata, nodata))[0]
        assert np.isnan(z[2, 0]) and np.isfinite(np.delete(z.ravel(), 6)).all()
        dem = read_asc(grid("a.asc", nodata, nodata), nodata="outside")
        assert dem.outside[2, 0] and dem.outside.sum() == 1
    with pytest.raises(TerrainError, match="non-finite values, first nan at row 2 from the south, col 0"):
        read_asc_array(grid("b.asc", "-9999", "nan"))
