"""torchslide.diagnose: verified evidence, refits, mode searches, screening and baseline refinement on solver-free targets."""
from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import torch

from torchslide.bayes import GaussianLikelihood, Prior, Uniform
from torchslide.diagnose.decide import Thresholds
from torchslide.diagnose.verify import rescore, savage_dickey, verified_evidence, waic



def _toy(d=0.3, sig=0.1, lo=-1.0, hi=1.0):
    """y = x (one datum d, sd sig), Uniform(lo, hi) prior: z(x) = log N(d | x, sig) - log(hi - lo)."""
    ev = SimpleNamespace(likelihood=GaussianLikelihood(torch.tensor([d]), sigma=torch.tensor([sig])),
                         prior=Prior({"x": Uniform(lo, hi)}), data=np.array([d]), sigma=np.array([sig]),
                         sigma_raw=np.array([sig]))
    true_logz = -math.log(hi - lo)  # the Gaussian integrates to ~1 inside the box
    return ev, true_logz


def test_verified_evidence_corrects_a_wrong_emulator():
    """An emulator whose peak is too high by 40 and shifted by half a posterior sd: its own evidence
    is off by ~40, the verified one (importance weights from solver values) recovers the truth."""
    ev, true_logz = _toy()
    rng = np.random.default_rng(0)
    shift, bump, s = 0.05, 40.0, 0.1
    g = lambda x: (-0.5 * ((x[:, 0] - 0.3 - shift) / s) ** 2 - math.log(s * math.sqrt(2 * math.pi))
                   - math.log(2.0) + bump)
    x = (0.3 + shift + s * rng.standard_normal(400))[:, None]           # draws from exp(g) / Z_hat
    cal = SimpleNamespace(log_evidence=true_logz + bump, samples=x, posterior_grid=None,
                          emulator=SimpleNamespace(mean=lambda t: torch.as_tensor(g(np.asarray(t)))))
    v = verified_evidence(ev, cal, x, x.copy())
    assert abs(cal.log_evidence - true_logz) > 39
    assert abs(v["log_evidence"] - true_logz) < 0.2 and v["ess_fraction"] > 0.5 and v["se"] < 0.1
    # a badly placed emulator peak: weights degenerate, ESS small (the decision then refuses to name)
    x_bad = (0.3 + 0.5 + s * rng.standard_normal(12))[:, None]
    g_bad = lambda t: torch.as_tensor(-0.5 * ((np.asarray(t)[:, 0] - 0.8) / s) ** 2)
    bad = verified_evidence(ev, SimpleNamespace(log_evidence=0.0, samples=x_bad, posterior_grid=None,
                                                emulator=SimpleNamespace(mean=g_bad)), x_bad, x_bad.copy())
    assert bad["ess"] < 3 and bad["log_evidence"] < true_logz


def test_savage_dickey_sign():
    far = SimpleNamespace(names=["mu", "kappa"], samples=np.column_stack([np.full(1000, 0.2),
                                                                          np.random.default_rng(0).uniform(0.005, 0.01, 1000)]))
    near = SimpleNamespace(names=["mu", "kappa"], samples=np.column_stack([np.full(1000, 0.2),
                                                                           np.random.default_rng(0).uniform(0, 0.0005, 1000)]))
    assert savage_dickey(far, "kappa", (0.0, 0.02))["two_ln_bf"] > 6
    assert savage_dickey(near, "kappa", (0.0, 0.02))["two_ln_bf"] < -4


def test_rescore_and_waic():
    """A located excess (values 0..3) that the 'after' draws reproduce is explained; WAIC prefers them."""
    rng = np.random.default_rng(1)
    k = 10
    data = np.zeros(k)
    data[:4] = 2.0
    ev = SimpleNamespace(data=data, sigma=np.full(k, 0.5), sigma_raw=np.full(k, 0.5))
    before = 0.05 * rng.standard_normal((12, k))
    after = before + np.where(np.arange(k) < 4, 2.0, 0.0)
    item = {"what": "excess cluster", "standardised_residual": 8.0, "_idx": [0, 1, 2, 3], "_f": 1.0, "_stat": "sum"}
    r = rescore(ev, [item], before, after)
    assert r["max_before"] > 7.5 and r["max_after"] < 1 and r["explained"] > 0.99
    assert waic(ev, after)["elpd"] - waic(ev, before)["elpd"] > 20


def test_hdi_includes_the_bound_and_savage_dickey_adapts():
    from torchslide.diagnose.verify import hdi_interval
    rng = np.random.default_rng(0)
    s = 1.0 - np.abs(0.08 * rng.standard_normal(4000))        # piled up against the upper bound 1
    lo, hi = hdi_interval(s, 0.0, 1.0)
    assert hi == 1.0 and 0.8 < lo < 0.9
    assert np.quantile(s, 0.95) < 1.0                            # the equal-tailed interval misses it
    # Savage-Dickey: the density at 0 follows the posterior width (no fixed bin)
    narrow = SimpleNamespace(names=["k"], samples=np.abs(0.001 * rng.standard_normal((4000, 1))))
    wide = SimpleNamespace(names=["k"], samples=np.abs(0.01 * rng.standard_normal((4000, 1))))
    a, b = savage_dickey(narrow, "k", (0.0, 0.02)), savage_dickey(wide, "k", (0.0, 0.02))
    # true densities at 0: 2 / (sqrt(2 pi) sd) -> 2 ln BF = 2 ln(sqrt(2 pi) sd / (2 * 0.02))
    for r, sd in ((a, 0.001), (b, 0.01)):
        assert abs(r["two_ln_bf"] - 2 * math.log(math.sqrt(2 * math.pi) * sd / 0.04)) < 0.6


