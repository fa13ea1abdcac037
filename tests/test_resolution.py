"""The inversion grid's resolution: maps averaged onto another grid, the grid chosen by its own error
(``[diagnose] cellsize = "auto"``), and the mismatches that finer cells remove."""
from __future__ import annotations

import math

import numpy as np
import pytest

from torchslide.bayes import Prior, Uniform
from torchslide.observe import Observation
from torchslide.observe_series import SeriesObservation
from torchslide.terrain.grid import DEM
from torchslide.terrain.resample import resample_map
from torchslide.terrain.synthetic import inclined_plane, release_from_shape


def test_a_map_is_averaged_over_the_cells_each_new_cell_overlaps():
    """resample_map: the area-weighted mean of the mapped source cells, NaN where they cover less than half
    of a new cell, 0/1 maps rounded; a 30 m grid over 20 m cells weights the overlaps by their area."""
    src = DEM(np.zeros((6, 6)), 10.0)
    a = np.arange(36.0).reshape(6, 6)
    a[0, :2] = np.nan
    a[1, 0] = np.nan
    out = resample_map(a, src, DEM(np.zeros((3, 3)), 20.0))
    assert np.isnan(out[0, 0])                                  # 1 of 4 source cells mapped
    assert out[0, 1] == np.mean([a[0, 2], a[0, 3], a[1, 2], a[1, 3]])
    assert out[2, 2] == np.mean(a[4:, 4:])
    full = np.arange(36.0).reshape(6, 6)
    half = resample_map(np.where(full % 2 == 0, np.nan, full), src, DEM(np.zeros((3, 3)), 20.0))
    assert np.all(np.isfinite(half))                            # half of every cell mapped: kept
    src20 = DEM(np.zeros((9, 9)), 20.0)
    b = np.arange(81.0).reshape(9, 9)
    o30 = resample_map(b, src20, DEM(np.zeros((6, 6)), 30.0))
    # new cell (0, 0) covers x, y in [0, 30): source cells 0 (20 m of it) and 1 (10 m) along each axis
    w = np.array([20.0, 10.0])
    assert math.isclose(o30[0, 0], float(w @ b[:2, :2] @ w) / 900.0)
    imp = np.where(a > 20, 1.0, 0.0)
    r = resample_map(imp, src, DEM(np.zeros((3, 3)), 20.0), binary=True)
    assert set(np.unique(r)) <= {0.0, 1.0}


def test_a_map_observation_follows_its_values_onto_a_coarser_grid():
    """SeriesObservation.on_grid: the deposit map's cells on the new grid (block means), its name, sigma
    and correlation length kept; a gauge series or a map already on the grid is returned as it is."""
    src, dst = DEM(np.zeros((8, 12)), 10.0), DEM(np.zeros((4, 6)), 20.0)
    a = np.full(src.shape, np.nan)
    a[2:6, 4:10] = np.arange(24.0).reshape(4, 6)
    o = SeriesObservation.from_array("deposit_map", a, src, 0.4, name="dep", corr_length=30.0)
    c = o.on_grid(src, dst)
    assert c.grid_shape == (4, 6) and c.cellsize == 20.0 and c.name == "dep" and c.corr_length == 30.0
    assert c.sigma == 0.4 and c.m == 6
    assert math.isclose(float(c.to_grid(c.values)[1, 2]), float(np.mean(a[2:4, 4:6])))
    assert c.on_grid(dst, dst) is c
    g = SeriesObservation("gauge_series", np.ones(3), 0.5, name="g:h", gauge="g", times=np.arange(3.0))
    assert g.on_grid(src, dst) is g


