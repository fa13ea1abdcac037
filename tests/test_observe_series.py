"""Vector observation kinds: gauge series and maps (readers, errors, operators, error model)."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from torchslide.observe import KINDS
from torchslide.observe_series import (GaugeSeriesError, SeriesObservation, effective_factor, interp_series,
                                       read_gauge_csv)
from torchslide.result import GaugeSeries, SimulationResult
from torchslide.terrain import DEM
from torchslide.terrain.grid import TerrainError
from torchslide.terrain.io import write_asc


def _result(B=2, ny=3, nx=4):
    dem = DEM(z=np.zeros((ny, nx)), cellsize=10.0)
    h = torch.arange(B * ny * nx, dtype=torch.float64).reshape(B, ny, nx) / 10
    t = torch.tensor([0.0, 1.0, 2.0], dtype=torch.float64)
    g = GaugeSeries("G", 5.0, 5.0, t, h=torch.tensor([[0.0, 2.0, 4.0]] * B, dtype=torch.float64),
                    u=torch.tensor([[0.0, 3.0, 0.0]] * B, dtype=torch.float64), v=torch.zeros(B, 3, dtype=torch.float64))
    z = torch.zeros(B, dtype=torch.float64)
    return dem, SimulationResult(dem=dem, h_max=h * 2, v_max=h, h_final=h, arrival_time=h, cell_area=torch.full((ny, nx), 100.0, dtype=torch.float64), map_cell_area=100.0,
                                 release_volume=z, final_volume=z, outflow_volume=z, entrained_volume=z,
                                 steps=z.long(), t_final=z, stopped=z.bool(), history_t=t,
                                 mass_history=torch.zeros(B, 3), ke_history=torch.zeros(B, 3), gauges={"G": g})


def test_kinds_registered():
    for k in ("gauge_series", "deposit_map", "impact_map"):
        assert k in KINDS


def test_gauge_csv_and_interp(tmp_path):
    f = tmp_path / "g.csv"
    f.write_text("t,h,speed\n0.5,1.0,1.5\n1.5,3.0,2.0\n")
    obs = SeriesObservation.from_gauge_csv(f, "G", {"h": 0.1, "speed": 0.2})
    assert [o.quantity for o in obs] == ["h", "speed"]
    dem, res = _result()
    p = obs[0].predict(res)
    assert p.shape == (2, 2)
    assert torch.allclose(p[0], torch.tensor([1.0, 3.0], dtype=torch.float64))
    sp = obs[1].predict(res)
    assert torch.allclose(sp[0], torch.tensor([1.5, 1.5], dtype=torch.float64))
    # clamped outside the sampled range
    y = interp_series(torch.tensor([0.0, 1.0]), torch.tensor([[0.0, 1.0]]), torch.tensor([-1.0, 0.25, 5.0]))
    assert torch.allclose(y, torch.tensor([[0.0, 0.25, 1.0]]))


@pytest.mark.parametrize("text,row", [("t,h\n0,1\n1,2\n1,3\n", 4), ("t,h\n0,1\n2,2\n1,3\n", 4), ("t,h\n0,1\nx,2\n", 3),
                                      ("t,h\n-0.5,1\n1,2\n", 2)])
def test_gauge_csv_errors_name_file_and_row(tmp_path, text, row):
    f = tmp_path / "bad.csv"
    f.write_text(text)
    with pytest.raises(GaugeSeriesError) as e:
        read_gauge_csv(f)
    assert str(f) in str(e.value) and f"row {row}" in str(e.value)


def test_gauge_csv_gaps_are_left_out_per_quantity(tmp_path):
    """A sensor drop-out (empty, NA, NaN or '-' in h or speed) drops that sample from that quantity only."""
    f = tmp_path / "g.csv"
    f.write_text("t,h,speed\n0.5,1.0,\n1.0,NA,1.5\n1.5,3.0,2.0\n2.0,nan,-\n2.5,4.0,2.5\n")
    cols = read_gauge_csv(f)
    assert np.isnan(cols["h"][[1, 3]]).all() and np.isnan(cols["speed"][[0, 3]]).all()
    h, sp = SeriesObservation.from_gauge_csv(f, "G", {"h": 0.1, "speed": 0.2})
    np.testing.assert_array_equal(h.times, [0.5, 1.5, 2.5])
    np.testing.assert_array_equal(h.values, [1.0, 3.0, 4.0])
    np.testing.assert_array_equal(sp.times, [1.0, 1.5, 2.5])
    np.testing.assert_array_equal(sp.values, [1.5, 2.0, 2.5])
    dem, res = _result()
    assert h.predict(res).shape == (2, 3) and torch.isfinite(h.predict(res)).all()
    assert sp.labels() == ["G:speed@t=1", "G:speed@t=1.5", "G:speed@t=2.5"]


@pytest.mark.parametrize("text,match", [
    ("t,h\n0,1\n,2\n", "row 3: has no time"),
    ("t,h\n0,1\n1,inf\n", "row 3: column 'h' is not finite.*empty cell or NA"),
    ("t,h,speed\n0,1,2\n1,NA,3\n", "column 'h' has 1 recorded samples \\(1 missing\\)"),
])
def test_gauge_csv_gap_errors(tmp_path, text, match):
    f = tmp_path / "bad.csv"
    f.write_text(text)
    with pytest.raises(GaugeSeriesError, match=match):
        SeriesObservation.from_gauge_csv(f, "G", 0.1)


def test_gauge_csv_missing_columns(tmp_path):
    f = tmp_path / "bad.csv"
    f.write_text("time,h\n0,1\n1,2\n")
    with pytest.raises(GaugeSeriesError, match="row 1"):
        read_gauge_csv(f)


def test_maps_and_grid_mismatch(tmp_path):
    dem, res = _result()
    arr = np.full(dem.shape, 0.5)
    arr[0, 0] = np.nan
    f = tmp_path / "dep.asc"
    write_asc(f, arr, dem)
    o = SeriesObservation.from_raster(f, "deposit_map", dem, 0.3)
    assert o.m == dem.shape[0] * dem.shape[1] - 1
    p = o.predict(res)
    assert p.shape == (2, o.m)
    assert torch.allclose(p[0], res.h_final[0].flatten()[1:])
    im = SeriesObservation.from_array("impact_map", np.ones(dem.shape), dem, 0.5, threshold=1.0)
    assert set(im.predict(res).unique().tolist()) <= {0.0, 1.0}
    other = DEM(z=np.zeros((3, 5)), cellsize=10.0)
    g = tmp_path / "other.asc"
    write_asc(g, np.zeros((3, 5)), other)
    with pytest.raises(TerrainError) as e:
        SeriesObservation.from_raster(g, "deposit_map", dem, 0.3)
    assert str(g) in str(e.value) and "3x5" in str(e.value) and "3x4" in str(e.value)


def test_effective_factor():
    assert effective_factor("deposit_map", None, 10.0) == 1.0
    assert math.isclose(effective_factor("deposit_map", 20.0, 10.0), 2 * math.pi * 4)
    assert math.isclose(effective_factor("gauge_series", 4.0, dt=2.0), 4.0)
    dem, _ = _result()
    o = SeriesObservation.from_array("deposit_map", np.zeros(dem.shape), dem, 0.5, corr_length=20.0)
    assert np.allclose(o.sigma_eff(), 0.5 * math.sqrt(8 * math.pi))
    assert math.isclose(o.n_eff, o.m / (8 * math.pi))


def test_sample_errors_have_the_stated_covariance():
    """Draws of the stated error model: per-value sigma, exponential correlation exp(-r / L) between map cells
    (r in m, diagonal neighbours included) and between series samples (|dt| in s); independent without L."""
    rng = np.random.default_rng(0)
    dem = DEM(z=np.zeros((20, 12)), cellsize=10.0)
    mask = np.ones(dem.shape, bool)
    mask[:3, :] = False                                            # unmapped rows: cell_index skips them
    sig = np.full(dem.shape, 0.5)
    sig[10:, :] = 1.0
    o = SeriesObservation.from_array("deposit_map", np.zeros(dem.shape), dem, sig[mask], corr_length=15.0,
                                     mask=mask)
    e = o.sample_errors(rng, 4000)
    assert e.shape == (4000, o.m)
    g = np.stack([o.to_grid(x) for x in e[:2000]])                 # (n, ny, nx), NaN off the map
    assert np.allclose(np.nanstd(g[:, 3:10], axis=0).mean(), 0.5, rtol=0.05)
    assert np.allclose(np.nanstd(g[:, 10:], axis=0).mean(), 1.0, rtol=0.05)
    z = g / sig
    for (dy, dx), r in (((1, 0), 10.0), ((0, 1), 10.0), ((2, 0), 20.0), ((1, 1), 10.0 * math.sqrt(2))):
        a, b = z[:, 3 + dy:, dx:], z[:, 3:z.shape[1] - dy, :z.shape[2] - dx]
        assert abs(np.mean(a * b) - math.exp(-r / 15.0)) < 0.03, (dy, dx)
    s = SeriesObservation("gauge_series", np.zeros(30), 0.2, name="g:h", gauge="g", times=np.arange(30) * 2.0,
                          corr_length=4.0)
    es = s.sample_errors(rng, 4000) / 0.2
    assert abs(es.var() - 1) < 0.05 and abs(np.mean(es[:, 1:] * es[:, :-1]) - math.exp(-0.5)) < 0.03
    iid = SeriesObservation("gauge_series", np.zeros(30), 0.2, name="g:h", gauge="g", times=np.arange(30) * 2.0)
    ei = iid.sample_errors(rng, 4000) / 0.2
    assert abs(ei.var() - 1) < 0.05 and abs(np.mean(ei[:, 1:] * ei[:, :-1])) < 0.03


def test_series_and_maps_refuse_negative_times_infinite_cells_and_non_binary_impact_maps():
    """Built in code rather than read from files, the same input errors as from files (name and value)."""
    dem = DEM(z=np.zeros((3, 4)), cellsize=10.0, xll=100.0, yll=200.0)
    with pytest.raises(GaugeSeriesError, match="since the release"):
        SeriesObservation("gauge_series", np.ones(3), 0.5, name="G:h", gauge="G", times=np.array([-1.0, 0.0, 1.0])).validate()
    a = np.zeros(dem.shape)
    a[1, 2] = -np.inf
    with pytest.raises(ValueError, match=r"1 infinite cells, first at row 1 from the south, col 2 \(x=125 m, y=215 m\): -inf"):
        SeriesObservation.from_array("deposit_map", a, dem, 0.5)
    b = np.ones(dem.shape)
    b[0, 0] = np.nan          # nodata: not mapped, allowed
    assert SeriesObservation.from_array("impact_map", b, dem, 0.5).m == 11
    b[2, 3] = 2.0
    with pytest.raises(ValueError, match="1 cells hold other values, first at row 2 from the south, col 3"):
        SeriesObservation.from_array("impact_map", b, dem, 0.5)
