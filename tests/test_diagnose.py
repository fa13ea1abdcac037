"""torchslide.diagnose: localisation pieces, decision rules, CLI bad input (exit 2), and a tiny blind harness."""
from __future__ import annotations


import numpy as np
import pytest

from torchslide.cli import main
from torchslide.diagnose.decide import Thresholds, decide
from torchslide.diagnose.localise import arrival_shift, benjamini_hochberg, map_clusters
from torchslide.terrain import DEM
from torchslide.terrain.io import write_asc


def test_benjamini_hochberg():
    p = np.array([0.001, 0.2, 0.01, 0.04, 0.9])
    assert benjamini_hochberg(p, 0.05).tolist() == [True, False, True, False, False]


def test_map_cluster_bbox_in_map_coordinates():
    rng = np.random.default_rng(0)
    z = rng.standard_normal((20, 30))
    z[5:9, 10:15] += 5.0
    dem = DEM(z=np.zeros((20, 30)), cellsize=10.0, xll=1000.0, yll=500.0)
    cl, _ = map_clusters(z, np.ones_like(z, bool), dem, radius=1, n_perm=99)
    assert cl and cl[0].sign == 1
    x0, y0, x1, y1 = cl[0].bbox
    assert 1080 <= x0 <= 1100 and 1150 <= x1 <= 1170 and 530 <= y0 <= 550 and 590 <= y1 <= 610


def test_arrival_shift():
    t = np.arange(0, 60, 1.0)
    y = np.exp(-((t - 20) / 4) ** 2)
    d = np.exp(-((t - 26) / 4) ** 2)
    assert abs(arrival_shift(t, d, y) - 6.0) <= 0.5


# ------------------------------------------------------------------------------------------------ CLI
BASE = """
[terrain]
synthetic = "inclined_plane"
cellsize = 50.0
options = {{ theta_deg = 30.0, slope_length = 500.0, runout_length = 700.0, width = 300.0 }}
release = {{ centre = [250.0, 150.0], radii = [120.0, 100.0], volume = 1.0e5 }}

[model]
rheology = "voellmy"
mu = 0.2
xi = 1000.0

[run]
t_end = 60.0

[[gauges]]
name = "G1"
x = 475.0
y = 150.0

[prior]
mu = [0.05, 0.5]
xi = [200.0, 2000.0]

[[observations]]
kind = "gauge_series"
file = "g1.csv"
gauge = "G1"
sigma = {{ h = 0.5, speed = 2.0 }}

[[observations]]
kind = "deposit_map"
file = "dep.asc"
sigma = 0.5

[diagnose]
candidates = {candidates}
"""


def _setup(tmp_path, csv="t,h,speed\n1,0,0\n2,1,3\n3,2,4\n", grid=(6, 24), candidates='["entrainment", "mu_i"]'):
    from torchslide.terrain.synthetic import inclined_plane
    (tmp_path / "g1.csv").write_text(csv)
    dem = inclined_plane(30.0, 50.0, slope_length=500.0, runout_length=700.0, width=300.0)
    other = DEM(z=np.zeros(grid), cellsize=50.0)
    write_asc(tmp_path / "dep.asc", np.zeros(grid), other)
    p = tmp_path / "diag.toml"
    p.write_text(BASE.format(candidates=candidates))
    return p, dem


@pytest.mark.parametrize("case", ["times", "grid", "candidate"])
def test_cli_bad_input_exit_2(tmp_path, capsys, case):
    from torchslide.terrain.synthetic import inclined_plane
    dem = inclined_plane(30.0, 50.0, slope_length=500.0, runout_length=700.0, width=300.0)
    kw = {"grid": dem.shape}
    if case == "times":
        kw["csv"] = "t,h,speed\n1,0,0\n3,1,3\n2,2,4\n"
    elif case == "grid":
        kw["grid"] = (dem.shape[0] + 1, dem.shape[1])
    else:
        kw["candidates"] = '["entrainment", "dark_matter"]'
    p, _ = _setup(tmp_path, **kw)
    rc = main(["diagnose", str(p), "--out", str(tmp_path / "out")])
    err = capsys.readouterr().err
    assert rc == 2
    assert not (tmp_path / "out").exists()
    if case == "times":
        assert "g1.csv" in err and "row 4" in err and "increase strictly" in err
    elif case == "grid":
        assert "dep.asc" in err and f"{dem.shape[0] + 1}x{dem.shape[1]}" in err and f"{dem.shape[0]}x{dem.shape[1]}" in err
    else:
        assert "dark_matter" in err and "unknown candidate" in err


