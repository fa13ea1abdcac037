"""torchslide.diagnose: verified evidence, refits and screening on solver-free targets."""
from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from torchslide.bayes import GaussianLikelihood, Prior, Uniform
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
    assert r["max_before"] > 7.5 and r["max_after"] < 1 and r["explained_all"] > 0.99
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


def test_detectable_switch_is_the_linear_gaussian_threshold():
    """power.detectable_switch on a model linear in (mu, xi, switch): with diagonal noise, a = |P J_c / sigma|
    and s_det = sqrt(bf_min + 2 ln(a W / sqrt(2 pi))) / a, predicted and measured on the model alike (the
    measurement's power law has exponent 2); noise correlated along the term's own effect (a full
    covariance, as the grid's error gives) raises it; a term that mu alone mimics is never detectable."""
    from torchslide.bayes import GaussianLikelihood
    from torchslide.diagnose.power import detectable_switch
    from torchslide.diagnose.screen import screen

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
    assert abs(d["per_unit"] - a) < 1e-4 * a and abs(d["per_unit_linear"] - a) < 1e-9 * a
    assert abs(d["switch"] - np.sqrt(10.0 + 2 * np.log(a * W / np.sqrt(2 * np.pi))) / a) < 1e-4 * d["switch"]
    assert abs(d["exponent"] - 2.0) < 1e-3 and all(abs(nc - (a * s) ** 2) < 1e-4 * nc for s, nc in d["measured"])
    assert d["within_prior"] == (d["switch"] <= W)
    # with noise, the profiled fit's 2 ln BF is max(0, s a + z)^2 - occam: at switch_power it reaches bf_min in
    # 80 % of the draws, at switch in half
    occam = 2 * np.log(a * W / np.sqrt(2 * np.pi))
    z = np.random.default_rng(0).standard_normal(200_000)
    for s, share in ((d["switch_power"], 0.8), (d["switch"], 0.5)):
        assert np.mean(np.maximum(0.0, s * a + z) ** 2 - occam >= 10.0) == pytest.approx(share, abs=0.005)
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


def test_detectable_switch_checks_the_re_tuned_baseline_on_the_solver():
    """A term that is a shift of mu seen through a nonlinear response (as mu(I) is, far from the screening's
    small mu step): the linear projection leaves it a large own effect, the baseline refitted on the model
    removes it, and the detectable switch moves beyond the prior; the linear value is kept as
    per_unit_linear. A term with its own effect keeps (within 1 %) its linear threshold."""
    from torchslide.bayes import GaussianLikelihood
    from torchslide.diagnose.power import detectable_switch
    from torchslide.diagnose.screen import screen

    rng = np.random.default_rng(5)
    k = 40
    b = rng.uniform(1.0, 4.0, k)
    own = rng.standard_normal(k)
    x0 = np.array([0.2, 500.0])
    sig = np.full(k, 0.002)

    class Ev:
        prior = Prior({"mu": Uniform(0.05, 0.5), "xi": Uniform(100.0, 2000.0)})
        fixed = {}
        likelihood = GaussianLikelihood(np.zeros(k), sigma=sig)
        data, sigma = np.zeros(k), sig

        def __init__(self, own_effect):
            self.own = own_effect

        def run_values(self, v):     # y = exp(b (mu + 5 kappa)) - exp(b mu0) + own * kappa, xi inert
            mu_eff = v["mu"][:, None] + 5.0 * v["kappa"][:, None]
            return np.exp(b * mu_eff) - np.exp(b * x0[0]) + np.outer(v["kappa"], self.own), np.zeros(len(v["mu"]), bool)

    ev = Ev(0.0 * own)
    d = detectable_switch(screen(ev, x0, ["entrainment"]), ev, bf_min=10.0)["entrainment"]
    assert d["per_unit_linear"] > 100.0 * d["per_unit"] and not d["within_prior"]
    assert detectable_switch(screen(ev, x0, ["entrainment"]), ev, bf_min=10.0, measure=False)["entrainment"][
        "within_prior"]                                      # what the linear projection alone claimed
    ev_own = Ev(own)
    d_own = detectable_switch(screen(ev_own, x0, ["entrainment"]), ev_own, bf_min=10.0)["entrainment"]
    assert d_own["within_prior"] and d_own["per_unit"] > 0.99 * d_own.get("per_unit_linear", d_own["per_unit"])
    # the report's screening table says how its switches were found ([diagnose] detectability)
    from torchslide.diagnose.report import _screening_section
    for measure, says in ((True, "measured on the solver near that switch"), (False, "linearised over the screening")):
        scr = screen(ev_own, x0, ["entrainment"])
        scr.detectable = detectable_switch(scr, ev_own, bf_min=10.0, measure=measure)
        assert ("measured" in scr.detectable["entrainment"]) == measure
        assert says in "\n".join(_screening_section(scr.to_json()["candidates"]))


