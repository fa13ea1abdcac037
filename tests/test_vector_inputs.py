"""Polygon inputs: release and erodible areas with a thickness per feature, observed outlines; their errors."""
from __future__ import annotations

import json

import numpy as np
import pytest

pytest.importorskip("pyogrio")
pytest.importorskip("shapely")

from shapely.geometry import LineString, Polygon, mapping  # noqa: E402

from torchslide.config import ConfigError, load_config  # noqa: E402
from torchslide.terrain import DEM  # noqa: E402
from torchslide.terrain.io import write_asc  # noqa: E402
from torchslide.terrain.vector import rasterize_outline, rasterize_thickness  # noqa: E402

CRS = "EPSG:2056"


def _plane(tmp_path, crs=None):
    x = (np.arange(30) + 0.5) * 10.0
    dem = DEM(np.tile(600.0 - x * np.tan(np.radians(35.0)), (20, 1)), 10.0, xll=2600000.0, yll=1200000.0, crs=crs)
    write_asc(tmp_path / "dem.asc", dem.z, dem, fmt="%.17g")
    return dem


def _box(x0, y0, x1, y1):
    return Polygon([(x0, y0), (x1, y0), (x1, y1), (x0, y1)])


def write_geojson(path, geoms, props):
    fc = {"type": "FeatureCollection",
          "features": [{"type": "Feature", "properties": p, "geometry": mapping(g)} for g, p in zip(geoms, props)]}
    path.write_text(json.dumps(fc))
    return path


def write_shp(path, geoms, thickness, crs=CRS):
    from pyogrio.raw import write

    write(str(path), geometry=np.array([g.wkb for g in geoms], dtype=object), field_data=[np.asarray(thickness, float)],
          fields=["thickness"], geometry_type=geoms[0].geom_type, crs=crs)
    return path


X0, Y0 = 2600000.0, 1200000.0


def test_shapefile_features_carry_their_own_thickness(tmp_path):
    """Two features, 2 m and 5 m: every cell whose centre lies inside a polygon gets its thickness."""
    dem = _plane(tmp_path, crs=CRS)
    a, b = _box(X0 + 20, Y0 + 20, X0 + 60, Y0 + 60), _box(X0 + 100, Y0 + 100, X0 + 140, Y0 + 130)
    h = rasterize_thickness(write_shp(tmp_path / "rel.shp", [a, b], [2.0, 5.0]), dem)
    assert (h == 2.0).sum() == 16 and (h == 5.0).sum() == 12 and set(np.unique(h)) == {0.0, 2.0, 5.0}
    # row 0 is the south: the 2 m block sits at rows 2-5, cols 2-5
    assert np.all(h[2:6, 2:6] == 2.0) and h[10:13, 10:14].min() == 5.0


def test_geojson_release_in_a_config_with_a_default_thickness(tmp_path):
    """GeoJSON polygons in [terrain] release: the attribute where given, the table's thickness elsewhere;
    the volume is normal thickness x surface area."""
    dem = _plane(tmp_path)
    write_geojson(tmp_path / "rel.geojson", [_box(X0 + 20, Y0 + 20, X0 + 60, Y0 + 60), _box(X0 + 100, Y0 + 100, X0 + 140, Y0 + 130)],
                  [{"thickness": 3.0}, {}])
    (tmp_path / "c.toml").write_text('[terrain]\ndem = "dem.asc"\nrelease = {polygons = "rel.geojson", thickness = 1.5}\n'
                                     '[model]\nmu = 0.3\nxi = 500.0\n[run]\nt_end = 1.0\n')
    cfg = load_config(tmp_path / "c.toml")
    r = cfg.terrain.release
    assert (r == 3.0).sum() == 16 and (r == 1.5).sum() == 12
    assert cfg.terrain.release_volume == pytest.approx(float((r * dem.surface_area()).sum()))
    assert cfg.terrain.release_volume == pytest.approx((16 * 3.0 + 12 * 1.5) * 100.0 / np.cos(np.radians(35.0)), rel=1e-9)


def test_polygon_erodible_area(tmp_path):
    _plane(tmp_path)
    write_geojson(tmp_path / "erod.geojson", [_box(X0 + 100, Y0 + 0, X0 + 250, Y0 + 200)], [{"thickness": 2.0}])
    (tmp_path / "c.toml").write_text('[terrain]\ndem = "dem.asc"\nerodible = "erod.geojson"\n'
                                     'release = {centre = [2600060.0, 1200100.0], radii = 40.0, volume = 1e4}\n'
                                     '[model]\nmu = 0.3\nxi = 500.0\nkappa = 0.01\n[run]\nt_end = 1.0\n')
    e = load_config(tmp_path / "c.toml").terrain.erodible_depth
    assert set(np.unique(e)) == {0.0, 2.0} and (e == 2.0).sum() == 15 * 20


