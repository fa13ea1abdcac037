"""The finer-grid check probe (experiments/hidden_physics/finer_check.py, finer_grid_profile.grid_profile)."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from experiments.hidden_physics.finer_check import finer_order, finer_pair
from experiments.hidden_physics.finer_grid_profile import finer_grid_evaluator, grid_profile, profile_starts
from torchslide.diagnose import Thresholds
from torchslide.diagnose.decide import decide
from torchslide.diagnose.refit import candidate_evaluator

from .test_diagnose import _cand
from .test_model_error import _evaluator

TH = Thresholds(bf_min=20.0, located_min=8.0, waic_min=6.0, margin_min=6.0)
BASE = {"ess": 5.0}
LOC = [{"standardised_residual": 9.0}]


def _with(cands, z_max):
    pair = finer_pair(cands, BASE, 100.0, TH)
    return decide(finer_order(cands, pair, z_max)[0], LOC, BASE, 100.0, TH)


def test_finer_order_takes_the_pairs_order_and_separation_from_the_finer_grid():
    """mu_i 25 ahead of yield stress in 2 ln BF (as in resolved 20 m yield-stress seeds 0 and 1): without
    the check mu_i is named; with yield stress 10 ahead in ln profile on the finer grid, yield stress;
    with the two within margin_min there, neither; the other checks stay the candidates' own."""
    cands = [_cand("mu_i", 60.0), _cand("yield_stress", 35.0), _cand("curvature", 5.0, two_ln_bf_lower=3.0)]
    assert finer_pair(cands, BASE, 100.0, TH) == ["mu_i", "yield_stress"]
    assert decide(cands, LOC, BASE, 100.0, TH)["missing_physics"] == "mu_i"
    new, fc = finer_order(cands, ["mu_i", "yield_stress"], {"mu_i": -20.0, "yield_stress": -10.0})
    assert fc == {"pair": ["mu_i", "yield_stress"], "z_max": {"mu_i": -20.0, "yield_stress": -10.0},
                  "leader": "yield_stress", "two_ln_ratio": 20.0}
    lbf = {c["name"]: c["log_bayes_factor"] for c in new}
    assert lbf == {"yield_stress": 30.0, "mu_i": 20.0, "curvature": 2.5}
    assert [c["two_ln_bf_lower"] for c in new] == [c["two_ln_bf_lower"] for c in cands]
    d = _with(cands, {"mu_i": -20.0, "yield_stress": -10.0})
    assert d["missing_physics"] == "yield_stress" and d["two_ln_bf_over_runner_up"] == pytest.approx(20.0)
    assert _with(cands, {"mu_i": -5.0, "yield_stress": -10.0})["missing_physics"] == "mu_i"
    d = _with(cands, {"mu_i": -10.0, "yield_stress": -9.0})
    assert d["verdict"] == "unexplained" and d["ambiguous"] and d["competitors"] == ["mu_i"]
    # one candidate passes the evidence check: no pair
    assert finer_pair([_cand("mu_i", 60.0), _cand("yield_stress", 20.0, two_ln_bf_lower=18.0)], BASE, 100.0, TH) is None


def test_finer_pair_needs_one_that_could_be_named():
    """Two pass the evidence check but neither passes every check (here their Savage-Dickey signs):
    no order between them can change the verdict, so no pair (and no finer-grid runs)."""
    both_fail = [_cand("earth_pressure", 40.0, two_ln_bf_savage_dickey=-1.0),
                 _cand("yield_stress", 36.0, two_ln_bf_savage_dickey=-2.0)]
    assert finer_pair(both_fail, BASE, 100.0, TH) is None
    one_ok = [both_fail[0], _cand("yield_stress", 36.0)]
    assert finer_pair(one_ok, BASE, 100.0, TH) == ["earth_pressure", "yield_stress"]
    assert _with(one_ok, {"earth_pressure": -14.0, "yield_stress": -10.0})["missing_physics"] == "yield_stress"


