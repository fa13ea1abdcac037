import torch

from torchslide.emulator import LogPosteriorEmulator, cap_low_values

B = torch.tensor([[-2.0, -3.0], [2.0, 1.0]], dtype=torch.float64)


def f(x):
    return -0.5 * (x[:, 0] ** 2 + (x[:, 1] + 1) ** 2 / 0.5)


def test_fit_predict_interpolates_and_unit_scaling():
    g = torch.Generator().manual_seed(0)
    x = B[0] + torch.rand(30, 2, generator=g, dtype=torch.float64) * (B[1] - B[0])
    em = LogPosteriorEmulator(B).fit(x, f(x))
    assert em.model.train_inputs[0].min() >= 0 and em.model.train_inputs[0].max() <= 1
    m, v = em.predict(x)
    assert torch.allclose(m, f(x), atol=1e-2)  # outputs come back in z units
    xt = B[0] + torch.rand(200, 2, generator=g, dtype=torch.float64) * (B[1] - B[0])
    mt, vt = em.predict(xt, batch=37)  # batched prediction
    assert mt.shape == (200,) and (vt >= 0).all()
    assert (mt - f(xt)).abs().max() < 0.3
    assert torch.allclose(em.mean(xt), mt)
    hp = em.hyperparameters()
    assert len(hp["lengthscale"]) == 2 and hp["noise"] > 0


def test_mean_alone_equals_the_predictive_mean_and_follows_refits():
    """mean() (k(x, X) alpha from the prediction cache) equals predict()[0] to round-off, in 2 and 3
    dimensions, in chunks, after a refit on more points (no stale cache), and in z units (Standardize)."""
    g = torch.Generator().manual_seed(1)
    for dim, n in ((2, 25), (3, 60)):
        b = torch.stack([-torch.ones(dim), 2 * torch.ones(dim)]).double()
        h = lambda x: -3.0 * ((x - 0.3) ** 2).sum(-1) + 100.0       # an offset the Standardize must restore
        x = b[0] + torch.rand(n, dim, generator=g, dtype=torch.float64) * (b[1] - b[0])
        em = LogPosteriorEmulator(b).fit(x, h(x))
        xt = b[0] + torch.rand(500, dim, generator=g, dtype=torch.float64) * (b[1] - b[0])
        first = em.mean(xt, batch=77)
        assert first.shape == (500,)
        assert torch.allclose(first, em.predict(xt)[0], rtol=1e-9, atol=1e-8)
        x2 = torch.cat([x, b[0] + torch.rand(n, dim, generator=g, dtype=torch.float64) * (b[1] - b[0])])
        em.fit(x2, h(x2) + 5.0)                     # refit: other data, other values
        again = em.mean(xt)
        assert torch.allclose(again, em.predict(xt)[0], rtol=1e-9, atol=1e-8)
        assert float((again - first).abs().mean()) > 1.0


def test_warm_start_and_jitter_retry_on_duplicates():
    x = torch.tensor([[0.0, 0.0], [0.0, 0.0], [1.0, -1.0], [-1.0, 0.5], [0.5, 0.5]], dtype=torch.float64)
    em = LogPosteriorEmulator(B, noise_floor=1e-12).fit(x, f(x))  # duplicated point: must not crash
    assert em.fit_info["attempts"] >= 1 and em._hyper_state is not None
    em.fit(torch.cat([x, torch.tensor([[1.5, -2.0]], dtype=torch.float64)]),
           f(torch.cat([x, torch.tensor([[1.5, -2.0]], dtype=torch.float64)])))
    assert em.model.train_inputs[0].shape[0] == 6


def test_cap_low_values():
    z = torch.tensor([0.0, -5.0, -1e4], dtype=torch.float64)
    assert cap_low_values(z, 50.0).tolist() == [0.0, -5.0, -50.0]
    assert cap_low_values(z, None).tolist() == z.tolist()


def test_cap_helps_with_huge_dynamic_range():
    """A few runs far from the data give z ~ -1e4; with the cap the GP still resolves the mode."""
    g = torch.Generator().manual_seed(1)
    x = B[0] + torch.rand(40, 2, generator=g, dtype=torch.float64) * (B[1] - B[0])

    def h(x):
        z = f(x)
        return torch.where(x[:, 0] > 1.5, z - 1e4, z)
    xt = torch.tensor([[0.0, -1.0], [0.5, -0.5], [-0.5, -1.2]], dtype=torch.float64)
    err_cap = (LogPosteriorEmulator(B, clip_range=30.0).fit(x, h(x)).mean(xt) - f(xt)).abs().max()
    err_raw = (LogPosteriorEmulator(B, clip_range=None).fit(x, h(x)).mean(xt) - f(xt)).abs().max()
    assert err_cap < 1.0 and 5 * err_cap < err_raw
