"""The real event of the msh2021 example (landlab's Mount St. Helens 2021 data): its files reproduce the
survey's figures, a failure-depth raster is a release (the bed lowered, the thickness converted), and the
surveyed DEM of difference is an elevation_change observation against the run's change of the surface."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from torchslide.cli import main
from torchslide.config import ConfigError, load_config
from torchslide.observe_series import SeriesObservation
from torchslide.physics import Params
from torchslide.solver import simulate
from torchslide.terrain.grid import DEM
from torchslide.terrain.io import read_asc_array, write_asc


@pytest.fixture(scope="module")
def msh(tmp_path_factory):
    out = tmp_path_factory.mktemp("msh") / "case"
    assert main(["example", "msh2021", "--out", str(out)]) == 0
    return out


def test_the_example_files_reproduce_the_surveys_figures(msh):
    """Release 22,481 m^3 on 30 cells (vertical); DoD deposition 22,543 m^3 on 130 cells and erosion
    26,407 m^3 on 94 (cell area 100 m^2); the licence and the source beside them."""
    depth = np.nan_to_num(read_asc_array(msh / "failure_depth.asc")[0])
    dod = read_asc_array(msh / "dod.asc")[0]
    assert (depth < 0).sum() == 30 and -depth.sum() * 100 == pytest.approx(22480.7, abs=0.5)
    assert (dod > 0).sum() == 130 and dod[dod > 0].sum() * 100 == pytest.approx(22542.8, abs=0.5)
    assert (dod < 0).sum() == 94 and -dod[dod < 0].sum() * 100 == pytest.approx(26406.6, abs=0.5)
    assert "MIT" in (msh / "LICENSE.md").read_text() and "landlab" in (msh / "SOURCE.md").read_text()
    cfg = load_config(msh / "simulate.toml")
    assert cfg.terrain.release_volume == pytest.approx(22480.7, abs=0.5)
    assert "30 cells, 22,481 m^3 (vertical)" in cfg.conventions()["release"]


def _tilted(tmp_path, theta_deg=30.0, n=12, dx=10.0):
    x = (np.arange(n) + 0.5) * dx
    dem = DEM(np.tile(-x * np.tan(np.radians(theta_deg)), (n, 1)) + 500.0, dx)
    write_asc(tmp_path / "dem.asc", dem.z, dem, fmt="%.17g")
    return dem


def test_a_failure_depth_is_a_release_with_the_bed_lowered_and_the_thickness_made_normal(tmp_path):
    """On a 30 degree plane, failure depths of -2 m (vertical) on 4 cells: the bed there is 2 m lower, the
    normal thickness is 2 m x cos theta of the failure surface and the volume 2 m x the map area, in
    either thickness convention."""
    dem = _tilted(tmp_path)
    d = np.zeros(dem.shape)
    d[5:7, 3:5] = -2.0
    write_asc(tmp_path / "depth.asc", d, dem, fmt="%.17g")
    for conv in ("normal", "vertical"):
        (tmp_path / "s.toml").write_text(f'[terrain]\ndem = "dem.asc"\nrelease = {{ failure_depth = "depth.asc" }}\n'
                                         f'thickness = "{conv}"\n[model]\nmu = 0.3\nxi = 500.0\n[run]\nt_end = 1.0\n')
        t = load_config(tmp_path / "s.toml").terrain
        thick = 2.0 * (100.0 / t.dem.surface_area()[d < 0]) if conv == "normal" else 2.0
        assert conv == "vertical" or (thick < 2.0).all()
        assert np.allclose(t.dem.z - dem.z, d) and np.allclose(t.release[d < 0], thick) and (t.release[d == 0] == 0).all()
        assert t.release_volume == pytest.approx(4 * 2.0 * 100.0, rel=1e-9)


@pytest.mark.parametrize("values, match", [(2.0, "positive"), (0.0, "no negative value")])
def test_a_failure_depth_without_a_failure_is_refused(tmp_path, values, match):
    dem = _tilted(tmp_path)
    d = np.zeros(dem.shape)
    d[5, 5] = values
    write_asc(tmp_path / "depth.asc", d, dem)
    (tmp_path / "s.toml").write_text('[terrain]\ndem = "dem.asc"\nrelease = { failure_depth = "depth.asc" }\n'
                                     '[model]\nmu = 0.3\nxi = 500.0\n[run]\nt_end = 1.0\n')
    with pytest.raises(ConfigError, match=match):
        load_config(tmp_path / "s.toml")


def test_the_elevation_change_is_the_surfaces_and_balances_the_outflow(tmp_path):
    """A release that friction holds changes nothing; one that flows leaves its source lower (negative
    change) and the change over the grid sums to minus the volume that left it, with entrainment too (the
    bed lowered where the flow gained it)."""
    dem = _tilted(tmp_path, theta_deg=20.0, n=16)
    rel = np.zeros(dem.shape)
    rel[6:10, 2:5] = 2.0
    held = simulate(dem, rel, Params.make(mu=1.0, xi=500.0), t_end=5.0)
    assert torch.equal(held.elevation_change, torch.zeros_like(held.elevation_change))
    erod = np.full(dem.shape, 0.3)
    for kappa in (0.0, 0.005):
        r = simulate(dem, rel, Params.make(mu=0.1, xi=500.0, kappa=kappa), t_end=20.0, erodible_depth=erod)
        dz = r.elevation_change[0].numpy()
        assert dz[rel > 0].mean() < -0.5
        assert dz.sum() * 100.0 == pytest.approx(-float(r.outflow_volume[0]), abs=1e-9 * float(r.release_volume[0]))
        if kappa:
            assert float(r.entrained_volume[0]) > 1.0 and (r.bed_change[0].numpy() < 0).any()


def test_the_dod_is_an_elevation_change_observation_of_its_surveyed_cells(msh):
    """The DoD's 224 mapped cells become the observation with their signs; unmapped cells are left out; a
    run predicts one value per mapped cell; the diagnose config reads it."""
    cfg = load_config(msh / "simulate.toml")
    obs = SeriesObservation.from_raster(msh / "dod.asc", "elevation_change", cfg.terrain.dem, 0.5).validate(cfg.terrain.dem)
    assert obs.m == 224 and (obs.values < 0).sum() == 94 and (obs.values > 0).sum() == 130
    r = simulate(cfg.terrain.dem, cfg.terrain.release, Params.make(mu=0.3, xi=1000.0), t_end=5.0)
    assert obs.predict(r).shape == (1, 224)
    from torchslide.commands.diagnose import load_diagnose_config

    dcfg = load_diagnose_config(msh / "diagnose.toml")
    assert any(getattr(o, "kind", "") == "elevation_change" for o in dcfg.extra["observations"])


def test_calibrate_predict_and_sweep_read_the_dod(msh, tmp_path):
    """The example's calibrate.toml (impact and deposit areas, the run-out measured on the DoD and the DoD as an
    elevation_change map) runs
    through calibrate, predict and sweep on a small budget and the emulator's path (the fit on the solver
    that "auto" chooses for a sharp posterior is tested in test_calibrate_cli): the map's 224 values are in
    runs.csv, the best run's fit reports the map as a whole, predict reports the share of its values
    inside their intervals."""
    import json
    import re

    cfg = (msh / "calibrate.toml").read_text().replace("t_end = 300.0", "t_end = 60.0")
    for k, v in {"n_initial": "4", "n_total": "6", "batch_size": "2"}.items():
        cfg = re.sub(rf"^{k} = .*$", f"{k} = {v}", cfg, flags=re.M)
    cfg = cfg.replace("[calibration]\n", '[calibration]\ninference = "emulator"\n')
    (msh / "small.toml").write_text(cfg)
    cal, pred, sw = tmp_path / "cal", tmp_path / "pred", tmp_path / "sweep"
    assert main(["calibrate", str(msh / "small.toml"), "--out", str(cal), "--quiet"]) == 0
    header = (cal / "runs.csv").read_text().splitlines()[0].split(",")
    assert sum(h.startswith("dod[") for h in header) == 224 and "impact" in header
    post = json.loads((cal / "posterior.json").read_text())
    dod = next(o for o in post["best_run_fit"]["observations"] if o["name"] == "dod")
    assert dod["n"] == 224 and dod["rms_standardised_residual"] > 0
    assert post["inference"]["path"] == "emulator"
    assert next(o for o in post["observations"] if o["name"] == "dod")["n"] == 224
    assert main(["predict", str(msh / "small.toml"), "--calibration", str(cal), "--out", str(pred), "--n", "3",
                 "--quiet"]) in (0, 1)
    info = json.loads((pred / "predictive.json").read_text())
    assert info["maps_and_series"]["dod"]["n"] == 224 and len(info["values"]) == 3 + 224 + 1123   # + the outline
    assert [o["name"] for o in info["observations"]] == ["impact", "deposit", "runout"]
    runout = next(o for o in info["observations"] if o["name"] == "runout")
    assert runout["value"] == pytest.approx(info["against_observations"]["dod"]["runout_m"]["mapped"], rel=1e-12)
    assert runout["value"] > 700 and "interval90_model_error" in runout
    mm = info["mismatches"]
    assert mm["footprint"] == "outline" and mm["runout"]["mapped_m"] == pytest.approx(runout["value"])
    assert all(c["what"].split(":")[0] in ("excess", "deficit") and c["n_cells"] >= 3 for c in mm["clusters"])
    assert (pred / "front.png").is_file() and (pred / "outlines.png").is_file() and (pred / "front.json").is_file()
    j = info["against_observations"]["dod"]["footprint_jaccard"]
    assert 0 <= j["q05"] <= j["median"] <= j["q95"] <= 1
    assert info["against_observations"]["dod"]["deposition_m3"]["survey"] == pytest.approx(22542.77, rel=1e-6)
    assert main(["sweep", str(msh / "small.toml"), "--out", str(sw), "--n", "2", "--quiet"]) in (0, 1)
    assert sum(h.startswith("dod[") for h in (sw / "sweep.csv").read_text().splitlines()[0].split(",")) == 224


def test_the_survey_figures_of_a_run():
    """torchslide.survey against a hand-made survey of 4 cells: footprint Jaccard, reached shares, volumes,
    rmse and run-out from the release's crown."""
    from torchslide.survey import change_figures, footprint_figures, runout_from_crown

    dod = np.full((3, 3), np.nan)
    dod[0, :2], dod[1, :2] = [-2.0, 1.0], [0.5, np.nan]
    dod[1, 1] = 0.0
    mapped = np.isfinite(dod) & (dod != 0)                     # 3 cells: (0,0), (0,1), (1,0)
    dz = np.zeros((3, 3))
    dz[0, 0], dz[0, 1], dz[2, 2] = -1.0, 2.0, 0.5
    reached = np.abs(dz) > 0                                  # (0,0), (0,1), (2,2)
    f = footprint_figures(reached, mapped)
    assert f["footprint_jaccard"] == pytest.approx(2 / 4) and f["share_of_mapped_reached"] == pytest.approx(2 / 3)
    assert f["share_of_reached_unmapped"] == pytest.approx(1 / 3)
    c = change_figures(dz, dod, cellsize=10.0)
    assert c["deposition_m3"] == {"survey": pytest.approx(150.0), "run": pytest.approx(250.0)}
    assert c["erosion_m3"] == {"survey": pytest.approx(200.0), "run": pytest.approx(100.0)}
    assert c["rmse_m"] == pytest.approx(np.sqrt((1 + 1 + 0.25 + 0) / 4))
    z = np.array([[5.0, 9.0, 1.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    release = np.zeros((3, 3))
    release[0, :2] = 1.0                                      # crown: (0,1), the higher release cell
    assert runout_from_crown(z, release, reached, 10.0) == pytest.approx(10.0 * np.hypot(2, 1))
    assert runout_from_crown(z, release, np.zeros((3, 3), bool), 10.0) == 0.0


def test_simulate_and_predict_report_the_survey_figures(msh, tmp_path):
    """`simulate` on the example's calibrate.toml reports the run against the DoD (summary.json and a line),
    with the figures torchslide.survey gives on its own rasters; predict gives the draws' spread."""
    import json

    from torchslide.observe_series import SeriesObservation
    from torchslide.survey import run_figures

    cfg = (msh / "calibrate.toml").read_text().replace("t_end = 300.0", "t_end = 60.0")
    (msh / "short.toml").write_text(cfg)
    out = tmp_path / "sim"
    assert main(["simulate", str(msh / "short.toml"), "--out", str(out), "--quiet", "--threshold", "0.1"]) == 0
    f = json.loads((out / "summary.json").read_text())["against_observations"]["dod"]
    c = load_config(msh / "short.toml")
    obs = SeriesObservation.from_raster(msh / "dod.asc", "elevation_change", c.terrain.dem, 0.5, name="dod")
    h_max = read_asc_array(out / "h_max.asc")[0]
    ref = run_figures(h_max, None, [obs], c.terrain.dem.z, c.terrain.release, 10.0, 0.1)["dod"]
    assert f["footprint_jaccard"] == pytest.approx(ref["footprint_jaccard"]) and 0 < f["footprint_jaccard"] < 1
    assert f["runout_m"]["mapped"] == pytest.approx(ref["runout_m"]["mapped"]) and f["runout_m"]["mapped"] > 700
    assert f["runout_m"]["run"] == pytest.approx(ref["runout_m"]["run"])
    assert f["deposition_m3"]["survey"] == pytest.approx(22542.77, rel=1e-6)
    assert f["erosion_m3"]["survey"] == pytest.approx(26406.6, rel=1e-5)
    # no entrainment: what the run deposits, it took from the source (outflow aside)
    assert f["deposition_m3"]["run"] == pytest.approx(f["erosion_m3"]["run"], rel=0.02)


def test_the_footprint_likelihood_is_smooth_and_peaks_at_the_truth():
    """A mapped outline of a synthetic chute run (mu 0.25): the footprint likelihood over mu is finite,
    largest at the truth among its neighbours, and its central differences converge as the step halves."""
    from torchslide.bayes import Prior, Uniform
    from torchslide.evaluator import LandslideEvaluator

    from .conftest import chute_case

    dem, rel = chute_case()
    truth = simulate(dem, rel, Params.make(mu=0.25, xi=600.0), t_end=60.0)
    outline = (truth.h_max[0].numpy() > 0.5).astype(float)
    obs = SeriesObservation.from_array("footprint", outline, dem, 0.3, name="footprint", threshold=0.5)
    ev = LandslideEvaluator(dem=dem, release=rel, observations=[obs], prior=Prior({"mu": Uniform(0.1, 0.4)}),
                            fixed={"xi": 600.0}, t_end=60.0)
    steps = [0.004, 0.002, 0.001, 0.0005]     # central differences at mu = 0.22, the step halving
    mus = np.array([0.25, 0.242, 0.258] + [0.22 + s * d for d in steps for s in (-1, 1)])
    z = ev.evaluate(torch.as_tensor(mus[:, None]))[0].z.numpy()
    assert np.isfinite(z).all() and z[0] > max(z[1], z[2])
    slopes = np.array([(z[4 + 2 * i] - z[3 + 2 * i]) / (2 * d) for i, d in enumerate(steps)])
    # a 0/1 reach (impact_map) gives 2778, 2778, 5556, 11111 here: its differences grow as 1 / step
    assert (slopes > 0).all() and slopes.max() < 1.1 * slopes.min(), slopes


def _dod_on_another_grid(case):
    lines = (case / "dod.asc").read_text().splitlines()
    rows = [" ".join(r.split()[1:]) for r in lines[6:]]
    (case / "dod_other.asc").write_text("\n".join(["ncols 79"] + lines[1:6] + rows) + "\n")
    return 'file = "dod.asc"', 'file = "dod_other.asc"'


def _footprint_outside(case):
    (case / "far.geojson").write_text('{"type": "FeatureCollection", "features": [{"type": "Feature", "properties": {}, '
                                      '"geometry": {"type": "Polygon", "coordinates": [[[0, 0], [10, 0], [10, 10], '
                                      '[0, 10], [0, 0]]]}}]}')
    return "[calibration]", '[[observations]]\nkind = "footprint"\nfile = "far.geojson"\nsigma = 0.3\n\n[calibration]'


@pytest.mark.parametrize("edit, match", [(_dod_on_another_grid, "does not match the DEM grid"),
                                         (_footprint_outside, "covers no cell centre of the DEM")])
def test_bad_survey_inputs_are_one_line_errors(msh, tmp_path, capsys, edit, match):
    import shutil

    case = tmp_path / "case"
    shutil.copytree(msh, case)
    old, new = edit(case)
    (case / "bad.toml").write_text((case / "calibrate.toml").read_text().replace(old, new))
    capsys.readouterr()
    assert main(["calibrate", str(case / "bad.toml"), "--out", str(tmp_path / "out"), "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and match in err[0] and "Traceback" not in err[0]


def test_the_event_page_reports_the_diagnosis_as_its_report_gives_it(tmp_path):
    """experiments.msh2021's page from a diagnosis report.json: the time is the sum of its stages' (a
    resumed diagnosis reports the run's, not the resume's), the located mismatches and each candidate's
    detectable switch, said to be measured or linearised as the report's entries are; the trade-offs, the
    learnt discrepancy and the predictions with and without the grid's and the model's own error."""
    from experiments.msh2021.__main__ import diagnosis_summary, write_page

    det = {"entrainment": {"switch": 0.00045, "within_prior": True, "measured": [[0.0006, 20.0]]},
           "curvature": {"switch": 4.69, "within_prior": False, "measured": [[1.0, 0.3]]}}
    rep = {"verdict": "unexplained", "decision": {"reason": "r"}, "timings": {"pilot_s": 400.0, "screen_s": 600.5},
           "located": [{"what": "dod deficit cluster", "where": [1.0, 2.0, 3.0, 4.0], "standardised_residual": -14.0}],
           "candidates": [{"name": "curvature", "two_ln_bf": 1.8}],
           "mismatches": {"runout": {"what": "run-out shortfall", "difference_m": -400.0, "mapped_m": 786.0,
                                     "interval_m": [-450.0, -300.0]},
                          "clusters": [{"what": "excess: reached, not mapped", "n_cells": 140, "area_m2": 14000.0,
                                        "box": [0.0, 0.0, 100.0, 200.0], "from_crown_m": [300.0, 500.0], "score": 90.0,
                                        "volume_m3": 2000.0}]},
           "screening": {"candidates": {c: {"score": 0.0, "detectable_switch": d} for c, d in det.items()}}}
    d = diagnosis_summary(rep)
    assert d["seconds"] == 1000.5 and d["candidates"] == {"curvature": 1.8}
    post = {k: {"mu": 0.31, "xi": 738.0} for k in ("mean", "sd")} | {"hdr90": {"mu": [0.3, 0.32], "xi": [650, 820]}}
    two = {"run": 1.0, "survey": 2.0}
    q = {"q05": 0.3, "median": 0.4, "q95": 0.5}
    pred = {"figures": {"runout_m": {"q05": 200.0, "median": 300.0, "q95": 400.0,
                                     "with_grid_error": {"q05": 150.0, "q95": 420.0, "shift": -40.0, "sd": 45.0}},
                        "impact_area_m2": {"q05": 1e4, "median": 2e4, "q95": 3e4}},
            "observations": [{"name": "runout", "value": 786.0, "interval90": [150.0, 450.0],
                              "interval90_model_error": [0.0, 1100.0]},
                             {"name": "impact", "value": 22400.0, "interval90": [1e4, 3e4]}],
            "against": {k: q for k in ("footprint_jaccard", "share_of_mapped_reached", "share_of_reached_unmapped",
                                       "rmse_m")},
            "mismatches": dict(rep["mismatches"], clusters=[dict(rep["mismatches"]["clusters"][0],
                                                                 path_point={"x": 50.0, "y": 120.0, "along_m": 310.0})])}
    out = {"posterior": post, "inference": "local", "median_run": {"mu": 0.31, "xi": 730.0}, "footprint_jaccard": 0.4,
           "share_of_mapped_reached": 0.6, "share_of_reached_unmapped": 0.5,
           "share_of_mapped_cells_with_p_impact_ge_0.5": 0.6, "deposition_m3": two, "erosion_m3": two, "rmse_m": 1.9,
           "runout_m": two, "diagnosis": d, "wall_s": 339.0, "calibrate_s": 52.0, "h_over_l": 0.3, "predictive": pred,
           "tradeoffs": ["no run meets impact and runout together: ..."],
           "discrepancy": [{"observation": "runout", "discrepancy_sd_over_sigma": 25.4}]}
    write_page(out, tmp_path / "README.md")
    page = (tmp_path / "README.md").read_text()
    assert "1000 s in its stages: verdict **unexplained**" in page
    assert "| dod deficit cluster | 1 - 3 | 2 - 4 | -14.0 |" in page
    assert "- run-out shortfall -400 m (90 % of the runs [-450, -300] m) of the mapped 786 m" in page
    assert "- excess: reached, not mapped: 140 cells (14,000 m^2, 2,000 m^3), 300-500 m from the crown" in page
    assert "| 1 | excess: reached, not mapped | 140 | 14,000 | 300 - 500 | 310 (50, 120) | 2,000 |" in page
    assert "Calibration, prediction and the figures: 339 s on the 2-core machine (calibration 52 s)." in page
    write_page(dict(out, threads=1), tmp_path / "README.md")
    assert "339 s on the 2-core machine on 1 torch thread (calibration 52 s)." in (tmp_path / "README.md").read_text()
    write_page(dict(out, solver_pace_s=2.5), tmp_path / "README.md")     # the machine's pace: the stages in its units
    assert ("1000 s in its stages (400 times the 2.5 s this machine takes for the event's 8-member batch of 300 s): "
            "verdict **unexplained**") in (tmp_path / "README.md").read_text()
    assert "- no run meets impact and runout together: ...." in page and "runout 25 x its sigma" in page
    assert "| run-out from the release's crown, m | 200 - 400 | 150 - 420 (+- 45) | 786 |" in page
    assert "| runout | 786 | 150 - 450 | 0 - 1,100 |" in page and "| impact | 22,400 | 10,000 - 30,000 | - |" in page
    assert ("(the screening's detectable switch, measured on the solver: a term this strong reaches bf_min in half "
            "the noise draws): entrainment from 0.00045, curvature from 4.69 (beyond its range).") in page
    for e in det.values():
        del e["measured"]
    det["curvature"]["switch"] = math.inf
    write_page(dict(out, diagnosis=diagnosis_summary(rep)), tmp_path / "README.md")
    page = (tmp_path / "README.md").read_text()
    assert "detectable switch, linearised:" in page and "curvature never (no own effect)." in page
