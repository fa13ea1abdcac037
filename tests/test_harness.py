"""The blind test harness (experiments/hidden_physics): cases end to end, its CLI, thresholds, summaries, page."""
from __future__ import annotations

import math

import numpy as np
import pytest

from torchslide.diagnose.decide import Thresholds, decide


from .conftest import TINY_HARNESS_BUDGETS, cand as _cand


def test_harness_case_end_to_end(tmp_path):
    """One blind case through the harness CLI with tiny budgets and the diagnosis' default thresholds, run on
    a Dask worker: the case file, its maps, the run's summary and the results page; the screening ranks the hidden term (entrainment) first."""
    import json
    from experiments.hidden_physics.harness import main as harness_main
    from experiments.hidden_physics.make_page import build_page

    out = tmp_path / "run"
    tiny = dict(TINY_HARNESS_BUDGETS, profile_top=0)
    budgets = [f"--budget={k}={v}" for k, v in tiny.items()]
    # the case runs as a task of a Dask LocalCluster of one worker process (--workers): files on this machine
    assert harness_main(["--seed-list", "0", "--scenarios", "entrainment", "--out", str(out), "--workers", "1",
                         "--thresholds", "defaults"] + budgets) == 0
    case = json.loads((out / "entrainment_s0.json").read_text())
    j = case["diagnosis"]
    assert j["verdict"] in ("missing_physics", "no_missing_physics", "unexplained")
    assert case["fine_factor"] == 2 and case["budgets"]["top_k"] == 1    # recordings on cells half the inversion's
    assert j["screening"]["ranking"][0] == "entrainment"
    assert j["screening"]["linear_opt"]["entrainment"]["kappa"] > 0
    refitted = [c for c in j["candidates"] if c.get("log_evidence") is not None]
    assert [c["name"] for c in refitted] == ["entrainment"]
    assert (out / "entrainment_s0.npz").exists() and not list(out.glob("*.running"))
    summary = json.loads((out / "summary.json").read_text())
    (row,) = summary["cases"]
    assert (row["scenario"], row["true"], row["verdict"]) == ("entrainment", "entrainment", j["verdict"])
    assert summary["settings"]["terrain"] == "narrow" and summary["settings"]["cellsize"] == 40.0
    from torchslide.diagnose import Thresholds
    assert summary["thresholds"] == json.loads(json.dumps(Thresholds().to_json()))   # not thresholds.json's
    runs = tmp_path / "runs"
    runs.mkdir()
    (runs / "tiny.json").write_text(json.dumps(summary))
    page = build_page(runs, tmp_path / "page", thresholds_file=tmp_path / "none.json").read_text()
    assert ("| `tiny`: narrow terrain, 40 m cells, a larger release weighed, the release taken as exact, "
            "budgets n_posterior_samples=8,") in page
    assert (tmp_path / "page" / "figures" / "confusion_tiny.png").exists()


@pytest.mark.slow
def test_small_harness(tmp_path):
    """Null + entrainment on the coarse channel with tiny budgets and three candidates: the screening ranks
    entrainment first where it is hidden and the null case names no yield stress."""
    from experiments.hidden_physics.harness import run_case

    cands = ["entrainment", "yield_stress", "mu_i"]
    out = tmp_path / "res"
    cases = {sc: run_case(sc, 0, out, budgets=TINY_HARNESS_BUDGETS, candidates=cands, log=lambda s: None)
             for sc in ("null", "entrainment")}
    for sc, c in cases.items():
        for cand in c["diagnosis"]["candidates"]:
            assert {"name", "log_evidence", "log_bayes_factor", "screening_score", "parameters"} <= set(cand)
    assert cases["entrainment"]["diagnosis"]["screening"]["ranking"][0] == "entrainment"
    assert cases["null"]["diagnosis"]["missing_physics"] != "yield_stress"


def test_harness_cli_refuses_bad_options(tmp_path):
    from experiments.hidden_physics.harness import main as harness_main

    for bad in (["--fine-factor", "0"], ["--max-batch", "0"], ["--budget", "local_max_iter"],
                ["--budget", "no_such_field=1"], ["--budget", "top_k=two"], ["--scenarios", "null,landslide"],
                ["--strengths", "x"], ["--terrain", "wide"],
                ["--budget", "model_error_runs=0"]):   # the release's error stated needs the grid-error runs
        with pytest.raises(SystemExit):
            harness_main(bad + ["--out", str(tmp_path / "never")])
    assert not (tmp_path / "never").exists()


def test_harness_refits_every_library_candidate_and_weighs_the_release_volume():
    from experiments.hidden_physics.harness import CANDIDATE_NAMES, HARNESS_BUDGETS, LIBRARY
    assert set(LIBRARY) < set(CANDIDATE_NAMES) and "release_volume" in CANDIDATE_NAMES
    assert HARNESS_BUDGETS["top_k"] >= len(CANDIDATE_NAMES)


