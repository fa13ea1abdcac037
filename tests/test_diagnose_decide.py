"""torchslide.diagnose: localisation (residuals, map clusters, gauge windows, fit flags) and the decision rules."""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from torchslide.diagnose.decide import Thresholds, decide
from torchslide.diagnose.localise import arrival_shift, benjamini_hochberg, map_clusters
from torchslide.diagnose.verify import rescore
from torchslide.terrain import DEM

from .conftest import cand as _cand


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




def test_decide_new_rules():
    th = Thresholds(bf_min=20.0, located_min=8.0, waic_min=6.0)
    base = {"ess": 5.0}
    loc = [{"standardised_residual": 9.0}]
    d = decide([_cand("entrainment", 60.0), _cand("curvature", 10.0)], loc, base, 100.0, th)
    assert d["verdict"] == "missing_physics" and d["missing_physics"] == "entrainment" and not d["ambiguous"]
    # supported by the evidence but the located structure stays: out-of-library -> never a name
    keep = {"items": [{"before": 9.0, "after": 8.5}], "max_after": 8.5, "explained_all": 0.1}
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


def test_a_strongly_supported_term_is_named_with_what_it_leaves_unexplained():
    th = Thresholds(bf_min=20.0, located_min=8.0, waic_min=6.0, margin_min=6.0)
    base = {"ess": 5.0}
    loc = [{"what": "final_volume", "where": "final_volume", "standardised_residual": 12.0},
           {"what": "g2 speed below prediction", "where": {"gauge": "g2", "t0": 20.0, "t1": 40.0},
            "standardised_residual": -10.0}]
    part = {"items": [{"what": "final_volume", "before": 12.0, "after": 1.0},
                      {"what": "g2 speed below prediction", "before": -10.0, "after": -9.5}],
            "max_after": 9.5}      # removes 1 - (1 + 9.5^2) / (12^2 + 10^2) = 63 % of the located mismatch
    little = {"items": [{"what": "final_volume", "before": 12.0, "after": 11.7}], "max_after": 11.7, "explained_all": 0.05}
    d = decide([_cand("entrainment", 500.0, located_rescored=part), _cand("curvature", 30.0, located_rescored=little)],
               loc, base, 100.0, th)
    assert d["verdict"] == "missing_physics" and d["missing_physics"] == "entrainment" and d["partial"]
    assert d["explained_share"] == pytest.approx(1 - 91.25 / 244)
    assert d["explained_shares"] == pytest.approx({"entrainment": 1 - 91.25 / 244, "curvature": 1 - 11.7 ** 2 / 144})
    # the verdict's share counts only the significant mismatches (|before| >= located_min); verify's counts all
    quiet_too = {"items": part["items"] + [{"what": "g1 h", "before": 3.0, "after": 0.0}], "max_after": 9.5}
    d2 = decide([_cand("entrainment", 500.0, located_rescored=quiet_too)], loc, base, 100.0, th)
    assert d2["explained_shares"]["entrainment"] == pytest.approx(1 - 91.25 / 244)
    assert d["remainder"] == [{"what": "g2 speed below prediction", "where": {"gauge": "g2", "t0": 20.0, "t1": 40.0},
                               "before": -10.0, "after": -9.5}]
    assert "63 %" in d["reason"] and "g2 speed below prediction" in d["reason"]
    from torchslide.diagnose.report import _verdict_section

    text = "\n".join(_verdict_section({"verdict": d["verdict"], "missing_physics": d["missing_physics"], "decision": d,
                                       "candidates": []}))
    assert "Partial: entrainment removes 63 %" in text and "| g2 speed below prediction |" in text
    # a share below explain_partial_min, or another failed check beside it: not named
    little_share = {"items": [dict(part["items"][0], after=11.0), part["items"][1]], "max_after": 11.0}   # 13 %
    for bad in ({"located_rescored": little_share}, {"located_rescored": part, "delta_waic": -5.0}):
        d = decide([_cand("entrainment", 500.0, **bad)], loc, base, 100.0, th)
        assert d["verdict"] == "unexplained" and d["missing_physics"] is None
    # a runner-up within the margin: "A or B", still with the remainder
    d = decide([_cand("entrainment", 500.0, located_rescored=part),
                _cand("release_volume", 497.0, located_rescored=little)], loc, base, 100.0, th)
    assert d["missing_physics"] == "entrainment or release_volume" and d["ambiguous"] and d["partial"]


