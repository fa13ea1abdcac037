"""Local Gaussian inference (torchslide.diagnose.local): the Laplace evidence against brute-force
integrals, the optimiser on a small solver case, the Schur-complement detectability."""
from __future__ import annotations

import math

import numpy as np
import pytest
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