def test_apply_thresholds_redecides_saved_cases(tmp_path):
    """Saved harness cases re-decided with thresholds set later on null seeds: same verdict as deciding
    with them directly, the decision as run kept; a second application changes nothing."""
    import json
    from dataclasses import asdict
    from experiments.hidden_physics.calibrate_thresholds import apply_thresholds

    loc = [{"standardised_residual": 9.0}]
    cands = [_cand("entrainment", 40.0), _cand("curvature", 10.0)]
    old, new = Thresholds(bf_min=20.0, located_min=8.0), Thresholds(bf_min=50.0, located_min=8.0)
    d0 = decide(cands, loc, {"ess": 5.0}, 100.0, old)
    assert d0["missing_physics"] == "entrainment"
    case = {"diagnosis": {"verdict": d0["verdict"], "missing_physics": d0["missing_physics"], "candidates": cands,
                          "located": loc, "decision": dict(d0, baseline_verification={"ess": 5.0}),
                          "fit_before": {"misfit": 100.0}, "thresholds": asdict(old)}}
    (tmp_path / "entrainment_s0.json").write_text(json.dumps(case))
    assert apply_thresholds(tmp_path, asdict(new)) == 1
    j = json.loads((tmp_path / "entrainment_s0.json").read_text())["diagnosis"]
    direct = decide(cands, loc, {"ess": 5.0}, 100.0, new)
    assert (j["verdict"], j["missing_physics"]) == (direct["verdict"], direct["missing_physics"]) == ("unexplained", None)
    assert j["decision_as_run"]["missing_physics"] == "entrainment" and j["thresholds"] == asdict(new)
    assert apply_thresholds(tmp_path, asdict(new)) == 0
    # --force: a case whose saved verdict differs from what the decision rule gives at its own thresholds
    # (a close runner-up failing only its Savage-Dickey sign joins an "A or B") is re-decided; a thresholds
    # file next to the cases is skipped
    close = [_cand("curvature", 82.3), _cand("earth_pressure", 78.0, two_ln_bf_savage_dickey=-1.0)]
    d1 = dict(decide(close, loc, {"ess": 5.0}, 100.0, old), verdict="missing_physics", missing_physics="curvature")
    case = {"diagnosis": {"verdict": d1["verdict"], "missing_physics": d1["missing_physics"], "candidates": close,
                          "located": loc, "decision": dict(d1, baseline_verification={"ess": 5.0}),
                          "fit_before": {"misfit": 100.0}, "thresholds": asdict(old)}}
    rule = tmp_path / "rule"
    rule.mkdir()
    (rule / "low_friction_patch_s1.json").write_text(json.dumps(case))
    (rule / "thresholds.json").write_text(json.dumps({"thresholds": asdict(old)}))
    assert apply_thresholds(rule, asdict(old)) == 0
    assert apply_thresholds(rule, asdict(old), force=True) == 1
    j = json.loads((rule / "low_friction_patch_s1.json").read_text())["diagnosis"]
    assert (j["verdict"], j["missing_physics"]) == ("missing_physics", "curvature or earth_pressure")


def test_a_thresholds_file_records_the_design_its_null_cases_were_diagnosed_with(tmp_path):
    """calibrate_thresholds writes the candidates and the release error of its null cases; the harness says when
    a thresholds file was set with other candidates or another release error than its cases; null cases of
    several release errors are refused."""
    import json
    from experiments.hidden_physics import calibrate_thresholds
    from experiments.hidden_physics.harness import CANDIDATE_NAMES, HARNESS_BUDGETS, unlike_design

    nulls = tmp_path / "nulls"
    nulls.mkdir()
    for seed in (100, 101, 102):
        case = {"terrain": "fan", "fine_terrain": True, "release_volume_sd": 0.0577,
                "diagnosis": {"candidates": [_cand(n, -3.0 + seed - 100) for n in CANDIDATE_NAMES], "located": [],
                              "decision": {}}}
        (nulls / f"null_s{seed}.json").write_text(json.dumps(case))
    out = tmp_path / "th.json"
    assert calibrate_thresholds.main(["--results", str(nulls), "--out", str(out)]) == 0
    t = json.loads(out.read_text())
    assert t["candidates"] == sorted(CANDIDATE_NAMES) and t["thresholds"]["bf_min"] == 6.0
    assert t["release_volume_sd"] == 0.0577 == HARNESS_BUDGETS["release_volume_sd"]
    assert unlike_design(out) is None and unlike_design(tmp_path / "none.json") is None
    assert "stated release_volume_sd 0.0577 (the cases 0)" in unlike_design(out, 0.0)
    t["candidates"] = [n for n in CANDIDATE_NAMES if n != "release_volume"]
    out.write_text(json.dumps(t))
    assert "set it again" in unlike_design(out) and "release_volume_sd" not in unlike_design(out)
    # a case saved before the field existed: the sd it was given as a budget, else 0
    (nulls / "null_s103.json").write_text(json.dumps({**case, "release_volume_sd": None, "budgets": {}}))
    with pytest.raises(SystemExit):
        calibrate_thresholds.main(["--results", str(nulls), "--out", str(out)])


def test_harness_skips_strengths_beyond_a_switch_range():
    from experiments.hidden_physics.harness import out_of_range
    assert out_of_range("earth_pressure", 2.0) and "earth_pressure = 2" in out_of_range("earth_pressure", 2.0)
    assert out_of_range("earth_pressure", 0.5) is None and out_of_range("entrainment", 2.0) is None
    assert out_of_range("null", 3.0) is None and out_of_range("low_friction_patch", 2.0) is None