def test_observed_outline_is_an_impact_map(tmp_path):
    from torchslide.observe_series import SeriesObservation

    dem = _plane(tmp_path)
    f = write_geojson(tmp_path / "outline.geojson", [_box(X0 + 50, Y0 + 50, X0 + 150, Y0 + 150)], [{}])
    a = rasterize_outline(f, dem)
    assert a.sum() == 100 and set(np.unique(a)) == {0.0, 1.0}
    o = SeriesObservation.from_raster(f, "impact_map", dem, 0.4)
    assert o.m == dem.z.size and float(np.sum(o.values)) == 100.0


@pytest.mark.parametrize("geoms,props,cfg_extra,match", [
    ([_box(0, 0, 10, 10)], [{"thickness": 2.0}], "", r"rel.geojson: feature 1 \(x 0\.\.10, y 0\.\.10 m\) covers no cell centre of the DEM"),
    ([_box(X0 + 20, Y0 + 20, X0 + 60, Y0 + 60), _box(X0 + 100, Y0 + 100, X0 + 140, Y0 + 130)], [{"thickness": 2.0}, {}], "",
     r"rel.geojson: feature 2 has no 'thickness' attribute and no release thickness is configured"),
    ([_box(X0 + 20, Y0 + 20, X0 + 60, Y0 + 60)], [{"thickness": -1.0}], "", r"rel.geojson: feature 1: thickness must be a number of m > 0, got -1.0"),
    ([_box(X0 + 20, Y0 + 20, X0 + 60, Y0 + 60)], [{"thickness": "thick"}], "", r"rel.geojson: feature 1: thickness = 'thick' is not a number"),
    ([LineString([(X0, Y0), (X0 + 50, Y0 + 50)])], [{"thickness": 2.0}], "", r"rel.geojson: feature 1 is a LineString, expected a Polygon or MultiPolygon"),
    ([Polygon([(X0, Y0), (X0 + 50, Y0 + 50), (X0 + 50, Y0), (X0, Y0 + 50)])], [{"thickness": 2.0}], "", r"rel.geojson: feature 1 is not a valid polygon"),
])
def test_bad_polygon_inputs_are_one_line_errors(tmp_path, geoms, props, cfg_extra, match):
    _plane(tmp_path)
    write_geojson(tmp_path / "rel.geojson", geoms, props)
    (tmp_path / "c.toml").write_text('[terrain]\ndem = "dem.asc"\nrelease = "rel.geojson"\n'
                                     '[model]\nmu = 0.3\nxi = 500.0\n[run]\nt_end = 1.0\n')
    with pytest.raises(ConfigError, match=match) as e:
        load_config(tmp_path / "c.toml")
    assert "\n" not in str(e.value)


def test_a_crs_unlike_the_dems_is_refused(tmp_path):
    """A shapefile in another CRS than the DEM (from its .prj / GeoTIFF): an error naming both."""
    from torchslide.terrain.io import write_raster

    dem = _plane(tmp_path, crs=CRS)
    write_raster(tmp_path / "dem.tif", dem.z, dem)
    write_shp(tmp_path / "rel.shp", [_box(X0 + 20, Y0 + 20, X0 + 60, Y0 + 60)], [2.0], crs="EPSG:21781")
    (tmp_path / "c.toml").write_text('[terrain]\ndem = "dem.tif"\nrelease = "rel.shp"\n'
                                     '[model]\nmu = 0.3\nxi = 500.0\n[run]\nt_end = 1.0\n')
    with pytest.raises(ConfigError, match=r"rel.shp: its CRS \(EPSG:21781\) differs from the DEM's \(EPSG:2056\)"):
        load_config(tmp_path / "c.toml")
    write_shp(tmp_path / "rel.shp", [_box(X0 + 20, Y0 + 20, X0 + 60, Y0 + 60)], [2.0], crs=CRS)
    assert load_config(tmp_path / "c.toml").terrain.release.max() == 2.0


def test_unknown_polygon_table_key_and_missing_file(tmp_path):
    _plane(tmp_path)
    for rel, match in (('{polygons = "rel.geojson", depth = 2.0}', r"unknown key 'depth' in \[terrain\] release"),
                       ('"missing.shp"', r"\[terrain\] release file not found"),
                       ('{polygons = "nothing.geojson"}', r"\[terrain\] release file not found")):
        (tmp_path / "c.toml").write_text(f'[terrain]\ndem = "dem.asc"\nrelease = {rel}\n'
                                         '[model]\nmu = 0.3\nxi = 500.0\n[run]\nt_end = 1.0\n')
        with pytest.raises(ConfigError, match=match):
            load_config(tmp_path / "c.toml")
    (tmp_path / "bad.geojson").write_text("not json")
    (tmp_path / "c.toml").write_text('[terrain]\ndem = "dem.asc"\nrelease = "bad.geojson"\n'
                                     '[model]\nmu = 0.3\nxi = 500.0\n[run]\nt_end = 1.0\n')
    with pytest.raises(ConfigError, match=r"bad.geojson: not a readable vector file"):
        load_config(tmp_path / "c.toml")