def _identity_evaluator(lik, prior):
    """A toy evaluator whose 'solver' predicts y = x (the likelihood / prior given)."""
    def evaluate(x):
        x = torch.as_tensor(x, dtype=torch.float64)
        return SimpleNamespace(failed=torch.zeros(len(x), dtype=torch.bool)), x.clone()

    return SimpleNamespace(evaluate=evaluate, likelihood=lik, prior=prior)


def test_refine_baseline_narrow_posterior():
    """A 2-D posterior ~1 % of the box wide, a 16-run global GP: the refinement (zoomed grid, local
    GP refits with the verification runs) recovers log Z with a trustworthy ESS."""
    from torchslide.active import maximin_lhs
    from torchslide.diagnose.verify import refine_baseline
    from torchslide.emulator import LogPosteriorEmulator

    d, sig = np.array([0.3, 0.55]), np.array([0.004, 0.006])
    lik = GaussianLikelihood(torch.tensor(d), sigma=torch.tensor(sig))
    prior = Prior({"a": Uniform(0.0, 1.0), "b": Uniform(0.0, 1.0)})

    Ev = _identity_evaluator(lik, prior)

    z_of = lambda x: (lik.log_likelihood(torch.as_tensor(x)) + prior.log_prob(torch.as_tensor(x))).numpy()
    b = np.array([[0.0, 0.0], [1.0, 1.0]])
    x = np.vstack([maximin_lhs(14, 2, seed=0), d + [0.01, -0.01], d - [0.02, 0.0]])
    z = z_of(x)
    em = LogPosteriorEmulator(torch.as_tensor(b)).fit(torch.as_tensor(x), torch.as_tensor(z))
    cal = SimpleNamespace(x=x, z=z, failed=np.zeros(len(x), bool), bounds=b, emulator=em)
    _, pred, ver, hist = refine_baseline(Ev, cal, 16, seed=0, log=lambda s: None)
    assert abs(ver["log_evidence"] - 0.0) < 0.5          # the Gaussian integrates to 1, prior density 1
    assert ver["ess"] >= 0.3 * 16 and len(pred.x) == 16


def test_needs_bound_probe_and_savage_dickey_on_a_zoomed_grid():
    """The bound probe fires when the switch posterior leans against an upper bound that no
    posterior-relevant run sampled, not when a good run lies there; Savage-Dickey on a zoomed grid
    that stops short of switch = 0 gives the floor density (strong evidence for the switch)."""
    from torchslide.diagnose.verify import needs_bound_probe
    rng = np.random.default_rng(0)
    b = np.array([[0.0, 0.0], [1.0, 1.0]])
    samples = np.column_stack([rng.uniform(0.4, 0.6, 2000), rng.uniform(0.75, 0.95, 2000)])
    x = np.column_stack([rng.uniform(0, 1, 20), np.r_[rng.uniform(0.0, 0.9, 19), 0.99]])
    z = -((x[:, 0] - 0.5) ** 2 + (x[:, 1] - 0.85) ** 2) * 100
    z[-1] = -500.0                       # the run at the bound is far from the posterior (irrelevant)
    cal = SimpleNamespace(samples=samples, emulator=object(), bounds=b, x=x, z=z, failed=np.zeros(20, bool))
    assert needs_bound_probe(cal)
    z2 = z.copy()
    z2[-1] = z.max()                     # a good run at the bound: nothing to probe
    assert not needs_bound_probe(SimpleNamespace(**{**cal.__dict__, "z": z2}))
    far = SimpleNamespace(**{**cal.__dict__, "samples": np.column_stack([samples[:, 0], 0.3 * samples[:, 1]])})
    assert not needs_bound_probe(far)
    axes = [np.linspace(0.1, 0.9, 10), np.linspace(0.52, 0.98, 24)]   # zoomed: switch axis starts at 0.51
    g = SimpleNamespace(names=["mu", "k"], samples=None, grid_axes=axes, posterior_grid=np.ones((10, 24)))
    sd = savage_dickey(g, "k", (0.0, 1.0))
    assert sd["at_floor"] and sd["two_ln_bf"] > 20