def test_harness_cli_passes_the_inversion_cellsize(tmp_path, monkeypatch):
    """``harness --cellsize 20`` runs its cases on a 20 m inversion grid (recordings at 10 m), with
    --device / --max-batch / --fine-terrain / --fine-factor / --compile passed on; the defaults stay 40 m,
    cpu, 16, off, 2, eager; saved cases are skipped on a rerun."""
    import experiments.hidden_physics.harness as H

    calls = []

    def fake(sc, seed, out, cellsize=40.0, **kw):
        calls.append((sc, seed, cellsize, kw["device"], kw["max_batch"], kw["fine_terrain"], kw["fine_factor"],
                      kw["budgets"], kw["compile_solver"]))
        out.mkdir(parents=True, exist_ok=True)
        (out / f"{sc}_s{seed}.json").write_text("{}")
        return {"wall_s": 0.0, "diagnosis": {"verdict": "no_missing_physics", "missing_physics": None}}

    monkeypatch.setattr(H, "run_case", fake)
    assert H.main(["--cellsize", "20", "--seed-list", "3", "--scenarios", "null", "--out", str(tmp_path / "a"),
                   "--device", "cuda", "--max-batch", "64", "--fine-terrain", "--fine-factor", "1",
                   "--budget", "model_error_runs=0", "--budget", "release_volume_sd=0", "--budget", "local_max_iter=12",
                   "--budget", "local_lhs=30", "--budget", "profile_top=5", "--compile"]) == 0
    assert H.main(["--seed-list", "3", "--scenarios", "null", "--out", str(tmp_path / "b")]) == 0
    assert H.main(["--seed-list", "3", "--scenarios", "null", "--out", str(tmp_path / "b")]) == 0
    assert calls == [("null", 3, 20.0, "cuda", 64, True, 1,
                      {"model_error_runs": 0, "release_volume_sd": 0.0, "local_max_iter": 12, "local_lhs": 30,
                       "profile_top": 5},
                      True),
                     ("null", 3, 40.0, "cpu", 16, False, 2, None, False)]
    # a case another process holds (its .running claim) is skipped; the claim goes when a case ends
    (tmp_path / "b" / "null_s4.running").write_text("")
    assert H.main(["--seed-list", "4,5", "--scenarios", "null", "--out", str(tmp_path / "b")]) == 0
    assert [c[:2] for c in calls[2:]] == [("null", 5)]
    assert sorted(p.name for p in (tmp_path / "b").glob("*.running")) == ["null_s4.running"]


def test_make_evaluator_compiles_the_solver_on_request():
    """scenarios.make_evaluator(compile_solver=True): the diagnosis' solver steps compiled, on the device
    given; eager by default (the harness' --compile)."""
    from experiments.hidden_physics.scenarios import SOLVER, make_evaluator, make_recording

    rec = make_recording("null", 0)
    eager, comp = make_evaluator(rec), make_evaluator(rec, compile_solver=True, max_batch=64)
    assert not eager.solver_config.compile and comp.solver_config.compile and comp.max_batch == 64
    for k, v in SOLVER.items():
        assert getattr(comp.solver_config, k) == v


def test_harness_terrain_variants(tmp_path, monkeypatch):
    """scenarios.SITES: ``harness --terrain resolved`` runs its cases on the wider channel with the larger
    release, ``--terrain fan`` on the bend-to-fan terrain with its three gauges and its own thresholds file,
    and the default (narrow) is restored afterwards; an unknown variant is refused naming it."""
    import experiments.hidden_physics.harness as H
    from experiments.hidden_physics import scenarios as S

    seen = []

    def fake(sc, seed, out, cellsize=40.0, thresholds=None, **kw):
        dem, erod = S.terrain(cellsize)
        rel = S.release(dem, S.V_NOMINAL)
        seen.append((S.TERRAIN, dem.shape, int((rel > 0).sum()), [g[0] for g in S.gauges()], thresholds))
        return {"wall_s": 0.0, "diagnosis": {"verdict": "no_missing_physics", "missing_physics": None}}

    monkeypatch.setattr(H, "run_case", fake)
    for terr in ("resolved", "fan", "narrow"):
        args = ["--terrain", terr] if terr != "narrow" else []
        assert H.main(args + ["--seed-list", "0", "--scenarios", "null", "--out", str(tmp_path / terr)]) == 0
    (r, shape_r, n_r, g_r, _), (f, shape_f, n_f, g_f, th_f), (n, shape_n, n_n, g_n, th_n) = seen
    assert (r, f, n) == ("resolved", "fan", "narrow") and S.TERRAIN == "narrow"
    assert n_r > 3 * n_n  # release radius 120 m against 60 m
    assert shape_f == (25, 40) and g_f == ["g1", "g2", "g3"] and g_n == ["g1", "g2"]
    assert H.thresholds_file("fan").name == "thresholds_fan.json" and H.thresholds_file("narrow") == H.THRESHOLDS_FILE
    assert H.thresholds_file("fan", fine_terrain=True).name == "thresholds_fan_fine.json"
    assert th_f == H.load_thresholds(H.thresholds_file("fan")) != th_n == H.load_thresholds()
    with pytest.raises(ValueError, match="unknown variant 'wide'"):
        S.use_terrain("wide")
    with pytest.raises(SystemExit):
        H.main(["--terrain", "wide", "--out", str(tmp_path)])


def test_the_fan_terrain_sends_the_flow_through_its_bend_onto_the_fan():
    """synthetic.bend_to_fan at the harness' truth (mu 0.25, xi 500) on 40 m cells: the release holds its
    volume, the erodible reach lies in the channel through the bend, the flow passes all three gauges and
    deposits on the fan's head (beyond the bend), nothing leaves the domain; the harness recording on
    cells of 20 m has the deposit map on the 40 m grid."""
    from experiments.hidden_physics import scenarios as S
    from torchslide.physics import Params
    from torchslide.solver import SolverConfig, simulate
    from torchslide.terrain.synthetic import FAN_APEX_X, bend_to_fan

    case = bend_to_fan(40.0)
    assert math.isclose(case.release_volume, 2.0e5, rel_tol=1e-9) and case.dem.shape == (25, 40)
    with S.terrain_variant("fan"):
        dem, erod = S.terrain(40.0)
        assert np.array_equal(dem.z, case.dem.z) and np.array_equal(erod, case.erodible_depth)
        r = simulate(dem, S.release(dem, S.V_NOMINAL), Params.make(**S.TRUE_BASE), t_end=S.T_END, gauges=S.gauges(),
                     config=SolverConfig(**S.SOLVER), erodible_depth=erod)
        assert all(float(g.h.max()) > 1.0 for g in r.gauges.values())
        h = r.h_final[0].numpy()
        x = dem.x_centres()
        assert float((h[:, x > FAN_APEX_X - 100] * dem.cellsize ** 2).sum()) > 0.5 * float(r.final_volume[0])
        assert abs(float(r.final_volume[0]) - S.V_NOMINAL) < 1e-6 * S.V_NOMINAL
        rec = S.make_recording("null", 0)
        assert rec.observations[0].grid_shape == (25, 40) and len(rec.observations) == 8