def test_grid_profile_on_the_finer_grid():
    """grid_profile with factor 2: the profile along the switch with every run on cells half as large;
    its maximum is the finer-grid evaluator's z at the profile's optimum, not the inversion grid's."""
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
    p = grid_profile(ev_c, par, factor=2, seed=0, n_values=3, n_iter=1, pop=2)
    assert len(p["switch"]) == len(p["z"]) >= 3 and np.isfinite(p["z_max"]) and p["runs"] > 0
    assert p["z_max"] == max(p["z"]) and p["best"] == p["switch"][int(np.argmax(p["z"]))]
    from torchslide.diagnose.profile import switch_profile
    r = switch_profile(finer_grid_evaluator(ev_c), s, par["tau_y"]["hdr90"], b, n_values=3, n_iter=1, pop=2,
                       min_half=0.02, seed=0)
    x = torch.as_tensor(r["x"][int(np.argmax(r["z"]))][None])
    z_fine = float(finer_grid_evaluator(ev_c).evaluate(x)[0].z[0])
    assert z_fine == pytest.approx(p["z_max"], abs=1e-9)
    assert abs(float(ev_c.evaluate(x)[0].z[0]) - z_fine) > 1e-6
    p1 = grid_profile(ev_c, par, factor=1, seed=0, n_values=3, n_iter=1, pop=2)
    assert p1["z_max"] != pytest.approx(p["z_max"], abs=1e-6)
    # the ladder over the whole prior: evenly from the switch's lower bound (0: the nested baseline) to its upper
    pp = grid_profile(ev_c, par, factor=1, seed=0, n_values=3, n_iter=1, pop=2, ladder="prior")
    assert pp["switch"] == pytest.approx(np.linspace(b[0, -1], b[1, -1], 3).tolist())
    assert pp["switch"][0] == 0.0 and np.isfinite(pp["z"]).all()
    with pytest.raises(ValueError, match="ladder must be one of"):
        grid_profile(ev_c, par, ladder="whole")
    # continuation sweeps after the profile: the first pass kept, no value lower after them
    ps = grid_profile(ev_c, par, factor=1, seed=0, n_values=3, n_iter=1, pop=2, ladder="prior", sweeps=1)
    assert ps["z_first"] == pytest.approx(pp["z"]) and len(ps["sweep_rises"]) == 1
    assert (np.asarray(ps["z"]) >= np.asarray(ps["z_first"])).all() and ps["runs"] > pp["runs"]
    assert ps["z_max"] == max(ps["z"])


def test_grid_profile_takes_its_values_from_the_sweeps(monkeypatch):
    """grid_profile(sweeps=N) reports the swept profile (its values, maximum and best switch), not the first
    pass, and passes the sweeps their number."""
    import experiments.hidden_physics.finer_grid_profile as fgp

    ev_c = candidate_evaluator(_evaluator(), "yield_stress")
    par = {"mu": {"mean": 0.3, "hdr90": [0.28, 0.32]}, "xi": {"mean": 600.0, "hdr90": [500.0, 700.0]},
           "tau_y": {"mean": 1.0, "hdr90": [0.5, 1.5]}}
    seen = []

    def fake(e, S, pz, px, b, sweeps, **kw):
        seen.append(sweeps)
        z = np.array(pz, float)
        z[0] += 1000.0                     # the lowest switch value becomes the best
        return z, np.array(px, float), [1000.0]

    monkeypatch.setattr(fgp, "neighbour_sweeps", fake)
    ps = fgp.grid_profile(ev_c, par, factor=1, seed=0, n_values=3, n_iter=1, pop=2, ladder="prior", sweeps=2)
    assert seen == [2] and ps["sweep_rises"] == [1000.0]
    assert ps["z"] == pytest.approx(np.asarray(ps["z_first"]) + np.array([1000.0, 0.0, 0.0]))
    assert ps["best"] == ps["switch"][0] == 0.0 and ps["z_max"] == pytest.approx(ps["z"][0])


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
    assert all(r["reproduced"] for r in json.loads(out.read_text())["rows"])
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
    D = json.loads(out.read_text())
    next(r for r in D["rows"] if r["case"] == "yield_stress_s0")["truth_minus_profile_max"] = {"yield_stress": 2.5,
                                                                                             "mu_i": -0.25}
    (tmp_path / "fc_truth.json").write_text(json.dumps(D))
    assert "| yield_stress_s0 | +2.5 | mu_i: -0.2 |" in "\n".join(_finer_check_section([tmp_path / "fc_truth.json"]))
    md = "\n".join(_finer_check_section([out]))
    assert "| yield_stress_s0 | mu_i > yield_stress | yield_stress, 20.0 | mu_i | yield_stress | True | " \
           "False -> False (True) |" in md
    assert "| yield_stress | 2 | 2 | 1 -> 2 | 1 -> 1 (2) |" in md
    assert "Cases lacking a profile (decided as before): yield_stress_s1" in md
    with pytest.raises(SystemExit, match="no profile file"):
        main(["--results", str(res), "--profiles", str(tmp_path / "none.json"), "--out", str(out)])


