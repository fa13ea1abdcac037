"""``torchslide diagnose``: bad input refused before any run (exit 2), the report end to end, its keys."""
from __future__ import annotations

import math

import numpy as np
import pytest

from torchslide.cli import main
from torchslide.terrain.io import write_asc

from .conftest import setup_diagnose_case as _setup, tiny_budgets


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


def _last_value(path, token: str) -> None:
    """Replace the last data value of an ESRI ASCII grid with ``token``."""
    text = path.read_text().rstrip().rsplit(" ", 1)[0]
    path.write_text(text + " " + token + "\n")


@pytest.mark.parametrize("case, msg", [
    ("gauge_after_t_end", "recorded until t = 90 s, after the simulated time t_end = 60 s"),
    ("gauge_negative_time", "row 2: times are seconds since the release and must be >= 0, got t = -1"),
    ("candidate_twice", "candidates lists ['mu_i'] more than once"),
    ("map_infinite_cell", "1 non-finite values, first inf at row 0 from the south, col 23"),
    ("map_all_nodata", "map has no finite cells"),
    ("impact_map_not_0_1", "an impact map holds 0 (not reached) or 1 (reached)"),
    ("bf_min_negative", "bf_min must be >= 0"),
    ("prior_below_zero", "[prior] parameter mu: range low = -0.05 is outside the allowed values (0, inf)"),
    ("negative_volume", "a recorded final_volume cannot be negative, got -1.0 m^3"),
    # a refit budget the active learner cannot start with (was a traceback after the baseline's runs)
    ("refit_n_initial_one", "[diagnose] n_initial must be an integer >= 2, got 1"),
])
def test_cli_refuses_more_bad_input_before_any_run(tmp_path, capsys, case, msg):
    """Each bad input gets one line naming the field and the value, exit 2, before any solver run."""
    from torchslide.terrain.synthetic import inclined_plane
    dem = inclined_plane(30.0, 50.0, slope_length=500.0, runout_length=700.0, width=300.0)
    kw = {"grid": dem.shape, "candidates": '["mu_i"]'}
    if case == "gauge_after_t_end":
        kw["csv"] = "t,h,speed\n1,0,0\n30,1,3\n90,2,4\n"
    elif case == "gauge_negative_time":
        kw["csv"] = "t,h,speed\n-1,0,0\n2,1,3\n3,2,4\n"
    elif case == "candidate_twice":
        kw["candidates"] = '["mu_i", "entrainment", "mu_i"]'
    elif case == "bf_min_negative":
        kw["candidates"] = '["mu_i"]\nbf_min = -1.0'
    elif case == "refit_n_initial_one":
        kw["candidates"] = '["mu_i"]\nn_initial = 1'
    p, _ = _setup(tmp_path, **kw)
    toml = p.read_text()
    if case == "map_infinite_cell":
        _last_value(tmp_path / "dep.asc", "inf")
    elif case == "map_all_nodata":
        head = tmp_path / "dep.asc"
        lines = head.read_text().splitlines()
        head.write_text("\n".join(lines[:6] + [" ".join(["-9999"] * dem.shape[1])] * dem.shape[0]) + "\n")
    elif case == "impact_map_not_0_1":
        write_asc(tmp_path / "imp.asc", np.full(dem.shape, 0.5), dem)
        toml += '\n[[observations]]\nkind = "impact_map"\nfile = "imp.asc"\nsigma = 0.3\n'
    elif case == "prior_below_zero":
        toml = toml.replace("mu = [0.05, 0.5]", "mu = [-0.05, 0.5]")
    elif case == "negative_volume":
        toml += '\n[[observations]]\nkind = "final_volume"\nvalue = -1.0\nsigma = 1000.0\n'
    p.write_text(toml)
    rc = main(["diagnose", str(p), "--out", str(tmp_path / "out")])
    err = capsys.readouterr().err
    assert rc == 2, err
    assert not (tmp_path / "out").exists()
    assert err.startswith("torchslide: error:") and len(err.strip().splitlines()) == 1, err
    assert msg in err, err
    assert "Traceback" not in err