def test_coverage_counts_a_truth_at_the_prior_bound(tmp_path):
    """A grid posterior's HDI whose last cell edge is 0.9999999999999999 covers a truth at the switch's
    bound 1 (earth pressure = 1); apply_thresholds recomputes a saved case's coverage that way."""
    import json
    from dataclasses import asdict
    from experiments.hidden_physics.calibrate_thresholds import apply_thresholds
    from experiments.hidden_physics.harness import coverage

    par = {"mean": 0.91, "hdr90": [0.70, 0.9999999999999999], "hdi90": [0.79, 0.9999999999999999]}
    diag = {"candidates": [{"name": "earth_pressure", "parameters": {"earth_pressure": par}}],
            "located": [], "thresholds": asdict(Thresholds()), "verdict": "no_missing_physics",
            "missing_physics": None, "decision": {}, "fit_before": {"misfit": 1.0}}
    truth = {"term": "earth_pressure", "earth_pressure": 1.0}
    assert coverage(diag, truth) == (True, True)
    assert coverage(diag, {"term": "earth_pressure", "earth_pressure": 0.75}) == (False, True)
    assert coverage(diag, {"term": "entrainment", "kappa": 0.0015}) == (None, None)
    # a profiled switch: its profile-likelihood interval is the one reported (and checked)
    prof = {"candidates": [{"name": "yield_stress", "parameters": {"tau_y": {
        "mean": 2.4, "hdr90": [2.1, 2.8], "hdi90": [2.1, 2.8], "profile90": [1.9, 3.2]}}}]}
    assert coverage(prof, {"term": "yield_stress", "tau_y": 3.0}) == (True, False)
    assert coverage(diag, {"term": None}) == (None, None)
    # a larger release: its excess over the stated release, the case's drawn release error included
    big = {"candidates": [{"name": "release_volume", "parameters": {"release_scale": {"hdr90": [0.2, 0.3]}}}]}
    larger = {"term": "release_volume", "release_scale": 0.25}
    assert coverage(big, larger) == (True, True) and coverage(big, larger, 1.08) == (False, False)
    case = {"truth": truth, "true_term_covered_hdr90": False, "true_term_covered_equal_tailed90": False,
            "diagnosis": diag}
    (tmp_path / "earth_pressure_s0.json").write_text(json.dumps(case))
    apply_thresholds(tmp_path, asdict(Thresholds()))
    c = json.loads((tmp_path / "earth_pressure_s0.json").read_text())
    assert c["true_term_covered_hdr90"] and c["true_term_covered_equal_tailed90"]


def test_harness_evaluator_with_the_fine_terrain():
    """scenarios.make_evaluator(fine_terrain=True): the recording grid's terrain cropped to the inversion
    grid's extent (the 20 m grid has one more column), the nominal release volume on it."""
    from types import SimpleNamespace
    from experiments.hidden_physics.scenarios import V_NOMINAL, make_evaluator, terrain
    from torchslide.observe import Observation

    rec = SimpleNamespace(observations=[Observation("final_volume", V_NOMINAL, 0.1 * V_NOMINAL, name="final_volume")])
    ev = make_evaluator(rec, fine_terrain=True)
    ft = ev.fine_terrain
    assert ft.factor_for(ev.dem) == 2 and ft.dem.shape == (2 * ev.dem.ny, 2 * ev.dem.nx)
    assert terrain(20.0)[0].shape[1] == ft.dem.shape[1] + 1
    assert np.array_equal(ft.dem.z, terrain(20.0)[0].z[:, :-1])
    assert math.isclose(float((ft.release * ft.dem.surface_area()).sum()), V_NOMINAL, rel_tol=1e-3)
    assert make_evaluator(rec).fine_terrain is None