# ---------------------------------------------------------------------------------- small blind harness
def test_small_harness(tmp_path):
    """Null + entrainment on the coarse channel with tiny budgets: runs end to end, writes reports,
    and the screening ranks entrainment first where entrainment is hidden."""
    from experiments.hidden_physics.harness import run_case
    from experiments.hidden_physics.make_page import build_page

    bud = dict(n_posterior_samples=8, n_posterior_samples_after=4, n_initial=6, n_total=8, n_total_max=8,
               baseline_n_initial=6, baseline_n_total=8, baseline_n_total_max=8, batch_size=8, top_k=1, n_perm=19,
               mcmc_steps=200)
    cands = ["entrainment", "yield_stress", "mu_i"]
    out = tmp_path / "res"
    cases = {sc: run_case(sc, 0, out, budgets=bud, candidates=cands, log=lambda s: None) for sc in ("null", "entrainment")}
    for sc, c in cases.items():
        j = c["diagnosis"]
        assert j["verdict"] in ("missing_physics", "no_missing_physics", "unexplained")
        for key in ("missing_physics", "located", "candidates", "fit_before", "fit_after"):
            assert key in j
        for cand in j["candidates"]:
            assert {"name", "log_evidence", "log_bayes_factor", "screening_score", "parameters"} <= set(cand)
    assert cases["entrainment"]["diagnosis"]["screening"]["ranking"][0] == "entrainment"
    assert cases["null"]["diagnosis"]["missing_physics"] != "yield_stress"
    page = build_page(out, tmp_path / "page")
    assert "Confusion matrix" in page.read_text()


# ------------------------------------------------------------------ verified evidence and the new decision
from types import SimpleNamespace

import math
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
    assert r["max_before"] > 7.5 and r["max_after"] < 1 and r["explained"] > 0.99
    assert waic(ev, after)["elpd"] - waic(ev, before)["elpd"] > 20


def _cand(name, two_ln_bf, **kw):
    c = {"name": name, "log_bayes_factor": two_ln_bf / 2, "two_ln_bf_lower": two_ln_bf - 2, "ess": 6.0,
         "two_ln_bf_savage_dickey": 8.0, "delta_waic": 30.0, "misfit_after": 50.0,
         "located_rescored": {"items": [{"before": 9.0, "after": 1.0}], "max_after": 1.0, "explained": 0.9}}
    c.update(kw)
    return c


def test_decide_new_rules():
    th = Thresholds(bf_min=20.0, located_min=8.0, waic_min=6.0)
    base = {"ess": 5.0}
    loc = [{"standardised_residual": 9.0}]
    d = decide([_cand("entrainment", 60.0), _cand("curvature", 10.0)], loc, base, 100.0, th)
    assert d["verdict"] == "missing_physics" and d["missing_physics"] == "entrainment" and not d["ambiguous"]
    # supported by the evidence but the located structure stays: out-of-library -> never a name
    keep = {"items": [{"before": 9.0, "after": 8.5}], "max_after": 8.5, "explained": 0.1}
    d = decide([_cand("curvature", 60.0, located_rescored=keep)], loc, base, 100.0, th)
    assert d["verdict"] == "unexplained" and d["missing_physics"] is None
    # untrustworthy evidence, Savage-Dickey disagreeing, or no out-of-sample gain: not named
    for bad in ({"ess": 1.0}, {"two_ln_bf_savage_dickey": -3.0}, {"delta_waic": -5.0}):
        d = decide([_cand("entrainment", 60.0, **bad)], loc, base, 100.0, th)
        assert d["missing_physics"] is None and d["verdict"] == "unexplained"
    # below the null-calibrated bf_min: nothing missing unless a located mismatch is significant
    assert decide([_cand("curvature", 15.0)], [{"standardised_residual": 6.0}], base, 100.0, th)["verdict"] == \
        "no_missing_physics"
    assert decide([_cand("curvature", 15.0)], loc, base, 100.0, th)["verdict"] == "unexplained"


