"""Thresholds set on null simulations of the user's own design (torchslide.diagnose.null)."""
from __future__ import annotations

import math

import numpy as np
import pytest

from torchslide.bayes import Prior, Uniform
from torchslide.diagnose import Budgets, DiagnosisEvaluator, Thresholds, diagnose
from torchslide.diagnose.model_error import fine_predictions
from torchslide.diagnose.null import (fit_max_from_null, null_calibration, null_recordings, thresholds_from_null,
                                      with_data)
from torchslide.observe import Observation
from torchslide.observe_series import SeriesObservation
from torchslide.physics import Params
from torchslide.solver import SolverConfig, simulate
from torchslide.terrain.synthetic import inclined_plane, release_from_shape

V = 2.0e4


def _evaluator():
    """A 40 m inclined plane; data: a run at mu 0.3, xi 600 (deposit map, one gauge's h, final volume)."""
    dem = inclined_plane(30.0, 40.0, slope_length=600.0, runout_length=600.0, width=320.0, transition=200.0)
    rel = release_from_shape(dem, (150.0, 160.0), 60.0, volume=V)
    t = np.arange(2.0, 40.0, 2.0)
    res = simulate(dem, rel, Params.make(mu=0.3, xi=600.0), t_end=40.0, gauges=[("g1", 700.0, 160.0)],
                   config=SolverConfig())
    g = res.gauges["g1"]
    obs = [SeriesObservation.from_array("deposit_map", res.h_final[0].numpy(), dem, 0.5, name="deposit",
                                        corr_length=40.0),
           SeriesObservation("gauge_series", np.interp(t, g.t.numpy(), g.h[0].numpy()), 0.5, name="g1:h", gauge="g1",
                             quantity="h", times=t),
           Observation("final_volume", V, 0.05 * V, name="final_volume")]
    return DiagnosisEvaluator(dem=dem, release=rel, observations=obs, t_end=40.0, gauges=[("g1", 700.0, 160.0)],
                              prior=Prior({"mu": Uniform(0.2, 0.45), "xi": Uniform(200.0, 1500.0)}),
                              solver_config=SolverConfig())


def _tiny(**kw):
    return Budgets(**{**dict(inference="emulator", baseline_n_initial=4, baseline_n_total=6, baseline_grid_size=40,
                             model_error_runs=0,
                             batch_size=8, n_initial=4, n_total=6, n_total_max=6, n_posterior_samples=6,
                             n_posterior_samples_after=4, top_k=1, n_perm=9, profile_top=0, mcmc_steps=200), **kw})


def test_null_recordings_are_finer_grid_runs_plus_the_stated_noise():
    """d = y_fine(theta; V (1 + delta)) + e: without noise the finer-grid run itself, its volume scaled by
    the release factor (mass conservation); the noise that of the stated error model (sigma 0.5 m per cell, not
    the likelihood's wider sigma_eff)."""
    ev = _evaluator()
    theta = np.array([[0.3, 600.0], [0.34, 900.0]])
    y, _ = fine_predictions(ev, theta, 2)
    d0, vf0 = null_recordings(ev, theta, 2, release_sd=0.0, seed=1, noise=False)
    assert np.array_equal(vf0, [1.0, 1.0]) and np.allclose(d0, y)
    d1, vf1 = null_recordings(ev, theta, 2, release_sd=0.05, seed=1, noise=False)
    a = math.sqrt(3) * 0.05
    assert np.all(np.abs(vf1 - 1) <= a) and np.all(vf1 != 1.0)
    fv = ev.block("final_volume").slice
    Vs = float((np.asarray(ev.release) * ev.dem.surface_area()).sum())       # normal thickness x surface area
    assert np.allclose(d1[:, fv].ravel(), vf1 * Vs, rtol=1e-3)                 # the release volume scaled
    # with the user's fine terrain, its release is scaled too
    from torchslide.diagnose.model_error import FineTerrain, refine_dem, repeat_cells
    ev_ft = ev._copy(fine_terrain=FineTerrain(refine_dem(ev.dem, 2), repeat_cells(ev.release, 2)))
    d2, vf2 = null_recordings(ev_ft, theta, 2, release_sd=0.05, seed=1, noise=False)
    assert np.array_equal(vf2, vf1) and np.allclose(d2[:, fv].ravel(), vf1 * Vs, rtol=1e-3)
    d, _ = null_recordings(ev, theta, 2, release_sd=0.0, seed=2)
    e = d - y
    dep = ev.block("deposit").obs
    assert dep.sigma_eff()[0] > 2 * 0.5                                       # the likelihood's stand-in is wider
    v = e[:, ev.block("deposit").slice].var()
    assert 0.25 * 0.6 < v < 0.25 * 1.6                                        # the stated sigma 0.5, not sigma_eff
    assert abs(e[:, fv].std() / (0.05 * V)) < 4
    # recording i comes from its own stream: the first of two equals the recording made alone
    assert np.allclose(null_recordings(ev, theta[:1], 2, release_sd=0.05, seed=2)[0][0],
                       null_recordings(ev, theta, 2, release_sd=0.05, seed=2)[0][0])
    assert np.allclose(null_recordings(ev, theta[1:], 2, release_sd=0.05, seed=2, start=1)[0][0],
                       null_recordings(ev, theta, 2, release_sd=0.05, seed=2)[0][1])
    assert not np.allclose(null_recordings(ev, theta, 2, seed=3)[0], d)      # another seed, other noise
    with pytest.raises(ValueError, match="release_volume_sd"):
        null_recordings(ev, theta, 2, release_sd=0.6)


