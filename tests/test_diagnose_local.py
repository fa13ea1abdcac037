"""Local Gaussian inference (torchslide.diagnose.local): the Laplace evidence against brute-force
integrals, the optimiser on a small solver case, the Schur-complement detectability."""
from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import stats
from scipy.special import logsumexp

from torchslide.diagnose.local import detectable_switch, fit, switch_information


def _model(M: np.ndarray, d: np.ndarray, curve: float = 0.0):
    """Batched whitened residuals r = y(x) - d, y = M x + curve (M x)^2 (sigma 1)."""
    def residuals(X):
        Y = X @ M.T
        return Y + curve * Y**2 - d, np.zeros(len(X), dtype=bool)
    return residuals


def _brute_log_evidence(residuals, bounds, n: int) -> float:
    """ln of the integral of exp(-|r|^2 / 2) / V over the box by the midpoint rule (n nodes per axis)."""
    lo, hi = bounds
    axes = [lo[i] + (np.arange(n) + 0.5) * (hi[i] - lo[i]) / n for i in range(len(lo))]
    G = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, len(lo))
    r, _ = residuals(G)
    cell = np.prod((hi - lo) / n)
    return float(logsumexp(-0.5 * (r**2).sum(axis=1)) + math.log(cell) - math.log(np.prod(hi - lo)))


@pytest.mark.parametrize("truth", [[0.4, 0.6], [-0.05, 0.5]])
def test_laplace_evidence_is_exact_for_a_linear_2d_model(truth):
    """Linear residuals, uniform prior: the Laplace evidence (with the box's share of the Gaussian) equals
    the integral, also when the mode sits on the box's edge (truth near 0: a switch at 0)."""
    rng = np.random.default_rng(0)
    M = rng.normal(size=(6, 2)) * 8.0
    d = M @ np.asarray(truth) + rng.normal(size=6) * 0.5
    res = _model(M, d)
    bounds = np.array([[0.0, 0.0], [1.0, 1.0]])
    f = fit(res, np.array([0.5, 0.5]), bounds, log_norm=0.0, log_prior=0.0)
    brute = _brute_log_evidence(res, bounds, 800)
    assert f.converged
    assert abs(f.log_evidence - brute) < 1e-3
    if truth[0] > 0:
        np.testing.assert_allclose(f.x, np.linalg.lstsq(M, d, rcond=None)[0], atol=1e-6)
    else:
        assert f.x[0] == pytest.approx(0.0, abs=1e-9)   # the mode on the edge


def test_laplace_evidence_of_a_gaussian_like_3d_model_within_a_tenth_of_a_nat():
    rng = np.random.default_rng(1)
    M = rng.normal(size=(9, 3)) * 6.0
    truth = np.array([0.3, 0.55, 0.7])
    y = M @ truth
    d = y + 0.03 * y**2 + rng.normal(size=9) * 0.5
    res = _model(M, d, curve=0.03)
    bounds = np.array([[0.0] * 3, [1.0] * 3])
    f = fit(res, np.array([0.5, 0.5, 0.5]), bounds, log_norm=0.0, log_prior=0.0)
    # the brute-force integral on a window of +-8 sd around the mode (the rest of the box holds nothing)
    win = np.stack([np.maximum(f.x - 8 * f.sd, 0.0), np.minimum(f.x + 8 * f.sd, 1.0)])
    brute = _brute_log_evidence(res, win, 90) + math.log(np.prod(win[1] - win[0]))
    assert abs(f.log_evidence - brute) < 0.1
    assert np.all(np.abs(f.x - truth) < 4 * f.sd)


def test_the_schur_complement_is_the_likelihood_ratio_of_a_switch():
    """Linear model y = T theta + s b: with theta re-tuned, 2 ln LR of a switch s is s^2 I_s exactly,
    so the detectable switch at 2 ln BF = 6 is sqrt(6 / I_s)."""
    rng = np.random.default_rng(2)
    J = rng.normal(size=(20, 3))
    s_true = 0.7
    d = J @ np.array([0.4, -0.3, s_true])
    full = np.linalg.lstsq(J, d, rcond=None)[0]
    base = np.linalg.lstsq(J[:, :2], d, rcond=None)[0]
    two_ln_lr = np.sum((d - J[:, :2] @ base) ** 2) - np.sum((d - J @ full) ** 2)
    info = switch_information(J, 2)
    assert two_ln_lr == pytest.approx(s_true**2 * info, rel=1e-10)
    assert detectable_switch(J, 2) == pytest.approx(math.sqrt(6.0 / info))
    # a switch whose column the nuisance columns reproduce carries no information
    J2 = np.column_stack([J[:, :2], J[:, 0] - 2 * J[:, 1]])
    assert switch_information(J2, 2) < 1e-20 and detectable_switch(J2, 2) > 1e9


def test_the_optimiser_recovers_the_optimum_of_a_small_solver_case():
    """Noise-free recordings of a small chute run at (mu, xi) = (0.3, 600): the least-squares fit on the
    solver from a start far off finds them, and its Gaussian has them at its centre."""
    import torch

    from torchslide import observe
    from torchslide.physics import Params
    from torchslide.solver import SolverConfig, simulate

    from .conftest import cap_release, chute_dem

    dem = chute_dem(nx=40, ny=12, dx=20.0, x_break=500.0)
    rel = cap_release(dem, 120.0, 120.0, 60.0, 6.0)
    cfg = SolverConfig(output_interval=5.0)
    pts = [(300.0, 120.0), (450.0, 120.0)]

    def observables(X):
        r = simulate(dem, rel, Params.make(mu=torch.tensor(X[:, 0]), xi=torch.tensor(X[:, 1])), t_end=80.0, config=cfg)
        cols = [observe.max_velocity(r, x, y) for x, y in pts] + [observe.max_height(r, x, y) for x, y in pts]
        cols.append(observe.impact_area(r, 0.2) / 1e4)
        return torch.stack(cols, dim=1).numpy(), r.failed.numpy()

    truth = np.array([[0.3, 600.0]])
    d, _ = observables(truth)
    sigma = np.maximum(0.02 * np.abs(d[0]), 0.05)

    def residuals(X):
        y, failed = observables(X)
        return (y - d[0]) / sigma, failed

    bounds = np.array([[0.15, 200.0], [0.45, 1500.0]])
    f = fit(residuals, np.array([0.4, 1200.0]), bounds, log_norm=0.0, log_prior=0.0)
    np.testing.assert_allclose(f.x, truth[0], rtol=0.02)
    assert f.log_like > -0.5 and f.n_runs <= 30 * 5