def test_cli_diagnose_end_to_end_writes_the_report(tmp_path, monkeypatch):
    """`torchslide diagnose CONFIG --out DIR` with tiny budgets: exit 0, report.json with the issue's keys,
    report.md and figures (a refit posterior plot included)."""
    import json
    from torchslide.terrain.synthetic import inclined_plane
    dem = inclined_plane(30.0, 50.0, slope_length=500.0, runout_length=700.0, width=300.0)
    p, _ = _setup(tmp_path, grid=dem.shape, candidates=tiny_budgets("release_volume_sd = 0.05\nfit_max = -1000\n"))
    out = tmp_path / "out"
    assert main(["diagnose", str(p), "--out", str(out), "--quiet", "--null-runs", "-1"]) == 2
    # null runs that fail (a finer-grid run): exit 1, the report with the thresholds given is written
    import torchslide.diagnose.null as null_mod

    def fail(*a, **k):
        # the null runs draw from the data's baseline posterior draws (Diagnosis.predictive.x), (M, p)
        assert isinstance(a[4], np.ndarray) and a[4].ndim == 2 and a[4].shape[1] == 2 and len(a[4]) >= 1
        raise RuntimeError("null recording 0: the finer-grid run failed")
    monkeypatch.setattr(null_mod, "null_calibration", fail)
    assert main(["diagnose", str(p), "--out", str(out), "--quiet", "--null-runs", "2"]) == 1
    assert json.loads((out / "report.json").read_text())["null_calibration"] is None
    monkeypatch.undo()
    assert main(["diagnose", str(p), "--out", str(out), "--quiet", "--null-runs", "1"]) == 0
    j = json.loads((out / "report.json").read_text())
    assert j["verdict"] in ("missing_physics", "no_missing_physics", "unexplained")
    assert "normal to the slope" in j["conventions"]["thickness"] and j["conventions"]["input_thickness"] == "normal"
    # --null-runs 1: one null recording diagnosed like the data; bf_min and located_min set on it (fit_max
    # needs 3, so the config's is kept), the data decided again, the first decision kept
    nc = j["null_calibration"]
    assert nc["n"] == 1 and len(nc["cases"]) == 1 and (out / "null" / "null_0.json").exists()
    c0 = nc["cases"][0]
    assert j["thresholds"]["bf_min"] == max(6.0, 1.25 * c0["max_two_ln_bf_lower"]) == nc["thresholds"]["bf_min"]
    assert j["thresholds"]["located_min"] == max(8.0, 1.25 * c0["max_located"]) and j["thresholds"]["fit_max"] == -1000
    assert j["decision"]["decision_before"]["thresholds"]["bf_min"] == 6.0
    md = (out / "report.md").read_text()
    assert "## Thresholds set on null simulations of this design" in md
    # which candidate came out best on the null run, in report.json and report.md
    best0 = max(c0["lower_by_candidate"], key=c0["lower_by_candidate"].get)
    assert c0["lower_by_candidate"][best0] == c0["max_two_ln_bf_lower"]
    assert f"nothing is missing there): {best0} in 1 of 1" in md
    assert nc["noise_model"] == "stated" and nc["release_volume_sd"] == 0.05 and c0["noise_model"] == "stated"
    assert nc["terrain"] == "interpolated" and "over the DEM interpolated bilinearly" in md
    assert "the release volume's error (relative sd 0.05)" in md
    for key in ("missing_physics", "located", "candidates", "fit_before", "fit_after"):
        assert key in j
    # each candidate's share of the significant located mismatch removed, in report.json and report.md's table
    assert j["decision"]["explained_shares"]
    for name, share in j["decision"]["explained_shares"].items():
        assert share <= 1.0 and any(l.startswith(f"| {name} |") and f"| {share:.0%} |" in l for l in md.splitlines())
    for key in ("log_evidence", "misfit", "residuals"):
        assert key in j["fit_before"]
    # every vector observable's fit with the likelihood's own covariance, before and after
    vec = [r for r in j["fit_before"]["residuals"].values() if "rms_z" in r]
    assert vec and all(np.isfinite(r["Z_fit"]) and 0 <= r["p_fit"] <= 1 for r in vec)
    assert all(np.isfinite(r["Z_fit"]) for r in j["fit_after"]["residuals"].values() if "rms_z" in r)
    assert "fit Z before" in (out / "report.md").read_text()
    # fit_max below every fit: each vector observable is flagged, so the verdict cannot be "nothing missing"
    assert sorted(f["observable"] for f in j["decision"]["fit_flags"]) == sorted(
        k for k, r in j["fit_before"]["residuals"].items() if "rms_z" in r)
    assert j["verdict"] != "no_missing_physics" and "whole-observable fit" in (out / "report.md").read_text()
    assert j["decision"]["fit_z_source"] == "calibrated baseline" and set(j["decision"]["fit_z"]) == set(
        f["observable"] for f in j["decision"]["fit_flags"])
    from torchslide.diagnose.report import _fit_notes
    notes = "\n".join(_fit_notes({"deposit": {"Z_fit": -36.0}, "g1:h": {"Z_fit": 0.4}, "g2:h": {"Z_fit": 4.2},
                                  "final_volume": {"z": 0.3}}))
    assert "better than the likelihood's covariance expects at deposit (-36.0)" in notes and "g1:h" not in notes
    assert "Mismatch beyond the likelihood's covariance at g2:h (4.2)" in notes
    assert _fit_notes({"g1:h": {"Z_fit": 1.0}}) == []
    c = j["candidates"][0]
    assert c["name"] == "mu_i" and {"log_evidence", "log_bayes_factor", "screening_score", "parameters"} <= set(c)
    assert set(c["parameters"]["mu_i"]) >= {"mean", "hdr90"}
    md = (out / "report.md").read_text()
    assert "Verdict" in md and "mu_i" in md
    assert c["evidence_history"] and "evidence from the" in md
    # subset consistency: one entry per observation, and its table in the report
    sc = j["subset_consistency"]
    assert sorted(e["block"] for e in sc) == sorted(j["fit_before"]["residuals"]) and len(sc) >= 2
    assert all(e["df"] >= 0 and 0 <= e["p_value"] <= 1 and e["statistic"] >= 0 for e in sc)
    assert "subset consistency" in md
    # the grid's approximation error (2 run pairs here) entered the likelihood
    assert j["model_error"]["n"] == 2
    assert j["model_error"]["release_sd"] == 0.05     # [diagnose] release_volume_sd reached the likelihood
    # every screened candidate has its detectable switch, and report.md its table
    dsw = j["screening"]["candidates"]["mu_i"]["detectable_switch"]
    assert dsw is not None and set(dsw) >= {"per_unit", "switch", "within_prior", "switch_power"}
    assert dsw["switch_power"] > dsw["switch"]
    assert dsw["measured"] and "measured on the solver near that switch" in md      # the default: measured
    assert "## Screening" in md and "detectable from" in md and "found 4 in 5 from" in md
    assert (out / "posteriors.png").exists() and any(f.suffix == ".png" and f.name.startswith("gauge_")
                                                     for f in out.iterdir())