# ------------------------------------------------- ambiguity, null-like evidence, HDI, baseline refinement
def test_decide_ambiguous_and_null_like():
    th = Thresholds(bf_min=20.0, located_min=8.0, waic_min=6.0, margin_min=6.0)
    base = {"ess": 5.0}
    loc = [{"standardised_residual": 9.0}]
    # the runner-up explains the located mismatch better: evidence and location disagree -> "A or B", no
    # single name
    better = {"items": [{"before": 9.0, "after": 0.5}], "max_after": 0.5, "explained_all": 0.99}
    part = {"items": [{"before": 9.0, "after": 5.0}], "max_after": 5.0, "explained_all": 0.7}
    d = decide([_cand("earth_pressure", 60.0, located_rescored=part),
                _cand("yield_stress", -10.0, located_rescored=better)], loc, base, 100.0, th)
    assert d["verdict"] == "missing_physics" and d["missing_physics"] == "earth_pressure or yield_stress"
    assert d["ambiguous"] and d["competitors"] == ["yield_stress"]
    assert d["alternatives"] == ["earth_pressure", "yield_stress"]
    # ... but not when both remove nearly all of it (0.99 against 0.98 is no disagreement): the evidence,
    # 2 ln BF 14 apart, names the term
    most = {"items": [{"before": 9.0, "after": 0.9}], "max_after": 0.9, "explained_all": 0.98}
    d = decide([_cand("release_volume", 38.0, located_rescored=most),
                _cand("entrainment", 24.0, located_rescored=better)], loc, base, 100.0, th)
    assert d["missing_physics"] == "release_volume" and not d["ambiguous"]
    assert decide([_cand("release_volume", 38.0, located_rescored=most),
                   _cand("entrainment", 24.0, located_rescored=better)], loc, base, 100.0,
                  Thresholds(bf_min=20.0, explain_margin=0.0))["missing_physics"] == "release_volume or entrainment"
    # candidates without located items to rescore (explained None) never contest a name
    d = decide([_cand("release_volume", 38.0, located_rescored=None), _cand("entrainment", 24.0, located_rescored=None)],
               loc, base, 100.0, th)
    assert not d.get("ambiguous") and " or " not in (d["missing_physics"] or "")
    # two candidates pass every check within margin_min: "A or B"
    d = decide([_cand("earth_pressure", 60.0), _cand("curvature", 57.0)], loc, base, 100.0, th)
    assert d["missing_physics"] == "earth_pressure or curvature" and d["ambiguous"]
    # a runner-up within margin_min that passes the evidence check but fails another one (here its
    # Savage-Dickey sign) still joins the verdict (the evidence does not separate them)
    close = [_cand("curvature", 82.3), _cand("earth_pressure", 78.0, two_ln_bf_savage_dickey=-1.0)]
    d = decide(close, loc, base, 100.0, th)
    assert d["missing_physics"] == "curvature or earth_pressure" and d["ambiguous"] and d["competitors"] == ["earth_pressure"]
    # ... but one below the evidence threshold does not
    weak = [_cand("curvature", 24.0), _cand("earth_pressure", 19.0, two_ln_bf_lower=17.0)]
    assert decide(weak, loc, base, 100.0, th)["missing_physics"] == "curvature"
    # a located mismatch at the noise's level (below located_min) is not one a term must remove: a term that
    # passes every other check is named though it stays
    keep = {"items": [{"before": 7.0, "after": 6.9}], "max_after": 6.9}
    quiet = [{"standardised_residual": 7.0}]
    d = decide([_cand("curvature", 25.0, located_rescored=keep)], quiet, base, 100.0, th)
    assert d["missing_physics"] == "curvature" and not d.get("partial")
    # ... but not one that turns it significant (nor "partial": there was nothing significant to remove)
    worse = {"items": [{"before": 7.0, "after": 9.0}], "max_after": 9.0}
    d = decide([_cand("curvature", 25.0, located_rescored=worse)], quiet, base, 100.0, th)
    assert d["missing_physics"] is None and not d.get("partial")
    # an evidence gain that fails another check where the baseline leaves no mismatch: null-like; with a fit
    # flag (an observable beyond its null level): "unexplained"
    d = decide([_cand("curvature", 25.0, located_rescored=keep, delta_waic=-5.0)], quiet, base, 100.0, th)
    assert d["verdict"] == "no_missing_physics" and "null data" in d["reason"]
    flagged = Thresholds(bf_min=20.0, located_min=8.0, waic_min=6.0, fit_max={"deposit": -30.0})
    d = decide([_cand("curvature", 25.0, located_rescored=keep, delta_waic=-5.0)], quiet, base, 100.0, flagged,
               fit_z={"deposit": -20.0})
    assert d["verdict"] == "unexplained" and "deposit fits at Z_fit -20.0" in d["reason"]