def test_refine_refit_reuses_untrusted_verification_runs():
    """A 3-D refit whose global GP put its posterior in the wrong place (untrusted first verification):
    refine_refit with those verification runs as ``extra`` starts from a local GP, ends trustworthy,
    recovers log Z and its switch interval covers the truth; the extra runs are counted as runs."""
    from torchslide.active import maximin_lhs
    from torchslide.diagnose.verify import refine_refit, solver_z
    from torchslide.emulator import LogPosteriorEmulator

    d, sig = np.array([0.3, 0.55, 0.7]), np.array([0.01, 0.015, 0.04])
    lik = GaussianLikelihood(torch.tensor(d), sigma=torch.tensor(sig))
    prior = Prior({"mu": Uniform(0.0, 1.0), "xi": Uniform(0.0, 1.0), "k": Uniform(0.0, 1.0)})

    Ev = _identity_evaluator(lik, prior)
    z_of = lambda x: (lik.log_likelihood(torch.as_tensor(x)) + prior.log_prob(torch.as_tensor(x))).numpy()
    b = np.array([[0.0] * 3, [1.0] * 3])
    x = maximin_lhs(20, 3, seed=1)
    z = z_of(x)
    em = LogPosteriorEmulator(torch.as_tensor(b)).fit(torch.as_tensor(x), torch.as_tensor(z))
    rng = np.random.default_rng(0)
    wrong = np.clip(d + [0.03, -0.04, -0.2] + 0.01 * rng.standard_normal((12, 3)), 0, 1)   # off-peak draws
    cal = SimpleNamespace(names=["mu", "xi", "k"], x=x, z=z, failed=np.zeros(len(x), bool), bounds=b, emulator=em,
                          samples=wrong, log_evidence=0.0)
    pred_first = SimpleNamespace(x=wrong, draws=wrong.copy())
    res, pred, ver = refine_refit(Ev, cal, 16, seed=0, max_rounds=3, grid=(40, 32), log=lambda s: None,
                                  extra=(wrong, solver_z(Ev, pred_first)))
    assert ver["rounds"][0]["extra_runs"] == 12 and ver["rounds"][0]["bound_probes"] == 0
    assert res.n_runs >= 20 + 12 + 16
    assert ver["ess"] >= 0.3 * 16 and abs(ver["log_evidence"]) < 1.0   # normalised Gaussian, prior density 1
    assert ver["converged"] and ver["rounds"][-1]["stable"]
    # no rounds left and the global GP's proposal off the peak: reported as not converged
    _, _, v0 = refine_refit(Ev, cal, 4, seed=0, max_rounds=0, grid=(40, 32), log=lambda s: None)
    assert v0["converged"] == bool(v0["ess_fraction"] >= 0.3 and v0["se"] <= 1.0)   # round 0 counts as stable
    from torchslide.diagnose.pipeline import _params
    lo, hi = _params(res)["k"]["hdi90"]
    assert lo <= 0.7 <= hi and hi - lo < 0.3


def test_local_search_climbs_to_a_mode_the_refit_missed():
    """polish.local_search from runs that missed a narrow 3-D peak (the best run ~0.1 away): it finds
    a point far better than every earlier run, near the peak, inside the box, in batched calls."""
    from torchslide.active import maximin_lhs
    from torchslide.diagnose.polish import local_search

    d, sig = np.array([0.3, 0.55, 0.07]), np.array([0.02, 0.03, 0.01])
    lik = GaussianLikelihood(torch.tensor(d), sigma=torch.tensor(sig))
    prior = Prior({"mu": Uniform(0.0, 1.0), "xi": Uniform(0.0, 1.0), "k": Uniform(0.0, 1.0)})
    calls = []

    def ev(x):
        x = torch.as_tensor(x, dtype=torch.float64)
        calls.append(len(x))
        return SimpleNamespace(z=lik.log_likelihood(x) + prior.log_prob(x), failed=torch.zeros(len(x), dtype=torch.bool))

    x = np.vstack([maximin_lhs(20, 3, seed=1), d + [0.04, -0.05, 0.06]])
    z = ev(x).z.numpy()
    calls.clear()
    r = local_search(ev, x, z, np.array([[0.0] * 3, [1.0] * 3]), n_iter=6, pop=8, n_starts=2,
                     step0=[0.02, 0.02, 0.02], seed=0)
    assert calls == [16] * 6 and r["x"].shape == (96, 3)
    assert np.all((r["x"] >= 0) & (r["x"] <= 1))
    assert r["improvement"] > 10 and r["best_z"] == r["z"].max()
    assert np.all(np.abs(r["best_x"] - d) < 3 * sig)
    # at the peak already: nothing to gain
    r2 = local_search(ev, np.vstack([x, d]), np.concatenate([z, ev(d[None]).z.numpy()]), np.array([[0.0] * 3, [1.0] * 3]),
                      n_iter=2, seed=0)
    assert r2["improvement"] <= 0.0


