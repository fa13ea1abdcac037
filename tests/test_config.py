"""TOML config loading and validation."""
from __future__ import annotations

import math

import numpy as np
import pytest

from torchslide.config import ConfigError, load_config
from torchslide.terrain import DEM

from .conftest import cfg_text, write_case


@pytest.fixture
def case(tmp_path):
    dem, rel = write_case(tmp_path)
    return tmp_path, dem, rel


def test_load_valid_batch(case):
    d, dem, rel = case
    (d / "c.toml").write_text(cfg_text(mu="[0.2, 0.25]", xi="1000.0"))
    cfg = load_config(d / "c.toml")
    assert cfg.batch_size == 2
    assert cfg.terrain.dem.same_grid(dem)
    np.testing.assert_array_equal(cfg.terrain.release, rel)
    assert cfg.terrain.release_volume == pytest.approx(2.0e4)
    p = cfg.make_params()
    assert p.mu.tolist() == [0.2, 0.25] and p.xi.tolist() == [1000.0, 1000.0]
    assert cfg.gauges[0].name == "G1"
    kw = cfg.simulate_kwargs()
    assert kw["t_end"] == 20.0 and kw["gauges"] == [("G1", 300.0, 100.0)]


def test_coulomb_and_other_params(case):
    d, _, _ = case
    text = cfg_text().replace('rheology = "voellmy"', 'rheology = "coulomb"').replace("xi = 1000.0", "k_ap = 1.5")
    (d / "c.toml").write_text(text)
    p = load_config(d / "c.toml").make_params()
    assert math.isinf(float(p.xi[0])) and float(p.k_ap[0]) == 1.5


def test_synthetic_terrain(tmp_path):
    (tmp_path / "c.toml").write_text(
        '[terrain]\nsynthetic = "bondo_like"\ncellsize = 40.0\n[model]\nmu = 0.23\nxi = 1000.0\n[run]\nt_end = 10.0\n'
    )
    cfg = load_config(tmp_path / "c.toml")
    assert cfg.terrain.release_volume == pytest.approx(3e6, rel=1e-9)
    assert cfg.terrain.case.thalweg is not None and cfg.terrain.erodible_depth is not None
    (tmp_path / "c2.toml").write_text(
        '[terrain]\nsynthetic = "inclined_plane"\ncellsize = 20.0\noptions = {theta_deg = 35.0}\n'
        'release = {centre = [200.0, 250.0], radii = [50.0, 50.0], volume = 1e4}\n'
        '[model]\nrheology = "coulomb"\nmu = 0.3\n[run]\nt_end = 10.0\n'
    )
    cfg = load_config(tmp_path / "c2.toml")
    assert cfg.terrain.release_volume == pytest.approx(1e4)


def test_extra_sections(case):
    d, _, _ = case
    (d / "c.toml").write_text(cfg_text(extra='\n[prior]\nmu = [0.02, 0.3]\n[calibration]\nq = 4\n'))
    cfg = load_config(d / "c.toml")  # other commands' sections are accepted
    assert cfg.raw["prior"]["mu"] == [0.02, 0.3]
    cfg = load_config(d / "c.toml", extra_sections={"prior": lambda t, c: {k: tuple(v) for k, v in t.items()}})
    assert cfg.extra["prior"] == {"mu": (0.02, 0.3)}


@pytest.mark.parametrize(
    "mutate,match",
    [
        (lambda t: t + "\n[modle]\nmu = 1\n", r"unknown section \[modle\]"),
        (lambda t: t.replace("t_end = 20.0", "t_edn = 20.0"), r"unknown key 't_edn' in \[run\]"),
        (lambda t: t.replace('rheology = "voellmy"', 'rheology = "bingham"'), "unknown rheology 'bingham'"),
        (lambda t: t.replace("mu = 0.2", "mu = -0.1"), r"\[model\] mu must be > 0"),
        (lambda t: t.replace("mu = 0.2", "mu = [0.2, 0.0]"), r"\[model\] mu must be > 0"),
        (lambda t: t.replace("xi = 1000.0", "xi = 0.0"), r"\[model\] xi must be > 0"),
        (lambda t: t.replace("xi = 1000.0", "xi = [1, 2, 3]").replace("mu = 0.2", "mu = [0.1, 0.2]"), "equal lengths"),
        (lambda t: t.replace("x = 300.0", "x = 9000.0"), "gauge 'G1' at x=9000, y=100 is outside the DEM"),
        (lambda t: t.replace('"release.asc"', '"nothere.asc"'), r"\[terrain\] release file not found"),
        (lambda t: t.replace('"dem.asc"', '"nothere.asc"'), r"\[terrain\] dem file not found"),
        (lambda t: t.replace('dtype = "float64"', 'dtype = "float16"'), "dtype must be"),
        (lambda t: t.replace("t_end = 20.0", "t_end = -1.0"), "t_end must be > 0"),
        (lambda t: t.replace("[run]", "[run]\nfoo = 1"), r"unknown key 'foo' in \[run\]"),
        (lambda t: t.replace("mu = 0.2", "mu = 0.2\nmue = 0.3"), r"unknown key 'mue' in \[model\]"),
        (lambda t: t.replace("mu = 0.2", "mu = 'abc'"), "mu must be a number"),
        (lambda t: t.replace("[run]", "[run\n"), "invalid TOML"),
        (lambda t: t + '\n[output]\nformat = "nc"\n', r"\[output\] format must be one of asc, tif, got 'nc'"),
        (lambda t: t + '\n[output]\nfromat = "tif"\n', r"unknown key 'fromat' in \[output\]"),
        (lambda t: t + "\n[sweep]\nn = 24\n", r"unknown section \[sweep\]"),  # no command reads it
    ],
)
def test_bad_configs(case, mutate, match):
    d, _, _ = case
    (d / "c.toml").write_text(mutate(cfg_text()))
    with pytest.raises(ConfigError, match=match) as e:
        load_config(d / "c.toml")
    assert "\n" not in str(e.value)
    assert "c.toml" in str(e.value)


