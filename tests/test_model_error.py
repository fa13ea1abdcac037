"""Approximation error of the inversion grid (torchslide.diagnose.model_error)."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from torchslide.bayes import Prior, Uniform
from torchslide.diagnose import DiagnosisEvaluator
from torchslide.diagnose.model_error import (FineTerrain, ModelError, approximation_error, coarsen_result,
                                             fine_predictions, refine_dem, repeat_cells)
from torchslide.observe import Observation
from torchslide.observe_series import SeriesObservation
from torchslide.solver import SolverConfig, simulate
from torchslide.terrain.synthetic import inclined_plane, release_from_shape


def test_refine_dem_keeps_a_plane_and_the_extent():
    dem = inclined_plane(30.0, 40.0, slope_length=400.0, runout_length=200.0, width=200.0, transition=0.0)
    dem.z[:] = 0.3 * dem.x_centres()[None, :] - 0.1 * dem.y_centres()[:, None] + 5.0   # a tilted plane
    f = refine_dem(dem, 2)
    assert f.shape == (2 * dem.ny, 2 * dem.nx) and f.cellsize == 20.0
    assert (f.xll, f.yll) == (dem.xll, dem.yll)
    exact = 0.3 * f.x_centres()[None, :] - 0.1 * f.y_centres()[:, None] + 5.0
    assert np.allclose(f.z, exact)                       # bilinear (and its linear extrapolation) is exact
    with pytest.raises(ValueError, match="refinement factor"):
        refine_dem(dem, 1)


def _case(cellsize=40.0):
    dem = inclined_plane(30.0, cellsize, slope_length=600.0, runout_length=600.0, width=320.0, transition=200.0)
    rel = release_from_shape(dem, (150.0, 160.0), 60.0, volume=2.0e4)
    return dem, rel


def test_coarsened_fine_run_conserves_volume_and_matches_the_coarse_layout():
    dem, rel = _case()
    rel_f = repeat_cells(rel, 2)
    dem_f = refine_dem(dem, 2)
    assert math.isclose(rel_f.sum() * dem_f.cellsize**2, rel.sum() * dem.cellsize**2, rel_tol=1e-12)
    from torchslide.physics import Params
    res = simulate(dem_f, rel_f, Params.make(mu=0.3, xi=500.0), t_end=20.0, config=SolverConfig())
    c = coarsen_result(res, dem, 2)
    assert c.h_final.shape == (1, dem.ny, dem.nx) and c.dem is dem
    vol_f = float((res.h_final[0] * res.cell_area).sum())
    vol_c = float((c.h_final[0] * c.cell_area).sum())
    assert math.isclose(vol_c, vol_f, rel_tol=1e-9)      # block means x summed areas: same volume
    assert torch.equal(c.arrival_time[0, 0, 0], res.arrival_time[0, :2, :2].min())


def _evaluator(model_error=None, discrepancy="none"):
    """The grid's error alone in the likelihood (the Gaussian it shifts and widens); ``discrepancy`` "learnt" adds
    the model's own error over it."""
    dem, rel = _case()
    g = [("g1", 700.0, 160.0)]
    t = np.arange(2.0, 40.0, 2.0)
    obs = [SeriesObservation.from_array("deposit_map", np.zeros(dem.shape), dem, 0.5, name="deposit"),
           SeriesObservation("gauge_series", np.zeros_like(t), 0.5, name="g1:h", gauge="g1", quantity="h", times=t),
           Observation("final_volume", 2.0e4, 2.0e3, name="final_volume")]
    prior = Prior({"mu": Uniform(0.2, 0.45), "xi": Uniform(200.0, 1500.0)})
    return DiagnosisEvaluator(dem=dem, release=rel, observations=obs, prior=prior, t_end=40.0, gauges=g,
                              solver_config=SolverConfig(), model_error=model_error, discrepancy=discrepancy)