def test_mode_search_starts_from_the_nested_baseline():
    """A refit whose runs all lie far below the baseline's peak (a lost mode: nested model, evidence
    far below the baseline's): pipeline._mode_search runs the best baseline points with the switch at
    0 and searches from them, so the missed mode is flagged and the search's best is at least there."""
    from torchslide.diagnose.pipeline import Budgets, _mode_search

    d, sig = np.array([0.3, 0.55, 0.0]), np.array([0.02, 0.03, 0.05])
    lik = GaussianLikelihood(torch.tensor(d), sigma=torch.tensor(sig))
    prior = Prior({"mu": Uniform(0.0, 1.0), "xi": Uniform(0.0, 1.0), "k": Uniform(0.0, 1.0)})

    def ev(x):
        x = torch.as_tensor(x, dtype=torch.float64)
        return SimpleNamespace(z=lik.log_likelihood(x) + prior.log_prob(x), failed=torch.zeros(len(x), dtype=torch.bool))

    rng = np.random.default_rng(0)
    x = np.clip([0.8, 0.2, 0.6] + 0.05 * rng.standard_normal((10, 3)), 0, 1)      # the refit's runs: off the peak
    cal = SimpleNamespace(x=x, z=ev(x).z.numpy(), failed=np.zeros(10, bool), bounds=np.array([[0.0] * 3, [1.0] * 3]),
                          samples=None)
    base = np.array([[0.31, 0.54], [0.29, 0.57]])
    ls = _mode_search(ev, cal, Budgets(mode_search_iters=2), base_best=base)
    assert np.allclose(ls["x"][:2], np.hstack([base, np.zeros((2, 1))]))
    z_base = ev(ls["x"][:2]).z.numpy()
    assert ls["best_z"] >= z_base.max() and ls["improvement"] >= z_base.max() - cal.z.max() > 100
    assert Budgets(mode_search_iters=0).mode_search_iters == 0 and _mode_search(ev, cal, Budgets(mode_search_iters=0)) is None
    # Budgets.mode_search_max_iters: the search goes on while it climbs (from the refit's own runs alone, far
    # from the peak, 2 iterations do not get there); it says how many iterations it made
    far = _mode_search(ev, cal, Budgets(mode_search_iters=2))
    climb = _mode_search(ev, cal, Budgets(mode_search_iters=2, mode_search_max_iters=30, mode_search_tol=0.5))
    assert far["iters"] == 2 and 2 < climb["iters"] <= 30 and len(climb["z"]) == 12 * climb["iters"]
    assert climb["best_z"] > far["best_z"] + 10


class _GaussianEvaluator:
    """A toy diagnosis evaluator whose 'solver' predicts y = x: ``ev(x)`` gives z = ln L + ln prior,
    ``evaluate`` the predictions (posterior_predictive, verified_evidence); ``calls`` the batch sizes."""

    def __init__(self, lik, prior):
        self.likelihood, self.prior, self.calls = lik, prior, []

    def evaluate(self, x):
        x = torch.as_tensor(x, dtype=torch.float64)
        return SimpleNamespace(failed=torch.zeros(len(x), dtype=torch.bool)), x.clone()

    def __call__(self, x):
        x = torch.as_tensor(x, dtype=torch.float64)
        self.calls.append(len(x))
        return SimpleNamespace(z=self.likelihood.log_likelihood(x) + self.prior.log_prob(x),
                               failed=torch.zeros(len(x), dtype=torch.bool))


def _off_peak_refit(flank: bool = False):
    """(evaluator, refit result) of a 3-D Gaussian posterior peaked at (0.3, 0.55, 0.7) whose refit
    posterior sits off the peak (k ~ 0.5). The emulator equals the solver's z, so the importance
    weights on the wrong draws are flat: the first verification is trustworthy, and its log Z (-40) is
    far from the truth (0). ``flank``: one refit run near the peak (z 0.72 below it)."""
    from torchslide.active import maximin_lhs

    d, sig = np.array([0.3, 0.55, 0.7]), np.array([0.01, 0.015, 0.04])
    lik = GaussianLikelihood(torch.tensor(d), sigma=torch.tensor(sig))
    prior = Prior({"mu": Uniform(0.0, 1.0), "xi": Uniform(0.0, 1.0), "k": Uniform(0.0, 1.0)})
    z_of = lambda x: lik.log_likelihood(torch.as_tensor(x)) + prior.log_prob(torch.as_tensor(x))

    rng = np.random.default_rng(0)
    wrong = np.clip(d + [0.03, -0.04, -0.2] + 0.005 * rng.standard_normal((200, 3)), 0, 1)
    x = np.vstack([maximin_lhs(20, 3, seed=1), wrong[:4]] + ([d + [0.012, 0.0, 0.0]] if flank else []))
    cal = SimpleNamespace(names=["mu", "xi", "k"], x=x, z=z_of(x).numpy(), failed=np.zeros(len(x), bool),
                          bounds=np.array([[0.0] * 3, [1.0] * 3]), samples=wrong, log_evidence=-40.0,
                          posterior_grid=None, n_runs=len(x), emulator=SimpleNamespace(mean=lambda t: z_of(t)))
    return _GaussianEvaluator(lik, prior), cal


def test_refit_candidate_refines_a_trusted_refit_that_missed_the_peak(monkeypatch):
    """A refit whose posterior sits off the peak but whose importance weights are flat there (the
    verification 'trusts' it: it cannot see mass it never drew): pipeline.refit_candidate's search
    beats every refit run, the refit is refined with the search's runs, and the kept posterior covers
    the peak with the right evidence."""
    from torchslide.diagnose import pipeline

    ev, cal = _off_peak_refit()
    monkeypatch.setattr(pipeline, "refit", lambda *a, **k: (ev, cal))
    bud = pipeline.Budgets(n_posterior_samples_after=16, refit_refine_rounds=3, refit_grid=(40, 32))
    _, res, _, ver, hist = pipeline.refit_candidate(ev, "entrainment", bud, None, log=lambda s: None)
    assert hist[0]["mode_search"]["missed_mode"] and pipeline._trusted(
        {"verified": True, "ess_fraction": hist[0]["ess"] / 16, "se": hist[0]["se"]}, bud)
    assert abs(ver["log_evidence"]) < 1.0                    # normalised Gaussian, prior density 1
    lo, hi = pipeline._params(res)["k"]["hdi90"]
    assert lo <= 0.7 <= hi
    # a refinement that ends below the first proposal's (flat, 16 of 16) ESS and untrusted (a strict ESS
    # bar) is still kept: the first proposal missed the peak, so its ESS says nothing
    strict = pipeline.Budgets(n_posterior_samples_after=16, refit_refine_rounds=1, refit_grid=(40, 32),
                              verify_ess_fraction=0.99)
    _, res2, _, ver2, hist2 = pipeline.refit_candidate(ev, "entrainment", strict, None, log=lambda s: None)
    assert ver2["ess"] < hist2[0]["ess"] and not hist2[0].get("kept")
    lo, hi = pipeline._params(res2)["k"]["hdi90"]
    assert lo <= 0.7 <= hi