def test_a_fit_runs_one_member_per_trial_point_and_its_jacobian_only_where_a_step_is_accepted():
    """local.fit: each trial point of the trust region is one run; the Jacobian's 2p runs are asked for only
    where least_squares accepts a step (near the mode most trial points are rejected); the mode, ln L and
    the Gauss-Newton precision are those of the same least squares with the central-difference Jacobian."""
    from scipy import optimize

    from torchslide.diagnose.local import steps

    t = np.linspace(0.0, 1.0, 25)
    d = 2.0 * np.exp(-3.0 * t) + 0.02 * np.random.default_rng(3).standard_normal(t.size)
    calls = []

    def residuals(X):       # the model's outputs quantised, as a solver's time steps make them near the mode
        calls.append(len(X))
        y = np.round(X[:, :1] * np.exp(-X[:, 1:2] * t), 3)
        return (y - d) / 0.02, np.zeros(len(X), dtype=bool)

    bounds = np.array([[0.5, 0.5], [4.0, 6.0]])
    f = fit(residuals, np.array([1.0, 1.0]), bounds, log_norm=0.0, log_prior=0.0)
    assert set(calls) == {1, 4} and f.n_runs == sum(calls)
    assert calls.count(4) < calls.count(1)          # some trial points were rejected: no Jacobian there
    lo, scale, h = bounds[0], bounds[1] - bounds[0], steps(bounds, 3e-3)

    def r(u):
        return residuals((lo + u * scale)[None])[0][0]

    def jac(u):
        x = lo + u * scale
        cols = []
        for i in range(2):
            e = np.zeros(2)
            e[i] = h[i]
            cols.append((residuals((x + e)[None])[0][0] - residuals((x - e)[None])[0][0]) / (2 * h[i]))
        return np.stack(cols, axis=1) * scale

    ref = optimize.least_squares(r, (np.array([1.0, 1.0]) - lo) / scale, jac=jac, bounds=(0.0, 1.0), method="trf",
                                 xtol=1e-6, ftol=1e-6, gtol=1e-10, max_nfev=30, x_scale="jac")
    np.testing.assert_allclose(f.x, lo + ref.x * scale, rtol=1e-12)
    np.testing.assert_allclose(f.log_like, -0.5 * ref.fun @ ref.fun, rtol=1e-12)
    np.testing.assert_allclose(f.precision, (ref.jac / scale).T @ (ref.jac / scale), rtol=1e-9)


# ---- the local path (torchslide.diagnose.local_path) ----

def test_the_boundary_corrected_likelihood_ratio_holds_its_level():
    """A switch s >= 0 whose true value is its bound 0, two nuisance parameters re-tuned: 2 ln LR is 0 in
    half of the null draws and chi2_1 in the other half, so p = P(chi2_1 > lambda) / 2 rejects at its level."""
    from torchslide.diagnose.local_path import lr_pvalue

    rng = np.random.default_rng(3)
    J = rng.normal(size=(15, 3))
    T, b = J[:, :2], J[:, 2]
    P = np.eye(15) - T @ np.linalg.pinv(T)            # what re-tuning the nuisance cannot absorb
    s_b = P @ b
    n = 20000
    E = rng.normal(size=(n, 15))                      # whitened noise, nothing hidden
    score = E @ s_b / (s_b @ s_b)                     # the unconstrained switch estimate
    lam = np.where(score > 0, score**2 * (s_b @ s_b), 0.0)
    p = np.array([lr_pvalue(v) for v in lam])
    assert np.mean(lam == 0) == pytest.approx(0.5, abs=0.015)
    for level in (0.05, 0.01):
        assert np.mean(p <= level) == pytest.approx(level, rel=0.15)


def _linear_problem(truth_s: float, seed: int = 4):
    rng = np.random.default_rng(seed)
    J = rng.normal(size=(12, 3)) * 4.0
    d = J @ np.array([0.5, 0.4, truth_s]) + rng.normal(size=12) * 0.5

    def full(X):
        return X @ J.T - d, np.zeros(len(X), dtype=bool)

    def nested(X):
        return X @ J[:, :2].T - d, np.zeros(len(X), dtype=bool)

    return full, nested


@pytest.mark.parametrize("truth_s", [0.0, 0.3])
def test_savage_dickey_of_the_laplace_marginal_equals_the_laplace_bayes_factor(truth_s):
    """Nested linear models with uniform priors: the Savage-Dickey ratio of the switch's truncated Gaussian
    marginal and the ratio of the two Laplace evidences are the same exact number."""
    from torchslide.diagnose.local_path import savage_dickey

    full, nested = _linear_problem(truth_s)
    wide = np.array([[-5.0, -5.0], [5.0, 5.0]])
    f0 = fit(nested, np.zeros(2), wide, log_norm=0.0, log_prior=-math.log(100.0))
    box = np.array([[-5.0, -5.0, 0.0], [5.0, 5.0, 1.0]])
    f1 = fit(full, np.array([0.0, 0.0, 0.5]), box, log_norm=0.0, log_prior=-math.log(100.0))
    two_ln_bf = 2 * (f1.log_evidence - f0.log_evidence)
    assert savage_dickey(f1, 2, (0.0, 1.0)) == pytest.approx(two_ln_bf, abs=1e-6)
    if truth_s == 0.0:
        assert two_ln_bf < 0          # nothing hidden: the Occam factor wins
    else:
        assert two_ln_bf > 10


def test_the_box_fraction_chooses_the_path():
    """The 90 % ellipse of a Gaussian with sds (0.005, 5) in a box of 0.28 x 2100 fills pi chi2_2(0.9) 0.025 /
    588 (6e-4) of it: the local path; one as wide as the box fills most of it: the emulator path."""
    from scipy import stats

    from torchslide.diagnose.local import LocalFit
    from torchslide.diagnose.local_path import box_fraction, choose_path

    bounds = np.array([[0.02, 100.0], [0.3, 2200.0]])

    def gauss(sd):
        cov = np.diag(np.square(sd))
        return LocalFit(x=np.array([0.2, 1000.0]), log_like=0.0, jacobian=np.eye(2), precision=np.linalg.inv(cov),
                        covariance=cov, centre=np.array([0.2, 1000.0]), log_evidence=0.0, n_runs=0, converged=True,
                        message="")

    narrow = gauss([0.005, 5.0])
    expected = math.pi * stats.chi2.ppf(0.9, 2) * 0.005 * 5.0 / (0.28 * 2100.0)
    assert box_fraction(narrow.covariance, bounds) == pytest.approx(expected, rel=1e-9)
    assert choose_path(narrow, bounds, 1e-3)[0] == "local"
    path, why = choose_path(gauss([0.1, 800.0]), bounds, 1e-3)
    assert path == "emulator" and "of the prior box" in why


def test_laplace_draws_stay_in_the_box_and_follow_the_truncated_gaussian():
    from torchslide.diagnose.local import LocalFit

    cov = np.array([[0.04, 0.0], [0.0, 0.01]])
    f = LocalFit(x=np.array([0.0, 0.5]), log_like=0.0, jacobian=np.eye(2), precision=np.linalg.inv(cov),
                 covariance=cov, centre=np.array([-0.1, 0.5]), log_evidence=0.0, n_runs=0, converged=True, message="")
    box = np.array([[0.0, 0.0], [1.0, 1.0]])
    d = f.draws(4000, box, seed=0)
    assert d.shape == (4000, 2) and np.all((d >= box[0]) & (d <= box[1]))
    from scipy import stats
    tn = stats.truncnorm((0 + 0.1) / 0.2, (1 + 0.1) / 0.2, loc=-0.1, scale=0.2)
    assert d[:, 0].mean() == pytest.approx(tn.mean(), abs=0.01)