def test_model_error_likelihood_is_the_shifted_gaussian_with_the_added_covariance():
    ev = _evaluator()
    k = ev.k
    rng = np.random.default_rng(0)
    eps = rng.normal(0.05, 0.02, (6, k))
    me = ModelError(samples=eps, x=np.zeros((6, 2)), factor=2)
    ev2 = ev.with_model_error(me)
    assert ev2.model_error is me and ev2.records == [] and np.array_equal(ev2.data_recorded, ev.data)
    y = rng.normal(0.0, 0.3, (3, k))
    cov = np.diag(ev.sigma**2) + np.cov(eps, rowvar=False)
    r = (ev.data - eps.mean(0))[None, :] - y
    sign, logdet = np.linalg.slogdet(cov)
    quad = np.einsum("ni,ij,nj->n", r, np.linalg.inv(cov), r)
    ref = -0.5 * (quad + logdet + k * math.log(2 * math.pi))
    assert np.allclose(ev2.likelihood.log_likelihood(torch.as_tensor(y)).numpy(), ref, rtol=1e-9)
    assert np.all(ev2.sigma > ev.sigma) and np.all(ev2.sigma_raw >= ev.sigma_raw)
    # with the learnt discrepancy the same Gaussian is its base (its normaliser and whitening)
    ev3 = _evaluator(discrepancy="learnt").with_model_error(me)
    assert ev3.likelihood.log_norm == pytest.approx(ev2.likelihood.log_norm, rel=1e-12)
    assert np.allclose(ev3.likelihood.whiten(torch.as_tensor(y)).numpy(), ev2.likelihood.whiten(torch.as_tensor(y)).numpy())
    # the candidate copies keep it
    from torchslide.diagnose.refit import candidate_evaluator
    assert candidate_evaluator(ev2, "mu_i").model_error is me
    with pytest.raises(ValueError, match="values per sample"):
        ev.with_model_error(ModelError(samples=eps[:, :-1], x=np.zeros((6, 2)), factor=2))


def test_approximation_error_is_the_fine_minus_coarse_difference():
    ev = _evaluator()
    x = np.array([[0.3, 500.0], [0.35, 800.0], [0.32, 600.0]])
    me = approximation_error(ev, x, factor=2)
    assert me.samples.shape == (3, ev.k) and ev.records == []       # no run records left behind
    fine, failed = fine_predictions(ev, x[:1], 2)
    _, coarse = ev.evaluate(torch.as_tensor(x[:1]))
    assert not failed.any()
    assert np.allclose(me.samples[0], fine[0] - coarse.numpy()[0])
    assert np.abs(me.samples).max() > 1e-3                         # the grids do differ
    fv = ev.block("final_volume").slice
    assert np.abs(me.samples[:, fv]).max() < 1e-3 * 2.0e4            # ... hardly in the conserved volume
    s = me.summary(ev.blocks)
    assert s["n"] == 3 and set(s["blocks"]) == {"deposit", "g1:h", "final_volume"}
    with pytest.raises(ValueError, match="at least 2"):
        approximation_error(ev, x[:1])


def _fine_terrain(ev, factor=2):
    """The same inclined plane as _case() sampled on cells ``factor`` times smaller, its own release."""
    dem_f, rel_f = _case(ev.dem.cellsize / factor)
    return FineTerrain(dem_f, rel_f)


def test_fine_terrain_replaces_the_refined_dem_in_the_finer_runs():
    """With a FineTerrain the finer runs use its DEM and release, not the bilinear refinement of the
    coarse ones: the sampled terrain of _case() at 20 m differs from the refined 40 m one at the foot of
    the slope (the curved transition), so the predictions differ; a copy keeps the fine terrain."""
    ev = _evaluator()
    ft = _fine_terrain(ev)
    assert ft.factor_for(ev.dem) == 2
    assert np.abs(ft.dem.z - refine_dem(ev.dem, 2).z).max() > 0.1
    ev_ft = ev._copy(fine_terrain=ft)
    x = np.array([[0.3, 500.0]])
    with_ft, failed = fine_predictions(ev_ft, x, 2)
    refined, _ = fine_predictions(ev, x, 2)
    assert not failed.any()
    assert np.abs(with_ft[0] - refined[0]).max() > 1e-3
    from torchslide.physics import Params
    res = simulate(ft.dem, ft.release, Params.make(mu=0.3, xi=500.0), t_end=40.0, gauges=list(ev.gauges),
                   config=SolverConfig())
    direct, _, _ = ev.predict(coarsen_result(res, ev.dem, 2))
    assert np.allclose(with_ft[0], direct.numpy()[0])
    assert ev_ft.with_model_error(None).fine_terrain is ft
    with pytest.raises(ValueError, match="differs from the fine terrain"):
        fine_predictions(ev_ft, x, 4)