def test_cli_diagnose_keys(tmp_path):
    from torchslide.commands.diagnose import load_diagnose_config
    from torchslide.config import ConfigError
    from torchslide.terrain.synthetic import inclined_plane
    dem = inclined_plane(30.0, 50.0, slope_length=500.0, runout_length=700.0, width=300.0)
    p, _ = _setup(tmp_path, grid=dem.shape, candidates='["entrainment"]\nwaic_min = 4\nexplain_min = 0.6\ness_min = 3\nn_total_max = 40\nprofile_top = 0')
    dg = load_diagnose_config(p).extra["diagnose"]
    assert (dg["waic_min"], dg["explain_min"], dg["ess_min"], dg["bf_min"]) == (4.0, 0.6, 3.0, 6.0)
    assert dg["n_total_max"] == 40 and dg["local_max_iter"] == 30 and dg["profile_top"] == 0
    assert dg["release_volume_sd"] == 0.0
    q, _ = _setup(tmp_path, grid=dem.shape, candidates='["entrainment"]\nrelease_volume_sd = 0.05')
    assert load_diagnose_config(q).extra["diagnose"]["release_volume_sd"] == 0.05
    for extra, msg in (("bf_minimum = 3", "unknown key 'bf_minimum'"), ("explain_min = 2", "explain_min"),
                       ("release_volume_sd = 0.6", r"release_volume_sd must be a relative sd in \[0, 0.5\), got 0.6"),
                       ("release_volume_sd = 'x'", "release_volume_sd must be"),
                       ("release_volume_sd = 0.1\nmodel_error_runs = 0", "release_volume_sd = 0.1 needs model_error_runs >= 2"),
                       ("refit_refine_rounds = 1", "unknown key 'refit_refine_rounds'"),
                       ("model_error_runs = 1", "model_error_runs"), ("model_error_factor = 1", "model_error_factor"),
                       ("local_lhs = -1", "local_lhs"), ("profile_top = -1", "profile_top"),
                       ("local_max_iter = 0", r"local_max_iter must be an integer >= 1, got 0"),
                       ("ess_min = 0.5", "ess_min"), ("waic_min = 'x'", "waic_min")):
        q, _ = _setup(tmp_path, grid=dem.shape, candidates=f'["entrainment"]\n{extra}')
        with pytest.raises(ConfigError, match=msg):
            load_diagnose_config(q)


