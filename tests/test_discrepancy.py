"""The model's own error learnt with the parameters (torchslide.discrepancy): the likelihood is the marginal of
the Gaussian over the discrepancy's size, its least-squares form is the same number, it costs almost nothing
where the model fits and it widens the intervals where it does not."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy import integrate, stats

from torchslide.bayes import GaussianLikelihood
from torchslide.discrepancy import DiscrepancyLikelihood, Group, correlation_factor
from torchslide.observe_series import exponential_field


def _marginal(d, y, sigma, c=1.0):
    """ln int_0^inf (1 + lam)^-2 prod_i N(d_i | y_i, sigma_i^2 (1 + lam w_i)) dlam, tempered by c (the
    module's (D1)-(D2), integrated by scipy.integrate.quad)."""
    m2 = ((np.abs(d) + np.abs(y)) / 2) ** 2
    w = m2 / m2.mean() if m2.mean() > 0 else np.ones_like(m2)

    def f(lam):
        sd = sigma * np.sqrt(1 + lam * w)
        return math.exp(c * np.sum(stats.norm.logpdf(d, y, sd))) * (1 + lam) ** -2

    return math.log(integrate.quad(f, 0, np.inf, limit=400, epsabs=0)[0])


@pytest.mark.parametrize("pred", [10.0, 11.0, 14.0, 30.0, 100.0])
def test_a_scalar_datum_takes_the_marginal_over_its_discrepancy(pred):
    lik = DiscrepancyLikelihood(GaussianLikelihood([10.0], sigma=[2.0]), [Group("a", np.array([0]), 1.0)])
    ll = float(lik.log_likelihood(torch.tensor([[pred]]))[0])
    assert ll == pytest.approx(_marginal(np.array([10.0]), np.array([pred]), np.array([2.0])), abs=1e-6)
    r = lik.residuals(torch.tensor([[pred]])).numpy()
    assert lik.log_norm - 0.5 * float(np.sum(r * r)) == pytest.approx(ll, abs=1e-9)


def test_a_map_weights_its_discrepancy_by_the_flow_and_its_least_squares_form_is_the_same_number():
    """A group of five values, two without flow in the data or the run (weight 0: no discrepancy there)."""
    d = np.array([1.0, 2.0, 0.0, 0.0, 3.0])
    y = np.array([2.0, 1.0, 0.0, 0.0, 1.0])
    sigma = np.full(5, 0.5)
    lik = DiscrepancyLikelihood(GaussianLikelihood(d, sigma=sigma), [Group("m", np.arange(5), 5.0)])
    ll = float(lik.log_likelihood(torch.tensor(y[None]))[0])
    assert ll == pytest.approx(_marginal(d, y, sigma), abs=1e-6)
    r = lik.residuals(torch.tensor(y[None])).numpy()[0]
    assert r.shape == (6,) and lik.log_norm - 0.5 * r @ r == pytest.approx(ll, abs=1e-9)
    # the stated errors correlated: 5 values carry the information of 2.5 (f = 2), the marginal tempered by 1/2
    # (up to the constant of the Gaussian's normaliser, which keeps 5 values of sigma sqrt(2))
    g2 = GaussianLikelihood(d, sigma=sigma * math.sqrt(2.0))
    tempered = DiscrepancyLikelihood(g2, [Group("m", np.arange(5), 2.5)])
    constant = g2.log_norm - 0.5 * np.sum(stats.norm.logpdf(0.0, 0.0, sigma))
    assert float(tempered.log_likelihood(torch.tensor(y[None]))[0]) == pytest.approx(
        _marginal(d, y, sigma, c=0.5) + constant, abs=1e-6)


def _fit_line(t, d, sigma, discrepancy):
    """The posterior of the slope a of y = a t on a grid of a (flat prior): (mean, 90 % interval); with the
    discrepancy, its correlation learnt from the residual of the Gaussian's best fit (as
    LandslideEvaluator.learn_discrepancy_from does)."""
    a = np.linspace(0.0, 4.0, 4001)
    gauss = GaussianLikelihood(d, sigma=np.full(d.size, sigma))
    best = a[np.argmax(gauss.log_likelihood(torch.as_tensor(a[:, None] * t[None, :])).numpy())]
    F = correlation_factor((best * t - d) / sigma)
    lik = gauss if discrepancy == "none" else \
        DiscrepancyLikelihood(gauss, [Group("m", np.arange(d.size), float(d.size), factor=max(1.0, F))])
    ll = lik.log_likelihood(torch.as_tensor(a[:, None] * t[None, :])).numpy()
    p = np.exp(ll - ll.max())
    cdf = np.cumsum(p) / p.sum()
    return float(np.sum(a * p) / p.sum()), (float(a[np.searchsorted(cdf, 0.05)]), float(a[np.searchsorted(cdf, 0.95)]))


def test_it_costs_almost_nothing_where_the_model_is_right():
    """Data from the model itself with the stated noise: the slope's mean and interval as the Gaussian's."""
    rng = np.random.default_rng(3)
    t = np.linspace(0.1, 2.0, 60)
    d = 2.0 * t + 0.3 * rng.standard_normal(t.size)
    m0, (lo0, hi0) = _fit_line(t, d, 0.3, "none")
    m1, (lo1, hi1) = _fit_line(t, d, 0.3, "learnt")
    assert m1 == pytest.approx(m0, abs=0.1 * (hi0 - lo0))
    assert 1.0 <= (hi1 - lo1) / (hi0 - lo0) < 1.15
    assert lo1 <= 2.0 <= hi1


def test_it_widens_the_interval_to_cover_the_truth_where_the_model_is_wrong():
    """Data of the line plus a smooth bump the model lacks: the Gaussian's interval excludes the true slope by
    many widths, the learnt discrepancy's covers it."""
    rng = np.random.default_rng(4)
    t = np.linspace(0.1, 2.0, 60)
    d = 2.0 * t + 0.8 * np.exp(-((t - 1.6) / 0.25) ** 2) + 0.05 * rng.standard_normal(t.size)
    _, (lo0, hi0) = _fit_line(t, d, 0.05, "none")
    _, (lo1, hi1) = _fit_line(t, d, 0.05, "learnt")
    assert not lo0 <= 2.0 <= hi0 and min(abs(2.0 - lo0), abs(2.0 - hi0)) > 3 * (hi0 - lo0)
    assert lo1 <= 2.0 <= hi1


def test_a_new_recordings_variance_factor_is_drawn_from_the_discrepancys_posterior():
    """For a scalar missed by 5 sigma the draws of 1 + lambda average E[1 + lambda | datum] (quadrature)."""
    lik = DiscrepancyLikelihood(GaussianLikelihood([0.0], sigma=[1.0]), [Group("a", np.array([0]), 1.0)])
    u = lik.sample_variance_factors(np.full((20000, 1), 5.0), np.random.default_rng(0))[:, 0]
    post = lambda lam: stats.norm.pdf(5.0, 0.0, math.sqrt(1 + lam)) * (1 + lam) ** -2
    mean = integrate.quad(lambda lam: (1 + lam) * post(lam), 0, np.inf)[0] / integrate.quad(post, 0, np.inf)[0]
    assert u.mean() == pytest.approx(mean, rel=0.05) and u.min() >= 1.0
    d = lik.describe(np.array([5.0]))[0]
    assert d["observation"] == "a" and d["discrepancy_sd_over_sigma"] == pytest.approx(math.sqrt(mean - 1), rel=0.02)


@pytest.mark.parametrize("L", [20.0, 40.0])
def test_the_correlation_factor_of_an_exponential_field(L):
    """Fields with exp(-r / L) on 10 m cells: F = 2 pi (L / cellsize)^2 within a factor 1.6 (median of 6),
    white noise F = 1, and a series' 2 L / dt."""
    rng = np.random.default_rng(1)
    F = [correlation_factor(exponential_field((40, 60), 10.0, L, rng)[0]) for _ in range(6)]
    assert np.median(F) / (2 * math.pi * (L / 10.0) ** 2) == pytest.approx(1.0, abs=0.6)
    assert correlation_factor(rng.standard_normal((40, 60))) < 1.5
    t = np.arange(0.0, 400.0, 2.0)
    c = np.exp(-np.abs(t[:, None] - t[None, :]) / 8.0)
    s = [correlation_factor(rng.standard_normal(t.size) @ np.linalg.cholesky(c + 1e-10 * np.eye(t.size)).T)
         for _ in range(6)]
    assert np.median(s) / (2 * 8.0 / 2.0) == pytest.approx(1.0, abs=0.6)
    masked = exponential_field((40, 60), 10.0, L, rng)[0]
    masked[:, :20] = np.nan            # a map's cells off the survey: left out
    assert 1.0 <= correlation_factor(masked) <= 40 * 40


def test_groups_must_cover_the_data_once():
    g = GaussianLikelihood([1.0, 2.0], sigma=[1.0, 1.0])
    with pytest.raises(ValueError, match="cover each"):
        DiscrepancyLikelihood(g, [Group("a", np.array([0]), 1.0)])
    with pytest.raises(ValueError, match=">= 1"):
        DiscrepancyLikelihood(g, [Group("a", np.array([0, 1]), 2.0, factor=0.5)])


def test_calibrate_on_the_solver_learns_the_correlation_from_its_initial_design(monkeypatch):
    """torchslide.calibrate on a LandslideEvaluator (the Python API, as the CLI runs it): a deposit map whose
    errors are correlated over 40 m but stated as independent gets a correlation factor > 1 from the best
    initial run, the initial design runs once (the pilot's runs are the loop's), the parameters take the
    evaluator's names, and the inference path is chosen as the CLI's ("auto")."""
    from torchslide import calibrate
    from torchslide.bayes import Prior, Uniform
    from torchslide.evaluator import LandslideEvaluator
    from torchslide.observe_series import SeriesObservation
    from torchslide.physics import Params
    from torchslide.solver import simulate

    from .conftest import chute_case

    dem, rel = chute_case()
    truth = simulate(dem, rel, Params.make(mu=0.25, xi=600.0), t_end=40.0).h_final[0].numpy()
    rng = np.random.default_rng(0)
    dep = truth + 0.3 * exponential_field(dem.shape, dem.cellsize, 40.0, rng)[0]
    obs = [SeriesObservation.from_array("deposit_map", dep, dem, 0.3, name="deposit")]
    ev = LandslideEvaluator(dem=dem, release=rel, observations=obs,
                            prior=Prior({"mu": Uniform(0.15, 0.4), "xi": Uniform(200.0, 1500.0)}), t_end=40.0)
    calls = []
    real = LandslideEvaluator._predictions_chunk
    monkeypatch.setattr(LandslideEvaluator, "_predictions_chunk", lambda self, v: (calls.append(len(v["mu"])), real(self, v))[1])
    res = calibrate(ev, ev.prior.bounds, n_initial=8, n_total=12, batch_size=4, seed=1, progress=False)
    assert res.names == ["mu", "xi"] and res.inference["path"] in ("local", "emulator")
    assert res.discrepancy_factors["deposit"] > 2.0 and ev.discrepancy_factors == res.discrepancy_factors
    assert calls[:2] == [8, 4]             # the initial design once (as the pilot), then the batch of 4
    lo, hi = res.summary["hdr90"]["mu"]
    assert lo <= 0.25 <= hi