def test_with_data_replaces_every_observation_in_the_flat_order():
    ev = _evaluator()
    old = ev.data.copy()
    new = ev.data + np.arange(ev.k)
    ev2 = with_data(ev, new)
    assert np.array_equal(ev2.data, new) and ev2.k == ev.k and ev2.records == []
    assert [b.name for b in ev2.blocks] == [b.name for b in ev.blocks] and np.array_equal(ev.data, old)   # a copy
    with pytest.raises(ValueError, match="data has 3 values"):
        with_data(ev, np.zeros(3))


def test_threshold_rule_from_null_statistics():
    th = thresholds_from_null({"bf": [3.0, 10.0, -2.0], "located": [4.0, 12.0, 5.0]})
    assert th["bf_min"] == 12.5 and th["located_min"] == 15.0 and "fit_max" not in th
    assert thresholds_from_null({"bf": [1.0], "located": [2.0]})["bf_min"] == 6.0     # floors 6 and 8
    rows = [{"a": 0.0, "b": 1.0}, {"a": 1.0, "b": None}, {"a": 2.0, "b": 2.0}, {"a": 3.0}]
    fm = fit_max_from_null(rows)
    from scipy import stats as st
    v = np.array([0.0, 1.0, 2.0, 3.0])
    assert set(fm) == {"a"}             # b: 2 finite values, below the 3 needed
    assert math.isclose(fm["a"], v.mean() + st.t.ppf(1 - 0.05, 3) * v.std(ddof=1) * math.sqrt(1.25))