def _plane_case(kappa: float, release_scale: float = 0.0):
    """Recordings on a small inclined plane (deposit map, two gauges' depth and speed series, the final
    volume; sigmas of centimetres and decimetres per second) made with entrainment switch ``kappa`` on
    an erodible layer from a release ``release_scale`` larger than stated, and the diagnosis evaluator of
    plain Voellmy with the stated release."""
    from torchslide.bayes import Prior, Uniform
    from torchslide.diagnose import DiagnosisEvaluator
    from torchslide.observe import Observation
    from torchslide.observe_series import SeriesObservation
    from torchslide.physics import Params
    from torchslide.solver import SolverConfig, simulate
    from torchslide.terrain.synthetic import inclined_plane, release_from_shape

    dem = inclined_plane(30.0, 40.0, slope_length=600.0, runout_length=600.0, width=320.0, transition=200.0)
    rel = release_from_shape(dem, (150.0, 160.0), 60.0, volume=2.0e4)
    erod = np.zeros(dem.shape)
    erod[:, : dem.shape[1] // 2] = 1.0
    gauges = [("g1", 450.0, 160.0), ("g2", 700.0, 160.0)]
    res = simulate(dem, rel, Params.make(mu=0.3, xi=600.0, kappa=kappa, release_scale=release_scale), t_end=40.0,
                   gauges=gauges, config=SolverConfig(), erodible_depth=erod)
    t = np.arange(2.0, 40.0, 2.0)
    obs = [SeriesObservation.from_array("deposit_map", res.h_final[0].numpy(), dem, 0.05, name="deposit"),
           Observation("final_volume", float(res.final_volume[0]), 200.0, name="final_volume")]
    for name, _, _ in gauges:
        g = res.gauges[name]
        obs += [SeriesObservation("gauge_series", np.interp(t, g.t.numpy(), g.h[0].numpy()), 0.05,
                                  name=f"{name}:h", gauge=name, quantity="h", times=t),
                SeriesObservation("gauge_series", np.interp(t, g.t.numpy(), g.speed[0].numpy()), 0.2,
                                  name=f"{name}:speed", gauge=name, quantity="speed", times=t)]
    return DiagnosisEvaluator(dem=dem, release=rel, observations=obs, t_end=40.0, gauges=gauges,
                              prior=Prior({"mu": Uniform(0.2, 0.45), "xi": Uniform(200.0, 1500.0)}),
                              solver_config=SolverConfig(), erodible_depth=erod)


def _with_fine_terrain(ev):
    """The plane case's evaluator with its terrain on cells half as large (a FineTerrain), as a user with
    the finer DEM has it: the grid-error rounds run only then."""
    from torchslide.diagnose.model_error import FineTerrain
    from torchslide.terrain.synthetic import inclined_plane, release_from_shape

    dem_f = inclined_plane(30.0, 20.0, slope_length=600.0, runout_length=600.0, width=320.0, transition=200.0)
    return ev._copy(fine_terrain=FineTerrain(dem_f, release_from_shape(dem_f, (150.0, 160.0), 60.0, volume=2.0e4)))


@pytest.mark.parametrize("kappa", [0.001, 0.0])
def test_the_local_path_fits_every_model_on_the_solver(kappa, tmp_path):
    """Rich recordings (a deposit map and a depth series): the baseline's posterior fills a tiny part of the
    box, so "auto" takes the local path and says why. With entrainment hidden its local fit recovers
    kappa within its 90 % interval, its likelihood ratio is far beyond the boundary-corrected reference and
    it is named; with nothing hidden its evidence is below the baseline's and nothing is named."""
    from torchslide.diagnose import Budgets, Thresholds, diagnose
    from torchslide.diagnose.report import write_markdown

    ev = _plane_case(kappa)
    bud = Budgets(model_error_runs=0, n_posterior_samples=8, n_posterior_samples_after=6, top_k=2, n_perm=9,
                  local_lhs=8, local_starts=1, profile_top=1)
    d = diagnose(ev, ["entrainment", "mu_i"], bud, Thresholds(), log=lambda s: None, workdir=tmp_path)
    # the discrepancy correlated as stated (pipeline.stated_correlation), not learnt from the baseline's residual
    assert ev.discrepancy_factors == {b.name: 1.0 for b in ev.blocks if b.is_vector}
    inf = d.decision["inference"]
    assert inf["path"] == "local" and "of the prior box" in inf["why"]
    ent = next(c for c in d.candidates if c["name"] == "entrainment")
    assert ent["inference"] == "laplace"
    assert sum(c.get("profile_ends") is not None for c in d.candidates) == 1      # profile_top = 1
    if kappa > 0:
        assert ent["profile_ends"] is not None and min(ent["profile_ends"]["two_ln_drop"]) > 0
        lo, hi = ent["parameters"]["kappa"]["hdr90"]
        assert lo <= kappa <= hi
        # the profile-likelihood interval, closed on both sides, of the Laplace one's order (about half its width)
        p_lo, p_hi = ent["parameters"]["kappa"]["profile90"]
        assert ent["parameters"]["kappa"]["profile90_closed"] == [True, True] and p_lo <= kappa <= p_hi
        assert 0.3 < (p_hi - p_lo) / (hi - lo) < 3
        assert ent["lr_pvalue"] < 1e-6 and ent["two_ln_bf"] > 10   # (> 20 with the stated errors alone: the learnt
        # discrepancy counts the baseline's misfit by its logarithm)
        assert d.verdict == "missing_physics" and d.missing_physics == "entrainment"
    else:
        assert ent["two_ln_bf"] < 0 and ent["lr_pvalue"] > 0.01
        assert d.verdict == "no_missing_physics"
    md = write_markdown(d.to_json(), [])
    assert "local" in md and "Laplace" in md


@pytest.mark.parametrize("release_scale, kappa, named", [(0.25, 0.0, "release_volume"), (0.0, 0.001, "entrainment")])
def test_a_release_larger_than_stated_is_not_named_entrainment(release_scale, kappa, named):
    """Recordings from a release 25 % larger than stated (no entrainment) name the release volume, with the
    truth in its 90 % interval, not entrainment, which alone would have been named;
    with entrainment hidden and the release as stated, entrainment is still named."""
    from torchslide.diagnose import Budgets, Thresholds, diagnose

    ev = _plane_case(kappa, release_scale)
    bud = Budgets(model_error_runs=0, n_posterior_samples=8, n_posterior_samples_after=6, top_k=3, n_perm=9,
                  local_lhs=8, local_starts=1, profile_top=1, detectability="linearised")
    d = diagnose(ev, ["entrainment", "release_volume", "mu_i"], bud, Thresholds(), log=lambda s: None)
    assert d.verdict == "missing_physics" and d.missing_physics == named
    by = {c["name"]: c for c in d.candidates}
    if named == "release_volume":
        lo, hi = by["release_volume"]["parameters"]["release_scale"]["hdr90"]
        assert lo <= release_scale <= hi
        # what would have named entrainment without the candidate (about 700 with the stated errors alone; the
        # learnt discrepancy counts the baseline's misfit by its logarithm)
        assert by["entrainment"]["two_ln_bf"] > Thresholds().bf_min + Thresholds().margin_min
        from torchslide.diagnose.report import write_markdown
        assert "Not a physics term" in write_markdown(d.to_json(), [])


def test_the_design_equals_the_detectability_with_the_extra_gauge_recorded():
    """The design's detectable switch at a cell equals what local.detectable_switch gives once a gauge's peak
    depth and peak speed at that cell are among the observations (same screening members), and a cell the
    flow never reaches adds nothing."""
    import dataclasses

    from torchslide.diagnose.design import design
    from torchslide.diagnose.local import detectable_switch
    from torchslide.diagnose.screen import members
    from torchslide.observe import Observation

    ev = _plane_case(0.0)
    x0 = np.array([0.3, 600.0])
    d = design(ev, x0, ["entrainment"], sigma_h=0.2, sigma_v=1.0, threshold=6.0, top=3)
    m = d.maps["entrainment"]
    best = d.best["entrainment"][0]
    assert best["switch"] == pytest.approx(m.min()) and best["switch"] < d.now["entrainment"]
    assert np.isfinite(d.now["entrainment"])
    far = np.unravel_index(np.argmax(np.where(np.isfinite(m), m, -np.inf)), m.shape)
    assert m[far] == pytest.approx(d.now["entrainment"], rel=1e-6)     # nothing reaches there
    # the same number from the observations with the gauge added
    x, y = best["x"], best["y"]
    extra = [Observation("max_height", 1.0, 0.2, x=x, y=y, name="new:h"),
             Observation("max_velocity", 1.0, 1.0, x=x, y=y, name="new:v")]
    ev2 = dataclasses.replace(ev, observations=list(ev.observations) + extra)
    values, steps = members(ev2, x0, ["entrainment"])
    preds, _ = ev2.run_values(values)
    W = ev2.likelihood.whiten(__import__("torch").as_tensor(preds)).numpy()
    J = ((W - W[0])[1:] / np.array([steps["mu"], steps["xi"], steps["entrainment"]])[:, None]).T
    assert detectable_switch(J, 2, 6.0) == pytest.approx(best["switch"], rel=1e-6)
    js = d.to_json()["candidates"]["entrainment"]
    assert len(js["best_new_gauges"]) == 3 and js["detectable_now"] == pytest.approx(d.now["entrainment"])


def test_discriminating_two_candidates_needs_more_than_detecting_either():
    """design.discriminate: entrainment's switch that the release volume (with mu, xi) cannot mimic is never
    smaller than the switch that reveals entrainment alone, at every cell, and the same the other way round;
    the two are told apart by the recorded data already (finite), better with one more gauge somewhere."""
    from torchslide.diagnose.design import design, discriminate

    ev = _plane_case(0.0)
    x0 = np.array([0.3, 600.0])
    kw = dict(sigma_h=0.2, sigma_v=1.0, threshold=6.0, top=2)
    alone = design(ev, x0, ["entrainment", "release_volume"], **kw)
    both = discriminate(ev, x0, "entrainment", "release_volume", **kw)
    for key, c in (("entrainment|release_volume", "entrainment"), ("release_volume|entrainment", "release_volume")):
        assert both.now[key] >= alone.now[c] * (1 - 1e-9) and np.isfinite(both.now[key])
        assert np.all(both.maps[key] >= alone.maps[c] * (1 - 1e-9))
        assert both.best[key][0]["switch"] <= both.now[key]
    assert set(both.to_json()["candidates"]) == {"entrainment|release_volume", "release_volume|entrainment"}
    with pytest.raises(ValueError, match="two different candidates"):
        discriminate(ev, x0, "entrainment", "entrainment")


def test_profiles_go_to_the_strongest_candidates_and_a_beaten_fit_restarts(monkeypatch):
    """_local_profiles profiles the profile_top candidates with the largest 2 ln BF; a profile point that
    beats a fit (a negative 2 ln drop beyond 1) restarts the fit from there: a better fit replaces the row
    (profiled again), a restart that finds nothing better leaves the candidate marked unreliable."""
    from torchslide.diagnose import pipeline

    drops = {"a": [2.7, -3.0], "a2": [2.7, 2.6], "b": [2.5, 2.9], "c": [2.6, 2.8], "d": [-4.0, 2.0]}
    monkeypatch.setattr(pipeline, "profile_ends",
                        lambda ev, cfs, bud, log: [({"two_ln_drop": drops[cf], "interval90": [0.0, 1.0],
                                                     "gaussian": 2.71, "lowest_point": [0.1]}, 10) for cf in cfs])
    monkeypatch.setattr(pipeline, "refit_from", lambda ev, cf, x, f0, bud, log: {"a": "a2"}.get(cf, cf))
    monkeypatch.setattr(pipeline, "_local_candidate",
                        lambda ev, cf, base, scr, bud, log: ("refit", {"name": "a", "param": "a", "two_ln_bf": 45.0,
                                                                       "log_evidence": -80.0, "reliable": True, "n_runs": 7,
                                                                       "parameters": {"a": {}}}))
    monkeypatch.setattr(pipeline, "profile_intervals90",
                        lambda ev, jobs, bud, log: [({"interval": [0.1, 0.9], "closed": [True, False],
                                                      "points": [[0.5, 0.0]]}, 3) for _ in jobs])
    monkeypatch.setattr(pipeline, "profile_two_ln_bf", lambda cf, p90: {"a2": 47.5, "b": 21.0}[cf])
    rows = [{"name": n, "param": n, "two_ln_bf": bf, "log_evidence": -100.0 + bf / 2, "reliable": True, "n_runs": 5,
             "profile_ends": None, "parameters": {n: {}}} for n, bf in (("a", 30.0), ("d", 25.0), ("b", 20.0), ("c", 10.0))]
    fits, refits = {n: n for n in "abcd"}, {}
    pipeline._local_profiles(None, rows, fits, refits, None, None, None, pipeline.Budgets(profile_top=3),
                             log=lambda s: None)
    by = {r["name"]: r for r in rows}
    assert by["c"]["profile_ends"] is None and by["b"]["profile_ends"] and by["b"]["reliable"]
    # a: fitted again from the profile point, the better fit's row, profiled again, reliable
    assert by["a"]["restarted_from_profile"] == 1 and by["a"]["two_ln_bf_laplace"] == 45.0 and by["a"]["reliable"]
    assert by["a"]["profile_ends"]["two_ln_drop"] == [2.7, 2.6] and fits["a"] == "a2" and refits["a"] == "refit"
    assert by["a"]["n_runs"] == 5 + 10 + 7 + 10 + 3
    # the profile-likelihood interval of every reliable profiled candidate; none for an unreliable one
    assert by["a"]["parameters"]["a"]["profile90"] == [0.1, 0.9] and by["b"]["parameters"]["b"]["profile90_closed"] == [
        True, False]
    assert "profile90" not in by["d"]["parameters"]["d"] and "profile90" not in by["c"]["parameters"]["c"]
    # the evidence of a profiled candidate at its mode takes its switch's factor from the profile
    assert (by["a"]["two_ln_bf"], by["a"]["two_ln_bf_laplace"], by["a"]["two_ln_bf_lower"]) == (47.5, 45.0, 47.5)
    assert by["b"]["two_ln_bf"] == by["b"]["two_ln_bf_lower"] == 21.0 and by["b"]["log_bayes_factor"] == 10.5
    assert (by["b"]["log_evidence"], by["b"]["log_evidence_laplace"]) == (-100.0 + 10.5, -100.0 + 10.0)
    assert by["d"]["two_ln_bf"] == 25.0 and "two_ln_bf_laplace" not in by["d"] and by["c"]["two_ln_bf"] == 10.0
    # d: the restart found nothing better: unreliable
    assert not by["d"]["reliable"] and "restarted_from_profile" not in by["d"]
    # e: its restarted fit is beaten again by its new profile: restarted once more (profile_restarts = 2), then
    # at its mode; with profile_restarts = 1 it stays unreliable
    drops.update(e=[-2.0, 2.0], e2=[2.5, -1.9], e3=[2.6, 2.5])
    monkeypatch.setattr(pipeline, "refit_from", lambda ev, cf, x, f0, bud, log: {"e": "e2", "e2": "e3"}.get(cf, cf))
    monkeypatch.setattr(pipeline, "profile_two_ln_bf", lambda cf, p90: 30.0)
    for restarts, reliable, times in ((2, True, 2), (1, False, 1)):
        rows = [{"name": "e", "param": "e", "two_ln_bf": 30.0, "log_evidence": -85.0, "reliable": True, "n_runs": 5,
                 "profile_ends": None, "parameters": {"e": {}}}]
        fits = {"e": "e"}
        pipeline._local_profiles(None, rows, fits, {}, None, None, None,
                                 pipeline.Budgets(profile_top=1, profile_restarts=restarts), log=lambda s: None)
        assert rows[0]["reliable"] is reliable and rows[0]["restarted_from_profile"] == times


# ---- fits in lockstep (torchslide.diagnose.lockstep) ----

def test_lockstep_answers_every_job_as_if_alone_in_one_call_per_round():
    """Jobs asking different numbers of times: each gets the answers a direct evaluation gives, a round
    holds one request of every job still running (so there are as many rounds as the longest job asks),
    a job's exception comes back in its place and an exception of evaluate reaches the jobs of its round."""
    from torchslide.diagnose.lockstep import Lockstep

    sizes = []

    def evaluate(reqs):
        sizes.append(len(reqs))
        if any(r == "boom" for r in reqs):
            raise ValueError("evaluate failed")
        return [r * r for r in reqs]

    ls = Lockstep(evaluate)

    def job(n):
        if n == 0:
            raise RuntimeError("job failed")
        return [ls.ask(n * 10 + k) for k in range(n)]

    out = ls.map(job, [3, 1, 0, 5])
    assert out[0] == [(30 + k) ** 2 for k in range(3)] and out[1] == [100] and out[3] == [(50 + k) ** 2 for k in range(5)]
    assert isinstance(out[2], RuntimeError)
    assert sizes == [3, 2, 2, 1, 1] and ls.rounds == 5
    bad = ls.map(lambda r: ls.ask(r), [2, "boom"])
    assert all(isinstance(o, ValueError) for o in bad)
    assert ls.ask(4) == 16          # outside map: evaluated at once


def test_merged_residuals_equal_each_model_run_alone():
    """The baseline, two candidate models (one with a fixed phi_int) and a profile model (switch held)
    evaluated in one batch give each model's residuals as its own runs do, and each point's alone, bit for
    bit (a local fit runs its trial points alone and their Jacobians apart)."""
    from torchslide.diagnose.local_path import merged_residuals, problem
    from torchslide.diagnose.refit import candidate_evaluator

    from torchslide.diagnose.model_error import ModelError

    ev = _plane_case(0.001)
    # a candidate with its own grid error (pipeline._candidate_grid_error): whitened by its own likelihood
    me = ModelError(samples=0.01 * np.random.default_rng(0).standard_normal((3, ev.k)), x=np.zeros((3, 2)), factor=2)
    ent = candidate_evaluator(ev, "entrainment")
    probs = [problem(ev), problem(ent),
             problem(candidate_evaluator(ev, "earth_pressure")),
             problem(ev.with_prior(ev.prior, fixed={"kappa": 0.002})), problem(ent.with_model_error(me))]
    X = [np.array([[0.3, 600.0], [0.35, 400.0]]), np.array([[0.3, 600.0, 0.001]]),
         np.array([[0.28, 700.0, 0.5], [0.3, 600.0, 0.0]]), np.array([[0.31, 650.0]]), np.array([[0.3, 600.0, 0.001]])]
    merged = merged_residuals(list(zip(probs, X)))
    for p, x, (r, bad) in zip(probs, X, merged):
        r1, bad1 = merged_residuals([(p, x)])[0]
        assert not bad.any() and not bad1.any()
        np.testing.assert_array_equal(r, r1)
        for i in range(len(x)):
            np.testing.assert_array_equal(merged_residuals([(p, x[i:i + 1])])[0][0][0], r[i])
    assert [p.n_runs for p in probs] == [4 + 2, 2 + 1, 4 + 2, 2 + 1, 2 + 1]
    assert not np.allclose(merged[1][0], merged[4][0])     # the same run, another likelihood
    with pytest.raises(ValueError, match="share the terrain"):
        merged_residuals([(probs[0], X[0]), (problem(_plane_case(0.0)), X[0])])


def _entrainment_fit_with_grid_error(bud):
    """(evaluator with a finer terrain, its grid error (3 run pairs, release sd 0.05), the evaluator with it,
    the baseline's local fit, {"entrainment": CandidateFit}) on the plane case with entrainment hidden."""
    from torchslide.diagnose.local_path import fit_candidates, fit_model
    from torchslide.diagnose.model_error import approximation_error

    ev = _with_fine_terrain(_plane_case(0.001))
    me0 = approximation_error(ev, np.array([[0.3, 600.0], [0.31, 640.0], [0.29, 560.0]]), release_sd=0.05)
    ev_me = ev.with_model_error(me0)
    f0, _ = fit_model(ev_me, n_lhs=0, extra_starts=np.array([[0.3, 600.0]]), max_iter=40, log=lambda s: None)
    return ev, me0, ev_me, f0, fit_candidates(ev_me, ["entrainment"], f0, {}, bud, log=lambda s: None)


def test_a_candidates_grid_error_is_taken_where_it_fits(monkeypatch):
    """pipeline._candidate_grid_error: the profile_top candidate's grid error gets the mean of run pairs at
    draws of its own fit and keeps the baseline's grid covariance; the release volume's Jacobian is taken at
    the same draws (entrainment grows a larger release more: the final volume's row exceeds the baseline's);
    the candidate is refitted with it, and its profile is taken in that likelihood (local_path.profile_drop)."""
    from torchslide.diagnose import Budgets, pipeline
    from torchslide.diagnose.local_path import profile_drop
    from torchslide.diagnose.model_error import approximation_error, release_jacobian

    bud = Budgets(model_error_runs=3, profile_top=1, candidate_lhs=0, local_max_iter=40, candidate_error_rounds=1)
    ev, me0, ev_me, f0, fits = _entrainment_fit_with_grid_error(bud)
    cf = fits["entrainment"]
    monkeypatch.setattr(pipeline, "_local_candidate", lambda e, c, base, scr, b, log: (
        "refit", {"name": c.name, "param": "kappa", "two_ln_bf": c.two_ln_bf, "n_runs": c.n_runs}))
    rows = [{"name": "entrainment", "param": "kappa", "two_ln_bf": cf.two_ln_bf, "n_runs": cf.n_runs}]
    pipeline._candidate_grid_error(ev_me, rows, fits, {}, None, f0, None, bud, log=lambda s: None)
    new = fits["entrainment"]
    me_c = new.evaluator.model_error
    np.testing.assert_allclose(me_c.grid_covariance, me0.grid_covariance, atol=1e-12)
    x = cf.fit.draws(3, cf.evaluator.prior.bounds.numpy().astype(np.float64), seed=bud.seed + 7)
    np.testing.assert_allclose(me_c.mean, approximation_error(cf.evaluator, x).mean, rtol=1e-9, atol=1e-12)
    assert not np.allclose(me_c.mean, me0.mean)
    J, _ = release_jacobian(cf.evaluator, x, 0.05)
    np.testing.assert_allclose(me_c.release_jacobian, J, rtol=1e-9, atol=1e-12)
    fv = ev.block("final_volume").slice
    assert me_c.release_sd == 0.05 and me_c.release_jacobian[:, fv].mean() > 1.01 * me0.release_jacobian[:, fv].mean()
    (rnd,) = rows[0]["grid_error_at_fit"]
    assert rnd["n"] == 3 and set(rnd["mean_shift_sigma"]) == {b.name for b in ev.blocks}
    assert rnd["kappa"] == float(new.fit.x[2])
    # the profile holds the switch in the candidate's own likelihood: next to the fit's own switch it drops
    # by about 0 (in the baseline's likelihood the same point would differ by the grid error's shift)
    i = list(new.evaluator.prior.names).index("kappa")
    drop, _, _ = profile_drop(ev_me, new, float(new.fit.x[i]) * (1 + 1e-6), bud, log=lambda s: None)
    assert abs(drop) < 0.5


def test_the_profile_likelihood_interval_is_where_the_drop_reaches_chi2(monkeypatch):
    """local_path.profile_interval90: from the Laplace ends, a side whose profile drops less than 2.71 is
    stepped outward until it does (the crossing interpolated in sqrt(drop): exact for a quadratic profile),
    a side that drops more is interpolated inward, and a side still below 2.71 at the prior's bound is open
    there. The profile here is quadratic with sd 0.2 below the mode 1.0 and 0.6 above it (a skewed likelihood
    whose Laplace interval is too narrow on the upper side)."""
    from types import SimpleNamespace
    from torchslide.bayes import Prior, Uniform
    from torchslide.diagnose import local_path as lp

    level = 2.705543454095404
    def drop(ev, cf, v, bud, log=print, lockstep=None):
        sd = 0.2 if v < 1.0 else 0.6
        return ((v - 1.0) / sd) ** 2, 4, None
    monkeypatch.setattr(lp, "profile_drop", drop)
    ev_c = SimpleNamespace(prior=Prior({"mu": Uniform(0.1, 0.4), "tau_y": Uniform(0.0, 5.0)}))
    cf = SimpleNamespace(name="yield_stress", evaluator=ev_c, fit=SimpleNamespace(x=np.array([0.25, 1.0])))
    z = math.sqrt(level)
    laplace = [1.0 - 0.3 * z, 1.0 + 0.3 * z]                      # sd 0.3 both sides
    prof = {"interval90": laplace, "two_ln_drop": [drop(None, None, v, None)[0] for v in laplace]}
    out, runs = lp.profile_interval90(None, cf, prof, None)
    assert out["closed"] == [True, True] and runs > 0
    np.testing.assert_allclose(out["interval"], [1.0 - 0.2 * z, 1.0 + 0.6 * z], rtol=1e-9)
    # every point of the profile, the mode's included, for the evidence (profile_two_ln_bf)
    pts = np.array(out["points"])
    assert [1.0, 0.0] in out["points"] and len(pts) == 3 + runs // 4 and np.all(np.diff(pts[:, 0]) > 0)
    np.testing.assert_allclose(pts[:, 1], [drop(None, None, v, None)[0] for v in pts[:, 0]], rtol=1e-12)
    # the upper side reaches the prior's bound 5 still below 2.71 (sd 6 there): open at the bound
    monkeypatch.setattr(lp, "profile_drop", lambda ev, cf, v, bud, log=print, lockstep=None: (((v - 1.0) / (0.2 if v < 1 else 6.0)) ** 2, 4, None))
    prof = {"interval90": laplace, "two_ln_drop": [(0.3 * z / 0.2) ** 2, (0.3 * z / 6.0) ** 2]}
    out, _ = lp.profile_interval90(None, cf, prof, None, steps=6)
    assert out["closed"] == [True, False] and out["interval"][1] == 5.0
    # steps that stop short of the bound: the bound itself is probed (still below 2.71: open there)
    out, _ = lp.profile_interval90(None, cf, prof, None, steps=1)
    assert out["closed"] == [True, False] and out["interval"][1] == 5.0
    # ... and where the drop passes 2.71 before the bound, the crossing lies between the last step and the bound
    monkeypatch.setattr(lp, "profile_drop", lambda ev, cf, v, bud, log=print, lockstep=None: (((v - 1.0) / (0.2 if v < 1 else 1.5)) ** 2, 4, None))
    prof = {"interval90": laplace, "two_ln_drop": [(0.3 * z / 0.2) ** 2, (0.3 * z / 1.5) ** 2]}
    out, _ = lp.profile_interval90(None, cf, prof, None, steps=0)
    assert out["closed"] == [True, True] and out["interval"][1] == pytest.approx(1.0 + 1.5 * z, rel=1e-9)


def test_the_profile_intervals_of_every_candidate_run_in_lockstep(monkeypatch):
    """local_path.profile_intervals90: every side of every candidate steps in the same rounds (one batched
    call per round: as many rounds as the longest side has points, not their sum), and each interval and
    point is the one of that candidate profiled alone."""
    from types import SimpleNamespace
    from torchslide.bayes import Prior, Uniform
    from torchslide.diagnose import local_path as lp

    calls = []
    monkeypatch.setattr(lp, "grouped_residuals", lambda reqs: calls.append(len(reqs)) or [None] * len(reqs))

    def drop(ev, cf, v, bud, log=print, lockstep=None):
        lockstep.ask(v)                                  # one solver request per profile point
        sd = cf.sd[0] if v < 1.0 else cf.sd[1]
        return ((v - 1.0) / sd) ** 2, 4, None

    monkeypatch.setattr(lp, "profile_drop", drop)
    ev_c = SimpleNamespace(prior=Prior({"mu": Uniform(0.1, 0.4), "tau_y": Uniform(0.0, 5.0)}))
    z = math.sqrt(2.705543454095404)
    jobs = []
    for sd in ((0.2, 0.6), (0.25, 2.0)):        # wider than the Laplace sd 0.3 on the upper side: stepped outward
        cf = SimpleNamespace(name="yield_stress", evaluator=ev_c, fit=SimpleNamespace(x=np.array([0.25, 1.0])), sd=sd)
        ends = [1.0 - 0.3 * z, 1.0 + 0.3 * z]
        jobs.append((cf, {"interval90": ends, "two_ln_drop": [((v - 1.0) / (sd[0] if v < 1 else sd[1])) ** 2
                                                               for v in ends]}))
    together = lp.profile_intervals90(None, jobs, None)
    rounds_together = len(calls)
    alone = []
    for j in jobs:
        calls.clear()
        alone.append((lp.profile_intervals90(None, [j], None)[0], len(calls)))
    assert [t for t in together] == [a for a, _ in alone]
    sides = [len(t[0]["points"]) - 1 for t in together]          # points beyond the mode per candidate
    assert rounds_together == max(n for _, n in alone) < sum(n for _, n in alone)
    assert sum(calls_a for _, calls_a in alone) == sum(sides) - 4         # the Laplace ends cost nothing here
    np.testing.assert_allclose(together[0][0]["interval"], [1.0 - 0.2 * z, 1.0 + 0.6 * z], rtol=1e-9)


def test_a_switchs_evidence_from_its_profile_is_exact_where_the_laplace_gaussian_is_not():
    """local_path.profile_two_ln_bf: a switch whose likelihood is skewed (sd 0.05 below its mode 0.16, 0.1 above,
    as mu(I)'s on the fan terrain, where the Laplace Gaussian from the curvature at the mode is narrower still,
    sd 0.025) gets the exact 2 ln BF of its profile, lambda + 2 ln((1 / W) int exp(-D / 2) ds), from the
    profile's points and the likelihood ratio at 0; the Laplace value misses it by 2 ln of the width ratio.
    A quadratic profile of the Laplace width leaves the Laplace value, and a mode on the switch's lower bound
    keeps it, as does one at the range's end."""
    from types import SimpleNamespace
    from torchslide.bayes import Prior, Uniform
    from torchslide.diagnose import local_path as lp
    from torchslide.diagnose.local import profile_evidence_shift, profile_log_integral

    m, lo_sd, hi_sd, W = 0.16, 0.05, 0.1, 0.4
    D = lambda v: ((v - m) / (lo_sd if v < m else hi_sd)) ** 2
    lam, sd_lap = D(0.0), 0.025
    exact = lam + 2 * math.log(math.sqrt(2 * math.pi) / W * (lo_sd * (0.5 - stats.norm.cdf(-m / lo_sd))
                                                             + hi_sd * (stats.norm.cdf((W - m) / hi_sd) - 0.5)))
    laplace = lam + 2 * math.log(math.sqrt(2 * math.pi) * sd_lap / W * (stats.norm.cdf((W - m) / sd_lap)
                                                                       - stats.norm.cdf(-m / sd_lap)))
    ev = SimpleNamespace(prior=Prior({"mu": Uniform(0.1, 0.4), "mu_i": Uniform(0.0, W)}))
    fit = SimpleNamespace(x=np.array([0.25, m]), centre=np.array([0.25, m]), covariance=np.diag([1e-4, sd_lap ** 2]))
    cf = SimpleNamespace(name="mu_i", evaluator=ev, fit=fit, two_ln_bf=laplace, lr=lam)
    pts = [[v, D(v)] for v in (m, m - 0.041, m + 0.041, m - 0.08, m + 0.16)]
    assert lp.profile_two_ln_bf(cf, {"points": pts}) == pytest.approx(exact, abs=1e-3)
    assert exact - laplace == pytest.approx(2 * math.log(0.075 / 0.025), abs=0.05)
    # the likelihood ratio is the profile's point at 0: with the lower side measured only near the mode, a
    # drop at 0 four times the quadratic's narrows that side (a secant from the mode alone would not)
    near = [p for p in pts if p[0] != m - 0.08]
    assert lp.profile_two_ln_bf(cf, {"points": near}) == pytest.approx(exact, abs=1e-3)
    steep = SimpleNamespace(**{**vars(cf), "lr": 4 * lam})
    assert lp.profile_two_ln_bf(steep, {"points": near}) < exact - 0.1
    # a quadratic profile of the Laplace Gaussian's own width: nothing to correct
    q = [[v, ((v - m) / sd_lap) ** 2] for v in (m, m - 0.041, m + 0.041)]
    assert profile_evidence_shift(q, m, sd_lap, (0.0, W)) == pytest.approx(0.0, abs=1e-6)
    # a point a little above the fit (a negative drop within the fit's tolerance) counts as the mode's level
    assert profile_log_integral(pts + [[m + 1e-3, -0.3]], m, (0.0, W)) == pytest.approx(
        profile_log_integral(pts, m, (0.0, W)), abs=1e-3)
    # a fit whose switch sits at 0 (its lower bound) keeps the Laplace value
    for edge in (0.0, W):     # ... and so does one at the range's end
        cf0 = SimpleNamespace(**{**vars(cf), "fit": SimpleNamespace(**{**vars(fit), "x": np.array([0.25, edge])})})
        assert lp.profile_two_ln_bf(cf0, {"points": pts}) == laplace


def test_the_baseline_gets_as_many_grid_error_rounds_as_the_candidates():
    """pipeline._local_baseline: with a finer terrain, after the pilot draws' grid error,
    candidate_error_rounds more rounds take its mean at draws of the baseline's refit (covariance kept), so
    a candidate's own rounds do not give it a likelihood the baseline was denied; without one, none."""
    from torchslide.diagnose import Budgets, pipeline
    from torchslide.diagnose.local_path import fit_model

    ev = _with_fine_terrain(_plane_case(0.0))
    pilot, _ = fit_model(ev, n_lhs=0, extra_starts=np.array([[0.3, 600.0]]), max_iter=20, log=lambda s: None)
    # without a finer terrain (the finer runs interpolate the inversion DEM) there are no rounds
    bare = _plane_case(0.0)
    assert pipeline.error_rounds(bare, Budgets()) == 0 and pipeline.error_rounds(ev, Budgets()) == 2
    assert pipeline._local_baseline(bare, pilot, Budgets(model_error_runs=3, local_max_iter=20),
                                    log=lambda s: None)[2]["rounds"] == []
    for rounds in (0, 1):
        bud = Budgets(model_error_runs=3, candidate_error_rounds=rounds, local_max_iter=20)
        ev_me, f, s = pipeline._local_baseline(ev, pilot, bud, log=lambda s: None)
        assert len(s["rounds"]) == rounds
        if rounds == 0:
            first, f_first = ev_me.model_error, f
    me = ev_me.model_error
    np.testing.assert_allclose(me.grid_covariance, first.grid_covariance, atol=1e-12)
    x = f_first.draws(3, ev.prior.bounds.numpy().astype(np.float64), seed=bud.seed + 6)
    from torchslide.diagnose.model_error import approximation_error
    np.testing.assert_allclose(me.mean, approximation_error(ev, x).mean, rtol=1e-9, atol=1e-12)


def test_a_finer_grid_evaluator_runs_every_member_on_the_fine_terrain():
    """DiagnosisEvaluator(finer_grid=True): its predictions are the fine terrain's runs seen on the inversion
    cells (model_error.fine_predictions), for the same data; without a fine terrain it is refused; a batch
    of the local path never mixes the two grids."""
    from torchslide.diagnose.local_path import grouped_residuals, merged_residuals, problem
    from torchslide.diagnose.model_error import fine_predictions

    ev = _with_fine_terrain(_plane_case(0.0))
    fine = ev._copy(finer_grid=True)
    x = np.array([[0.3, 600.0], [0.33, 900.0]])
    got, _ = fine.run_values({"mu": x[:, 0], "xi": x[:, 1]})
    want, _ = fine_predictions(ev, x)
    coarse, _ = ev.run_values({"mu": x[:, 0], "xi": x[:, 1]})
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-12)
    assert not np.allclose(got, coarse)
    assert np.array_equal(fine.data, ev.data)
    with pytest.raises(ValueError, match="finer_grid needs a fine_terrain"):
        _plane_case(0.0)._copy(finer_grid=True)
    with pytest.raises(ValueError, match="same grid"):
        merged_residuals([(problem(ev), x), (problem(fine), x)])
    # a round of fits on both grids: one batch per grid, each request answered as alone
    both = grouped_residuals([(problem(ev), x), (problem(fine), x[:1]), (problem(ev), x[1:])])
    np.testing.assert_allclose(both[0][0], merged_residuals([(problem(ev), x)])[0][0], rtol=1e-12)
    np.testing.assert_allclose(both[1][0], merged_residuals([(problem(fine), x[:1])])[0][0], rtol=1e-12)
    np.testing.assert_allclose(both[2][0], both[0][0][1:], rtol=1e-12)


