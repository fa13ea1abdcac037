"""The finer-grid check (torchslide.diagnose.finer, decide(finer=...), Budgets.finer_check)."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from torchslide.diagnose import Budgets, Thresholds
from torchslide.diagnose.decide import decide, finer_pair
from torchslide.diagnose.finer import compare, finer_grid_evaluator, finer_profile, profile_starts
from torchslide.diagnose.refit import candidate_evaluator

from .test_diagnose import _cand
from .test_model_error import _evaluator

TH = Thresholds(bf_min=20.0, located_min=8.0, waic_min=6.0, margin_min=6.0)
BASE = {"ess": 5.0}
LOC = [{"standardised_residual": 9.0}]


def test_decide_takes_the_pairs_order_from_the_finer_grid():
    """mu_i 25 ahead of yield stress in 2 ln BF (as in resolved 20 m yield-stress seeds 0 and 1): without
    the check mu_i is named; with yield stress 10 ahead in ln profile on the finer grid, yield stress;
    with the two within margin_min there, neither; the reason says which."""
    cands = [_cand("mu_i", 60.0), _cand("yield_stress", 35.0), _cand("curvature", 5.0, two_ln_bf_lower=3.0)]
    assert finer_pair(cands, BASE, 100.0, TH) == ["mu_i", "yield_stress"]
    assert decide(cands, LOC, BASE, 100.0, TH)["missing_physics"] == "mu_i"
    d = decide(cands, LOC, BASE, 100.0, TH, finer={"mu_i": -20.0, "yield_stress": -10.0})
    assert d["verdict"] == "missing_physics" and d["missing_physics"] == "yield_stress" and d["runner_up"] == "mu_i"
    fc = d["finer_check"]
    assert fc["applied"] and fc["leader"] == "yield_stress" and fc["two_ln_ratio"] == pytest.approx(20.0)
    assert "finer-grid check: yield_stress ahead of mu_i by 2 ln profile ratio 20.0" in d["reason"]
    assert "against mu_i ahead by 2 ln BF 25.0" in d["reason"] and "bf_pair" not in d
    # the finer grid confirms the Bayes factors' order: unchanged name
    assert decide(cands, LOC, BASE, 100.0, TH, finer={"mu_i": -5.0, "yield_stress": -10.0})["missing_physics"] == "mu_i"
    # within margin_min on the finer grid: the pair is not separated, no name (whatever the Bayes factors)
    d = decide(cands, LOC, BASE, 100.0, TH, finer={"mu_i": -10.0, "yield_stress": -9.0})
    assert d["verdict"] == "unexplained" and d["ambiguous"] and d["competitors"] == ["mu_i"]
    assert "within 2 ln profile ratio (finer grid) 6.0" in d["reason"]
    # a pair member without a profile: not applied, said so, the Bayes factors decide
    d = decide(cands, LOC, BASE, 100.0, TH, finer={"yield_stress": -10.0})
    assert d["missing_physics"] == "mu_i" and not d["finer_check"]["applied"]
    assert "finer-grid check not applied: no finer-grid profile of ['mu_i']" in d["reason"]
    # one candidate passes the evidence check: nothing to compare; a profile of a weak third is ignored
    weak = [_cand("mu_i", 60.0), _cand("yield_stress", 20.0, two_ln_bf_lower=18.0)]
    assert finer_pair(weak, BASE, 100.0, TH) is None
    d = decide(weak, LOC, BASE, 100.0, TH, finer={"mu_i": -20.0, "yield_stress": -10.0})
    assert d["missing_physics"] == "mu_i" and not d["finer_check"]["applied"]


def test_finer_pair_needs_one_that_could_be_named():
    """Two pass the evidence check but neither passes every check (here their Savage-Dickey signs):
    no order between them can change the verdict, so no pair (and no finer-grid runs)."""
    both_fail = [_cand("earth_pressure", 40.0, two_ln_bf_savage_dickey=-1.0),
                 _cand("yield_stress", 36.0, two_ln_bf_savage_dickey=-2.0)]
    assert finer_pair(both_fail, BASE, 100.0, TH) is None
    one_ok = [both_fail[0], _cand("yield_stress", 36.0)]
    assert finer_pair(one_ok, BASE, 100.0, TH) == ["earth_pressure", "yield_stress"]
    # the finer grid puts the one that passes every check first, 8 ahead: it is named
    d = decide(one_ok, LOC, BASE, 100.0, TH, finer={"earth_pressure": -14.0, "yield_stress": -10.0})
    assert d["missing_physics"] == "yield_stress"
    assert compare({"a": 1.0, "b": 3.5}, ("a", "b")) == {"pair": ["a", "b"], "z_max": {"a": 1.0, "b": 3.5},
                                                          "leader": "b", "two_ln_ratio": 5.0}


def test_finer_profile_runs_on_the_finer_grid():
    """finer_profile: the profile along the switch with every run on cells half as large; its maximum is
    the finer-grid evaluator's z at the profile's optimum, and differs from the inversion grid's there."""
    ev_c = candidate_evaluator(_evaluator(), "yield_stress")
    names = list(ev_c.prior.names)
    assert names[-1] == "tau_y"
    par = {"mu": {"mean": 0.3, "hdr90": [0.28, 0.32]}, "xi": {"mean": 600.0, "hdr90": [500.0, 700.0]},
           "tau_y": {"mean": 1.0, "hdr90": [0.5, 1.5]}}
    b = ev_c.prior.bounds.numpy()
    s = profile_starts(par, names, b, n=32, seed=0)
    assert s.shape == (32, 3) and (s >= b[0]).all() and (s <= b[1]).all()
    assert np.array_equal(s, profile_starts(par, names, b, n=32, seed=0))
    with pytest.raises(ValueError, match=r"lack mean / hdr90 for \['tau_y'\]"):
        profile_starts({"mu": par["mu"], "xi": par["xi"]}, names, b)
    with pytest.raises(ValueError, match="factor must be an integer >= 2, got 1"):
        finer_grid_evaluator(ev_c, 1)
    p = finer_profile(ev_c, par, factor=2, seed=0, n_values=3, n_iter=1, pop=2)
    assert len(p["switch"]) == len(p["z"]) >= 3 and np.isfinite(p["z_max"]) and p["runs"] > 0
    assert p["z_max"] == max(p["z"]) and p["best"] == p["switch"][int(np.argmax(p["z"]))]
    # the profile's optimum re-run: the finer-grid evaluator gives its z, the inversion grid another
    from torchslide.diagnose.profile import switch_profile
    r = switch_profile(finer_grid_evaluator(ev_c), s, par["tau_y"]["hdr90"], b, n_values=3, n_iter=1, pop=2,
                       min_half=0.02, seed=0)
    x = torch.as_tensor(r["x"][int(np.argmax(r["z"]))][None])
    z_fine = float(finer_grid_evaluator(ev_c).evaluate(x)[0].z[0])
    assert z_fine == pytest.approx(p["z_max"], abs=1e-9)
    assert abs(float(ev_c.evaluate(x)[0].z[0]) - z_fine) > 1e-6