def test_null_calibration_sets_thresholds_resumes_and_redecides(tmp_path, monkeypatch):
    """The whole path on a tiny design: a diagnosis of the data, 3 null recordings diagnosed like it, the
    thresholds by the rule from their statistics, the data's verdict decided again with them (equal to a run
    with those thresholds); a second call reuses the finished null cases."""
    from torchslide.diagnose import pipeline

    ev = _evaluator()
    bud = _tiny()
    th0 = Thresholds(bf_min=6.0, located_min=8.0, waic_min=5.0)
    d = diagnose(ev, ["mu_i"], bud, th0, log=lambda s: None, workdir=tmp_path / "data")
    seen, run = [], pipeline.diagnose
    monkeypatch.setattr(pipeline, "diagnose",
                        lambda ev, c, b, *a, **k: seen.append(b.detectability) or run(ev, c, b, *a, **k))
    nc = null_calibration(ev, ["mu_i"], bud, th0, d.predictive.x, 3, tmp_path / "null", log=lambda s: None)
    assert seen == ["linearised"] * 3            # the null cases' detectable switches are not used
    cases = nc["cases"]
    assert nc["n"] == 3 and len(cases) == 3 and len({tuple(c["theta"]) for c in cases}) == 3
    pool = {tuple(x) for x in d.predictive.x.tolist()}
    assert all(tuple(c["theta"]) in pool for c in cases)       # drawn from the verdict's posterior draws
    assert sorted(p.name for p in (tmp_path / "null").glob("null_*.json")) == ["null_0.json", "null_1.json", "null_2.json"]
    th = nc["thresholds"]
    assert th.bf_min == max(6.0, 1.25 * max(c["max_two_ln_bf_lower"] for c in cases))
    assert th.located_min == max(8.0, 1.25 * max(c["max_located"] for c in cases))
    assert th.fit_max == fit_max_from_null([c["fit_z"] for c in cases]) and set(th.fit_max) == {"deposit", "g1:h"}
    assert th.waic_min == 5.0                                   # the thresholds not set on null data are kept
    assert all(set(c["lower_by_candidate"]) == {"mu_i"} and c["lower_by_candidate"]["mu_i"] == c["max_two_ln_bf_lower"]
               for c in cases)                                  # every refitted candidate's value is kept
    # resumed: the finished cases are read back, no diagnosis runs
    monkeypatch.setattr(pipeline, "diagnose", lambda *a, **k: pytest.fail("a finished null case was re-run"))
    again = null_calibration(ev, ["mu_i"], bud, th0, d.predictive.x, 3, tmp_path / "null", log=lambda s: None)
    assert again["cases"] == cases and again["thresholds"] == th
    fewer = null_calibration(ev, ["mu_i"], bud, th0, d.predictive.x, 2, tmp_path / "null", log=lambda s: None)
    assert fewer["cases"] == cases[:2]                          # a smaller n: the first runs of the larger one
    import json
    f1 = tmp_path / "null" / "null_1.json"
    old = json.loads(f1.read_text())
    f1.write_text(json.dumps({k: v for k, v in old.items() if k != "noise_model"}))    # a case made with another noise model

    def rerun(*a, **k):
        raise RuntimeError("re-run")
    monkeypatch.setattr(pipeline, "diagnose", rerun)
    with pytest.raises(RuntimeError, match="re-run"):
        null_calibration(ev, ["mu_i"], bud, th0, d.predictive.x, 3, tmp_path / "null", log=lambda s: None)
    monkeypatch.undo()
    # the data decided again with them equals a run with them
    before = (d.verdict, d.missing_physics)
    d.redecide(th, "set on 3 null simulations")
    ref = diagnose(ev, ["mu_i"], bud, th, log=lambda s: None, workdir=tmp_path / "ref")
    assert (d.verdict, d.missing_physics, d.decision["reason"]) == (ref.verdict, ref.missing_physics, ref.decision["reason"])
    assert d.decision["decision_before"]["verdict"] == before[0] and d.decision["fit_z"] == ref.decision["fit_z"]
    assert d.decision["thresholds_source"] == "set on 3 null simulations" and d.thresholds == th
    with pytest.raises(ValueError, match="null runs must be >= 1"):
        null_calibration(ev, ["mu_i"], bud, th0, d.predictive.x, 0, tmp_path / "null")
    with pytest.raises(ValueError, match="posterior draws"):
        null_calibration(ev, ["mu_i"], bud, th0, np.zeros((0, 2)), 2, tmp_path / "null")