# ------------------------------------------------- ambiguity, null-like evidence, HDI, baseline refinement
def test_decide_ambiguous_and_null_like():
    th = Thresholds(bf_min=20.0, located_min=8.0, waic_min=6.0, margin_min=6.0)
    base = {"ess": 5.0}
    loc = [{"standardised_residual": 9.0}]
    # the runner-up explains the located mismatch better: evidence and location disagree -> no name
    better = {"items": [{"before": 9.0, "after": 0.5}], "max_after": 0.5, "explained": 0.99}
    d = decide([_cand("earth_pressure", 60.0), _cand("yield_stress", -10.0, located_rescored=better)],
               loc, base, 100.0, th)
    assert d["verdict"] == "unexplained" and d["missing_physics"] is None and d["ambiguous"]
    assert d["competitors"] == ["yield_stress"]
    # two candidates pass every check within margin_min: no name
    d = decide([_cand("earth_pressure", 60.0), _cand("curvature", 57.0)], loc, base, 100.0, th)
    assert d["verdict"] == "unexplained" and d["ambiguous"]
    # evidence gain without a significant located mismatch and without explaining it: null-like
    keep = {"items": [{"before": 7.0, "after": 6.9}], "max_after": 6.9, "explained": 0.03}
    d = decide([_cand("curvature", 25.0, located_rescored=keep)], [{"standardised_residual": 7.0}], base, 100.0, th)
    assert d["verdict"] == "no_missing_physics"


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


def test_refine_baseline_narrow_posterior():
    """A 2-D posterior ~1 % of the box wide, a 16-run global GP: the refinement (zoomed grid, local
    GP refits with the verification runs) recovers log Z with a trustworthy ESS."""
    from torchslide.active import maximin_lhs
    from torchslide.diagnose.predictive import Predictive
    from torchslide.diagnose.verify import refine_baseline
    from torchslide.emulator import LogPosteriorEmulator

    d, sig = np.array([0.3, 0.55]), np.array([0.004, 0.006])
    lik = GaussianLikelihood(torch.tensor(d), sigma=torch.tensor(sig))
    prior = Prior({"a": Uniform(0.0, 1.0), "b": Uniform(0.0, 1.0)})

    class Ev:
        def evaluate(self, x):
            x = torch.as_tensor(x, dtype=torch.float64)
            return SimpleNamespace(failed=torch.zeros(len(x), dtype=torch.bool)), x.clone()

    Ev.likelihood, Ev.prior = lik, prior

    z_of = lambda x: (lik.log_likelihood(torch.as_tensor(x)) + prior.log_prob(torch.as_tensor(x))).numpy()
    b = np.array([[0.0, 0.0], [1.0, 1.0]])
    x = np.vstack([maximin_lhs(14, 2, seed=0), d + [0.01, -0.01], d - [0.02, 0.0]])
    z = z_of(x)
    em = LogPosteriorEmulator(torch.as_tensor(b)).fit(torch.as_tensor(x), torch.as_tensor(z))
    cal = SimpleNamespace(x=x, z=z, failed=np.zeros(len(x), bool), bounds=b, emulator=em)
    _, pred, ver, hist = refine_baseline(Ev(), cal, 16, seed=0, log=lambda s: None)
    assert abs(ver["log_evidence"] - 0.0) < 0.5          # the Gaussian integrates to 1, prior density 1
    assert ver["ess"] >= 0.3 * 16 and len(pred.x) == 16