def test_detectable_switch_measures_a_nonlinear_effect_on_the_solver():
    """An effect that saturates (as mu(I)'s does) or grows faster than linearly (a threshold term): the
    screening's step mispredicts the noise-free 2 ln LR nc(s) at the switches it names by more than twice;
    the measured power law gives nc within 10 % there, and the four-in-five switch lies Phi^-1(0.8)
    whitened units beyond the detectable one (sqrt(nc) + z reaches bf_min in 80 % of the draws)."""
    from scipy import stats as st

    from torchslide.diagnose.power import detectable_switch, lr_at
    from torchslide.diagnose.screen import screen

    rng = np.random.default_rng(6)
    k = 30
    Jm, Jx, own = rng.standard_normal(k), rng.standard_normal(k) * 0.01, rng.standard_normal(k)
    x0 = np.array([0.2, 500.0])
    sig = np.full(k, 0.5)
    A = np.column_stack([Jm, Jx]) / sig[:, None]
    j = own / sig
    a2 = float(np.sum((j - A @ np.linalg.lstsq(A, j, rcond=None)[0]) ** 2))     # |P own / sigma|^2
    laws = {"saturating": (300.0, lambda s: s / (1.0 + s / 0.004)),          # (scale of own, effect g(switch))
            "threshold": (40.0, lambda s: s + s * s / 0.001)}

    class Ev:
        prior = Prior({"mu": Uniform(0.05, 0.5), "xi": Uniform(100.0, 2000.0)})
        fixed = {}
        data, sigma = np.zeros(k), sig
        likelihood = GaussianLikelihood(np.zeros(k), sigma=sig)

        def __init__(self, scale, g):
            self.scale, self.g = scale, g

        def run_values(self, v):
            y = (np.outer(v["mu"] - x0[0], Jm) + np.outer(v["xi"] - x0[1], Jx)
                 + np.outer(self.g(v["kappa"]), self.scale * own))
            return y, np.zeros(len(v["mu"]), bool)

    for name, (scale, g) in laws.items():
        ev = Ev(scale, g)
        d = detectable_switch(screen(ev, x0, ["entrainment"]), ev, bf_min=10.0)["entrainment"]
        assert d["within_prior"], name
        nc = {s: scale**2 * a2 * g(s) ** 2 for s in (d["switch"], d["switch_power"])}
        linear_off = [max(r, 1.0 / r) for r in ((d["per_unit_linear"] * s) ** 2 / v for s, v in nc.items())]
        assert max(linear_off) > 2.0, name
        assert all(abs(lr_at(d, s) - v) < 0.1 * v for s, v in nc.items()), name
        gap = math.sqrt(nc[d["switch_power"]]) - math.sqrt(nc[d["switch"]])
        assert abs(gap - st.norm.ppf(0.8)) < 0.12, name


def test_screen_linear_optimum_recovers_a_linear_model():
    """screen's linear_opt is the joint least-squares optimum of (baseline re-tune, switch): on a model
    that is linear in (mu, xi, kappa) it is the truth; a residual the switch can only make worse
    (beta < 0) gives none."""
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
    ev_neg = Ev(model(np.array([0.2]), np.array([500.0]), np.array([-0.004]))[0])
    scr_neg = screen(ev_neg, x0, ["entrainment"])
    assert scr_neg.linear_opt["entrainment"] is None


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


def test_a_refit_with_untrustworthy_evidence_is_continued(monkeypatch):
    """pipeline.refit_candidate: a refit whose emulator is off the peak (importance weights spread, the
    verified evidence not trustworthy) is continued to n_total_max runs; the continued refit's verified
    evidence is the normalised Gaussian's (log Z = 0 with a unit prior box), and a trustworthy first refit
    is kept as it is."""
    from torchslide.diagnose import pipeline

    d, sig = np.array([0.3, 0.55, 0.7]), np.array([0.01, 0.015, 0.04])
    lik = GaussianLikelihood(torch.tensor(d), sigma=torch.tensor(sig))
    prior = Prior({"mu": Uniform(0.0, 1.0), "xi": Uniform(0.0, 1.0), "k": Uniform(0.0, 1.0)})
    z_of = lambda x: lik.log_likelihood(torch.as_tensor(x)) + prior.log_prob(torch.as_tensor(x))
    ev = _GaussianEvaluator(lik, prior)
    rng = np.random.default_rng(0)

    def refit_at(centre, spread, n_runs):
        s = np.clip(centre + spread * rng.standard_normal((400, 3)), 0, 1)
        # the emulator: a Gaussian of the draws' own spread around ``centre`` (exact when centre = d, spread = sig)
        mean = lambda t: torch.as_tensor(-0.5 * (((np.asarray(t) - centre) / spread) ** 2).sum(1)
                                         - np.log(np.sqrt(2 * np.pi) * spread).sum())
        return SimpleNamespace(names=["mu", "xi", "k"], x=s[:4], z=z_of(s[:4]).numpy(), failed=np.zeros(4, bool),
                               bounds=np.array([[0.0] * 3, [1.0] * 3]), samples=s, log_evidence=0.0,
                               posterior_grid=None, n_runs=n_runs, emulator=SimpleNamespace(mean=mean))

    off, good = refit_at(d + [0.01, -0.01, 0.05], 3 * sig, 24), refit_at(d, sig, 36)
    monkeypatch.setattr(pipeline, "refit", lambda *a, **k: (ev, off))
    monkeypatch.setattr(pipeline, "calibrate_evaluator", lambda *a, **k: good)
    bud = pipeline.Budgets(n_posterior_samples_after=16, n_total=24, n_total_max=36)
    _, res, _, ver, hist = pipeline.refit_candidate(ev, "entrainment", bud, None, log=lambda s: None)
    assert len(hist) == 2 and hist[0]["n_runs"] == 24 and hist[1]["n_runs"] == 36 and res is good
    assert not pipeline._trusted({"verified": True, "ess_fraction": hist[0]["ess"] / 16, "se": hist[0]["se"]}, bud)
    assert pipeline._trusted(ver, bud) and abs(ver["log_evidence"]) < 0.05
    monkeypatch.setattr(pipeline, "refit", lambda *a, **k: (ev, good))
    _, res, _, ver, hist = pipeline.refit_candidate(ev, "entrainment", bud, None, log=lambda s: None)
    assert len(hist) == 1 and res is good