def test_detectable_switch_is_the_linear_gaussian_threshold():
    """screen.detectable_switch on a model linear in (mu, xi, switch): with diagonal noise, a = |P J_c / sigma|
    and s_det = sqrt(bf_min + 2 ln(a W / sqrt(2 pi))) / a; noise correlated along the term's own effect
    (a full covariance, as the grid's error gives) raises it; a term that mu alone mimics is never
    detectable."""
    from torchslide.bayes import GaussianLikelihood
    from torchslide.diagnose.screen import detectable_switch, screen

    rng = np.random.default_rng(4)
    k = 30
    Jm, Jx = rng.standard_normal(k), rng.standard_normal(k) * 0.01
    Jc = rng.standard_normal(k) * 20.0
    x0 = np.array([0.2, 500.0])
    sig = np.full(k, 0.5)

    class Ev:
        prior = Prior({"mu": Uniform(0.05, 0.5), "xi": Uniform(100.0, 2000.0)})
        fixed = {}

        def __init__(self, jc, cov=None):
            self.jc, self.data, self.sigma = jc, np.zeros(k), sig
            self.likelihood = (GaussianLikelihood(self.data, sigma=sig) if cov is None
                               else GaussianLikelihood(self.data, covariance=cov))

        def run_values(self, v):
            y = np.outer(v["mu"] - x0[0], Jm) + np.outer(v["xi"] - x0[1], Jx) + np.outer(v["kappa"], self.jc)
            return y, np.zeros(len(v["mu"]), bool)

    ev = Ev(Jc)
    scr = screen(ev, x0, ["entrainment"])
    d = detectable_switch(scr, ev, bf_min=10.0)["entrainment"]
    A = np.column_stack([Jm, Jx]) / sig[:, None]
    j = Jc / sig
    a = np.linalg.norm(j - A @ np.linalg.lstsq(A, j, rcond=None)[0])
    W = 0.02
    assert abs(d["per_unit"] - a) < 1e-6 * a
    assert abs(d["switch"] - np.sqrt(10.0 + 2 * np.log(a * W / np.sqrt(2 * np.pi))) / a) < 1e-9
    assert d["within_prior"] == (d["switch"] <= W)
    # noise with extra variance along the candidate's own direction: it is harder to see
    u = Jc / np.linalg.norm(Jc)
    cov = np.diag(sig**2) + 4.0 * np.outer(u, u)
    ev_c = Ev(Jc, cov)
    d_c = detectable_switch(screen(ev_c, x0, ["entrainment"]), ev_c, bf_min=10.0)["entrainment"]
    assert d_c["switch"] > 1.5 * d["switch"] and d_c["per_unit"] < d["per_unit"]
    # mimicked by mu: no own effect
    ev_m = Ev(Jm * 3.0)
    d_m = detectable_switch(screen(ev_m, x0, ["entrainment"]), ev_m, bf_min=10.0)["entrainment"]
    assert d_m["per_unit"] < 1e-9 * a and not d_m["within_prior"]


def test_screen_linear_optimum_recovers_a_linear_model():
    """screen's linear_opt is the joint least-squares optimum of (baseline re-tune, switch): on a model
    that is linear in (mu, xi, kappa) it is the truth, and _linear_starts puts the f = 1 start there;
    a residual the switch can only make worse (beta < 0) gives no start."""
    from torchslide.diagnose.pipeline import _linear_starts
    from torchslide.diagnose.screen import screen

    rng = np.random.default_rng(3)
    k = 12
    Jm, Jx, Jk = rng.standard_normal(k), rng.standard_normal(k) * 0.01, rng.standard_normal(k) * 50
    x0 = np.array([0.2, 500.0])
    truth = {"mu": 0.21, "xi": 520.0, "kappa": 0.006}

    def model(mu, xi, kappa):
        return (np.outer(mu - x0[0], Jm) + np.outer(xi - x0[1], Jx) + np.outer(kappa, Jk))

    class Ev:
        prior = Prior({"mu": Uniform(0.05, 0.5), "xi": Uniform(100.0, 2000.0)})
        fixed, sigma = {}, np.full(k, 0.1)

        def __init__(self, data):
            self.data = data

        def run_values(self, v):
            return model(v["mu"], v["xi"], v["kappa"]), np.zeros(len(v["mu"]), bool)

    ev = Ev(model(np.array([truth["mu"]]), np.array([truth["xi"]]), np.array([truth["kappa"]]))[0])
    scr = screen(ev, x0, ["entrainment"])
    lo = scr.linear_opt["entrainment"]
    assert lo is not None and scr.scores["entrainment"] > 0
    for n, v in truth.items():
        assert abs(lo[n] - v) < 1e-6 * max(1.0, abs(v))
    st = _linear_starts(scr, "entrainment", ["mu", "xi", "kappa"])
    assert st.shape == (3, 3) and np.allclose(st[1], [truth["mu"], truth["xi"], truth["kappa"]])
    assert np.allclose(st[0], 0.5 * (st[1] + [x0[0], x0[1], 0.0]))
    ev_neg = Ev(model(np.array([0.2]), np.array([500.0]), np.array([-0.004]))[0])
    scr_neg = screen(ev_neg, x0, ["entrainment"])
    assert scr_neg.linear_opt["entrainment"] is None and _linear_starts(scr_neg, "entrainment", ["mu", "xi", "kappa"]) is None


