"""Bad inputs raise ValueError naming the field and the value."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from torchslide.physics import Params, earth_pressure_sh
from torchslide.solver import SolverConfig, simulate
from torchslide.terrain import DEM


def _dem():
    return DEM(np.zeros((6, 8)), 10.0)


@pytest.mark.parametrize("kw,match", [
    (dict(mu=0.0), "mu"), (dict(mu=-0.1), "mu"), (dict(mu=0.2, xi=0.0), "xi"), (dict(mu=0.2, xi=-5.0), "xi"),
    (dict(mu=0.2, kappa=-1e-3), "kappa"), (dict(mu=0.2, tau_y=-1.0), "tau_y"),
    (dict(mu=0.2, earth_pressure=0.5), "earth_pressure"), (dict(mu=0.2, earth_pressure=1.5, phi_int=30.0), "earth_pressure"),
    (dict(mu=0.9, phi_int=30.0), "phi_int"), (dict(mu=[0.1, 0.2], xi=[1.0, 2.0, 3.0]), "has 2 values but B = 3"),
    (dict(mu=float("nan")), "mu"), (dict(mu=0.2, bogus=1.0), "bogus"), (dict(xi=100.0), "mu"),
])
def test_params_bad(kw, match):
    with pytest.raises(ValueError, match=match):
        Params.make(**kw)


def test_params_broadcast_and_types():
    p = Params.make(mu=[0.1, 0.2, 0.3], xi=500.0, dtype=torch.float32)
    assert p.B == 3 and p.xi.shape == (3,) and p.mu.dtype == torch.float32
    p2 = Params.make(B=4, mu=torch.tensor(0.2))
    assert p2.B == 4 and math.isinf(float(p2.xi[0]))
    ka, kp = earth_pressure_sh(torch.tensor(35.0, dtype=torch.float64), torch.tensor(0.0, dtype=torch.float64))
    # delta = 0: k_act/pass = (1 -/+ sin phi) / (1 +/- sin phi) (Rankine)
    s = math.sin(math.radians(35))
    assert abs(float(ka) - (1 - s) / (1 + s)) < 1e-12 and abs(float(kp) - (1 + s) / (1 - s)) < 1e-12


def test_negative_thickness():
    rel = np.zeros((6, 8)); rel[2, 3] = -1.0
    with pytest.raises(ValueError, match="release"):
        simulate(_dem(), rel, Params.make(mu=0.2), t_end=1.0)


def test_nan_release():
    rel = np.zeros((6, 8)); rel[2, 3] = np.nan
    with pytest.raises(ValueError, match="release.*non-finite"):
        simulate(_dem(), rel, Params.make(mu=0.2), t_end=1.0)


def test_release_shape_mismatch():
    with pytest.raises(ValueError, match=r"release has shape \(5, 8\)"):
        simulate(_dem(), np.zeros((5, 8)), Params.make(mu=0.2), t_end=1.0)
    with pytest.raises(ValueError, match="B = 3"):
        simulate(_dem(), np.zeros((2, 6, 8)), Params.make(mu=[0.1, 0.2, 0.3]), t_end=1.0)


def test_gauge_outside():
    with pytest.raises(ValueError, match="gauge 'far'.*outside"):
        simulate(_dem(), np.ones((6, 8)), Params.make(mu=0.2), t_end=1.0, gauges=[("far", 500.0, 5.0)])


def test_bad_t_end_and_config():
    with pytest.raises(ValueError, match="t_end"):
        simulate(_dem(), np.ones((6, 8)), Params.make(mu=0.2), t_end=-1.0)
    with pytest.raises(ValueError, match="cfl"):
        simulate(_dem(), np.ones((6, 8)), Params.make(mu=0.2), t_end=1.0, config=SolverConfig(cfl=2.0))


def test_kappa_needs_erodible():
    with pytest.raises(ValueError, match="kappa"):
        simulate(_dem(), np.ones((6, 8)), Params.make(mu=0.2, kappa=0.01), t_end=1.0)


def test_failed_member_flagged_not_silent():
    """A member that blows up is marked failed with a reason; the others are unaffected."""
    dem = _dem()
    rel = np.ones((6, 8))
    p = Params.make(mu=[0.2, 0.2])
    # float overflow: an absurd release thickness in member 1 only
    rel_b = np.stack([rel, np.full((6, 8), 1e300)])
    r = simulate(dem, rel_b, p, t_end=2.0)
    single = simulate(dem, rel, p.select([0]), t_end=2.0)
    assert bool(r.failed[1]) and "non-finite" in r.failure_reason[1]
    assert not bool(r.failed[0]) and r.failure_reason[0] is None
    assert torch.equal(r.member(0).h_final, single.h_final)


def _holed(nodata_cols=(14, 15)):
    """A 20 x 12 plane at 30 degrees towards +x whose columns ``nodata_cols`` are outside the domain."""
    from tests.conftest import plane_dem

    dem = plane_dem(20, 12, 10.0, math.tan(math.radians(30.0)))
    outside = np.zeros(dem.shape, dtype=bool)
    outside[:, list(nodata_cols)] = True
    return DEM(dem.z, dem.cellsize, outside=outside)


def test_nodata_cells_are_outside_the_domain():
    """A flow reaching nodata cells: with "outflow" what enters them leaves (counted as outflow, the cells
    stay empty, nothing reaches beyond); with "wall" nothing enters them, and less leaves the domain
    (only through the DEM's side edges). Mass balances to round-off either way."""
    dem = _holed()
    rel = np.zeros(dem.shape)
    rel[3:9, 2:6] = 2.0
    out = {}
    for nodata in ("outflow", "wall"):
        r = simulate(dem, rel, Params.make(mu=0.2, xi=500.0), t_end=30.0, config=SolverConfig(nodata=nodata))
        h = r.h_max[0].numpy()
        assert h[:, 14:16].max() == 0.0 and h[:, 16:].max() == 0.0   # never inside the hole, nor beyond it
        assert h[:, 13].max() > 0.1                                  # the flow got there
        bal = float(r.final_volume[0] + r.outflow_volume[0] - r.release_volume[0])
        assert abs(bal) < 1e-10 * float(r.release_volume[0])
        out[nodata] = float(r.outflow_volume[0]) / float(r.release_volume[0])
    assert out["outflow"] > 0.2 and out["wall"] < 0.5 * out["outflow"]


def test_a_release_or_gauge_on_nodata_is_refused():
    dem = _holed()
    rel = np.zeros(dem.shape)
    rel[3:9, 12:15] = 2.0
    with pytest.raises(ValueError, match=r"release covers 6 cells outside the DEM's domain \(nodata\), first at row 3"):
        simulate(dem, rel, Params.make(mu=0.2), t_end=1.0)
    rel[:] = 0.0
    rel[3:9, 2:6] = 2.0
    with pytest.raises(ValueError, match=r"gauge 'g' lies in a cell outside the DEM's domain"):
        simulate(dem, rel, Params.make(mu=0.2), t_end=1.0, gauges=[("g", 145.0, 55.0)])
    with pytest.raises(ValueError, match=r"SolverConfig.nodata = 'sink' is invalid"):
        simulate(dem, rel, Params.make(mu=0.2), t_end=1.0, config=SolverConfig(nodata="sink"))


def test_dem_nodata_read_as_outside_and_written_back_as_nodata(tmp_path):
    """A DEM file with nodata: read as cells outside the domain (never silently filled); every raster
    written on that grid has nodata there again; the .prj beside an .asc carries the CRS both ways."""
    from torchslide.terrain.io import read_raster, write_asc

    dem = _holed()
    write_asc(tmp_path / "dem.asc", np.where(dem.outside, np.nan, dem.z), DEM(dem.z, dem.cellsize, crs="EPSG:2056"),
              fmt="%.17g")
    back = read_raster(tmp_path / "dem.asc", nodata="outside")
    assert np.array_equal(back.outside, dem.outside) and np.isfinite(back.z).all()
    assert back.crs.strip() == "EPSG:2056"
    write_asc(tmp_path / "h.asc", np.ones(dem.shape), back)
    again = read_raster(tmp_path / "h.asc", nodata="outside")
    assert np.array_equal(again.outside, dem.outside) and again.crs.strip() == "EPSG:2056"
    with pytest.raises(Exception, match="nodata cells"):
        read_raster(tmp_path / "dem.asc")


def test_release_scale_scales_each_members_release_and_is_plain_at_zero():
    """Params.release_scale: member b starts from release x (1 + release_scale[b]); 0 gives the run of the
    release as given bitwise; <= -1 is refused naming the field."""
    import pytest
    import torch

    from torchslide.physics import Params
    from torchslide.solver import simulate

    from .conftest import chute_case

    dem, rel = chute_case()
    r = simulate(dem, rel, Params.make(mu=0.3, xi=500.0, release_scale=[0.0, 0.25, -0.2]), t_end=5.0)
    assert torch.allclose(r.release_volume / r.release_volume[0], torch.tensor([1.0, 1.25, 0.8], dtype=torch.float64),
                          rtol=1e-12)
    plain = simulate(dem, rel, Params.make(mu=0.3, xi=500.0), t_end=5.0)
    assert torch.equal(plain.h_final[0], r.h_final[0]) and torch.equal(plain.v_max[0], r.v_max[0])
    with pytest.raises(ValueError, match="release_scale"):
        Params.make(mu=0.3, release_scale=-1.0)