def _plane_evaluator(cellsize=25.0, map_sigma=0.5, gauge_sigma=0.5, record_factor=1):
    """A DiagnosisEvaluator on a 30 deg plane with a deposit map and a gauge, its recordings made by the
    solver on cells ``record_factor`` times smaller (the deposit block-averaged onto the grid)."""
    from torchslide.diagnose import DiagnosisEvaluator
    from torchslide.physics import Params
    from torchslide.solver import SolverConfig, simulate

    dem = inclined_plane(30.0, cellsize, slope_length=500.0, runout_length=500.0, width=300.0)
    rel = release_from_shape(dem, (200.0, 150.0), (100.0, 80.0), volume=1.0e5)
    cfg = SolverConfig(stop_ke_fraction=2e-3, output_interval=1.0)
    gauges = [("G1", 610.0, 150.0)]
    f = record_factor
    dem_r = inclined_plane(30.0, cellsize / f, slope_length=500.0, runout_length=500.0, width=300.0)
    rel_r = release_from_shape(dem_r, (200.0, 150.0), (100.0, 80.0), volume=1.0e5)
    r = simulate(dem_r, rel_r, Params.make(mu=0.3, xi=800.0), t_end=40.0, gauges=gauges, config=cfg)
    dep = r.h_final[0].numpy().reshape(dem.ny, f, dem.nx, f).mean(axis=(1, 3))
    g = r.gauges["G1"]
    t = np.arange(2.0, 40.0, 2.0)
    from torchslide.observe_series import interp_series
    import torch
    h = interp_series(g.t, g.h, torch.as_tensor(t))[0].numpy()
    obs = [SeriesObservation.from_array("deposit_map", dep, dem, map_sigma, name="deposit"),
           SeriesObservation("gauge_series", h, gauge_sigma, name="G1:h", gauge="G1", quantity="h", times=t),
           Observation("final_volume", 1.0e5, 1.0e4, name="final_volume")]
    prior = Prior({"mu": Uniform(0.25, 0.35), "xi": Uniform(500.0, 1200.0)})
    return DiagnosisEvaluator(dem=dem, release=rel, observations=obs, prior=prior, t_end=40.0, gauges=gauges,
                              solver_config=cfg, max_batch=8)


def test_regrid_keeps_the_release_volume_and_averages_the_maps():
    from torchslide.diagnose.resolution import fine_terrain_from, regrid

    ev = _plane_evaluator()
    c = regrid(ev, 50.0)
    assert c.dem.cellsize == 50.0 and c.dem.shape == (6, 20)
    area = lambda e: float((np.asarray(e.release) * e.dem.surface_area()).sum())
    assert math.isclose(area(c), area(ev), rel_tol=1e-9)
    dep, dep0 = c.observations[0], ev.observations[0]
    assert dep.grid_shape == (6, 20) and c.observations[1] is ev.observations[1]
    full0 = dep0.to_grid(dep0.values)
    assert math.isclose(float(dep.to_grid(dep.values)[3, 10]), float(np.mean(full0[6:8, 20:22])))
    assert regrid(ev, 25.0) is ev
    with pytest.raises(ValueError, match=r"gauge G1 at \(990, 150\) lies outside the 75 m grid's extent"):
        regrid(ev._copy(gauges=[("G1", 990.0, 150.0)]), 75.0)
    ft = fine_terrain_from(ev, c)                # cells of 25 m: the configured grid itself
    assert ft.factor_for(c.dem) == 2 and np.array_equal(ft.dem.z, ev.dem.z)
    assert fine_terrain_from(ev, ev) is None     # 12.5 m: finer than the configured grid


def test_the_grid_is_the_coarsest_whose_error_is_below_the_stated_noise():
    """choose_grid: with generous stated errors the coarsest candidate passes and is chosen; with tight
    ones none does and the finest within the budget is taken, the report naming the blocks that exceed;
    a budget below a grid's cells passes it over."""
    from torchslide.diagnose.resolution import choose_grid

    loose = _plane_evaluator(map_sigma=50.0, gauge_sigma=50.0)
    ev, ft, rep = choose_grid(loose, factors=(2, 1), n_sets=2, log=lambda s: None)
    assert rep["cellsize"] == 50.0 and rep["tried"][0]["passes"] and len(rep["tried"]) == 1
    assert ev.dem.cellsize == 50.0 and ft is not None and ft.dem.cellsize == 25.0
    assert "below the stated noise" in rep["reason"]
    tight = _plane_evaluator(map_sigma=1e-4, gauge_sigma=1e-4)
    ev, ft, rep = choose_grid(tight, factors=(2, 1), n_sets=2, log=lambda s: None)
    assert [t["cellsize"] for t in rep["tried"]] == [50.0, 25.0] and ev is tight and ft is None
    assert not rep["tried"][1]["passes"] and "exceeds the stated noise in deposit" in rep["reason"]
    assert rep["tried"][1]["ratio"]["deposit"] > 1.0
    ev, _, rep = choose_grid(tight, factors=(2, 1), n_sets=2, max_cells=200, log=lambda s: None)
    assert ev.dem.cellsize == 50.0 and rep["tried"][1]["skipped"] == "over the budget of 200 cells"