def test_fine_terrain_on_another_grid_is_refused_before_any_run():
    ev = _evaluator()
    ft = _fine_terrain(ev)
    with pytest.raises(ValueError, match=r"fine_terrain.dem: shape"):
        ev._copy(fine_terrain=FineTerrain(ft.dem.__class__(ft.dem.z[:, :-1], ft.dem.cellsize), ft.release[:, :-1]))
    with pytest.raises(ValueError, match=r"fine_terrain.dem: cellsize 15"):
        ev._copy(fine_terrain=FineTerrain(ft.dem.__class__(np.zeros((10, 10)), 15.0), np.zeros((10, 10))))
    with pytest.raises(ValueError, match=r"lower-left corner"):
        ev._copy(fine_terrain=FineTerrain(ft.dem.__class__(ft.dem.z, ft.dem.cellsize, xll=5.0), ft.release))
    with pytest.raises(ValueError, match=r"fine_terrain.release: shape"):
        ev._copy(fine_terrain=FineTerrain(ft.dem, ft.release[:-1]))
    bad = ft.release.copy()
    bad[0, 0] = np.nan
    with pytest.raises(ValueError, match=r"fine_terrain.release: contains non-finite"):
        ev._copy(fine_terrain=FineTerrain(ft.dem, bad))


def test_grid_model_error_from_a_pilot_calibration(tmp_path):
    """The pipeline's step: pilot baseline calibration, posterior draws, run pairs; the returned
    evaluator carries the model error; a given baseline cannot be combined with it."""
    from torchslide.diagnose import Budgets, diagnose
    from torchslide.diagnose.pipeline import grid_model_error

    ev = _evaluator()
    bud = Budgets(inference="emulator", baseline_n_initial=4, baseline_n_total=6, baseline_grid_size=40,
                  model_error_runs=3, batch_size=8,
                  mcmc_steps=200, release_volume_sd=0.05)
    ev_me, me = grid_model_error(ev, bud, tmp_path, log=lambda s: None)
    assert me.samples.shape == (3, ev.k) and ev_me.model_error is me
    assert me.release_sd == 0.05 and me.release_jacobian.shape == (3, ev.k)   # Budgets.release_volume_sd reaches it
    assert np.all((me.x >= ev.prior.bounds[0].numpy()) & (me.x <= ev.prior.bounds[1].numpy()))
    with pytest.raises(ValueError, match="baseline must be calibrated here"):
        diagnose(ev, ["mu_i"], bud, baseline=object(), workdir=tmp_path)


def test_model_error_seed_holds_the_grid_error_estimate_fixed(tmp_path):
    """Budgets.model_error_seed seeds the pilot and its draws (None: Budgets.seed), so the likelihood can be
    held fixed while the rest of the inference's seed changes."""
    from torchslide.diagnose import Budgets
    from torchslide.diagnose.pipeline import grid_model_error

    ev = _evaluator()
    small = dict(baseline_n_initial=4, baseline_n_total=6, baseline_grid_size=40, model_error_runs=3, batch_size=8,
                 mcmc_steps=200)
    x = {}
    for tag, kw in (("fixed", dict(seed=0, model_error_seed=7)), ("seed7", dict(seed=7)), ("seed0", dict(seed=0))):
        x[tag] = grid_model_error(ev, Budgets(**small, **kw), tmp_path / tag, log=lambda s: None)[1].x
    assert np.array_equal(x["fixed"], x["seed7"])
    assert not np.array_equal(x["fixed"], x["seed0"])