def test_case_evaluator_finer_inputs():
    """finer_grid_profile.case_evaluator: "dem" runs the finer grid over the inversion DEM (no fine
    terrain), "terrain" over the recording grid's own surface, "terrain_volume" also with the
    recording's release volume on both grids."""
    import json

    from experiments.hidden_physics.finer_grid_profile import RESULTS, case_evaluator

    D = json.loads((RESULTS["narrow"] / "yield_stress_s4.json").read_text())
    rec, ev = case_evaluator(D, "dem")
    assert ev.fine_terrain is None
    _, ev_t = case_evaluator(D, "terrain")
    _, ev_v = case_evaluator(D, "terrain_volume")
    assert ev_t.fine_terrain is not None and ev_t.fine_terrain.dem.cellsize == ev.dem.cellsize / 2
    vol = lambda r, c: float(np.asarray(r).sum()) * c ** 2  # noqa: E731
    v0 = vol(ev.release, ev.dem.cellsize)
    assert vol(ev_t.release, ev.dem.cellsize) == pytest.approx(v0)
    assert vol(ev_v.release, ev.dem.cellsize) == pytest.approx(v0 * rec.volume_factor)
    c_f = ev_t.fine_terrain.dem.cellsize
    assert vol(ev_v.fine_terrain.release, c_f) == pytest.approx(vol(ev_t.fine_terrain.release, c_f) * rec.volume_factor)
    assert abs(rec.volume_factor - 1) > 0.01
    with pytest.raises(ValueError, match="finer_inputs must be one of"):
        case_evaluator(D, "lidar")


def test_truth_on_finer_grid_is_the_true_terms_z_there():
    """finer_check.truth_on_finer_grid: z of the true term at the case's truth on cells half as large
    (finite, and far above the same model at a switch four times the truth)."""
    import json

    from experiments.hidden_physics.finer_check import truth_on_finer_grid
    from experiments.hidden_physics.finer_grid_profile import RESULTS

    D = json.loads((RESULTS["narrow"] / "yield_stress_s1.json").read_text())
    z = truth_on_finer_grid(D)
    far = dict(D, truth=dict(D["truth"], tau_y=4 * D["truth"]["tau_y"]))
    assert np.isfinite(z) and z > truth_on_finer_grid(far) + 10


def test_converged_maxima_climb_from_the_profile_and_the_truth():
    """finer_check.converged_maxima: per candidate of the pair, the best ln L + ln prior on the finer grid
    after a search over every parameter; at least the profile's maximum and, for the true term, the
    truth's z; the finer grid's z at the returned x is the returned z."""
    import json

    from experiments.hidden_physics.finer_check import _candidate_evaluator, converged_maxima
    from experiments.hidden_physics.finer_grid_profile import RESULTS

    D = json.loads((RESULTS["narrow"] / "yield_stress_s1.json").read_text())
    cm = converged_maxima(D, ["yield_stress", "mu_i"], n_iter=1, pop=3, profile={"n_values": 3, "n_iter": 1, "pop": 2})
    y, m = cm["yield_stress"], cm["mu_i"]
    assert m["truth_z"] is None and np.isfinite(y["truth_z"])
    assert y["z"] >= max(y["profile_z"], y["truth_z"]) and m["z"] >= m["profile_z"]
    for name, v in cm.items():
        e = finer_grid_evaluator(_candidate_evaluator(D, name))
        b = e.prior.bounds.numpy()
        assert len(v["x"]) == 3 and (np.array(v["x"]) >= b[0]).all() and (np.array(v["x"]) <= b[1]).all()
        assert float(e.evaluate(torch.tensor([v["x"]], dtype=torch.float64))[0].z[0]) == pytest.approx(v["z"], abs=1e-6)