def test_refit_candidate_checks_the_search_against_the_posterior_draws(monkeypatch):
    """A refit with a run on the peak's flank (the search gains little over its best run) whose
    posterior lies off the peak: the search is compared with the best of the posterior draws' runs,
    the refit is flagged and refined, and the kept posterior covers the peak."""
    from torchslide.diagnose import pipeline

    ev, cal = _off_peak_refit(flank=True)
    monkeypatch.setattr(pipeline, "refit", lambda *a, **k: (ev, cal))
    bud = pipeline.Budgets(n_posterior_samples_after=16, refit_refine_rounds=3, refit_grid=(40, 32))
    _, res, _, ver, hist = pipeline.refit_candidate(ev, "entrainment", bud, None, log=lambda s: None)
    ms = hist[0]["mode_search"]
    assert ms["improvement"] <= bud.mode_margin < ms["gap_to_draws"] and ms["missed_mode"]
    assert abs(ver["log_evidence"]) < 1.0
    lo, hi = pipeline._params(res)["k"]["hdi90"]
    assert lo <= 0.7 <= hi
    # a check against the refit's runs alone would have kept the wrong posterior: the first verification
    # is trusted (flat weights) and far from log Z = 0
    assert pipeline._trusted({"verified": True, "ess_fraction": hist[0]["ess"] / 16, "se": hist[0]["se"]}, bud)
    assert hist[0]["log_evidence"] < -20


def test_params_snaps_a_grid_interval_to_the_prior_bound():
    """_params reports a grid posterior's interval that ends in the last cell as ending at the bound
    itself (not 0.9999999999999999)."""
    from torchslide.diagnose.pipeline import _params

    e = np.linspace(0.8776381909547739, 1.0, 33)
    ax = (e[:-1] + e[1:]) / 2                                      # centres; last edge one ulp short of 1
    assert ax[-1] + (ax[1] - ax[0]) / 2 < 1.0
    dens = np.exp(30 * (ax - 1.0))
    cal = SimpleNamespace(names=["k"], bounds=np.array([[0.0], [1.0]]), samples=None, posterior_grid=dens,
                          grid_axes=[ax], summary={"mean": {"k": 0.95}, "hdr90": {"k": [0.9, ax[-1] + (ax[1] - ax[0]) / 2]},
                                                   "map": {"k": ax[-1]}})
    p = _params(cal)["k"]
    assert p["hdi90"][1] == 1.0 and p["hdr90"][1] == 1.0 and 0.87 < p["hdi90"][0] < 1.0


def test_baseline_mode_check_refines_a_baseline_that_missed_its_mode():
    """The baseline's runs sit on a secondary slope far below the peak that a refit (nesting the
    baseline) found with its switch near 0: pipeline.baseline_mode_check runs the refits' nested points
    in the baseline model, flags the missed mode and refines the baseline from all runs, whose verified
    log Z is then right (the Gaussian likelihood integrates to 1 over the unit box); with the peak
    already among the baseline's runs nothing is refined."""
    from torchslide.diagnose.pipeline import Budgets, baseline_mode_check, nested_points

    d, sig = np.array([0.3, 0.55]), np.array([0.01, 0.015])
    lik = GaussianLikelihood(torch.tensor(d), sigma=torch.tensor(sig))
    prior = Prior({"mu": Uniform(0.0, 1.0), "xi": Uniform(0.0, 1.0)})
    ev = _GaussianEvaluator(lik, prior)
    calls = ev.calls
    rng = np.random.default_rng(0)
    xb = np.clip([0.7, 0.2] + 0.05 * rng.standard_normal((20, 2)), 0, 1)       # the baseline's runs: off the peak
    zb = ev(xb).z.numpy()
    # two refits (switch = last column, prior box [0, 1]): one has a run near the peak with its switch
    # at 0.03, its best run (switch 0.6) is elsewhere
    xr = np.array([[0.31, 0.56, 0.03], [0.6, 0.3, 0.6], [0.9, 0.9, 0.05]])
    zr = np.array([-5.0, 0.0, -50.0])
    cal_r = SimpleNamespace(x=xr, z=zr, failed=np.zeros(3, bool), bounds=np.array([[0.0] * 3, [1.0] * 3]))
    cal_q = SimpleNamespace(x=xr[[2]], z=zr[[2]], failed=np.zeros(1, bool), bounds=np.array([[0.0] * 3, [1.0] * 3]))
    pts = nested_points({"a": (None, cal_r), "b": (None, cal_q)}, 2)
    assert pts.shape == (3, 2) and any(np.allclose(p, [0.31, 0.56]) for p in pts)
    bud = Budgets(mode_search_iters=2, mode_search_pop=4, n_posterior_samples=16, baseline_refine_rounds=3,
                  baseline_grid_size=120)
    calls.clear()
    out = baseline_mode_check(ev, (xb, zb), {"a": (None, cal_r), "b": (None, cal_q)}, bud, log=lambda s: None)
    assert calls[:3] == [3, 8, 8]                      # the nested points in one call, then the search's batches
    assert out["missed_mode"] and out["improvement"] > 100
    assert abs(out["verification"]["log_evidence"]) < 0.5 and out["verification"]["ess"] >= 0.3 * 16
    assert len(out["predictive"].x) == 16
    # the refined posterior as the report shows it (pipeline._params of verify.grid_result)
    from torchslide.diagnose.pipeline import _params
    from torchslide.diagnose.verify import grid_result
    par = _params(grid_result(out["proposal"], ["mu", "xi"], np.array([[0.0, 0.0], [1.0, 1.0]])))
    for n, v, sg in zip(("mu", "xi"), d, sig):
        assert abs(par[n]["mean"] - v) < sg and par[n]["hdi90"][0] < v < par[n]["hdi90"][1]
    # the peak among the baseline's runs already: no mode missed, nothing refined
    xb2 = np.vstack([xb, d])
    out2 = baseline_mode_check(ev, (xb2, ev(xb2).z.numpy()), {"a": (None, cal_r)}, bud, log=lambda s: None)
    assert not out2["missed_mode"] and "verification" not in out2 and out2["improvement"] <= bud.mode_margin


