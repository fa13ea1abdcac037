import math

import numpy as np
import pytest
import torch
from scipy import stats

from torchslide.bayes import (EvaluationResult, FunctionEvaluator, Gamma, GaussianLikelihood, LogNormal, Prior,
                              TruncatedNormal, Uniform, check_bounds, log_posterior)
from torchslide.posterior import (adaptive_metropolis, grid_posterior, hdr_mask, log_evidence_importance,
                                  tv_distance)


def test_priors_match_scipy_inside_and_minus_inf_outside():
    v = torch.tensor([0.5, 1.0, 2.0], dtype=torch.float64)
    assert torch.allclose(Uniform(0.0, 4.0).log_prob(v), torch.full((3,), -math.log(4.0), dtype=torch.float64))
    tn = TruncatedNormal(1.0, 0.5, 0.0, 3.0)
    ref = stats.truncnorm((0 - 1) / 0.5, (3 - 1) / 0.5, loc=1, scale=0.5).logpdf(v.numpy())
    assert np.allclose(tn.log_prob(v).numpy(), ref)
    ln = LogNormal(0.0, 1.0, 1e-3, 1e3)
    ref = stats.lognorm(1.0).logpdf(v.numpy()) - math.log(stats.lognorm(1.0).cdf(1e3) - stats.lognorm(1.0).cdf(1e-3))
    assert np.allclose(ln.log_prob(v).numpy(), ref)
    g = Gamma(2.0, 1.5, 0.0, 50.0)
    assert np.allclose(g.log_prob(v).numpy(), stats.gamma(2.0, scale=1 / 1.5).logpdf(v.numpy()), atol=1e-10)
    assert torch.isinf(Uniform(0.0, 1.0).log_prob(torch.tensor([2.0], dtype=torch.float64))).all()


def test_bad_bounds_rejected_with_name_and_values():
    with pytest.raises(ValueError, match=r"'mu'.*low=0.3.*high=0.02"):
        Prior({"mu": (0.3, 0.02), "xi": (100, 2200)})
    with pytest.raises(ValueError, match="xi"):
        check_bounds([[0.0, 5.0], [1.0, 5.0]], names=["mu", "xi"])
    with pytest.raises(ValueError):
        Uniform(1.0, 1.0)
    with pytest.raises(ValueError, match="finite"):
        check_bounds([[0.0, 0.0], [1.0, float("inf")]])


def test_prior_joint_and_bounds():
    p = Prior({"mu": (0.02, 0.3), "xi": TruncatedNormal(1000, 300, 100, 2200)})
    assert p.names == ["mu", "xi"]
    assert torch.allclose(p.bounds, torch.tensor([[0.02, 100.0], [0.3, 2200.0]], dtype=torch.float64))
    x = torch.tensor([[0.1, 900.0], [0.5, 900.0]], dtype=torch.float64)
    lp = p.log_prob(x)
    assert torch.isfinite(lp[0]) and torch.isinf(lp[1])


def test_gaussian_likelihood_diag_and_full_match_scipy():
    d = torch.tensor([1.0, 2.0, 3.0], dtype=torch.float64)
    sim = torch.tensor([[1.1, 1.8, 3.3], [0.0, 0.0, 0.0]], dtype=torch.float64)
    sig = torch.tensor([0.1, 0.2, 0.3], dtype=torch.float64)
    ll = GaussianLikelihood(d, sigma=sig).log_likelihood(sim)
    ref = stats.multivariate_normal(d.numpy(), np.diag(sig.numpy() ** 2)).logpdf(sim.numpy())
    assert np.allclose(ll.numpy(), ref)
    cov = np.array([[0.04, 0.01, 0.0], [0.01, 0.09, 0.02], [0.0, 0.02, 0.16]])
    ll = GaussianLikelihood(d, covariance=cov)(sim)
    assert np.allclose(ll.numpy(), stats.multivariate_normal(d.numpy(), cov).logpdf(sim.numpy()))
    # log space end to end: far residuals stay finite (no exp-then-log underflow)
    far = GaussianLikelihood(d, sigma=1e-3)(torch.tensor([[100.0, 100.0, 100.0]], dtype=torch.float64))
    assert torch.isfinite(far).all() and far.item() < -1e9


def test_log_posterior_sums():
    prior = Prior({"a": (-1, 1)})
    x = torch.tensor([[0.5]], dtype=torch.float64)
    z = log_posterior(x, lambda x: -x[:, 0] ** 2, prior)
    assert torch.allclose(z, torch.tensor([-0.25 - math.log(2.0)], dtype=torch.float64))


def test_evaluation_result_flags_nonfinite():
    r = EvaluationResult(z=torch.tensor([1.0, float("nan"), float("-inf"), 2.0]),
                         failed=torch.tensor([False, False, False, True]), reasons=["", "", "", "solver blew up"])
    assert r.failed.tolist() == [False, True, True, True]
    assert "non-finite" in r.reasons[1] and r.reasons[3] == "solver blew up"
    assert torch.isnan(r.z[1:]).all()
    fe = FunctionEvaluator(lambda x: (x[:, 0], x[:, 0] > 0.5))
    out = fe(torch.tensor([[0.1], [0.9]], dtype=torch.float64))
    assert out.failed.tolist() == [False, True] and out.reasons[1]