def test_paths_give_run_out_in_the_summary_and_as_an_observation(tmp_path, capsys):
    """[[paths]] from a line file or inline points: summary.json holds the run-out along each, and a
    runout_length observation names its path."""
    from torchslide.calibration_config import load_calibration_config
    from torchslide.cli import main

    dem = _plane(tmp_path)
    write_geojson(tmp_path / "path.geojson", [LineString([(X0 + 5, Y0 + 100), (X0 + 295, Y0 + 100)])], [{}])
    text = ('[terrain]\ndem = "dem.asc"\nrelease = {centre = [2600060.0, 1200100.0], radii = 40.0, volume = 2e4}\n'
            '[model]\nmu = 0.3\nxi = 500.0\n[run]\nt_end = 20.0\n'
            '[[paths]]\nname = "down"\nline = "path.geojson"\n'
            '[[paths]]\nname = "across"\npoints = [[2600100.0, 1200005.0], [2600100.0, 1200195.0]]\nmax_offset = 15.0\n')
    (tmp_path / "c.toml").write_text(text)
    assert main(["simulate", str(tmp_path / "c.toml"), "--out", str(tmp_path / "out"), "-q"]) == 0
    s = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert set(s["runout"]) == {"down", "across"}
    h = np.loadtxt(tmp_path / "out" / "h_max.asc", skiprows=7)[::-1]
    reached = np.nonzero((h > 0.5).any(axis=0))[0]
    assert s["runout"]["down"] == pytest.approx((reached.max() + 0.5) * 10.0 - 5.0)   # the farthest cell centre
    assert 0.0 < s["runout"]["across"] < 190.0
    cal = text + ('[prior]\nmu = [0.2, 0.4]\nxi = [200.0, 1000.0]\n'
                  '[[observations]]\nkind = "runout_length"\npath = "down"\nvalue = 200.0\nsigma = 20.0\n'
                  '[calibration]\nn_total = 4\nn_initial = 2\n')
    (tmp_path / "cal.toml").write_text(cal)
    o = load_calibration_config(tmp_path / "cal.toml").extra["observations"][0]
    assert np.allclose(o.thalweg, [[X0 + 5, Y0 + 100], [X0 + 295, Y0 + 100]])
    (tmp_path / "cal.toml").write_text(cal.replace('path = "down"', 'path = "river"'))
    with pytest.raises(ConfigError, match=r"observation 1: path 'river' is not a \[\[paths\]\] name \(known: \['across', 'down'\]\)"):
        load_calibration_config(tmp_path / "cal.toml")


def test_a_dem_without_a_crs_takes_the_release_files(tmp_path):
    """dem.asc without a .prj and a release shapefile in EPSG:2056: the terrain, and so every output
    raster's .prj, carries the shapefile's CRS."""
    from torchslide.terrain.grid import same_crs

    _plane(tmp_path)
    assert not (tmp_path / "dem.prj").exists()
    write_shp(tmp_path / "rel.shp", [_box(X0 + 20, Y0 + 20, X0 + 60, Y0 + 60)], [2.0], crs=CRS)
    (tmp_path / "c.toml").write_text('[terrain]\ndem = "dem.asc"\nrelease = "rel.shp"\n'
                                     '[model]\nmu = 0.3\nxi = 500.0\n[run]\nt_end = 1.0\n')
    dem = load_config(tmp_path / "c.toml").terrain.dem
    assert dem.crs and same_crs(dem.crs, CRS) and not same_crs(dem.crs, "EPSG:21781")


def test_a_dem_without_a_crs_takes_a_release_rasters_also_when_resampled(tmp_path):
    """release.asc with a .prj beside it, dem.asc without: the terrain carries the release's CRS, on the
    DEM's own grid and on a resampled one."""
    from torchslide.terrain.grid import same_crs
    from torchslide.terrain.io import write_asc

    dem = _plane(tmp_path)
    rel = np.zeros(dem.shape)
    rel[5:9, 3:7] = 2.0
    write_asc(tmp_path / "release.asc", rel, DEM(dem.z, dem.cellsize, dem.xll, dem.yll, crs=CRS))
    assert (tmp_path / "release.prj").exists() and not (tmp_path / "dem.prj").exists()
    for extra in ("", "cellsize = 20.0\n"):
        (tmp_path / "c.toml").write_text('[terrain]\ndem = "dem.asc"\nrelease = "release.asc"\n' + extra +
                                         '[model]\nmu = 0.3\nxi = 500.0\n[run]\nt_end = 1.0\n')
        crs = load_config(tmp_path / "c.toml").terrain.dem.crs
        assert crs and same_crs(crs, CRS), extra