def test_fit_flags_turn_nothing_missing_into_unexplained():
    """An observable whose baseline Z_fit exceeds fit_max is a mismatch at the level of the whole
    observable: with no candidate supported it makes the verdict "unexplained" (rules 2 and 3), it never
    blocks or gives a name, and without fit_max (the default) or a level for that observable it is ignored."""
    base = {"ess": 5.0}
    weak = [_cand("curvature", 15.0)]
    z = {"g1:speed": 0.4, "g1:h": -3.0, "deposit": -36.0}
    th0 = Thresholds(bf_min=20.0, located_min=8.0)
    assert decide(weak, [], base, 100.0, th0, fit_z=z)["verdict"] == "no_missing_physics"
    th = Thresholds(bf_min=20.0, located_min=8.0, fit_max={"g1:speed": -1.5, "g1:h": 2.0})
    d = decide(weak, [], base, 100.0, th, fit_z=z)
    assert d["verdict"] == "unexplained" and d["missing_physics"] is None
    assert d["fit_flags"] == [{"observable": "g1:speed", "Z_fit": 0.4, "fit_max": -1.5}]
    assert "g1:speed fits at Z_fit 0.4 > -1.5" in d["reason"]
    assert decide(weak, [], base, 100.0, th, fit_z={"g1:speed": -2.0, "deposit": 50.0})["verdict"] == \
        "no_missing_physics"                       # below its level; no level for the deposit
    assert decide(weak, [], base, 100.0, Thresholds(bf_min=20.0, fit_max=0.0), fit_z=z)["fit_flags"][0]["observable"] \
        == "g1:speed"                              # one level for every observable
    # rule 2: evidence above bf_min that explains nothing located is "nothing missing" without a flag
    supported = [_cand("curvature", 40.0, misfit_after=150.0, located_rescored={})]
    assert decide(supported, [], base, 100.0, th0, fit_z=z)["verdict"] == "no_missing_physics"
    assert decide(supported, [], base, 100.0, th, fit_z=z)["verdict"] == "unexplained"
    # a term passing every check is still named
    d = decide([_cand("entrainment", 60.0)], [{"standardised_residual": 9.0}], base, 100.0, th, fit_z=z)
    assert d["missing_physics"] == "entrainment" and d["fit_flags"]


def test_fit_max_from_null_is_a_prediction_bound():
    """torchslide.diagnose.null.fit_max_from_null: per observable mean + t-quantile * sd * sqrt(1 + 1/n)
    (Bonferroni over the observables), so fresh null rows from the same distribution raise a flag on
    about 5 % of cases or fewer."""
    from scipy import stats as st
    from torchslide.diagnose.null import fit_max_from_null

    rng = np.random.default_rng(3)
    loc = {"deposit": (-36.0, 1.0), "g1:h": (2.0, 2.0), "g1:speed": (-4.0, 0.8)}
    rows = [{k: m + s * rng.standard_normal() for k, (m, s) in loc.items()} for _ in range(25)]
    fm = fit_max_from_null(rows + [{"only_two": 1.0}, {"only_two": 2.0}])
    assert set(fm) == set(loc)                     # fewer than 3 null values: no level
    v = np.array([r["g1:speed"] for r in rows])
    q = st.t.ppf(1 - 0.05 / 3, 24)
    assert np.isclose(fm["g1:speed"], v.mean() + q * v.std(ddof=1) * np.sqrt(1 + 1 / 25))
    alarms = np.mean([any(m + s * rng.standard_normal() > fm[k] for k, (m, s) in loc.items()) for _ in range(4000)])
    assert 0.005 < alarms < 0.12
    # a shift of the speed fit by 5 null sds is flagged nearly always
    assert np.mean([-4.0 + 4.0 + 0.8 * rng.standard_normal() > fm["g1:speed"] for _ in range(500)]) > 0.95


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
    assert abs(r["items"][0]["after"]) < 3.0 and r["explained_all"] > 0.8