def test_export_case_gives_the_cli_the_harness_case(tmp_path):
    """experiments.hidden_physics.export_case: the files and diagnose.toml it writes give the CLI the
    harness' case exactly: the same data, sigmas, terrain, release, erodible depth, gauges, prior,
    solver settings, the same z at a parameter point, and the harness' budgets and thresholds (so
    `torchslide diagnose` on them is the harness case); the truth is kept apart."""
    import json
    import torch
    from experiments.hidden_physics import export_case, scenarios
    from experiments.hidden_physics.harness import HARNESS_BUDGETS, load_thresholds, thresholds_file
    from torchslide.commands.diagnose import budgets_and_thresholds, load_diagnose_config
    from torchslide.commands.diagnose import make_evaluator as cli_evaluator
    from torchslide.diagnose import Budgets

    with scenarios.terrain_variant("resolved"):
        assert export_case.main(["yield_stress", "2", "--out", str(tmp_path), "--terrain", "resolved"]) == 0
        harness_ev = scenarios.make_evaluator(scenarios.make_recording("yield_stress", 2))
    cfg = load_diagnose_config(tmp_path / "diagnose.toml")
    ev = cli_evaluator(cfg)
    assert [b.name for b in ev.blocks] == [b.name for b in harness_ev.blocks]
    for attr in ("data", "sigma", "release", "erodible_depth"):
        assert np.array_equal(getattr(ev, attr), getattr(harness_ev, attr)), attr
    assert np.array_equal(ev.dem.z, harness_ev.dem.z) and ev.dem.cellsize == harness_ev.dem.cellsize
    assert ev.gauges == harness_ev.gauges and ev.prior.names == harness_ev.prior.names
    assert ev.solver_config == harness_ev.solver_config and ev.t_end == harness_ev.t_end
    x = torch.tensor([[0.27, 600.0]], dtype=torch.float64)
    assert float(ev(x).z[0]) == float(harness_ev(x).z[0])
    bud, th = budgets_and_thresholds(cfg)
    # the terrain's own thresholds (the resolved channel has none set: the defaults)
    assert bud == Budgets(**HARNESS_BUDGETS, seed=2) and th == load_thresholds(thresholds_file("resolved")) == Thresholds()
    truth = json.loads((tmp_path / "truth.json").read_text())
    assert truth["truth"]["tau_y"] == 3.0 and truth["terrain"] == "resolved"
    with pytest.raises(SystemExit, match="earth_pressure's switch earth_pressure = 2 beyond its range"):
        export_case.main(["earth_pressure", "0", "--strength", "2", "--out", str(tmp_path / "x")])
    text = (tmp_path / "diagnose.toml").read_text()
    assert "tau_y" not in text and not any("yield" in l for l in text.splitlines() if l.startswith("#"))
    # the release's error stated as the harness states it: the sd of the factor every recording draws
    assert cfg.extra["diagnose"]["fine_terrain"] is None and bud.release_volume_sd == scenarios.RELEASE_VOLUME_SD
    assert abs(scenarios.RELEASE_VOLUME_SD - np.diff(scenarios.RELEASE_FACTOR)[0] / 12 ** 0.5) < 5e-5
    # --fine-terrain / --release-volume-sd: the harness' --fine-terrain and --budget release_volume_sd
    out = tmp_path / "fine"
    assert export_case.main(["null", "0", "--out", str(out), "--fine-terrain", "--release-volume-sd", "0.05"]) == 0
    harness_ev = scenarios.make_evaluator(scenarios.make_recording("null", 0), fine_terrain=True)
    cfg = load_diagnose_config(out / "diagnose.toml")
    ft, hft = cli_evaluator(cfg).fine_terrain, harness_ev.fine_terrain
    assert ft is not None and hft is not None
    assert np.array_equal(ft.dem.z, hft.dem.z) and ft.dem.cellsize == hft.dem.cellsize == 20.0
    assert (ft.dem.xll, ft.dem.yll) == (hft.dem.xll, hft.dem.yll)
    assert np.array_equal(ft.release, hft.release) and np.array_equal(ft.erodible_depth, hft.erodible_depth)
    bud, _ = budgets_and_thresholds(cfg)
    assert bud == Budgets(**{**HARNESS_BUDGETS, "release_volume_sd": 0.05}, seed=0)
    for bad in ("-0.1", "0.5"):
        with pytest.raises(SystemExit, match=f"--release-volume-sd {bad}: must be a relative sd in"):
            export_case.main(["null", "0", "--out", str(out), "--release-volume-sd", bad])


def test_harness_sigmas_stated_as_the_noise(tmp_path, monkeypatch):
    """``harness --sigmas noise``: passed to run_case (default "harness");
    run_case states the noise drawn as the recording's sigmas (scenarios.noise_sigmas) before the diagnosis and
    records the choice; an unknown choice fails before any run."""
    import experiments.hidden_physics.harness as H

    calls = []

    def fake(sc, seed, out, cellsize=40.0, **kw):
        calls.append(kw["sigmas"])
        out.mkdir(parents=True, exist_ok=True)
        (out / f"{sc}_s{seed}.json").write_text("{}")
        return {"wall_s": 0.0, "diagnosis": {"verdict": "no_missing_physics", "missing_physics": None}}

    real = H.run_case
    monkeypatch.setattr(H, "run_case", fake)
    assert H.main(["--seed-list", "3", "--scenarios", "null", "--out", str(tmp_path / "a"), "--sigmas", "noise"]) == 0
    assert H.main(["--seed-list", "3", "--scenarios", "null", "--out", str(tmp_path / "b")]) == 0
    assert calls == ["noise", "harness"]
    with pytest.raises(SystemExit):
        H.main(["--seed-list", "3", "--scenarios", "null", "--out", str(tmp_path / "c"), "--sigmas", "tight"])
    assert calls == ["noise", "harness"]
    with pytest.raises(ValueError, match="sigmas must be one of"):
        real("null", 3, tmp_path / "d", sigmas="tight")
    # what run_case hands the diagnosis
    seen = {}

    def fake_diagnose(ev, cands, bud, th, log=None):
        seen["sigmas"] = {o.name: o.sigma for o in ev.observations}
        raise RuntimeError("stop here")

    monkeypatch.setattr(H, "diagnose", fake_diagnose)
    with pytest.raises(RuntimeError, match="stop here"):
        real("null", 3, tmp_path / "d", sigmas="noise")
    assert seen["sigmas"]["g1:h"] == 0.2 and seen["sigmas"]["g2:speed"] == 0.5 and seen["sigmas"]["deposit"] == 0.3
    assert seen["sigmas"]["final_volume"] == pytest.approx(0.1 * 2.0e5)


def _case(scenario, found, covered=True, margin=10.0, after=50.0, seed=0, strength=1.0):
    """A saved harness case reduced to what the summary reads."""
    from experiments.hidden_physics.scenarios import SCENARIOS

    term = SCENARIOS[scenario][0]
    verdict = {"none": "no_missing_physics", "unexplained": "unexplained"}.get(found, "missing_physics")
    return {"scenario": scenario, "seed": seed, "strength": strength, "truth": {"term": term},
            "true_term_covered_hdr90": covered, "wall_s": 100.0 + seed,
            "diagnosis": {"verdict": verdict, "missing_physics": found if verdict == "missing_physics" else None,
                          "decision": {"two_ln_bf_over_runner_up": margin, "two_ln_bf": 40.0},
                          "fit_before": {"misfit": 100.0}, "fit_after": {"misfit": after},
                          "thresholds": {"bf_min": 40.0}}}