def test_cli_fine_terrain_for_the_model_error(tmp_path):
    """[diagnose] fine_terrain: a [terrain]-like table on cells model_error_factor times smaller reaches the
    evaluator as a FineTerrain; another grid, another factor or another release volume stop with an
    error naming the key, before any run."""
    from torchslide.commands.diagnose import load_diagnose_config, make_evaluator
    from torchslide.config import ConfigError
    from torchslide.terrain.synthetic import inclined_plane
    dem = inclined_plane(30.0, 50.0, slope_length=500.0, runout_length=700.0, width=300.0)
    opts = "options = { theta_deg = 30.0, slope_length = 500.0, runout_length = 700.0, width = 300.0 }"

    def table(cellsize=25.0, volume=1.0e5):
        return (f'["entrainment"]\nfine_terrain = {{ synthetic = "inclined_plane", cellsize = {cellsize}, {opts}, '
                f'release = {{ centre = [250.0, 150.0], radii = [120.0, 100.0], volume = {volume} }} }}')

    p, _ = _setup(tmp_path, grid=dem.shape, candidates=table())
    cfg = load_diagnose_config(p)
    ft = cfg.extra["diagnose"]["fine_terrain"]
    assert ft.dem.cellsize == 25.0 and ft.dem.shape == (2 * dem.ny, 2 * dem.nx)
    assert math.isclose(float((ft.release * ft.dem.surface_area()).sum()), 1.0e5, rel_tol=1e-9)
    assert make_evaluator(cfg).fine_terrain is ft
    p0, _ = _setup(tmp_path, grid=dem.shape, candidates='["entrainment"]')
    assert load_diagnose_config(p0).extra["diagnose"]["fine_terrain"] is None
    for kw, msg in ((dict(cellsize=30.0), r"fine_terrain.*cellsize 30 m must divide"),
                    (dict(cellsize=12.5), r"fine_terrain: its cells are 4 times smaller.*model_error_factor is 2"),
                    (dict(volume=2.0e5), r"fine_terrain: release volume 2e\+05 m3 differs")):
        q, _ = _setup(tmp_path, grid=dem.shape, candidates=table(**kw))
        with pytest.raises(ConfigError, match=msg):
            load_diagnose_config(q)