def _gauss_logpdf(mu, cov):
    P = np.linalg.inv(cov)
    ld = np.log(np.linalg.det(2 * np.pi * np.asarray(cov)))
    mu_t, P_t = torch.tensor(mu, dtype=torch.float64), torch.tensor(P, dtype=torch.float64)

    def f(x):
        r = x - mu_t
        return -0.5 * ((r @ P_t) * r).sum(-1) - 0.5 * ld
    return f


def test_grid_posterior_of_gaussian_matches_analytic():
    mu, cov = [0.5, -1.0], np.array([[1.0, 0.6], [0.6, 2.0]])
    f = _gauss_logpdf(mu, cov)
    B = [[-8.0, -10.0], [8.0, 8.0]]
    post = grid_posterior(f, B, 100)
    assert abs(post.density.sum() * post.cell_volume - 1) < 1e-12
    s = post.summary(["a", "b"])
    assert np.allclose(s.mean, mu, atol=1e-3)
    assert np.allclose(s.sd, np.sqrt(np.diag(cov)), rtol=2e-3)
    assert abs(post.log_evidence) < 0.05  # normalised Gaussian: log Z = 0
    # TV against the exact density evaluated on the same grid: small
    fine = grid_posterior(f, B, 100)
    assert tv_distance(post.density, fine.density, post.cell_volume) < 1e-12
    # TV to a shifted Gaussian is the analytic 2 Phi(d/2) - 1 for Mahalanobis shift d
    g = _gauss_logpdf([mu[0] + 0.5, mu[1]], cov)
    tv = tv_distance(post.density, grid_posterior(g, B, 100).density, post.cell_volume)
    d = 0.5 / math.sqrt(np.linalg.inv(cov)[0, 0] ** -1)  # Mahalanobis distance of the shift
    d = math.sqrt(0.5**2 * np.linalg.inv(cov)[0, 0])
    assert abs(tv - (2 * stats.norm.cdf(d / 2) - 1)) < 5e-3
    # 90 % HDR of a 2-D Gaussian: ellipse with chi2_2(0.9) radius; mass and per-axis bounds
    m = post.hdr_mask(0.9)
    assert abs(post.density[m].sum() * post.cell_volume - 0.9) < 0.01
    r = math.sqrt(stats.chi2(2).ppf(0.9))
    lo, hi = s.hdr90[0]
    assert abs(hi - (mu[0] + r * math.sqrt(cov[0, 0]))) < 0.2 and abs(lo - (mu[0] - r * math.sqrt(cov[0, 0]))) < 0.2


def test_log_evidence_scaled_gaussian():
    f0 = _gauss_logpdf([0.0, 0.0], np.eye(2))
    post = grid_posterior(lambda x: f0(x) + 3.7, [[-8, -8], [8, 8]], 100)
    assert abs(post.log_evidence - 3.7) < 0.05


def test_mcmc_gaussian_3d_with_diagnostics():
    cov = np.array([[1.0, 0.5, 0.0], [0.5, 1.0, 0.2], [0.0, 0.2, 0.5]])
    f = _gauss_logpdf([0.0, 1.0, -1.0], cov)
    B = [[-6, -6, -6], [6, 6, 6]]
    mc = adaptive_metropolis(f, B, n_chains=8, n_steps=3000, seed=1)
    assert np.all(mc.rhat < 1.05), mc.rhat
    assert np.all(mc.ess > 300), mc.ess
    assert np.allclose(mc.samples.mean(0), [0, 1, -1], atol=0.1)
    assert np.allclose(mc.samples.std(0), np.sqrt(np.diag(cov)), rtol=0.1)
    lz = log_evidence_importance(f, B, mc.samples, n=20000, seed=0)
    assert abs(lz) < 0.05
    s = mc.summary()
    assert len(s.hdr90) == 3 and "rhat" in s.to_dict()


def test_hdr_mask_mass():
    d = np.array([[0.5, 0.3], [0.15, 0.05]])
    m = hdr_mask(d, 0.9)
    assert m.sum() == 3 and not m[1, 1]


def test_bounds_forms_and_the_square_case():
    from torchslide.bayes import check_bounds

    lows_highs = check_bounds([[0.0, 10.0], [1.0, 20.0]])  # (2, p): [lows; highs]
    assert lows_highs.tolist() == [[0.0, 10.0], [1.0, 20.0]]
    assert check_bounds({"mu": (0.0, 1.0), "xi": (10.0, 20.0)}).tolist() == [[0.0, 10.0], [1.0, 20.0]]
    assert check_bounds([(0, 1), (2, 3), (4, 5)]).tolist() == [[0, 2, 4], [1, 3, 5]]  # p pairs, p != 2
    with pytest.raises(ValueError, match="read as \\[lows; highs\\]"):
        check_bounds([(0.0, 1.0), (0.0, 1.0)])  # pairs for p = 2 are not guessed