def test_strict_success_is_the_blind_tests_target():
    """summary.strict_success: "nothing missing" for the null, no library name for the patch, and for a
    library term its name with 2 ln BF >= 6 over the runner-up, its interval covering the truth and the
    misfit reduced."""
    from experiments.hidden_physics.summary import strict_success

    assert strict_success(_case("null", "none")) and not strict_success(_case("null", "unexplained"))
    assert strict_success(_case("low_friction_patch", "unexplained"))
    assert strict_success(_case("low_friction_patch", "none"))
    assert not strict_success(_case("low_friction_patch", "curvature"))
    assert strict_success(_case("entrainment", "entrainment"))
    assert not strict_success(_case("entrainment", "mu_i"))
    assert not strict_success(_case("entrainment", "entrainment", covered=False))
    assert not strict_success(_case("entrainment", "entrainment", margin=5.9))
    assert not strict_success(_case("entrainment", "entrainment", after=100.0))
    # an "A or B" verdict that contains the term, its interval covering the truth; never for the patch
    either = _case("entrainment", "entrainment or yield_stress")
    either["diagnosis"]["decision"]["alternatives"] = ["entrainment", "yield_stress"]
    assert strict_success(either)
    either["true_term_covered_hdr90"] = False
    assert not strict_success(either)
    other = _case("mu_i", "entrainment or yield_stress")
    other["diagnosis"]["decision"]["alternatives"] = ["entrainment", "yield_stress"]
    assert not strict_success(other)
    patch = _case("low_friction_patch", "entrainment or yield_stress")
    patch["diagnosis"]["decision"]["alternatives"] = ["entrainment", "yield_stress"]
    assert not strict_success(patch)
    # a release larger than stated: no library name (entrainment above all), its own name or none
    for found, ok in (("none", True), ("unexplained", True), ("release_volume", True), ("entrainment", False)):
        assert strict_success(_case("release_volume", found)) is ok, found


def test_the_release_volume_scenario_records_a_release_a_quarter_larger():
    """The release_volume scenario: the same recording as the null of its seed but from a release 1.25 times as
    large (the final volume recorded 1.25 times the null's up to its noise), truth labelled "release_volume"."""
    from experiments.hidden_physics import scenarios as S
    from experiments.hidden_physics.summary import case_row

    null, big = S.make_recording("null", 3), S.make_recording("release_volume", 3)
    assert big.truth["term"] == "release_volume" and big.truth["release_scale"] == 0.25
    assert big.volume_factor == null.volume_factor
    v0, v1 = (next(o.value for o in r.observations if o.kind == "final_volume") for r in (null, big))
    assert abs(v1 / v0 - 1.25) < 0.05
    assert float(big.fine_h_final.sum()) > 1.2 * float(null.fine_h_final.sum())
    c = _case("release_volume", "none")
    c["truth"] = big.truth
    assert case_row(c)["true"] == "release_volume" and case_row(c)["true_switch"] is None
    # the screening's detectable switch of the release candidate gives no 4-in-5 switch without a true switch
    c["diagnosis"]["screening"] = {"candidates": {"release_volume": {"detectable_switch": {"switch": 0.2,
                                                                                          "per_unit": 12.0}}}}
    assert case_row(c)["power_switch"] is None


def test_success_against_detectability():
    """Below the switch the recordings can reveal, "nothing missing" or "unexplained" succeed and another
    term's name fails; at or above it only a strict success counts; null and patch cases are scored as before."""
    from experiments.hidden_physics.summary import case_row, detectability_success

    def det(scenario, found, truth, switch, **kw):
        c = _case(scenario, found, **kw)
        c["truth"]["curvature"] = truth
        c["diagnosis"]["screening"] = {"candidates": {"curvature": {"detectable_switch": {"switch": switch}}}}
        return c

    assert detectability_success(det("curvature", "none", 1.0, 4.6))
    assert detectability_success(det("curvature", "unexplained", 1.0, 4.6))
    assert not detectability_success(det("curvature", "mu_i", 1.0, 4.6))
    assert not detectability_success(det("curvature", "none", 1.0, 0.5))
    assert detectability_success(det("curvature", "curvature", 1.0, 0.5))
    row = case_row(det("curvature", "none", 1.0, 4.6))
    assert row["true_switch"] == 1.0 and row["detectable_switch"] == 4.6 and row["detectability_success"]
    assert row["power_switch"] is None                        # no whitened effect per unit recorded
    assert row["detectability_measured"] is False and case_row(_case("null", "none"))["detectability_measured"] is None
    # the switch found in four noise draws of five: (sqrt(bf_min + occam) + z_0.8) / a, prior width 1, bf_min 40
    c = det("curvature", "curvature", 1.0, 0.5)
    c["diagnosis"]["screening"]["candidates"]["curvature"]["detectable_switch"]["per_unit"] = 8.0
    t = math.sqrt(40.0 + 2 * math.log(8.0 / math.sqrt(2 * math.pi)))
    assert case_row(c)["power_switch"] == pytest.approx((t + 0.841621) / 8.0, rel=1e-6)
    # the 2 ln LR the linearised screening predicts at the true switch, (a s)^2, against the true term's fitted one
    assert (case_row(c)["lr_predicted"], case_row(c)["lr_found"]) == (pytest.approx(64.0), None)
    c["diagnosis"]["candidates"] = [{"name": "mu_i", "likelihood_ratio": 90.0},
                                    {"name": "curvature", "likelihood_ratio": 16.0}]
    assert case_row(c)["lr_found"] == 16.0
    assert case_row(_case("null", "none"))["lr_predicted"] is None
    # measured on the solver (power.detectable_switch): its four-in-five switch as stored, and the 2 ln LR at the
    # true switch from the power law through the measured points (the nearest one as reference)
    c["diagnosis"]["screening"]["candidates"]["curvature"]["detectable_switch"].update(
        switch_power=0.7, measured=[[0.5, 10.0], [0.7, 22.0]], exponent=2.5)
    assert case_row(c)["power_switch"] == 0.7 and case_row(c)["detectability_measured"]
    assert case_row(c)["lr_predicted"] == pytest.approx(22.0 * (1.0 / 0.7) ** 2.5)
    assert detectability_success(_case("null", "none")) and not detectability_success(_case("null", "mu_i"))