def _shifted_row(moved: float, two_ln_bf: float) -> dict:
    """A candidate's row whose grid-error round at its fit moved the mean error by ``moved`` sigma."""
    return {"name": "entrainment", "param": "kappa", "two_ln_bf": two_ln_bf,
            "grid_error_at_fit": [{"mean_shift_sigma": {"deposit": 0.1, "g1:h": moved}}]}


@pytest.mark.parametrize("moved, two_ln_bf, bf_min, finer_shift, why", [
    (2.0, 3.0, np.inf, 1.0, "moved by up to 2 sigma"), (0.5, 300.0, 6.0, 1.0, "reaches 2 ln BF >= 6"),
    (0.5, 300.0, np.inf, 1.0, None), (0.5, 3.0, 6.0, 1.0, None), (2.0, 300.0, 6.0, 0.0, None)])
def test_the_comparison_moves_to_the_finer_grid_when_the_grid_error_moves_or_a_candidate_is_supported(
        moved, two_ln_bf, bf_min, finer_shift, why):
    """pipeline._finer_grid_reason: a round that moved the grid's mean error at a fitted candidate by more
    than finer_shift sigma, or a fitted candidate at 2 ln BF >= bf_min, sends the comparison to the finer
    grid, with the reason; otherwise, or with finer_shift 0, it stays; an unfitted row never counts."""
    from torchslide.diagnose import Budgets, pipeline

    bud = Budgets(finer_shift=finer_shift)
    rows = [_shifted_row(moved, two_ln_bf)]
    got = pipeline._finer_grid_reason(rows, {"entrainment": None}, bud, bf_min)
    assert (got is None) == (why is None) and (why is None or why in got)
    assert pipeline._finer_grid_reason(rows, {}, bud, bf_min) is None