def test_finer_check_converge_redecides_from_the_converged_maxima(tmp_path, monkeypatch):
    """--converge: a case whose true term is in the pair gets row["converged"], the check's verdict from
    converged_maxima (here mu_i's profile lead of 10 becomes a tie: "unexplained"); other cases none."""
    import json

    import experiments.hidden_physics.finer_check as fc

    res = tmp_path / "results"
    res.mkdir()
    _saved_case(res, "yield_stress", 0, [_cand("mu_i", 60.0), _cand("yield_stress", 35.0)])
    _saved_case(res, "null", 0, [_cand("curvature", 10.0, two_ln_bf_lower=8.0)])
    prof = tmp_path / "profiles.json"
    prof.write_text(json.dumps([_profile_row("yield_stress_s0", "mu_i", -10.0),
                                _profile_row("yield_stress_s0", "yield_stress", -20.0)]))
    calls = []

    def fake(case, pair, finer_inputs="dem"):
        calls.append((list(pair), finer_inputs))
        z = {"mu_i": -9.5, "yield_stress": -9.0}
        return {n: {"profile_z": -10.0, "truth_z": None, "z": z[n], "x": [0.2, 500.0, 1.0], "runs": 7} for n in pair}

    monkeypatch.setattr(fc, "converged_maxima", fake)
    out = tmp_path / "fc.json"
    assert fc.main(["--results", str(res), "--profiles", str(prof), "--out", str(out), "--converge"]) == 0
    rows = {r["case"]: r for r in json.loads(out.read_text())["rows"]}
    r = rows["yield_stress_s0"]
    assert calls == [(["mu_i", "yield_stress"], "dem")]
    assert (r["leader"], r["named_after"]) == ("mu_i", "mu_i")
    c = r["converged"]["dem"]
    assert c["leader"] == "yield_stress" and c["two_ln_ratio"] == pytest.approx(1.0)
    assert (c["verdict"], c["named"]) == ("unexplained", None) and c["runs"] == {"mu_i": 7, "yield_stress": 7}
    assert "converged" not in rows["null_s0"]
    from experiments.hidden_physics.make_page import _finer_check_section
    md = "\n".join(_finer_check_section([out]))
    assert "| yield_stress_s0 | dem | -10.0 -> -9.0 (-) | mu_i: -10.0 -> -9.5 | +0.0 -> +0.5 | mu_i -> unexplained |" in md
    # --cases: only the named cases are re-decided (no converged search here); the others' rows are kept
    assert fc.main(["--results", str(res), "--profiles", str(prof), "--out", str(out), "--converge",
                    "--cases", "null_s0"]) == 0
    assert calls == [(["mu_i", "yield_stress"], "dem")]
    assert {r["case"]: r for r in json.loads(out.read_text())["rows"]} == rows
    # another finer-grid input for the same case: its search is added, the earlier one kept
    assert fc.main(["--results", str(res), "--profiles", str(prof), "--out", str(out), "--converge", "terrain_volume",
                    "--cases", "yield_stress_s0"]) == 0
    assert calls[-1] == (["mu_i", "yield_stress"], "terrain_volume")
    r2 = {r["case"]: r for r in json.loads(out.read_text())["rows"]}["yield_stress_s0"]
    assert set(r2["converged"]) == {"dem", "terrain_volume"} and r2["converged"]["dem"] == c
    md = "\n".join(_finer_check_section([out]))
    assert "| yield_stress_s0 | terrain_volume | -10.0 -> -9.0 (-) | mu_i: -10.0 -> -9.5 | +0.0 -> +0.5 | unexplained |" in md
    with pytest.raises(SystemExit, match=r"no saved case\(s\) \['mu_i_s9'\]"):
        fc.main(["--results", str(res), "--profiles", str(prof), "--out", str(out), "--cases", "mu_i_s9"])