def test_cli_fit_max(tmp_path):
    """[diagnose] fit_max: off by default, one number or a table per observable name; an unknown
    observable or a non-number stops with an error naming the key before any run."""
    from torchslide.commands.diagnose import budgets_and_thresholds, load_diagnose_config
    from torchslide.config import ConfigError
    from torchslide.terrain.synthetic import inclined_plane
    dem = inclined_plane(30.0, 50.0, slope_length=500.0, runout_length=700.0, width=300.0)
    p, _ = _setup(tmp_path, grid=dem.shape, candidates='["entrainment"]')
    assert budgets_and_thresholds(load_diagnose_config(p))[1].fit_max is None
    p, _ = _setup(tmp_path, grid=dem.shape, candidates='["entrainment"]\nfit_max = 4')
    assert budgets_and_thresholds(load_diagnose_config(p))[1].fit_max == 4.0
    p, _ = _setup(tmp_path, grid=dem.shape, candidates='["entrainment"]\nfit_max = { "G1:speed" = -1.5, deposit_map = -30 }')
    assert budgets_and_thresholds(load_diagnose_config(p))[1].fit_max == {"G1:speed": -1.5, "deposit_map": -30.0}
    for extra, msg in (('fit_max = { "G9:h" = 1.0 }', r"fit_max names unknown observable\(s\) \['G9:h'\]"),
                       ('fit_max = { "G1:h" = "x" }', "fit_max: every level must be a finite number"),
                       ("fit_max = 'high'", "fit_max must be a finite number or a table")):
        q, _ = _setup(tmp_path, grid=dem.shape, candidates=f'["entrainment"]\n{extra}')
        with pytest.raises(ConfigError, match=msg):
            load_diagnose_config(q)


def test_report_cell_says_how_each_candidate_was_checked():
    from torchslide.diagnose.report import _refit_check

    assert _refit_check({"log_evidence": None}) == "-"
    assert _refit_check({"log_evidence": -110.0, "evidence_converged": True}) == "evidence converged"
    assert _refit_check({"log_evidence": -110.0, "evidence_converged": False}) == "evidence NOT converged"
    cell = _refit_check({"log_evidence": -110.0, "inference": "laplace", "likelihood_ratio": 12.3, "lr_pvalue": 2.3e-4,
                         "profile_ends": {"two_ln_drop": [2.5, 3.1], "gaussian": 2.71}})
    assert cell.startswith("local fit (Laplace); 2 ln LR 12.3, p 0.00023") and "2.50 / 3.10 (Gaussian 2.71)" in cell
    assert "profile (Laplace" not in cell
    cell = _refit_check({"log_evidence": -109.0, "inference": "laplace", "likelihood_ratio": 12.3, "lr_pvalue": 2.3e-4,
                         "profile_ends": {"two_ln_drop": [0.8, 0.5], "gaussian": 2.71}, "two_ln_bf_laplace": 5.2})
    assert cell.endswith("log Z with the switch's profile (Laplace: 2 ln BF 5.2)")


def test_cli_design_ranks_where_a_new_gauge_reveals_each_candidate(tmp_path, capsys):
    """`torchslide diagnose CONFIG --out DIR --design`: the baseline's local fit, then design.json (every
    candidate's detectable switch now and the best new gauges), a raster per candidate and the figure;
    a bad --design-sigma is a one-line error."""
    import json
    from torchslide.terrain.synthetic import inclined_plane
    dem = inclined_plane(30.0, 50.0, slope_length=500.0, runout_length=700.0, width=300.0)
    p, _ = _setup(tmp_path, grid=dem.shape,
                  candidates='["curvature", "mu_i"]\nlocal_lhs = 4\nlocal_starts = 1\nlocal_max_iter = 4\n')
    out = tmp_path / "out"
    assert main(["diagnose", str(p), "--out", str(out), "--design", "--design-sigma", "0.5"]) == 2
    assert "--design-sigma must be two numbers" in capsys.readouterr().err
    assert main(["diagnose", str(p), "--out", str(out), "--quiet", "--design", "--design-top", "2"]) == 0
    j = json.loads((out / "design.json").read_text())
    assert set(j["candidates"]) == {"curvature", "mu_i"} and set(j["baseline"]) == {"mu", "xi"}
    for c, v in j["candidates"].items():
        assert len(v["best_new_gauges"]) == 2
        assert (out / f"design_{c}.asc").exists()
    assert (out / "design.png").exists()
    # --discriminate A,B: where one more gauge tells two candidates apart; bad pairs are one line
    assert main(["diagnose", str(p), "--out", str(out), "--design", "--discriminate", "mu_i,mu_i"]) == 2
    assert "--discriminate needs two different candidates" in capsys.readouterr().err
    assert main(["diagnose", str(p), "--out", str(out), "--discriminate", "mu_i,curvature"]) == 2
    assert "goes with --design" in capsys.readouterr().err
    d2 = tmp_path / "disc"
    assert main(["diagnose", str(p), "--out", str(d2), "--quiet", "--design", "--discriminate", "mu_i,curvature"]) == 0
    j = json.loads((d2 / "design.json").read_text())
    assert set(j["candidates"]) == {"mu_i|curvature", "curvature|mu_i"}
    assert (d2 / "design_mu_i_vs_curvature.asc").exists() and (d2 / "design.png").exists()