def test_chi2_score_is_a_normal_score_with_finite_tails():
    """localise.chi2_score: chi-square(m) draws give Z ~ N(0, 1); extreme statistics stay finite and ordered."""
    from torchslide.diagnose.localise import chi2_score
    rng = np.random.default_rng(0)
    for m in (1, 45, 600):
        z = np.array([chi2_score(float(c), m)[0] for c in rng.chisquare(m, 4000)])
        assert abs(z.mean()) < 0.06 and 0.95 < z.std() < 1.05, (m, z.mean(), z.std())
    lo, hi = chi2_score(1e-3 * 600, 600), chi2_score(1e6, 600)
    assert np.isfinite(lo[0]) and lo[0] < -30 and lo[1] == 1.0
    assert np.isfinite(hi[0]) and hi[0] > 100 and hi[1] == 0.0
    assert chi2_score(700.0, 600)[0] > chi2_score(650.0, 600)[0] > 0 > chi2_score(550.0, 600)[0]


def test_block_fit_whitens_correlated_errors_and_sees_a_real_offset():
    """localise.block_fit with the likelihood's own covariance: strongly correlated errors (AR(1), rho 0.95,
    the grid error's kind) give Z_fit ~ N(0, 1), where the per-value chi-square Z_block (diagonal
    variances) is far too spread; a local offset the covariance does not expect gives Z_fit >> 3."""
    from torchslide.diagnose.localise import block_fit
    rng = np.random.default_rng(1)
    m, rho = 45, 0.95
    idx = np.arange(m)
    cov = 0.5**2 * rho ** np.abs(idx[:, None] - idx[None, :])
    L = np.linalg.cholesky(cov)
    z_fit, z_diag = [], []
    for _ in range(2000):
        r = L @ rng.standard_normal(m)
        z_fit.append(block_fit(r, cov)["Z_fit"])
        z_diag.append((np.sum((r / 0.5) ** 2) - m) / np.sqrt(2 * m))
    z_fit, z_diag = np.array(z_fit), np.array(z_diag)
    assert abs(z_fit.mean()) < 0.08 and 0.9 < z_fit.std() < 1.1
    assert z_diag.std() > 3 * z_fit.std()
    bump = 2.5 * np.exp(-((idx - 20) / 3.0) ** 2)
    assert block_fit(L @ rng.standard_normal(m) + bump, cov)["Z_fit"] > 3
    # the draws' covariance widens the reference: the same offset with parameter spread scores lower
    draws = rng.standard_normal((16, 1)) * bump[None, :]
    r = bump.copy()
    assert block_fit(r, cov, draws)["Z_fit"] < block_fit(r, cov)["Z_fit"]