def test_page_counts_strict_successes_per_scenario_and_run(tmp_path):
    """make_page from summaries written by summary.py: a scenario meets its target with 4 of 5 strict
    successes; a run with every scenario at 5 seeds says how many of 7 targets it meets, a partial one
    says which seeds it has; the confusion matrix counts verdicts per hidden term."""
    import json
    from experiments.hidden_physics import make_page
    from experiments.hidden_physics.scenarios import SCENARIOS
    from experiments.hidden_physics.summary import summarise

    full = tmp_path / "full"
    full.mkdir()
    for sc in SCENARIOS:
        for seed in range(5):
            right = {"null": "none", "low_friction_patch": "unexplained"}.get(sc, sc)
            wrong = {"null": "unexplained", "low_friction_patch": "curvature"}.get(sc, "none")
            found = right if (sc != "curvature" and seed < 4) or sc == "entrainment" else wrong
            (full / f"{sc}_s{seed}.json").write_text(json.dumps(_case(sc, found, seed=seed)))
    (full / "entrainment_s0_x0.5.json").write_text(json.dumps(_case("entrainment", "none", strength=0.5)))
    runs = tmp_path / "runs"
    runs.mkdir()
    (runs / "full.json").write_text(json.dumps(summarise(full)))
    part = summarise(full)
    part["cases"] = [r for r in part["cases"] if r["scenario"] == "mu_i" and r["seed"] < 3]
    (runs / "part.json").write_text(json.dumps(part))
    s = make_page.load_runs(runs)
    counts = make_page.scenario_counts(make_page.evaluation_rows(s["full"]))
    assert counts["entrainment"] == (5, 5) and counts["curvature"] == (0, 5) and counts["null"] == (4, 5)
    assert make_page.targets_met(counts) == (7, 8)
    true, found, M = make_page.confusion(make_page.evaluation_rows(s["full"]))
    assert M[true.index("curvature"), found.index("none")] == 5 and M.sum() == 40
    either = make_page.confusion([{"true": "mu_i", "found": "yield_stress or earth_pressure"}])
    assert either[1] == ["mu_i", "A or B"] and either[2].tolist() == [[0, 1]]
    page = make_page.build_page(runs, tmp_path / "page", thresholds_file=tmp_path / "none.json").read_text()
    assert "| **4/5** | **5/5** | 0/5 | **4/5** |" in page and "| 7 of 8 |" in page
    assert "strict successes above the 4-in-5 switch |" in page
    mu_i = [r for r in s["full"]["cases"] if r["scenario"] == "mu_i" and r["strength"] == 1.0]
    rows = [{**r, "true_switch": 0.2, "detectable_switch": 0.1, "power_switch": p}
            for r, p in zip(mu_i, (0.15, 0.3, 0.18, 0.1, 0.5))]
    assert len(rows) == 5 and [r["strict_success"] for r in rows] == [True] * 4 + [False]
    sec = "\n".join(make_page._run_section("m", {**s["full"], "cases": rows}, tmp_path, tmp_path))
    assert "| mu_i | 4/5 | mu_i 4, none 1 |" in sec and "| 4/5 | 3/3 | - |" in sec     # seeds 0, 2, 3 above it
    lr = [{**r, "lr_predicted": 16.0, "lr_found": f} for r, f in zip(rows, (4.0, 8.0, 16.0, 32.0, None))]
    sec = "\n".join(make_page._run_section("m", {**s["full"], "cases": lr}, tmp_path, tmp_path))
    assert "| 3/3 | 0.75 (0.25-2.00) |" in sec                   # the median of the four seeds with both
    assert "| 3/3 | - | - | partial run: 1 scenario, seeds 0-2 |" in page
    assert "--strengths 0.5 --seed-list 0 --scenarios entrainment --out DIR" in page and (tmp_path / "page" / "figures" / "detection_vs_strength_full.png").exists()
    # the ladder: per term and strength, named / another term / nothing missing; the null seeds' false naming
    lad = {(r["term"], r["strength"]): r for r in make_page.ladder_rows(s["full"])}
    assert lad[("entrainment", 0.5)] == {"term": "entrainment", "strength": 0.5, "n": 1, "ratio_median": None,
                                         "named": 0, "in_either": 0, "strict": 0, "other_term": 0, "quiet": 1}
    assert lad[("entrainment", 1.0)]["named"] == 5 and lad[("curvature", 1.0)]["quiet"] == 5
    assert "| entrainment | 0.5 | - | 0/1 | 0/1 | 0/1 | 0/1 | 1/1 |" in page
    either = make_page.ladder_rows({"cases": [{"true": "mu_i", "found": f, "strength": 1.0, "strict_success": s}
                                              for f, s in (("yield_stress or mu_i", True), ("yield_stress", False))]})
    assert (either[0]["named"], either[0]["in_either"], either[0]["other_term"]) == (0, 1, 1)
    assert "Null seeds (0, 1, 2, 3, 4): nothing missing in 4 of 5, a library term named (false naming) in 0" in page
    # a run with the recording grid's terrain says so, and its command carries --fine-terrain
    fine = {"settings": {"terrain": "fan", "cellsize": 40.0, "fine_terrain": True},
            "cases": [{"scenario": "null", "seed": 0, "strength": 1.0}]}
    assert "--terrain fan --cellsize 40 --fine-terrain" in make_page.command(fine)
    # the release's error: the harness states it by default; a run that took the release as exact says so
    assert "--budget release_volume_sd=0 " in make_page.command(fine)
    stated = {**fine, "settings": {**fine["settings"], "release_volume_sd": 0.0577}}
    assert "release_volume_sd" not in make_page.command(stated)
    assert "the release's error stated (sd 0.0577)" in make_page.describe(stated["settings"])
    assert "the release taken as exact" in make_page.describe(fine["settings"])
    assert "the recording grid's terrain" in make_page.describe(fine["settings"])
    assert "a larger release weighed" in make_page.describe({**fine["settings"], "candidates": ["release_volume"]})
    weighed = tmp_path / "weighed"
    weighed.mkdir()
    c = _case("null", "none")
    c["diagnosis"]["candidates"] = [_cand("mu_i", 1.0), _cand("release_volume", 2.0)]
    (weighed / "null_s0.json").write_text(json.dumps(c))
    assert summarise(weighed)["settings"]["candidates"] == ["mu_i", "release_volume"]
    assert summarise(weighed)["settings"]["release_volume_sd"] == 0.0
    c["budgets"] = {"release_volume_sd": 0.05, "top_k": 6}      # given as a budget: its own setting
    (weighed / "null_s0.json").write_text(json.dumps(c))
    st = summarise(weighed)["settings"]
    assert st["release_volume_sd"] == 0.05 and st["budgets"] == {"top_k": 6}