def test_output_format(case, monkeypatch):
    """[output] format: "asc" by default; "tif" needs rasterio, refused with the install hint without it."""
    import sys

    d, _, _ = case
    (d / "c.toml").write_text(cfg_text())
    assert load_config(d / "c.toml").output_format == "asc"
    (d / "c.toml").write_text(cfg_text(extra='\n[output]\nformat = "TIF"\n'))
    monkeypatch.setitem(sys.modules, "rasterio", None)
    with pytest.raises(ConfigError, match=r"\[output\] format = \"tif\" needs rasterio.*torchslide\[geo\]"):
        load_config(d / "c.toml")


def test_bad_rasters(tmp_path):
    write_case(tmp_path, nan_dem=True)
    (tmp_path / "c.toml").write_text(cfg_text())
    with pytest.raises(ConfigError, match=r"\[terrain\] release covers 1 nodata cells of the DEM \(outside its domain\)"):
        load_config(tmp_path / "c.toml")
    d2 = tmp_path / "neg"
    d2.mkdir()
    write_case(d2, neg_release=True)
    (d2 / "c.toml").write_text(cfg_text())
    with pytest.raises(ConfigError, match="release thickness must be >= 0"):
        load_config(d2 / "c.toml")
    d3 = tmp_path / "grid"
    d3.mkdir()
    other = DEM(z=np.zeros((10, 35)), cellsize=20.0, xll=20.0)
    write_case(d3, release_dem=other)
    (d3 / "c.toml").write_text(cfg_text())
    with pytest.raises(ConfigError, match=r"release\.asc: release grid .* does not match the DEM grid"):
        load_config(d3 / "c.toml")


def test_missing_config(tmp_path):
    with pytest.raises(ConfigError, match="config file not found"):
        load_config(tmp_path / "none.toml")


def test_terrain_thickness_convention_sets_the_release_volume(tmp_path):
    """[terrain] thickness: a release table's volume is normal thickness x surface area by default and
    vertical thickness x map area with "vertical"; anything else is a one-line error naming the key."""
    from torchslide.terrain.io import write_asc

    x = (np.arange(20) + 0.5) * 10.0
    dem = DEM(np.tile(-x * np.tan(np.radians(35.0)), (12, 1)) + 500.0, 10.0)
    write_asc(tmp_path / "dem.asc", dem.z, dem, fmt="%.17g")
    base = ('[terrain]\ndem = "dem.asc"\nrelease = {centre = [100.0, 60.0], radii = [40.0, 30.0], volume = 1e4}\n'
            '{extra}[model]\nmu = 0.3\nxi = 500.0\n[run]\nt_end = 1.0\n')
    for extra, thickness in (("", "normal"), ('thickness = "vertical"\n', "vertical")):
        p = tmp_path / f"{thickness}.toml"
        p.write_text(base.replace("{extra}", extra))
        cfg = load_config(p)
        area = dem.surface_area() if thickness == "normal" else np.full(dem.shape, 100.0)
        assert cfg.terrain.thickness == thickness
        assert abs(float((cfg.terrain.release * area).sum()) - 1e4) < 1e-6
        assert abs(cfg.terrain.release_volume - 1e4) < 1e-6
        assert cfg.simulate_kwargs()["thickness"] == thickness
    p = tmp_path / "bad.toml"
    p.write_text(base.replace("{extra}", 'thickness = "slope"\n'))
    with pytest.raises(ConfigError, match=r"bad.toml: \[terrain\] thickness must be one of 'normal', 'vertical'.*'slope'"):
        load_config(p)
    p.write_text(base.replace("{extra}", "").replace("xi = 500.0", "xi = 500.0\ndensity = -1.0"))
    with pytest.raises(ConfigError, match=r"\[model\] density must be"):
        load_config(p)