def test_neighbour_sweeps_lift_a_profile_value_its_search_left_off_the_ridge():
    """finer_grid_profile.neighbour_sweeps: on a ridge z = -100 (mu - (0.3 - 0.5 s))^2 (its top 0 at every
    switch s), a profile value whose search stopped off the ridge (s = 0 at mu 0.1: z = -4) is searched again
    from its neighbour's optimum and reaches the ridge; values already on it stay; the switch stays held."""
    from types import SimpleNamespace

    from experiments.hidden_physics.finer_grid_profile import neighbour_sweeps

    def ev_c(x):
        x = torch.as_tensor(x, dtype=torch.float64)
        z = -100.0 * (x[:, 0] - (0.3 - 0.5 * x[:, 1])) ** 2
        return SimpleNamespace(z=z, failed=torch.zeros(len(x), dtype=torch.bool))

    b = np.array([[0.0, 0.0], [1.0, 0.4]])
    S = np.array([0.0, 0.2, 0.4])
    px = np.array([[0.1, 0.0], [0.2, 0.2], [0.1, 0.4]])
    pz = ev_c(px).z.numpy()
    assert pz[0] == pytest.approx(-4.0) and pz[1] == pytest.approx(0.0)
    z, x, rises = neighbour_sweeps(ev_c, S, pz, px, b, sweeps=3, n_iter=3, pop=6)
    assert z[0] > -0.05 and z[1] == pytest.approx(0.0) and z[2] == pytest.approx(0.0)
    assert np.array_equal(x[:, -1], S) and rises[0] > 3.9 and len(rises) <= 3
    assert (z >= pz).all()
    # a value whose runs all failed (-inf) is lifted by its neighbour's start; its rise is not recorded as infinite
    z2, _, rises2 = neighbour_sweeps(ev_c, S, np.array([-np.inf, 0.0, 0.0]), px, b, sweeps=1, n_iter=1, pop=4)
    assert np.isfinite(z2).all() and np.isfinite(rises2).all()


def test_terrain_screen_measures_the_raw_and_the_unmimicked_effect():
    """terrain_screen.screen on a stub of a noise-free recording made at (mu, s) = (0.30, 1):
    z = -(mu - 0.30 + 0.05 (1 - s))^2 / 2e-4 - 8 (1 - s)^2 (0 at the truth). Without the term (s = 0) the true mu
    loses 12.5 + 8, so raw = 41 in 2 ln L; re-tuning mu to 0.25 absorbs the 12.5 and leaves 8: unmimicked 16.
    The switch stays at 0 in every baseline run."""
    from types import SimpleNamespace

    from experiments.hidden_physics.terrain_screen import screen

    seen = []

    def evc(x):
        x = torch.as_tensor(x, dtype=torch.float64)
        seen.append(x[:, -1].clone())
        z = -((x[:, 0] - 0.30 + 0.05 * (1 - x[:, 1])) ** 2) / 2e-4 - 8.0 * (1 - x[:, 1]) ** 2
        return SimpleNamespace(z=z, failed=torch.zeros(len(x), dtype=torch.bool))

    b = np.array([[0.12, 0.0], [0.4, 1.0]])
    r = screen(evc, [0.30, 1.0], b, n_iter=12)
    assert r["raw"] == pytest.approx(41.0)
    assert r["unmimicked"] == pytest.approx(16.0, abs=0.5)
    assert r["best_baseline"][0] == pytest.approx(0.25, abs=0.005) and r["best_baseline"][1] == 0.0
    assert seen[0].tolist() == [1.0, 0.0] and all((s == 0).all() for s in seen[1:])
    assert r["runs"] == 2 + sum(len(s) for s in seen[1:])