def test_a_diagnosis_killed_after_each_final_write_resumes_to_every_file(tmp_path, monkeypatch, capsys):
    """Killed after its checkpoint or after any report file, `diagnose --resume` writes every report file
    (report.json equal to the uninterrupted run's) and finished.json last, without running the solver again;
    a resume with no checkpoint or with another recording is one line, exit 2."""
    import json
    import shutil

    from torchslide.terrain.synthetic import inclined_plane

    from .conftest import killed_after_write
    dem = inclined_plane(30.0, 50.0, slope_length=500.0, runout_length=700.0, width=300.0)
    p, _ = _setup(tmp_path, grid=dem.shape, candidates=tiny_budgets('detectability = "linearised"'))
    ref = tmp_path / "ref"
    assert main(["diagnose", str(p), "--out", str(ref), "--quiet"]) == 0
    done = json.loads((ref / "finished.json").read_text())["files"]
    assert "diagnosis.pkl" in done and "report.json" in done and "report.md" in done and len(done) >= 5
    import torchslide.diagnose as diagnose_pkg
    monkeypatch.setattr(diagnose_pkg, "diagnose", lambda *a, **k: pytest.fail("a resume ran the inference again"))
    k = 0
    while True:
        k += 1
        out = tmp_path / f"killed_{k}"
        out.mkdir()
        shutil.copy(ref / "diagnosis.pkl", out / "diagnosis.pkl")     # killed right after the checkpoint
        if not killed_after_write(monkeypatch, done, k,
                                  lambda: main(["diagnose", str(p), "--out", str(out), "--quiet", "--resume"])):
            break
        assert not (out / "finished.json").exists()
        assert main(["diagnose", str(p), "--out", str(out), "--quiet", "--resume"]) == 0
        assert json.loads((out / "report.json").read_text()) == json.loads((ref / "report.json").read_text())
        assert sorted(json.loads((out / "finished.json").read_text())["files"]) == sorted(done), k
        assert all((out / f).is_file() for f in done), k
    assert k == len(done)              # each report file was a kill point (the checkpoint, copied, the first)
    capsys.readouterr()
    assert main(["diagnose", str(p), "--out", str(tmp_path / "empty"), "--quiet", "--resume"]) == 2
    assert "holds no interrupted diagnosis" in capsys.readouterr().err
    (tmp_path / "g1.csv").write_text((tmp_path / "g1.csv").read_text().replace("2,1,3", "2,1.5,3"))
    assert main(["diagnose", str(p), "--out", str(ref), "--quiet", "--resume"]) == 2
    assert "made from another config or recording" in capsys.readouterr().err