def test_release_volume_error_enters_the_covariance_through_its_jacobian():
    """release_sd > 0: J = dy/d(relative volume) by central differences at the same draws. Without
    entrainment the final volume is the release volume (mass conservation), so its row of J is V and its
    variance grows by (s_V V)^2; the deposit map gains variance too, the grid part is unchanged."""
    from torchslide.diagnose.model_error import release_jacobian

    ev = _evaluator()
    x = np.array([[0.3, 500.0], [0.35, 800.0], [0.32, 600.0]])
    V = float((np.asarray(ev.release) * ev.dem.surface_area()).sum())   # normal thickness x surface area
    me0 = approximation_error(ev, x, factor=2)
    me = approximation_error(ev, x, factor=2, release_sd=0.05)
    assert me.release_jacobian.shape == (3, ev.k) and me.release_sd == 0.05
    fv = ev.block("final_volume").slice
    assert np.allclose(me.release_jacobian[:, fv], V, rtol=1e-3)   # up to float32 and outflow
    assert np.allclose(me.samples, me0.samples) and np.allclose(me.grid_covariance, me0.covariance)
    added = np.diag(me.covariance - me0.covariance)
    assert math.isclose(added[fv][0], (0.05 * V) ** 2, rel_tol=2e-3)
    dep = ev.block("deposit").slice
    assert added[dep].max() > 0 and np.all(added >= -1e-12)
    s = me.summary(ev.blocks)
    assert s["release_sd"] == 0.05 and math.isclose(s["blocks"]["final_volume"]["rms_sd_release"], 0.05 * V, rel_tol=1e-3)
    assert "release_sd" not in me0.summary(ev.blocks)
    # the likelihood carries it: a prediction off by the volume's sd costs less with it
    ev_me, ev_me0 = ev.with_model_error(me), ev.with_model_error(me0)
    assert ev_me.sigma[fv][0] > ev_me0.sigma[fv][0]
    with pytest.raises(ValueError, match=r"release_volume_sd must be in \(0, 0.5\)"):
        release_jacobian(ev, x, 0.7)


def test_release_volume_sd_needs_the_model_error_runs(tmp_path):
    from torchslide.diagnose import Budgets, diagnose

    ev = _evaluator()
    with pytest.raises(ValueError, match="release_volume_sd = 0.05 needs model_error_runs >= 2"):
        diagnose(ev, ["mu_i"], Budgets(model_error_runs=0, release_volume_sd=0.05), workdir=tmp_path)
    with pytest.raises(ValueError, match=r"release_volume_sd must be in \[0, 0.5\)"):
        diagnose(ev, ["mu_i"], Budgets(release_volume_sd=-0.1), workdir=tmp_path)
    with pytest.raises(ValueError, match=r"detectability must be \"measured\" or \"linearised\", got 'linear'"):
        diagnose(ev, ["mu_i"], Budgets(detectability="linear"), workdir=tmp_path)


def test_the_gauge_figure_shows_the_recording_as_given(tmp_path):
    """With the grid's error in the likelihood, the localisation keeps the user's recording ("recorded")
    beside the shifted data, and the report's gauge figure plots the recording, not recording - mean error."""
    from torchslide.diagnose.localise import localise

    ev = _evaluator()
    k = ev.k
    eps = np.random.default_rng(1).normal(3.0, 0.1, (6, k))          # a mean error of about +3 everywhere
    ev2 = ev.with_model_error(ModelError(samples=eps, x=np.zeros((6, 2)), factor=2))
    draws = np.random.default_rng(2).normal(0.0, 0.1, (4, k))
    L = localise(ev2, draws, n_perm=9)
    g = L.maps["g1:h"]
    b = next(b for b in ev2.blocks if b.name == "g1:h")
    assert np.array_equal(g["recorded"], ev.data[b.slice])              # what the user gave (zeros)
    assert np.allclose(g["data"], ev.data[b.slice] - eps.mean(0)[b.slice])
    assert np.allclose(g["offset"], eps.mean(0)[b.slice]) and np.all(g["offset"] > 2.5)