def test_terrain_screen_rejects_bad_variants_and_scenarios_before_any_run(tmp_path):
    from experiments.hidden_physics import terrain_screen as ts

    assert ts.parse_variants("a=resolved;theta_deg:35;amplitude:150,b=narrow") == {
        "a": ("resolved", {"theta_deg": 35.0, "amplitude": 150.0}), "b": ("narrow", {})}
    for spec, msg in (("a=flat", "is not NAME=TERRAIN"), ("a=resolved;slope:3", "unknown terrain key 'slope'"),
                      ("a=resolved;theta_deg:steep", "theta_deg = 'steep' is not a number"),
                      ("a=resolved;theta_deg:nan", "is not finite"), ("", "no variant")):
        with pytest.raises(ValueError, match=msg):
            ts.parse_variants(spec)
    out = tmp_path / "s.json"
    with pytest.raises(SystemExit, match="--variants: variant 'a=flat'"):
        ts.main(["--variants", "a=flat", "--out", str(out)])
    with pytest.raises(SystemExit, match="--scenario: 'null' is not a scenario with a library term"):
        ts.main(["--scenario", "null", "--out", str(out)])
    with pytest.raises(SystemExit, match="--search-iters: 0"):
        ts.main(["--search-iters", "0", "--out", str(out)])
    with pytest.raises(SystemExit):
        ts.main(["--sigmas", "tight", "--out", str(out)])
    assert not out.exists()
    with pytest.raises(ValueError, match="sigmas must be one of"):
        ts.screen_variant("x", "resolved", {}, "curvature", sigmas="tight")


def test_noise_sigmas_state_the_noise_drawn():
    """noise_sigmas: gauge series get the sd of the noise the harness draws for their quantity, the deposit map its
    noise sd; the final volume keeps its sigma; values are untouched."""
    from experiments.hidden_physics import scenarios
    from experiments.hidden_physics.scenarios import noise_sigmas
    from torchslide.observe import Observation
    from torchslide.observe_series import SeriesObservation

    t = np.arange(2.0, 10.0, 2.0)
    obs = [SeriesObservation("gauge_series", np.ones(4), 0.5, name="g1:h", gauge="g1", quantity="h", times=t),
           SeriesObservation("gauge_series", np.ones(4), 2.0, name="g1:speed", gauge="g1", quantity="speed", times=t),
           SeriesObservation("deposit_map", np.ones(3), 0.5, name="deposit", cell_index=np.arange(3), grid_shape=(1, 3)),
           Observation("final_volume", 1.0, 0.1, name="final_volume")]
    new = noise_sigmas(obs)
    assert [o.sigma for o in new] == [scenarios.GAUGE_ERRORS["h"][1], scenarios.GAUGE_ERRORS["speed"][1],
                                      scenarios.DEPOSIT_NOISE, 0.1] == [0.2, 0.5, 0.3, 0.1]
    assert [o.sigma for o in obs] == [0.5, 2.0, 0.5, 0.1] and all(np.array_equal(a.values, b.values) for a, b in
                                                                 zip(obs[:3], new[:3]))


def test_page_section_of_the_oracle_profiles(tmp_path):
    """make_page._oracle_section: per terrain, scenario and candidate, each seed's 2 ln L gain over switch 0 on the
    recording's own grid, the best switch, the last sweep's rise and how many seeds gain >= 10; no file or no
    finer-grid profile: nothing."""
    import json

    from experiments.hidden_physics.make_page import _oracle_section

    def row(case, cand, z, truth=None, rises=(1.0, 0.2)):
        return {"terrain": "resolved", "cellsize": 40.0, "case": case, "candidate": cand, "truth": truth,
                "finer_inputs": "terrain", "ladder": "prior", "profiles": {"finer_grid": {
                    "switch": [0.0, 0.2, 0.4], "z": z, "best": [0.0, 0.2, 0.4][int(np.argmax(z))],
                    "sweep_rises": list(rises)}}}

    f = tmp_path / "oracle.json"
    f.write_text(json.dumps([row("mu_i_s1", "mu_i", [-10.0, -2.0, -4.0], 0.2), row("mu_i_s0", "mu_i", [-5.0, -1.0, -6.0], 0.2),
                             row("null_s0", "mu_i", [-1.0, -1.2, -3.0], rises=[0.1]),
                             {**row("mu_i_s0", "mu_i", [-50.0, -1.0, -6.0], 0.2), "sigmas": "noise"}]))
    text = "\n".join(_oracle_section(f))
    assert "| resolved | mu_i | mu_i | harness | 0.2 | s0 8.0, s1 16.0 | 0.2, 0.2 | 0.2, 0.2 | 1 of 2 |" in text
    assert "| resolved | null | mu_i | harness | - | s0 0.0 | 0 | 0.1 | 0 of 1 |" in text
    assert "| resolved | mu_i | mu_i | noise | 0.2 | s0 98.0 | 0.2 | 0.2 | 1 of 1 |" in text
    assert _oracle_section(tmp_path / "absent.json") == []
    f.write_text(json.dumps([{**row("mu_i_s0", "mu_i", [0.0]), "profiles": {"inversion_grid": {}}}]))
    assert _oracle_section(f) == []