def test_mismatches_the_grid_error_accounts_for_are_reported_as_resolution():
    from torchslide.diagnose.resolution import removed_by_resolution

    raw = [{"what": "cluster", "where": "deposit", "standardised_residual": 9.0, "_idx": [1, 2, 3]},
           {"what": "window", "where": "g1:speed", "standardised_residual": -12.0, "_idx": [40, 41]}]
    kept = [{"what": "cluster", "where": "deposit", "standardised_residual": 8.5, "_idx": [2, 3, 4]}]
    out = removed_by_resolution(raw, kept)
    assert out == [{"what": "window", "where": "g1:speed", "standardised_residual": -12.0}]
    assert removed_by_resolution(raw, []) == [{k: v for k, v in r.items() if k != "_idx"} for r in raw]


def test_a_config_map_on_the_dem_file_grid_is_averaged_onto_terrain_cellsize(tmp_path):
    """[terrain] cellsize coarser than the DEM file: the elevation-change and footprint maps (on the DEM
    file's grid) are averaged onto the inversion grid, not refused (the msh2021 example at 20 m)."""
    from torchslide.cli import main
    from torchslide.commands.diagnose import load_diagnose_config
    from torchslide.observe_series import read_map

    assert main(["example", "msh2021", "--out", str(tmp_path)]) == 0
    text = (tmp_path / "diagnose.toml").read_text().replace('thickness = "normal"\n',
                                                             'thickness = "normal"\ncellsize = 20.0\n', 1)
    (tmp_path / "d20.toml").write_text(text)
    cfg = load_diagnose_config(tmp_path / "d20.toml")
    assert cfg.terrain.dem.cellsize == 20.0 and cfg.terrain.source_dem.cellsize == 10.0
    dod = next(o for o in cfg.extra["observations"] if o.name == "dod")
    src = cfg.terrain.source_dem
    ny, nx = cfg.terrain.dem.shape
    want = resample_map(read_map(tmp_path / "dod.asc", src), src, cfg.terrain.dem)
    got = dod.to_grid(dod.values)
    assert dod.grid_shape == (ny, nx)
    assert np.allclose(got[np.isfinite(got)], want[np.isfinite(got)])
    fp = next(o for o in cfg.extra["observations"] if o.kind == "footprint")
    assert set(np.unique(fp.values)) <= {0.0, 1.0}


def test_the_diagnosis_reports_what_the_grid_error_accounts_for():
    """Recordings made on cells half as large with nothing hidden, stated errors tight: against the data as
    given the calibrated baseline shows located mismatches; with the grid's error in the likelihood they are
    gone, and _assess lists them as the grid's own (decision["resolution"])."""
    from torchslide.diagnose import Budgets, Thresholds
    from torchslide.diagnose.model_error import approximation_error
    from torchslide.diagnose.pipeline import _assess, _Baseline
    from torchslide.diagnose.predictive import posterior_predictive

    ev = _plane_evaluator(map_sigma=0.02, gauge_sigma=0.02, record_factor=2)
    x = np.array([[0.30, 800.0], [0.295, 780.0], [0.305, 820.0], [0.3, 760.0], [0.3, 840.0], [0.298, 800.0]])
    ev_me = ev.with_model_error(approximation_error(ev, x))
    base = _Baseline(calibration=None, pred=posterior_predictive(ev_me, x), ver={})
    _assess(ev_me, base, Thresholds(), Budgets(n_perm=19))
    assert base.resolution, "the raw data show no located mismatch: the case does not test anything"
    assert all(abs(r["standardised_residual"]) >= Thresholds().located_min for r in base.resolution)
    assert any(r["what"].startswith("deposit_map") for r in base.resolution)
    without = _Baseline(calibration=None, pred=posterior_predictive(ev, x), ver={})
    _assess(ev, without, Thresholds(), Budgets(n_perm=19))
    assert without.resolution is None          # no grid error in the likelihood: nothing to attribute