def test_candidates_whose_grid_error_moves_beyond_the_noise_are_compared_on_the_finer_grid():
    """pipeline._finer_grid_stage: when a round moved the grid's mean error at a profile_top candidate's fit
    by more than finer_shift sigma (the test above: or a candidate reaches bf_min), the baseline and that
    candidate are fitted again on the finer grid; the row's 2 ln BF is then the finer grid's (the
    candidate's Laplace evidence against the baseline's, both there, the release error kept, no grid
    error) and the inversion grid's is kept beside it; the profile is then taken on the finer grid."""
    from torchslide.diagnose import Budgets, pipeline
    from torchslide.diagnose.local_path import fit_model
    from torchslide.diagnose.screen import ScreenResult

    moved, bf_min = 2.0, np.inf
    bud = Budgets(model_error_runs=3, profile_top=1, candidate_lhs=0, local_max_iter=40, n_posterior_samples_after=4)
    ev, me0, ev_me, f0, fits = _entrainment_fit_with_grid_error(bud)
    cf = fits["entrainment"]
    rows = [{**_shifted_row(moved, cf.two_ln_bf), "n_runs": cf.n_runs}]
    cal = pipeline.laplace_result(f0, ["mu", "xi"], ev.prior.bounds.numpy())
    base = pipeline._Baseline(cal, pipeline.posterior_predictive(ev_me, cal.samples[:4]), pipeline._laplace_ver(f0))
    pipeline._assess(ev_me, base, pipeline.Thresholds(), bud)
    scr = ScreenResult(x0={}, scores={"entrainment": 1.0}, mimic={"entrainment": None}, norms={},
                       ranking=["entrainment"])
    out, fine = pipeline._finer_grid_stage(ev_me, rows, fits, {}, base, f0, scr, bud, log=lambda s: None,
                                           before={"entrainment": cf.two_ln_bf}, bf_min=bf_min)
    new = fits["entrainment"]
    assert new.evaluator.finer_grid and new.evaluator.model_error.release_sd == 0.05
    assert np.allclose(new.evaluator.model_error.grid_covariance, 0.0)
    row = rows[0]
    assert row["two_ln_bf"] == pytest.approx(new.two_ln_bf)
    assert row["finer_grid"]["two_ln_bf_inversion_grid"] == cf.two_ln_bf and row["finer_grid"]["moved_sigma"] == moved
    assert cf.two_ln_bf >= 6.0
    fine0 = ev._copy(finer_grid=True, model_error=pipeline._release_only(me0))
    f0_fine, _ = fit_model(fine0, n_lhs=0, extra_starts=f0.x[None], max_iter=40, log=lambda s: None)
    assert new.two_ln_bf == pytest.approx(2 * (new.fit.log_evidence - f0_fine.log_evidence), abs=1e-6)
    assert out["candidates"] == ["entrainment"] and out["baseline_log_evidence"] == pytest.approx(f0_fine.log_evidence)
    assert out["baseline_converged"] == f0_fine.converged and out["baseline_message"] == f0_fine.message
    assert "moved by up to 2 sigma" in out["why"]
    assert fine[0].finer_grid and fine[1] is not f0 and fine[2].source.endswith("finer grid (Laplace)")
    # profiled on the finer grid: the profile holds the switch in the candidate's own (finer) likelihood
    pipeline._local_profiles(ev_me, rows, fits, {}, base, f0, scr, bud, log=lambda s: None, fine=fine)
    assert "finer_grid" in row and row["profile_ends"]["two_ln_drop"][0] > 0
    assert "profile90" in row["parameters"]["kappa"]
    from torchslide.diagnose.report import _verdict_section
    j = {"verdict": "missing_physics", "missing_physics": "entrainment", "candidates": rows,
         "decision": {"reason": "-", "finer_grid": out}}
    text = "\n".join(_verdict_section(j))
    assert "fitted again on the finer grid" in text and "did not converge" not in text
    j["decision"]["finer_grid"] = {**out, "baseline_converged": False, "baseline_message": "max_iter"}
    assert "did not converge (max_iter)" in "\n".join(_verdict_section(j))
    assert f"| entrainment | {cf.two_ln_bf:.1f} | {row['two_ln_bf']:.1f} |" in text
