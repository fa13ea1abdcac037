"""experiments.sweep: node axes, observable interpolation, reference posterior, chunked resume.

The solver is replaced by an analytic stand-in here (fast); the real solver runs in
tests/test_experiments_bondo.py.
"""
import numpy as np
import pytest
import torch

from experiments.bondo.config import OBSERVABLES, BondoConfig
from experiments.bondo.simulator import CachedSimulator
from experiments.sweep import reference_posterior, run_sweep, sweep_axes
from experiments.sweep.core import SweepResult, interpolate_observables
from torchslide.posterior import grid_axes, grid_points


def _analytic(x):
    """Smooth stand-in observables (n, k): bilinear in (mu, xi) so interpolation is exact."""
    x = np.asarray(x).reshape(-1, 2)
    mu, xi = x[:, 0], x[:, 1]
    cols = [1e6 * (1 + mu) + xi, 5e5 + 100 * xi, 3e6 - 1e5 * mu, 30 + 100 * mu + 0.01 * xi, 20 + 0.01 * xi * mu,
            5 + 20 * mu, 2 + mu * 3, 10 + 10 * mu + 0.001 * xi]
    return np.stack(cols, axis=1)


class FakeSim(CachedSimulator):
    calls = 0

    def simulate_batch(self, x):
        FakeSim.calls += 1
        x = np.asarray(x).reshape(-1, 2)
        return _analytic(x), np.zeros(len(x), dtype=bool), [""] * len(x)


def test_sweep_axes_include_edges():
    ax = sweep_axes(np.array([[0.02, 100.0], [0.3, 2200.0]]), 6)
    assert len(ax) == 2 and ax[0][0] == 0.02 and ax[0][-1] == 0.3 and ax[1][-1] == 2200.0 and len(ax[1]) == 6


def test_interpolation_exact_for_bilinear_observables():
    b = np.array([[0.02, 100.0], [0.3, 2200.0]])
    axes = sweep_axes(b, 5)
    y = _analytic(grid_points(axes).numpy()).reshape(5, 5, -1)
    sw = SweepResult(axes=axes, y=y, failed=np.zeros((5, 5), bool), names=list(OBSERVABLES), seconds=0.0)
    g = grid_axes(torch.as_tensor(b), 20)
    yi = interpolate_observables(sw, g)
    np.testing.assert_allclose(yi, _analytic(grid_points(g).numpy()), rtol=1e-10)


def test_reference_posterior_is_normalised_and_peaks_at_data():
    b = np.array([[0.02, 100.0], [0.3, 2200.0]])
    axes = sweep_axes(b, 9)
    y = _analytic(grid_points(axes).numpy()).reshape(9, 9, -1)
    sw = SweepResult(axes=axes, y=y, failed=np.zeros((9, 9), bool), names=list(OBSERVABLES), seconds=0.0)

    class LP:  # Gaussian likelihood on column 5 (5 + 20 mu): data at mu = 0.2
        def from_observables(self, x, yy):
            return torch.as_tensor(-0.5 * ((yy[:, 5] - 9.0) / 0.2) ** 2)

    g, dens, _ = reference_posterior(sw, LP(), b, 40)
    cv = (g[0][1] - g[0][0]) * (g[1][1] - g[1][0])
    assert abs(dens.sum() * cv - 1) < 1e-9
    mu_marg = dens.sum(1)
    assert abs(g[0][np.argmax(mu_marg)] - 0.2) < 0.01


def test_run_sweep_chunked_and_resumable(tmp_path, monkeypatch):
    import experiments.bondo.simulator as simmod

    monkeypatch.setattr(simmod, "CachedSimulator", FakeSim)
    cfg = BondoConfig.quick(str(tmp_path))
    FakeSim.calls = 0
    r1 = run_sweep(cfg, 4, chunk=5, progress=False)
    assert FakeSim.calls == 4  # 16 runs in chunks of 5
    assert r1.y.shape == (4, 4, len(OBSERVABLES)) and r1.n_failed == 0
    # interrupted sweep: drop the file's last chunk by saving a partial cache, then resume
    sim = FakeSim(cfg, None)
    sim.run(grid_points(r1.axes).numpy()[:7])
    sim.path = tmp_path / "partial.npz"
    sim.save()
    FakeSim.calls = 0
    r2 = run_sweep(cfg, 4, path=tmp_path / "partial.npz", chunk=5, progress=False)
    assert FakeSim.calls == 2  # only the 9 missing runs
    np.testing.assert_allclose(r2.y, r1.y)
    FakeSim.calls = 0
    run_sweep(cfg, 4, chunk=5, progress=False)
    assert FakeSim.calls == 0  # finished sweep: nothing is rerun


def test_cache_rejects_other_setup(tmp_path):
    cfg = BondoConfig.quick(str(tmp_path))
    sim = FakeSim(cfg, tmp_path / "c.npz")
    sim.run(np.array([[0.1, 500.0]]))
    with pytest.raises(ValueError, match="tag"):
        FakeSim(cfg.with_(cellsize=50.0), tmp_path / "c.npz")