def test_cli_cellsize_auto_chooses_the_grid_and_reports_it(tmp_path):
    """[diagnose] cellsize = "auto": the grid chosen by its own error (the deposit map averaged onto it)
    reaches the diagnosis, report.json "grid" and report.md say which and why, the located mismatches the
    grid's error accounts for are in decision["resolution"]; a fixed number or fine_terrain with "auto" is
    refused naming the key."""
    import json
    from torchslide.commands.diagnose import load_diagnose_config
    from torchslide.config import ConfigError
    from torchslide.terrain.synthetic import inclined_plane
    dem = inclined_plane(30.0, 50.0, slope_length=500.0, runout_length=700.0, width=300.0)
    p, _ = _setup(tmp_path, grid=dem.shape,
                  candidates=tiny_budgets('cellsize = "auto"\nmax_cells = 150\ndetectability = "linearised"'))
    out = tmp_path / "out"
    assert main(["diagnose", str(p), "--out", str(out), "--quiet"]) == 0
    j = json.loads((out / "report.json").read_text())
    g = j["grid"]
    assert g["max_cells"] == 150 and g["cellsize"] in [t["cellsize"] for t in g["tried"] if "ratio" in t]
    assert [t["cellsize"] for t in g["tried"]] == sorted((t["cellsize"] for t in g["tried"]), reverse=True)
    assert all("skipped" in t or set(t["ratio"]) == {"G1:h", "G1:speed", "deposit_map"} for t in g["tried"])
    assert "resolution" in j["decision"]
    md = (out / "report.md").read_text()
    assert f"Inversion grid: {g['cellsize']:g} m, chosen by its own error" in md
    for extra, msg in (("cellsize = 40.0", r'cellsize must be "auto"'), ("max_cells = 5", "max_cells must be an integer"),
                       ('cellsize = "auto"\nfine_terrain = { synthetic = "inclined_plane", cellsize = 25.0, options = '
                        '{ theta_deg = 30.0, slope_length = 500.0, runout_length = 700.0, width = 300.0 }, release = '
                        '{ centre = [250.0, 150.0], radii = [120.0, 100.0], volume = 1.0e5 } }', "leave out fine_terrain")):
        q, _ = _setup(tmp_path, grid=dem.shape, candidates=f'["mu_i"]\n{extra}')
        with pytest.raises(ConfigError, match=msg):
            load_diagnose_config(q)


def test_cli_finer_shift(tmp_path):
    """[diagnose] finer_shift: the sigmas a grid-error round must move a candidate's error by before the
    comparison is made on the finer grid (Budgets.finer_shift; 0: never); a negative or non-number is refused
    naming the key."""
    from torchslide.commands.diagnose import budgets_and_thresholds, load_diagnose_config
    from torchslide.config import ConfigError
    from torchslide.diagnose import Budgets
    from torchslide.terrain.synthetic import inclined_plane
    dem = inclined_plane(30.0, 50.0, slope_length=500.0, runout_length=700.0, width=300.0)
    p, _ = _setup(tmp_path, grid=dem.shape, candidates='["entrainment"]')
    assert budgets_and_thresholds(load_diagnose_config(p))[0].finer_shift == Budgets().finer_shift == 1.0
    p, _ = _setup(tmp_path, grid=dem.shape, candidates='["entrainment"]\nfiner_shift = 0')
    assert budgets_and_thresholds(load_diagnose_config(p))[0].finer_shift == 0.0
    for extra in ("finer_shift = -1", "finer_shift = 'x'"):
        q, _ = _setup(tmp_path, grid=dem.shape, candidates=f'["entrainment"]\n{extra}')
        with pytest.raises(ConfigError, match=r"finer_shift must be a number of sigmas >= 0"):
            load_diagnose_config(q)


def test_cli_detectability(tmp_path):
    """[diagnose] detectability: "measured" (default) or "linearised" reaches Budgets; anything else is
    refused naming the key and the value."""
    from torchslide.commands.diagnose import budgets_and_thresholds, load_diagnose_config
    from torchslide.config import ConfigError
    from torchslide.terrain.synthetic import inclined_plane
    dem = inclined_plane(30.0, 50.0, slope_length=500.0, runout_length=700.0, width=300.0)
    p, _ = _setup(tmp_path, grid=dem.shape, candidates='["entrainment"]')
    assert budgets_and_thresholds(load_diagnose_config(p))[0].detectability == "measured"
    p, _ = _setup(tmp_path, grid=dem.shape, candidates='["entrainment"]\ndetectability = "linearised"')
    assert budgets_and_thresholds(load_diagnose_config(p))[0].detectability == "linearised"
    q, _ = _setup(tmp_path, grid=dem.shape, candidates='["entrainment"]\ndetectability = "linear"')
    with pytest.raises(ConfigError, match=r"diag.toml: \[diagnose\] detectability must be \"measured\" or "
                                          r"\"linearised\", got 'linear'"):
        load_diagnose_config(q)