def test_diagnose_runs_the_finer_grid_check_without_the_model_error(tmp_path, monkeypatch):
    """Budgets.finer_check: the pipeline profiles the pair on the finer grid, each with its refit's
    evaluator stripped of the grid's model error (the finer runs are what it stands for), and the
    decision keeps the profiles (report.md shows them); off by default."""
    import torchslide.diagnose.pipeline as pl
    from torchslide.diagnose import diagnose
    from torchslide.diagnose.report import _finer_check_lines

    assert Budgets().finer_check is False
    seen = []
    real = pl.finer_profile

    def spy(ev_c, par, **kw):
        seen.append((ev_c.prior.names[-1], ev_c.model_error))
        return real(ev_c, par, **{**kw, "n_values": 3, "n_iter": 1, "pop": 2})
    monkeypatch.setattr(pl, "finer_profile", spy)
    monkeypatch.setattr(pl, "finer_pair", lambda cands, *a: [c["name"] for c in cands[:2]])
    bud = Budgets(n_posterior_samples=4, n_posterior_samples_after=4, n_initial=4, n_total=6, n_total_max=6,
                  baseline_n_initial=4, baseline_n_total=6, baseline_refine_rounds=0, refit_refine_rounds=0,
                  top_k=2, n_perm=9, model_error_runs=2, mode_search_iters=0, profile_top=0, slice_check=False,
                  baseline_mode_check=False, batch_size=4, baseline_grid_size=30, finer_check=True)
    d = diagnose(_evaluator(), ["yield_stress", "mu_i"], bud, Thresholds(), log=lambda m: None, workdir=tmp_path)
    assert sorted(n for n, _ in seen) == ["mu_i", "tau_y"] and all(me is None for _, me in seen)
    fp = d.decision["finer_profiles"]
    assert set(fp) == {"yield_stress", "mu_i"} and all(np.isfinite(p["z_max"]) for p in fp.values())
    assert "finer_check" in d.decision and "finer_s" in d.timings
    j = d.to_json()
    assert set(j["decision"]["finer_profiles"]) == {"yield_stress", "mu_i"}
    # re-deciding (e.g. with thresholds from null runs) keeps the profiles and applies them again
    d.redecide(Thresholds(bf_min=-1e9, waic_min=-1e9, explain_min=0.0, ess_min=1.0), "test")
    assert d.decision["finer_profiles"] == fp and "finer_check" in d.decision
    lines = "\n".join(_finer_check_lines(d.decision))
    assert "## Finer-grid check" in lines
    fc = {"applied": True, "pair": ["mu_i", "yield_stress"], "leader": "yield_stress", "two_ln_ratio": 18.4,
          "z_max": {"mu_i": -20.0, "yield_stress": -10.8}}
    md = "\n".join(_finer_check_lines({"finer_check": fc, "finer_profiles": fp}))
    assert "yield_stress leads by 2 ln profile ratio 18.4" in md and "| mu_i | -20.00 |" in md