def test_refit_recheck_refines_a_refit_below_the_refined_baseline():
    """After the baseline was refined to a peak the refit never sampled (the refit's posterior sits
    elsewhere on the ridge), pipeline.refit_recheck runs the new baseline's best points in the
    candidate's model with the switch at 0, finds them far above every posterior draw, and refines the
    refit from them: its verified log Z is then right and its switch interval reaches 0. A refit whose
    draws already cover those points is left as it is."""
    from torchslide.diagnose import pipeline
    from torchslide.diagnose.predictive import posterior_predictive
    from torchslide.diagnose.verify import verified_evidence

    d, sig = np.array([0.3, 0.55, 0.0]), np.array([0.01, 0.015, 0.05])
    lik = GaussianLikelihood(torch.tensor(d), sigma=torch.tensor(sig))
    prior = Prior({"mu": Uniform(0.0, 1.0), "xi": Uniform(0.0, 1.0), "k": Uniform(0.0, 1.0)})
    ev = _GaussianEvaluator(lik, prior)
    z_of = lambda x: ev(x).z
    rng = np.random.default_rng(1)
    wrong = np.clip([0.36, 0.45, 0.3] + 0.005 * rng.standard_normal((200, 3)), 0, 1)   # another ridge peak
    from torchslide.active import maximin_lhs
    x = np.vstack([maximin_lhs(20, 3, seed=2), wrong[:4]])
    cal = SimpleNamespace(names=["mu", "xi", "k"], x=x, z=z_of(x).numpy(), failed=np.zeros(len(x), bool),
                          bounds=np.array([[0.0] * 3, [1.0] * 3]), samples=wrong, log_evidence=-60.0,
                          posterior_grid=None, n_runs=len(x), emulator=SimpleNamespace(mean=lambda t: z_of(t)))
    p_c = posterior_predictive(ev, wrong[:16])
    ver = verified_evidence(ev, cal, p_c.x, p_c.draws, seed=0)
    assert ver["log_evidence"] < -20                           # the first estimate missed the peak
    hist = [{"n_runs": len(x), "log_evidence": ver["log_evidence"], "kept": True}]
    bud = pipeline.Budgets(n_posterior_samples_after=16, refit_refine_rounds=3, refit_grid=(40, 32),
                           mode_search_iters=2, mode_search_pop=4)
    pts = np.array([[0.301, 0.552], [0.297, 0.548]])          # the refined baseline's best runs
    res, p_r, v_r, h_r, out = pipeline.refit_recheck(ev, cal, p_c, ver, hist, pts, bud, log=lambda s: None)
    assert out["refined"] and out["gap_to_draws"] > 30 and out["log_evidence_before"] == ver["log_evidence"]
    # normalised Gaussian truncated to k >= 0 (half its mass): log Z = ln 0.5
    assert abs(v_r["log_evidence"] - np.log(0.5)) < 0.5 and out["log_evidence"] == v_r["log_evidence"]
    assert not h_r[0]["kept"] and all(h.get("recheck") for h in h_r[1:]) and len(h_r) > 1
    par = pipeline._params(res)
    assert par["k"]["hdi90"][0] <= 0.01 and par["mu"]["hdi90"][0] < 0.3 < par["mu"]["hdi90"][1]
    # the re-checked refit's draws already reach the points: nothing is refined
    _, _, v2, h2, out2 = pipeline.refit_recheck(ev, res, p_r, v_r, h_r, pts, bud, log=lambda s: None)
    assert not out2["refined"] and out2["gap_to_draws"] <= bud.mode_margin and v2 is v_r and h2 is h_r
    assert not pipeline.refit_recheck(ev, cal, p_c, ver, hist, pts, pipeline.Budgets(refit_refine_rounds=0),
                                      log=lambda s: None)[4]["refined"]