def test_subset_consistency_flags_the_observation_that_wants_other_parameters():
    """consistency.subset_consistency on a linear-Gaussian model: with consistent data T_b follows
    chi2(df) (mean df, ~1 % flagged at alpha 0.01 before Bonferroni); when one observation is made
    with other parameters it is flagged, and it alone wants those parameters while the rest wants the
    truth; a scalar observation (rank 1 of p = 2) has df 1 and no 'wants'."""
    from types import SimpleNamespace as NS
    from torchslide.diagnose.consistency import subset_consistency

    rng = np.random.default_rng(0)
    blocks = [NS(name="deposit", slice=slice(0, 30)), NS(name="g1", slice=slice(30, 50)), NS(name="volume", slice=slice(50, 51))]
    A = rng.standard_normal((51, 2))
    x_true, x0 = np.array([0.2, 500.0]), np.array([0.2, 500.0])
    scale = np.array([0.01, 20.0])                      # whitened sensitivity per unit of mu, xi
    J = A / scale                                        # d y / d x, whitened
    Ts, flagged = {b.name: [] for b in blocks}, 0
    for s in range(400):
        r = rng.standard_normal(51)                      # data = truth + noise, linearised at the truth
        out = {e["block"]: e for e in subset_consistency(blocks, J, r, ["mu", "xi"], x0)}
        for n in Ts:
            Ts[n].append(out[n]["statistic"])
        flagged += sum(e["conflict"] for e in out.values())
    assert abs(np.mean(Ts["deposit"]) - 2) < 0.35 and abs(np.mean(Ts["volume"]) - 1) < 0.25
    assert flagged <= 12                                 # 1200 tests at 0.01 / 3
    assert out["volume"]["df"] == 1 and out["volume"]["wants"] is None and out["deposit"]["df"] == 2
    # the gauge made with mu 0.23, xi 420: flagged, and each side wants its own parameters
    x_g = np.array([0.23, 420.0])
    r = 0.05 * rng.standard_normal(51)
    r[30:50] += J[30:50] @ (x_g - x0)
    res = subset_consistency(blocks, J, r, ["mu", "xi"], x0)
    assert res[0]["block"] == "g1" and res[0]["conflict"] and res[0]["p_value"] < 1e-6
    assert abs(res[0]["wants"]["mu"] - 0.23) < 0.002 and abs(res[0]["wants"]["xi"] - 420) < 5
    assert abs(res[0]["rest_wants"]["mu"] - 0.2) < 0.002
    with pytest.raises(ValueError, match="do not match"):
        subset_consistency(blocks, J[:, :1], r, ["mu", "xi"], x0)


def test_local_path_checks_reliability_and_the_likelihood_ratio():
    """A local-path candidate is named only when both local fits are reliable and its likelihood ratio
    reaches lr_alpha; the emulator's ESS check does not apply to it."""
    from torchslide.diagnose.decide import Thresholds, decide

    from .conftest import cand

    base = {"log_evidence": 0.0, "reliable": True}
    th = Thresholds(bf_min=6.0)
    ok = cand("entrainment", 40.0, ess=None, reliable=True, lr_pvalue=1e-8)
    d = decide([ok], [], base, 100.0, th)
    assert d["verdict"] == "missing_physics" and d["checks"]["entrainment"]["likelihood_ratio"]
    d = decide([dict(ok, lr_pvalue=0.2)], [], base, 100.0, th)
    assert d["missing_physics"] is None and not d["checks"]["entrainment"]["likelihood_ratio"]
    d = decide([dict(ok, reliable=False)], [], base, 100.0, th)
    assert d["missing_physics"] is None and not d["checks"]["entrainment"]["reliable"]
    d = decide([ok], [], dict(base, reliable=False), 100.0, th)
    assert d["missing_physics"] is None


def test_separation_names_the_data_where_the_alternatives_differ():
    """pipeline.separation: per value |mean_A - mean_B| / sigma, largest first, and per block the root sum
    of squares: the data that would tell two unseparated candidates apart."""
    from types import SimpleNamespace as NS

    from torchslide.diagnose.pipeline import separation

    ev = NS(sigma=np.array([1.0, 2.0, 0.5, 1.0]), observation_names=["v", "g:h[0]", "g:h[1]", "vol"],
            blocks=[NS(name="v", slice=slice(0, 1)), NS(name="g:h", slice=slice(1, 3)), NS(name="vol", slice=slice(3, 4))])
    pred = lambda m: NS(pred=NS(mean=np.array(m, float), draws=np.zeros((3, 4))))
    refits = {"A": pred([1.0, 4.0, 1.0, 5.0]), "B": pred([1.5, 0.0, 1.0, 5.0])}
    s = separation(ev, refits, ["A", "B"], top=2)
    assert s["alternatives"] == ["A", "B"]
    assert s["values"] == [{"observation": "g:h[0]", "difference_sigma": 2.0}, {"observation": "v", "difference_sigma": 0.5}]
    assert s["blocks"][0] == {"block": "g:h", "difference_sigma_rss": 2.0}
    assert separation(ev, {"A": refits["A"]}, ["A", "B"]) == {}