def test_redetect_updates_a_case_whose_baseline_it_reproduces(tmp_path, monkeypatch):
    """redetect: the case's screening entries replaced by what baseline_screening measures when its baseline mode
    is the saved one; a case whose mode differs is left as it was (and the CLI says so with exit code 1)."""
    import json
    from types import SimpleNamespace
    from experiments.hidden_physics import redetect as R

    new = {"mu_i": {"switch": 0.3, "switch_power": 0.4, "per_unit": 9.0, "measured": [[0.4, 22.0]], "exponent": 2.0}}
    seen = {}

    def fake(ev, cands, bud, th, log=print):
        seen.update(cands=cands, seed=bud.seed, bf_min=th.bf_min)
        return SimpleNamespace(x0={"mu": 0.25, "xi": 500.0}, detectable=new)

    monkeypatch.setattr(R, "baseline_screening", fake)
    monkeypatch.setattr(R, "make_evaluator", lambda rec, **kw: None)
    monkeypatch.setattr(R, "make_recording", lambda *a, **kw: None)
    case = _case("mu_i", "none", seed=2)
    case.update(cellsize=40.0, fine_factor=2, terrain="narrow", fine_terrain=False, budgets={"top_k": 2})
    case["diagnosis"]["screening"] = {"x0": {"mu": 0.25, "xi": 500.0},
                                      "candidates": {"mu_i": {"score": 1.0, "detectable_switch": {"switch": 0.1}}}}
    (tmp_path / "mu_i_s2.json").write_text(json.dumps(case))
    assert R.main([str(tmp_path)]) == 0
    saved = json.loads((tmp_path / "mu_i_s2.json").read_text())["diagnosis"]["screening"]["candidates"]["mu_i"]
    assert saved == {"score": 1.0, "detectable_switch": new["mu_i"]}
    assert seen == {"cands": ["mu_i"], "seed": 2, "bf_min": 40.0}
    case["diagnosis"]["screening"]["x0"]["mu"] = 0.26
    (tmp_path / "mu_i_s2.json").write_text(json.dumps(case))
    assert R.main([str(tmp_path)]) == 1
    assert json.loads((tmp_path / "mu_i_s2.json").read_text()) == case
    # --from-measured: the switches derived again from the measured points alone (no solver)
    from torchslide.diagnose.power import measured_threshold
    pts = [[0.3, 40.0], [0.1, 2.0], [0.15, 5.0]]
    case["diagnosis"]["screening"]["candidates"]["mu_i"]["detectable_switch"] = {
        "switch": 9.0, "measured": pts, "per_unit_linear": 20.0}
    (tmp_path / "mu_i_s2.json").write_text(json.dumps(case))
    assert R.main([str(tmp_path), "--from-measured"]) == 0
    d = json.loads((tmp_path / "mu_i_s2.json").read_text())["diagnosis"]["screening"]["candidates"]["mu_i"]
    assert d["detectable_switch"] == measured_threshold(pts, (0.0, 0.4), 40.0, 20.0)
    assert d["detectable_switch"]["exponent"] == pytest.approx(math.log(5.0 / 2.0) / math.log(1.5))
    # the law through the last two points (the first, an outlier, drops out): at the four-in-five switch,
    # sqrt(nc) = sqrt(bf_min + Occam) + Phi^-1(0.8), the Occam term at the last point's effect per unit
    t = math.sqrt(40.0 + max(0.0, 2 * math.log(math.sqrt(5.0) / 0.15 * 0.4 / math.sqrt(2 * math.pi))))
    k = math.log(5.0 / 2.0) / math.log(1.5)
    assert d["detectable_switch"]["switch_power"] == pytest.approx(0.15 * ((t + 0.841621) ** 2 / 5.0) ** (1 / k),
                                                                   rel=1e-5)


@pytest.mark.slow
def test_redetect_reproduces_a_local_path_case(tmp_path):
    """A harness case on the local path, then redetect on its file: the baseline's mode is found again (the
    same stages as the diagnosis') and the detectable switches are measured on the solver."""
    import json
    from experiments.hidden_physics.harness import run_case
    from experiments.hidden_physics.redetect import redetect

    bud = dict(TINY_HARNESS_BUDGETS, inference="local", profile_top=0)
    run_case("entrainment", 0, tmp_path, budgets=bud, candidates=["entrainment"], log=lambda s: None)
    assert redetect(tmp_path / "entrainment_s0.json")
    d = json.loads((tmp_path / "entrainment_s0.json").read_text())["diagnosis"]["screening"]["candidates"]
    assert d["entrainment"]["detectable_switch"]["measured"]