def test_cli_finer_check_key(tmp_path):
    from torchslide.commands.diagnose import budgets_and_thresholds, load_diagnose_config
    from torchslide.config import ConfigError
    from torchslide.terrain.synthetic import inclined_plane

    from .test_diagnose import _setup

    dem = inclined_plane(30.0, 50.0, slope_length=500.0, runout_length=700.0, width=300.0)
    p, _ = _setup(tmp_path, grid=dem.shape, candidates='["entrainment"]\nfiner_check = true')
    assert budgets_and_thresholds(load_diagnose_config(p))[0].finer_check is True
    q, _ = _setup(tmp_path, grid=dem.shape, candidates='["entrainment"]')
    assert budgets_and_thresholds(load_diagnose_config(q))[0].finer_check is False
    r, _ = _setup(tmp_path, grid=dem.shape, candidates='["entrainment"]\nfiner_check = 1')
    with pytest.raises(ConfigError, match="finer_check must be true or false, got 1"):
        load_diagnose_config(r)


def _saved_case(tmp_path, scenario, seed, cands, covered=True):
    """A saved harness case (the keys finer_check.py and the page read) decided without the check."""
    import json
    from dataclasses import asdict

    th = Thresholds(bf_min=20.0, located_min=8.0)
    d = decide(cands, LOC, BASE, 100.0, th)
    term = {"null": None, "low_friction_patch": "outside"}.get(scenario, scenario)
    case = {"scenario": scenario, "seed": seed, "terrain": "resolved", "cellsize": 20.0, "truth": {"term": term},
            "true_term_covered_hdr90": covered,
            "diagnosis": {"verdict": d["verdict"], "missing_physics": d["missing_physics"], "candidates": cands,
                          "located": LOC, "decision": dict(d, baseline_verification=BASE),
                          "fit_before": {"misfit": 100.0}, "fit_after": {"misfit": 50.0}, "thresholds": asdict(th)}}
    (tmp_path / f"{scenario}_s{seed}.json").write_text(json.dumps(case))


def _profile_row(case, cand, z):
    return {"terrain": "resolved", "cellsize": 20.0, "case": case, "candidate": cand,
            "profiles": {"finer_grid": {"switch": [0.0, 1.0, 2.0], "z": [z - 3.0, z, z - 1.0]}}}


def test_finer_check_script_redecides_saved_cases_and_the_page_shows_them(tmp_path):
    """finer_check.py: a yield-stress case that the Bayes factors gave to mu_i is named yield stress after
    the check (strict with the finer margin only); a case whose profiles are missing stays as it was
    and is listed; a null case without a pair is untouched; the saved cases are not changed."""
    import json

    from experiments.hidden_physics.finer_check import main
    from experiments.hidden_physics.make_page import _finer_check_section

    res = tmp_path / "results"
    res.mkdir()
    _saved_case(res, "yield_stress", 0, [_cand("mu_i", 60.0), _cand("yield_stress", 35.0)])
    _saved_case(res, "yield_stress", 1, [_cand("yield_stress", 60.0), _cand("mu_i", 50.0)])
    _saved_case(res, "null", 0, [_cand("curvature", 10.0, two_ln_bf_lower=8.0)])
    before = {p.name: p.read_text() for p in res.iterdir()}
    prof = tmp_path / "profiles.json"
    prof.write_text(json.dumps([_profile_row("yield_stress_s0", "mu_i", -20.0),
                                _profile_row("yield_stress_s0", "yield_stress", -10.0)]))
    out = tmp_path / "fc.json"
    assert main(["--results", str(res), "--profiles", str(prof), "--out", str(out)]) == 0
    assert {p.name: p.read_text() for p in res.iterdir()} == before
    rows = {r["case"]: r for r in json.loads(out.read_text())["rows"]}
    r0 = rows["yield_stress_s0"]
    assert r0["pair"] == ["mu_i", "yield_stress"] and r0["applied"] and r0["leader"] == "yield_stress"
    assert r0["two_ln_ratio"] == pytest.approx(20.0)
    assert (r0["named_before"], r0["named_after"]) == ("mu_i", "yield_stress")
    assert (r0["strict_before"], r0["strict_after"], r0["strict_after_finer"]) == (False, False, True)
    r1 = rows["yield_stress_s1"]
    assert r1["missing_profiles"] == ["yield_stress", "mu_i"] and not r1["applied"]
    assert r1["named_after"] == r1["named_before"] == "yield_stress"
    assert rows["null_s0"]["pair"] is None and rows["null_s0"]["verdict_after"] == rows["null_s0"]["verdict_before"]
    md = "\n".join(_finer_check_section(out))
    assert "| yield_stress_s0 | mu_i > yield_stress | yield_stress, 20.0 | mu_i | yield_stress | True | " \
           "False -> False (True) |" in md
    assert "| yield_stress | 2 | 2 | 1 -> 2 | 1 -> 1 (2) |" in md
    assert "Cases lacking a profile (decided as before): yield_stress_s1" in md
    with pytest.raises(SystemExit, match="no profile file"):
        main(["--results", str(res), "--profiles", str(tmp_path / "none.json"), "--out", str(out)])
