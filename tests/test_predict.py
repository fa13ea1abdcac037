"""`torchslide predict`: posterior-predictive runs of a calibration (maps, data check) and its bad input."""
from __future__ import annotations

import json
import re

import numpy as np
import pytest

from torchslide.cli import main
from torchslide.predict import observation_check, posterior_samples
from torchslide.terrain import read_asc

from .conftest import CALIBRATE_BASE as BASE, CALIBRATE_CAL as CAL, CALIBRATE_OBS as OBS, CALIBRATE_PRIOR as PRIOR, truth_velocity, write_config as write

IMPACT = """
[[observations]]
kind = "impact_area"
name = "area"
value = {value}
sigma = {sigma}
"""


@pytest.fixture(scope="module")
def calibrated(tmp_path_factory):
    """A finished tiny calibration (max velocity at one point and the impact area, recorded from the truth)."""
    d = tmp_path_factory.mktemp("pred")
    v = truth_velocity(d)
    truth = json.loads((d / "truth" / "summary.json").read_text())
    cfg = write(d, BASE + PRIOR + OBS.format(value=v, sigma=0.1 * v)
                + IMPACT.format(value=truth["impact_area"], sigma=0.1 * truth["impact_area"]) + CAL)
    assert main(["calibrate", str(cfg), "--out", str(d / "cal"), "--quiet"]) == 0
    return d, cfg, truth


def test_predict_writes_maps_and_checks_the_data(calibrated, capsys):
    d, cfg, truth = calibrated
    out = d / "pred"
    capsys.readouterr()
    code = main(["predict", str(cfg), "--calibration", str(d / "cal"), "--out", str(out), "--n", "12", "--quiet"])
    _, err = capsys.readouterr()
    assert code == 0, err
    names = {p.name for p in out.iterdir()}
    assert {"impact_probability.asc", "h_max_p05.asc", "h_max_p50.asc", "h_max_p95.asc", "v_max_p50.asc",
            "v_max_p95.asc", "h_final_p50.asc", "h_final_p95.asc", "predictive.json", "draws.csv",
            "impact_probability.png", "observations.png"} <= names
    info = json.loads((out / "predictive.json").read_text())
    assert info["n_draws"] == 12 and info["n_ok"] + info["n_failed"] == 12
    p = read_asc(out / "impact_probability.asc").z
    assert p.min() >= 0.0 and p.max() <= 1.0 and p.max() == 1.0  # the release cells are reached by every draw
    lo, mid, hi = (read_asc(out / f"h_max_p{q}.asc").z for q in ("05", "50", "95"))
    assert np.all(lo <= mid + 1e-9) and np.all(mid <= hi + 1e-9)
    # the truth made the data, so each recorded value lies inside its 90 % posterior-predictive interval
    by = {c["name"]: c for c in info["observations"]}
    assert set(by) == {"v_plane", "area"}
    for c in by.values():
        assert c["inside"], c
        assert 0.0 <= c["interval90"][0] < c["value"] < c["interval90"][1]     # a speed and an area: >= 0
    # the mean impact area of the maps is the draws' own impact-area prediction (same threshold, 0.5 m)
    rows = np.genfromtxt(out / "draws.csv", delimiter=",", names=True)
    assert rows.shape == (info["n_ok"],)
    assert info["impact_area_m2"]["mean"] == pytest.approx(rows["area"].mean(), rel=1e-9)
    assert by["area"]["model_mean"] == pytest.approx(rows["area"].mean(), rel=1e-12)
    # draws come from the posterior: inside the prior box, around the calibrated mean
    post = json.loads((d / "cal" / "posterior.json").read_text())
    assert 0.05 <= rows["mu"].min() and rows["mu"].max() <= 0.5
    assert abs(info["parameters"]["mu"]["mean"] - post["mean"]["mu"]) < 3 * post["sd"]["mu"]