def test_refined_baseline_is_adopted_only_when_larger_beyond_noise_and_reliable():
    from torchslide.diagnose.pipeline import adopt_refined_baseline

    old = {"log_evidence": -100.0, "se": 0.3, "ess": 6.0}
    new = lambda lz, se=0.4, ess=8.0: {"log_evidence": lz, "se": se, "ess": ess}
    assert adopt_refined_baseline(new(-95.0), old, 16, 2.0)                # +5, noise 2 x 0.5 = 1
    assert not adopt_refined_baseline(new(-99.5), old, 16, 2.0)            # +0.5: within the noise
    assert not adopt_refined_baseline(new(-95.0, se=3.0), old, 16, 2.0)    # +5 but noise 6
    assert not adopt_refined_baseline(new(-95.0, ess=1.5), old, 16, 2.0)   # ESS below ess_min
    assert not adopt_refined_baseline(new(-95.0), old, 1, 2.0)             # a single draw


def test_fit_flags_use_the_calibrated_baselines_fit_not_the_refined_one(tmp_path, monkeypatch):
    """The fit flags' levels are set on the calibrated baseline's Z_fit, so the decision must use the first localisation's Z_fit even when the mode check refines the baseline
    afterwards (then fit_before, re-localised, carries the refined baseline's Z_fit, which differs)."""
    from torchslide.diagnose import Budgets, DiagnosisEvaluator, diagnose, pipeline
    from torchslide.observe import Observation
    from torchslide.observe_series import SeriesObservation
    from torchslide.physics import Params
    from torchslide.solver import SolverConfig, simulate
    from torchslide.terrain.synthetic import inclined_plane, release_from_shape

    dem = inclined_plane(30.0, 40.0, slope_length=600.0, runout_length=600.0, width=320.0, transition=200.0)
    rel = release_from_shape(dem, (150.0, 160.0), 60.0, volume=2.0e4)
    t = np.arange(2.0, 40.0, 2.0)
    res = simulate(dem, rel, Params.make(mu=0.3, xi=600.0), t_end=40.0, gauges=[("g1", 700.0, 160.0)],
                   config=SolverConfig())
    g = res.gauges["g1"]
    obs = [SeriesObservation.from_array("deposit_map", res.h_final[0].numpy(), dem, 0.5, name="deposit"),
           SeriesObservation("gauge_series", np.interp(t, g.t.numpy(), g.h[0].numpy()), 0.5,
                             name="g1:h", gauge="g1", quantity="h", times=t),
           Observation("final_volume", 2.0e4, 2.0e3, name="final_volume")]
    ev = DiagnosisEvaluator(dem=dem, release=rel, observations=obs, t_end=40.0, gauges=[("g1", 700.0, 160.0)],
                            prior=Prior({"mu": Uniform(0.2, 0.45), "xi": Uniform(200.0, 1500.0)}),
                            solver_config=SolverConfig())
    calls = []
    real_localise = pipeline.localise
    monkeypatch.setattr(pipeline, "localise", lambda *a, **k: calls.append(real_localise(*a, **k)) or calls[-1])
    # the mode check always refines (margin -inf) and its refinement is always adopted
    monkeypatch.setattr(pipeline, "adopt_refined_baseline", lambda *a: True)
    bud = Budgets(inference="emulator", baseline_n_initial=4, baseline_n_total=6, baseline_grid_size=40,
                  model_error_runs=0, batch_size=8,
                  n_initial=4, n_total=6, n_total_max=6, n_posterior_samples=6, n_posterior_samples_after=4,
                  refit_refine_rounds=1, baseline_refine_rounds=0,
                  top_k=1, n_perm=9, mode_search_iters=1, mode_search_pop=2, mode_margin=-math.inf,
                  refit_recheck=False, profile_top=0, slice_check=False, mcmc_steps=200)
    d = diagnose(ev, ["mu_i"], bud, Thresholds(fit_max=-1000.0), log=lambda s: None, workdir=tmp_path)
    dec = d.decision
    assert dec["baseline_verification"]["source"] == "baseline refined from the refits' nested points"
    first = {b: i["Z_fit"] for b, i in calls[0].blocks.items() if "Z_fit" in i}
    final = {b: r["Z_fit"] for b, r in d.fit_before["residuals"].items() if "Z_fit" in r}
    assert set(first) == {"deposit", "g1:h"} and set(final) == set(first)
    assert dec["fit_z"] == first and dec["fit_z_source"] == "calibrated baseline"
    assert any(abs(first[b] - final[b]) > 1e-6 for b in first)      # the refined baseline fits differently
    assert {f["observable"]: f["Z_fit"] for f in dec["fit_flags"]} == first
    # report.md shows the flags' statistic next to the final baseline's fit Z when the two differ
    from torchslide.diagnose.report import write_markdown
    j = d.to_json()
    md = write_markdown(j, [])
    row = next(l for l in md.splitlines() if l.startswith("| g1:h (rms z)"))
    assert "fit Z calibrated |" in md and row.endswith(f" {first['g1:h']:.1f} |")
    j["decision"]["fit_z"] = final
    assert "fit Z calibrated" not in write_markdown(j, [])