def test_page_section_of_the_terrain_screen(tmp_path):
    import json

    from experiments.hidden_physics.make_page import _terrain_screen_section

    f = tmp_path / "screen.json"
    f.write_text(json.dumps([
        {"variant": "resolved", "terrain": "resolved", "geom": {}, "scenario": "curvature", "raw": 23.34, "unmimicked": 3.0},
        {"variant": "steep", "terrain": "resolved", "geom": {"theta_deg": 35.0}, "scenario": "curvature", "raw": 10.5,
         "unmimicked": 1.0},
        {"variant": "resolved", "terrain": "resolved", "geom": {}, "scenario": "mu_i", "raw": 40.0, "unmimicked": 12.25},
        {"variant": "resolved", "terrain": "resolved", "geom": {}, "scenario": "curvature", "sigmas": "noise",
         "raw": 150.0, "unmimicked": 20.0}]))
    text = "\n".join(_terrain_screen_section(f))
    assert ("| variant | changed | curvature: raw / unmimicked | mu_i: raw / unmimicked | curvature (noise sigmas): raw / "
            "unmimicked |") in text
    assert "| resolved (resolved) | - | 23.3 / 3.0 | 40.0 / 12.2 | 150.0 / 20.0 |" in text
    assert "| steep (resolved) | theta_deg 35 | 10.5 / 1.0 | - | - |" in text
    assert _terrain_screen_section(tmp_path / "absent.json") == []


def test_case_label_marks_sigmas_stated_as_the_noise():
    from experiments.hidden_physics.make_page import _case_label

    assert _case_label({"case": "mu_i_s0"}) == "mu_i_s0"
    assert _case_label({"case": "mu_i_s0", "sigmas": "noise", "ladder": "prior"}) == (
        "mu_i_s0 (ladder over the whole prior; sigmas stated as the noise drawn)")


def test_terrain_screen_leaves_the_harness_terrains_as_they_were(monkeypatch):
    """screen_variant registers its variant for the call only: a new name is removed after, and a variant named
    like a harness terrain (here "resolved" with a steeper slope) does not change that terrain for later runs,
    also when the run fails; the terrain in force is the variant's during the call."""
    from experiments.hidden_physics import scenarios, terrain_screen

    before = {k: (dict(v[0]), v[1], v[2]) for k, v in scenarios.TERRAINS.items()}
    seen = []

    def boom(*a, **k):
        seen.append((scenarios.TERRAIN, scenarios.GEOM.get("theta_deg")))
        raise RuntimeError("stop")

    monkeypatch.setattr(scenarios, "make_recording", boom)
    for name in ("resolved", "steep"):
        with pytest.raises(RuntimeError, match="stop"):
            terrain_screen.screen_variant(name, "resolved", {"theta_deg": 35.0}, "curvature")
    assert seen == [("resolved", 35.0), ("steep", 35.0)]
    assert {k: (dict(v[0]), v[1], v[2]) for k, v in scenarios.TERRAINS.items()} == before
    assert scenarios.TERRAIN == "narrow" and "theta_deg" not in scenarios.GEOM