def test_predict_flags_a_value_the_model_cannot_reproduce(calibrated, capsys, tmp_path):
    d, cfg, truth = calibrated
    bad = write(tmp_path, cfg.read_text().replace(f"value = {truth['impact_area']}", f"value = {3 * truth['impact_area']}"))
    capsys.readouterr()
    code = main(["predict", str(bad), "--calibration", str(d / "cal"), "--out", str(tmp_path / "p"), "--n", "8",
                 "--quiet"])
    _, err = capsys.readouterr()
    assert code == 0
    info = json.loads((tmp_path / "p" / "predictive.json").read_text())
    area = [c for c in info["observations"] if c["name"] == "area"][0]
    assert not area["inside"] and area["percentile"] == 1.0
    assert "area = " in err and "outside the 90 % posterior-predictive interval" in err


def test_predict_map_threshold_follows_the_impact_area_observation(calibrated, capsys, tmp_path):
    """Without --threshold the map uses the impact_area observation's threshold, so its mean impact area
    (sum of P times the solver's cell area) is the draws' own impact-area prediction."""
    d, cfg, _ = calibrated
    c = write(tmp_path, cfg.read_text().replace('name = "area"\n', 'name = "area"\nthreshold = 2.0\n'))
    assert main(["predict", str(c), "--calibration", str(d / "cal"), "--out", str(tmp_path / "p"), "--n", "6",
                 "--quiet"]) == 0
    info = json.loads((tmp_path / "p" / "predictive.json").read_text())
    rows = np.genfromtxt(tmp_path / "p" / "draws.csv", delimiter=",", names=True)
    assert info["threshold_m"] == 2.0
    assert info["impact_area_m2"]["mean"] == pytest.approx(rows["area"].mean(), rel=1e-9)


@pytest.mark.parametrize("mutate,args,match", [
    (None, ["--n", "0"], "--n must be >= 1"),
    (None, ["--threshold", "-1"], "--threshold must be >= 0"),
    (lambda t: t.replace("mu = [0.05, 0.5]", "mu = [0.05, 0.6]"), [], "ran on the prior box"),
    (lambda t: t.replace("xi = [200.0, 2000.0]\n", "").replace("truth = { mu = 0.2, xi = 1000.0 }", "truth = { mu = 0.2 }"),
     [], r"calibrated \['mu', 'xi'\], but the config's \[prior\] names \['mu'\]"),
])
def test_predict_bad_input_exit_2(calibrated, capsys, tmp_path, mutate, args, match):
    d, cfg, _ = calibrated
    c = cfg if mutate is None else write(tmp_path, mutate(cfg.read_text()))
    capsys.readouterr()
    code = main(["predict", str(c), "--calibration", str(d / "cal"), "--out", str(tmp_path / "p"), "--quiet", *args])
    _, err = capsys.readouterr()
    assert code == 2 and err.startswith("torchslide: error: ") and err.count("\n") == 1, err
    assert re.search(match, err), err
    assert not (tmp_path / "p").exists()


def test_predict_without_a_calibration_folder(calibrated, capsys, tmp_path):
    d, cfg, _ = calibrated
    code = main(["predict", str(cfg), "--calibration", str(tmp_path / "none"), "--out", str(tmp_path / "p")])
    _, err = capsys.readouterr()
    assert code == 2 and "no posterior.json" in err and "torchslide calibrate" in err


def test_observation_check_coverage_on_a_known_model():
    """f(x) + e with e ~ N(0, sigma): a value drawn from the same model lands inside the 90 % interval
    about 90 % of the time, and its percentile is uniform."""
    rng = np.random.default_rng(1)
    f = rng.normal(10.0, 1.0, size=(400, 1))
    inside, pct = [], []
    for k in range(300):
        v = rng.normal(10.0, 1.0) + rng.normal(0.0, 0.5)
        c = observation_check(f, np.array([v]), np.array([0.5]), ["a"], seed=k)[0]
        inside.append(c["inside"])
        pct.append(c["percentile"])
    assert 0.85 <= np.mean(inside) <= 0.95
    assert abs(np.mean(pct) - 0.5) < 0.05
    c = observation_check(f, np.array([10.0]), np.array([0.5]), ["a"])[0]
    assert c["interval90"][0] == pytest.approx(10 - 1.645 * np.sqrt(1.25), abs=0.15)