def test_cli_diagnose_keys(tmp_path):
    from torchslide.commands.diagnose import load_diagnose_config
    from torchslide.config import ConfigError
    from torchslide.terrain.synthetic import inclined_plane
    dem = inclined_plane(30.0, 50.0, slope_length=500.0, runout_length=700.0, width=300.0)
    p, _ = _setup(tmp_path, grid=dem.shape, candidates='["entrainment"]\nwaic_min = 4\nexplain_min = 0.6\ness_min = 3')
    dg = load_diagnose_config(p).extra["diagnose"]
    assert (dg["waic_min"], dg["explain_min"], dg["ess_min"], dg["bf_min"]) == (4.0, 0.6, 3.0, 6.0)
    for extra, msg in (("bf_minimum = 3", "unknown key 'bf_minimum'"), ("explain_min = 2", "explain_min"),
                       ("ess_min = 0.5", "ess_min"), ("waic_min = 'x'", "waic_min")):
        q, _ = _setup(tmp_path, grid=dem.shape, candidates=f'["entrainment"]\n{extra}')
        with pytest.raises(ConfigError, match=msg):
            load_diagnose_config(q)


def test_rescore_gauge_window_uses_the_localisation_statistic():
    """A gauge-window mismatch is re-scored with the statistic that located it (arrival-aligned running
    mean, max |.| in the window), so the 'before' score equals the located score and is on the scale
    of located_min; a model that reproduces the bump removes it."""
    from torchslide.diagnose.evaluator import Block
    from torchslide.diagnose.localise import localise
    from torchslide.observe_series import SeriesObservation

    rng = np.random.default_rng(3)
    t = np.arange(2.0, 92.0, 2.0)
    shape = 3.0 * np.exp(-((t - 30) / 10) ** 2)
    bump = 2.5 * np.exp(-((t - 70) / 8) ** 2)
    data = shape + bump + 0.2 * rng.standard_normal(t.size)
    o = SeriesObservation("gauge_series", data, 0.5, name="g:h", gauge="g", quantity="h", times=t.copy(),
                          corr_length=4.0)
    ev = SimpleNamespace(blocks=[Block("g:h", "gauge_series", 0, t.size, o)], data=data,
                         sigma=o.sigma_eff(), sigma_raw=o.sigma_vector(), dem=None)
    before = shape + 0.05 * rng.standard_normal((16, t.size))
    after = shape + bump + 0.05 * rng.standard_normal((16, t.size))
    loc = localise(ev, before, n_perm=9)
    win = [l for l in loc.located if l.get("_stat") == "window"]
    assert win, loc.located
    r = rescore(ev, win, before, after)
    assert abs(r["items"][0]["before"] - win[0]["standardised_residual"]) < 1e-9
    assert abs(r["items"][0]["after"]) < 3.0 and r["explained"] > 0.8


def test_harness_refits_every_library_candidate():
    from experiments.hidden_physics.harness import HARNESS_BUDGETS, LIBRARY
    assert HARNESS_BUDGETS["top_k"] >= len(LIBRARY)


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


def test_decide_competitor_needs_evidence_variant():
    """Default rule: a competitor explaining more of the located mismatch blocks the name even without
    evidence; the (post-hoc) variant requires the competitor to pass the evidence check too."""
    th = Thresholds(bf_min=20.0, located_min=8.0, waic_min=6.0, margin_min=6.0)
    base = {"ess": 5.0}
    loc = [{"standardised_residual": 6.0}]
    a = {"items": [{"before": 6.0, "after": 3.7}], "max_after": 3.7, "explained": 0.61}
    b = {"items": [{"before": 6.0, "after": 3.6}], "max_after": 3.6, "explained": 0.63}
    cands = [_cand("earth_pressure", 64.0, located_rescored=a), _cand("mu_i", 8.0, located_rescored=b)]
    d = decide(cands, loc, base, 100.0, th)
    assert d["verdict"] == "unexplained" and d["ambiguous"] and d["competitors"] == ["mu_i"]
    d = decide(cands, loc, base, 100.0, th, competitor_needs_evidence=True)
    assert d["verdict"] == "missing_physics" and d["missing_physics"] == "earth_pressure"
    # a supported competitor that explains more still blocks
    cands[1] = _cand("mu_i", 40.0, located_rescored=b)
    assert decide(cands, loc, base, 100.0, th, competitor_needs_evidence=True)["ambiguous"]