def test_a_candidate_at_the_end_of_an_open_range_is_not_named():
    """A release_volume fit whose interval reaches +50 % (the end of its range, a budget, not a limit): the
    data want more than the range allows, so it is not named even when it passes every other check; the
    report says so. pipeline.at_range_end reads it from the switch's interval."""
    from torchslide.diagnose.pipeline import at_range_end
    from torchslide.diagnose.report import _verdict_section

    th = Thresholds(bf_min=20.0, located_min=8.0, waic_min=6.0, margin_min=6.0)
    loc = [{"standardised_residual": 14.0}]
    edge = {"release_scale": {"mean": 0.5, "hdr90": [0.4994, 0.5]}}
    assert at_range_end("release_volume", edge) and not at_range_end("release_volume", {"release_scale": {"hdr90": [0.2, 0.3]}})
    assert not at_range_end("earth_pressure", {"earth_pressure": {"hdr90": [0.9, 1.0]}})   # a limit of the term
    c = _cand("release_volume", 228.0, at_range_end=True, parameters=edge, param="release_scale")
    d = decide([c, _cand("entrainment", -12.0)], loc, {"ess": 5.0}, 100.0, th)
    assert d["verdict"] == "unexplained" and d["missing_physics"] is None
    assert d["checks"]["release_volume"]["within_range"] is False and "within_range" in d["reason"]
    j = {"verdict": d["verdict"], "missing_physics": None, "decision": d, "candidates": [c]}
    assert any("the data want more than the range allows" in line for line in _verdict_section(j))
    ok = _cand("release_volume", 228.0, at_range_end=False)
    assert decide([ok], loc, {"ess": 5.0}, 100.0, th)["missing_physics"] == "release_volume"


def test_a_term_at_the_end_of_its_budget_is_set_aside_for_one_that_fits_within_its_range():
    """mu(I)'s 90 % interval [0.358, 0.4] reaches the end of its range: set aside. With less evidence than
    yield stress the yield stress is named; with more (2 ln BF 30.9 against 18.5: a yield stress mimicked by
    mu(I) beyond its budget, or mu(I) at its budget's end mimicked by a yield stress, as on the narrow
    channel's mu(I) at twice its nominal value) the data do not tell them apart: "yield_stress or mu_i"."""
    from torchslide.diagnose.pipeline import at_range_end

    th = Thresholds(bf_min=9.2, located_min=8.0, waic_min=6.0, margin_min=6.0)
    mu_i = {"mu_i": {"mean": 0.38, "hdr90": [0.358, 0.4]}}
    assert at_range_end("mu_i", mu_i) and at_range_end("yield_stress", {"tau_y": {"hdr90": [18.0, 20.0]}})
    assert not at_range_end("mu_i", {"mu_i": {"hdr90": [0.15, 0.25]}})
    cands = [_cand("mu_i", 30.9, at_range_end=True, parameters=mu_i, param="mu_i"), _cand("yield_stress", 18.5)]
    d = decide(cands, [], {"ess": 5.0}, 100.0, th)
    assert d["missing_physics"] == "yield_stress or mu_i" and d["ambiguous"] and d["set_aside"] == ["mu_i"]
    assert "set aside at the end of its range, has more evidence" in d["reason"]
    d = decide([_cand("mu_i", 16.0, at_range_end=True, parameters=mu_i, param="mu_i"), cands[1]], [], {"ess": 5.0},
               100.0, th)
    assert d["missing_physics"] == "yield_stress" and d["set_aside"] == ["mu_i"] and "set aside" in d["reason"]
    # with nothing else left the set-aside term is still not named
    d = decide(cands[:1], [{"standardised_residual": 9.0}], {"ess": 5.0}, 100.0, th)
    assert d["missing_physics"] is None and "set_aside" not in d and "set aside" not in d["reason"]