def test_posterior_samples_follow_the_grid_density():
    from types import SimpleNamespace

    ax = [np.linspace(0.05, 0.95, 10), np.linspace(0.05, 0.95, 10)]
    dens = np.zeros((10, 10))
    dens[2, 7] = 3.0
    dens[8, 1] = 1.0
    cal = SimpleNamespace(samples=None, posterior_grid=dens, grid_axes=ax, bounds=np.array([[0.0, 0.0], [1.0, 1.0]]))
    s = posterior_samples(cal, 4000, seed=0)
    near_a = (np.abs(s[:, 0] - ax[0][2]) <= 0.05) & (np.abs(s[:, 1] - ax[1][7]) <= 0.05)
    near_b = (np.abs(s[:, 0] - ax[0][8]) <= 0.05) & (np.abs(s[:, 1] - ax[1][1]) <= 0.05)
    assert near_a.sum() + near_b.sum() == 4000
    assert near_a.mean() == pytest.approx(0.75, abs=0.03)


def test_new_recording_interval_respects_the_observables_bound():
    """A speed or thickness cannot be recorded below 0: with lower = 0 the interval of a new recording is
    that of max(0, f + e); without a bound it is the Gaussian one, negative here."""
    f = np.full((50, 1), 0.5)
    free = observation_check(f, np.array([0.2]), np.array([4.0]), ["v"], seed=1)[0]
    bounded = observation_check(f, np.array([0.2]), np.array([4.0]), ["v"], seed=1, lower=np.array([0.0]))[0]
    assert free["interval90"][0] < -5.0
    assert bounded["interval90"][0] == 0.0 and bounded["interval90"][1] == pytest.approx(free["interval90"][1])
    assert bounded["inside"]


def test_predictive_progress_counts_each_chunk_as_it_finishes(calibrated):
    """run_predictive reports the runs done after every chunk of max_batch members, not only at the end."""
    import dataclasses

    from torchslide.calibration_config import load_calibration_config, make_evaluator
    from torchslide.predict import run_predictive

    _, cfg, _ = calibrated
    ev = dataclasses.replace(make_evaluator(load_calibration_config(cfg)), max_batch=2)
    calls, seen = [], []
    chunk = ev.maps_chunk
    ev.maps_chunk = lambda v: calls.append(1) or chunk(v)

    def progress(n):
        seen.append((n, len(calls)))    # the runs reported done, and the chunks run so far

    pr = run_predictive(ev, np.array([[0.2, 1000.0], [0.25, 800.0], [0.3, 1200.0], [0.22, 900.0], [0.28, 700.0]]),
                        0.1, progress=progress)
    assert seen == [(2, 1), (4, 2), (5, 3)] and len(pr.x) == 5


def test_the_grid_error_widens_the_figures_both_ways():
    """A grid's error measured as +30 m on every run widens the run-out's interval by about 1.645 x 30 m on
    both sides, not shifted by +30 m: the calibrated parameters may have absorbed that bias already (its
    sign on a figure is unknown, its size is measured); the area (no half-cell term) likewise."""
    from torchslide.predict import figure_intervals

    figures = np.column_stack([np.full(64, 2e5), np.full(64, 1000.0)])
    error = np.column_stack([np.full(4, 1e4), np.array([29.0, 30.0, 31.0, 30.0])])
    f = figure_intervals(figures, error, seed=0, cellsize=0.0)
    g = f["runout_m"]["with_grid_error"]
    assert g["shift"] == pytest.approx(30.0) and g["sd"] == pytest.approx(30.0, rel=0.01)
    assert g["q05"] == pytest.approx(1000.0 - 1.645 * 30.0, abs=3.0)
    assert g["q95"] == pytest.approx(1000.0 + 1.645 * 30.0, abs=3.0)
    a = f["impact_area_m2"]["with_grid_error"]
    assert a["q05"] < 2e5 - 1.5e4 and a["q95"] > 2e5 + 1.5e4
    assert f["runout_m"]["q05"] == f["runout_m"]["q95"] == 1000.0        # the draws alone are kept as they are