def test_a_null_cases_checkpoints_are_kept_only_for_the_same_recording(tmp_path):
    """The active-learning checkpoints in case_<i>/ do not know their data: they are reused when the recording,
    candidates and budgets are the same (an interrupted case resumes) and cleared otherwise."""
    from torchslide.diagnose.null import _case_workdir

    p = tmp_path / "case_0"
    p.mkdir()
    (p / "refit_mu_i.pt").write_text("made on another recording")
    a, b = np.arange(5.0), np.arange(5.0) + 1e-9
    assert _case_workdir(p, a, ["mu_i"], _tiny()) == p and not (p / "refit_mu_i.pt").exists()   # unknown: cleared
    (p / "refit_mu_i.pt").write_text("this recording's")
    _case_workdir(p, a.copy(), ["mu_i"], _tiny())
    assert (p / "refit_mu_i.pt").exists()                                  # the same: resumed
    for other in ((b, ["mu_i"], _tiny()), (a, ["mu_i", "curvature"], _tiny()), (a, ["mu_i"], _tiny(n_total=7))):
        _case_workdir(p, a, ["mu_i"], _tiny())
        (p / "refit_mu_i.pt").write_text("this recording's")
        _case_workdir(p, *other)
        assert not (p / "refit_mu_i.pt").exists()


def test_report_says_which_release_error_the_null_runs_carry():
    from torchslide.diagnose.report import _null_section

    nc = {"n": 1, "rule": "r", "thresholds": {"bf_min": 6.0, "located_min": 8.0, "fit_max": None},
          "cases": [{"max_two_ln_bf_lower": 1.0, "max_located": 2.0, "verdict": "no_missing_physics",
                     "missing_physics": None}]}
    exact = "\n".join(_null_section(dict(nc, release_volume_sd=0.0)))
    assert "the release volume as given (release_volume_sd 0: an error in it is not in these runs)" in exact
    assert "an error not stated" in exact and "| 0 | 1.0 | - | 2.0 | no_missing_physics |" in exact
    assert "the release volume's error (relative sd 0.0577)" in "\n".join(_null_section(dict(nc, release_volume_sd=0.0577)))
    # which terrain the finer runs used
    assert "over the finer DEM given as fine_terrain," in "\n".join(_null_section(dict(nc, terrain="fine_terrain")))
    assert "interpolated bilinearly (no fine_terrain given" in "\n".join(_null_section(dict(nc, terrain="interpolated")))
    assert "finer grid, the release volume as given" in exact      # a null calibration without the field


def test_report_says_how_often_each_candidate_is_best_on_null_runs():
    """report._null_section: each null case's best candidate, how often each candidate came out best on the
    null runs (with its largest value there), and whether the data's best candidate is one of them; null
    cases without the per-candidate values give no such lines."""
    from torchslide.diagnose.report import _null_section

    def case(by):
        return {"max_two_ln_bf_lower": max(by.values()), "max_located": 3.0, "verdict": "no_missing_physics",
                "missing_physics": None, "lower_by_candidate": by}

    nc = {"n": 3, "rule": "r", "thresholds": {"bf_min": 17.0, "located_min": 8.0, "fit_max": None},
          "cases": [case({"curvature": 13.6, "mu_i": 2.0}), case({"curvature": 4.0, "entrainment": 9.0}),
                    case({"curvature": 6.0, "mu_i": -1.0})]}
    data = [{"name": "curvature", "two_ln_bf_lower": 14.8}, {"name": "mu_i", "two_ln_bf_lower": -4.1},
            {"name": "yield_stress", "two_ln_bf_lower": None}]
    text = "\n".join(_null_section(nc, data))
    assert "| 0 | 13.6 | curvature | 3.0 | no_missing_physics |" in text
    assert "| 1 | 9.0 | entrainment | 3.0 | no_missing_physics |" in text
    assert ("nothing is missing there): curvature in 2 of 3 (up to 13.6), entrainment in 1 of 3 (up to 9.0).") in text
    assert ("On these data the best candidate is curvature (lower-bound 2 ln BF 14.8); on the null runs it was the "
            "best in 2 of 3: coming out best is, on its own, no sign of it here") in text
    other = [{"name": "yield_stress", "two_ln_bf_lower": 30.0}]
    assert ("best candidate is yield_stress (lower-bound 2 ln BF 30.0); on the null runs it was the best in 0 of 3."
            in "\n".join(_null_section(nc, other)))
    old = dict(nc, cases=[{k: v for k, v in c.items() if k != "lower_by_candidate"} for c in nc["cases"]])
    text = "\n".join(_null_section(old, data))
    assert "| 0 | 13.6 | - | 3.0 |" in text and "Best candidate on the null runs" not in text
