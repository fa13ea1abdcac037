"""End-to-end `torchslide calibrate` on a tiny terrain, and its bad-input errors (exit 2, nothing run)."""
from __future__ import annotations

import csv
import json

import numpy as np
import pytest

from torchslide.cli import main

from .conftest import CALIBRATE_BASE as BASE, CALIBRATE_CAL as CAL, CALIBRATE_OBS as OBS, CALIBRATE_PRIOR as PRIOR, truth_velocity, write_config as write


def test_calibrate_round_trip_and_resume(tmp_path, capsys):
    v = truth_velocity(tmp_path)
    assert v > 1.0
    cfg = write(tmp_path, BASE + PRIOR + OBS.format(value=v, sigma=0.1 * v) + CAL)
    out = tmp_path / "cal"
    capsys.readouterr()
    assert main(["calibrate", str(cfg), "--out", str(out), "--quiet"]) == 0
    post = json.loads((out / "posterior.json").read_text())
    for key in ("mean", "sd", "map", "hdr90", "log_evidence", "runs"):
        assert key in post, key
    assert post["n_runs"] == 10 and len(post["runs"]) == 10
    assert np.isfinite(post["log_evidence"])
    assert post["truth"] == {"mu": 0.2, "xi": 1000.0}
    for n in ("mu", "xi"):
        lo, hi = post["hdr90"][n]
        assert lo <= post["map"][n] <= hi
    npz = np.load(out / "posterior.npz")
    dens, a0, a1 = npz["posterior_grid"], npz["axis_0"], npz["axis_1"]
    assert dens.shape == (30, 30)
    assert abs(dens.sum() * (a0[1] - a0[0]) * (a1[1] - a1[0]) - 1.0) < 1e-6
    rows = list(csv.DictReader(open(out / "runs.csv")))
    assert len(rows) == 10 and all(r["v_plane"] != "" for r in rows)
    # z of every run is Eq. 10 with the uniform prior density and, by default, the likelihood of the learnt
    # discrepancy: the Gaussian of Eq. 6-7 with its variance u sigma^2 integrated over p(u) = u^-2, u >= 1
    from scipy import integrate, stats

    sigma = 0.1 * v
    log_prior = -np.log((0.5 - 0.05) * (2000.0 - 200.0))
    assert post["discrepancy_factors"] == {}        # no map or series: nothing to learn a correlation of
    for r in rows:
        pred = float(r["v_plane"])
        marginal = integrate.quad(lambda u: u**-2 * stats.norm.pdf(v, pred, sigma * np.sqrt(u)), 1.0, np.inf)[0]
        assert float(r["z"]) == pytest.approx(np.log(marginal) + log_prior, rel=1e-7, abs=1e-7)
    assert (out / "posterior.png").exists()
    assert any((out / "tensorboard").rglob("events.out.tfevents*"))
    # the best run's fit of every observation: that run's prediction, standardised by sigma
    fit = post["best_run_fit"]
    best = max(rows, key=lambda r: float(r["z"]))
    assert fit["x"] == pytest.approx({"mu": float(best["mu"]), "xi": float(best["xi"])}, rel=1e-9)
    (o,) = fit["observations"]
    assert o["name"] == "v_plane" and o["predicted"] == pytest.approx(float(best["v_plane"]), rel=1e-9)
    assert o["standardised_residual"] == pytest.approx((o["predicted"] - v) / sigma, rel=1e-9)
    assert abs(o["standardised_residual"]) < 3
    assert "misses" not in capsys.readouterr().err

    # a second call without --resume refuses to overwrite the earlier calibration
    assert main(["calibrate", str(cfg), "--out", str(out), "--quiet"]) == 2
    assert "--resume" in capsys.readouterr().err
    # --resume on a finished calibration repeats no run and gives the same posterior
    assert main(["calibrate", str(cfg), "--out", str(out), "--quiet", "--resume"]) == 0
    post2 = json.loads((out / "posterior.json").read_text())
    assert post2["n_runs"] == 10
    assert [r["x"] for r in post2["runs"]] == [r["x"] for r in post["runs"]]
    assert post2["map"] == pytest.approx(post["map"])
    # the resumed invocation ran nothing: the best-run fit of the first invocation's runs is kept
    assert post2["best_run_fit"] == post["best_run_fit"]


@pytest.mark.parametrize("prior, obs, msg", [
    ("[prior]\nmu = [0.3, 0.1]\n", OBS.format(value=10.0, sigma=1.0), "low"),
    (PRIOR, OBS.format(value=10.0, sigma=0.0), "sigma"),
    (PRIOR, OBS.format(value=10.0, sigma=-1.0), "sigma"),
    (PRIOR, '[[observations]]\nkind = "max_velocity"\nx = 475.0\ny = 150.0\nvalue = 3.0\n', "sigma"),
    (PRIOR, '[[observations]]\nkind = "peak_pressure"\nvalue = 3.0\nsigma = 1.0\n', "unknown observation kind"),
    (PRIOR, '[[observations]]\nkind = "max_velocity"\nx = 9000.0\ny = 150.0\nvalue = 3.0\nsigma = 1.0\n', "outside the DEM"),
    ("[prior]\nfriction = [0.1, 0.3]\n", OBS.format(value=10.0, sigma=1.0), "friction"),
    (PRIOR, OBS.format(value=10.0, sigma=1.0) + "[calibration]\nn_initial = 10\nn_total = 5\n", "n_total"),
    (PRIOR, OBS.format(value=10.0, sigma=1.0) + "[calibration]\ntruth = { mu = 0.2 }\n", "truth"),
    # a prior reaching values the model refuses (mu <= 0; a switch beyond [0, 1]), before any run
    ("[prior]\nmu = [-0.1, 0.4]\n", OBS.format(value=10.0, sigma=1.0), "range low = -0.1 is outside the allowed values (0, inf)"),
    ("[prior]\nmu = { dist = \"truncnormal\", mean = 0.2, sd = 0.1, low = 0.0, high = 0.5 }\n",
     OBS.format(value=10.0, sigma=1.0), "parameter mu: range low = 0.0"),
    ("[prior]\nmu = [0.1, 0.4]\nearth_pressure = [0.0, 1.5]\n", OBS.format(value=10.0, sigma=1.0),
     "parameter earth_pressure: range high = 1.5 is outside the allowed values [0, 1]"),
    # a recorded speed cannot be negative
    (PRIOR, OBS.format(value=-3.0, sigma=1.0), "a recorded max_velocity cannot be negative, got -3.0 m/s"),
    # budgets the active learner cannot start with, and settings of the wrong type (were tracebacks)
    (PRIOR, OBS.format(value=10.0, sigma=1.0) + "[calibration]\nn_initial = 1\nn_total = 1\n", "n_initial must be >= 2"),
    (PRIOR, OBS.format(value=10.0, sigma=1.0) + "[calibration]\ngrid_size = 1\n", "grid_size must be >= 2"),
    (PRIOR, OBS.format(value=10.0, sigma=1.0) + "[calibration]\nseed = -1\n", "seed must be an integer >= 0, got -1"),
    (PRIOR, OBS.format(value=10.0, sigma=1.0) + "[calibration]\nclip_range = 0.0\n", "clip_range must be a finite number > 0"),
    (PRIOR, OBS.format(value=10.0, sigma=1.0) + '[calibration]\ntv_threshold = "small"\n',
     "tv_threshold must be a finite number >= 0, got 'small'"),
    (PRIOR, OBS.format(value=10.0, sigma=1.0) + '[calibration]\ninference = "laplace"\n',
     'inference must be "auto", "local" or "emulator", got \'laplace\''),
    (PRIOR, OBS.format(value=10.0, sigma=1.0) + '[calibration]\nlocal_max_fraction = 0\n',
     "local_max_fraction must be a share of the prior box in (0, 1], got 0"),
])
def test_bad_input_is_refused_before_any_run(tmp_path, capsys, prior, obs, msg):
    cfg = write(tmp_path, BASE + prior + obs)
    out = tmp_path / "cal"
    assert main(["calibrate", str(cfg), "--out", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("torchslide: error:") and msg in err
    assert len(err.strip().splitlines()) == 1
    assert not out.exists()


def test_every_documented_prior_distribution_parses_to_its_density(tmp_path):
    """The [prior] forms of the command's doc (uniform, truncnormal (mean, sd), lognormal (mean_log, sd_log),
    gamma (concentration, rate)) build the bayes components with those values, and their log densities
    are the truncated scipy ones."""
    from scipy import stats

    from torchslide.bayes import Gamma, LogNormal, TruncatedNormal, Uniform
    from torchslide.calibration_config import load_calibration_config

    prior = """
[prior]
mu = { dist = "truncnormal", mean = 0.2, sd = 0.1, low = 0.05, high = 0.5 }
xi = { dist = "lognormal", mean_log = 6.9, sd_log = 0.5, low = 100.0, high = 2200.0 }
tau_y = { dist = "gamma", concentration = 2.0, rate = 0.5, low = 0.0, high = 20.0 }
kappa = { dist = "uniform", low = 0.0, high = 0.01 }
"""
    cfg = load_calibration_config(write(tmp_path, BASE + prior + OBS.format(value=10.0, sigma=1.0)))
    c = cfg.extra["prior"].components
    assert isinstance(c["mu"], TruncatedNormal) and (c["mu"].loc, c["mu"].scale) == (0.2, 0.1)
    assert isinstance(c["xi"], LogNormal) and (c["xi"].mu, c["xi"].sigma) == (6.9, 0.5)
    assert isinstance(c["tau_y"], Gamma) and (c["tau_y"].concentration, c["tau_y"].rate) == (2.0, 0.5)
    assert isinstance(c["kappa"], Uniform) and (c["kappa"].low, c["kappa"].high) == (0.0, 0.01)
    checks = [("mu", stats.truncnorm((0.05 - 0.2) / 0.1, (0.5 - 0.2) / 0.1, loc=0.2, scale=0.1), [0.1, 0.3]),
              ("xi", stats.lognorm(0.5, scale=np.exp(6.9)), [300.0, 1500.0]),
              ("tau_y", stats.gamma(2.0, scale=2.0), [1.0, 7.0])]
    for name, d, v in checks:
        lp = c[name].log_prob(np.asarray(v)).numpy()
        if name in ("xi", "tau_y"):     # truncated to [low, high]: renormalised by the mass inside
            lo, hi = c[name].low, c[name].high
            expect = d.logpdf(v) - np.log(d.cdf(hi) - d.cdf(lo))
        else:
            expect = d.logpdf(v)
        assert lp == pytest.approx(expect, rel=1e-9), name


def test_a_datum_no_run_reproduces_is_reported(tmp_path, capsys):
    """A recorded speed ten times what any parameter set gives (a typo, a wrong unit): the posterior can only
    follow the prior, so calibrate says which observation the best run misses, by how many sigma."""
    v = truth_velocity(tmp_path)
    cal = CAL.replace("n_initial = 6\nn_total = 10", "n_initial = 4\nn_total = 4")
    cfg = write(tmp_path, BASE + PRIOR + OBS.format(value=10 * v, sigma=0.1 * v) + cal)
    capsys.readouterr()
    assert main(["calibrate", str(cfg), "--out", str(tmp_path / "cal"), "--quiet"]) == 0
    err = capsys.readouterr().err
    fit = json.loads((tmp_path / "cal" / "posterior.json").read_text())["best_run_fit"]
    r = fit["observations"][0]["standardised_residual"]
    assert r < -3 and fit["n_runs"] == 4
    assert f"torchslide: warning: the best of 4 runs misses v_plane by {r:+.1f} sigma" in err
    assert "does the flow reach it by t_end?" in err


def test_calibrate_shows_the_solver_calls_progress(tmp_path, capsys):
    """Without --quiet, calibrate's bar of runs is accompanied by each solver call's simulated time, so a
    long initial call does not look like a hang."""
    cfg = write(tmp_path, BASE + PRIOR + OBS.format(value=20.0, sigma=2.0) + CAL)
    assert main(["calibrate", str(cfg), "--out", str(tmp_path / "cal")]) == 0
    err = capsys.readouterr().err
    assert "calibrate:" in err and "s simulated" in err and "/60 s simulated" in err


def test_a_posterior_too_sharp_for_the_emulator_is_fitted_on_the_solver(tmp_path, capsys):
    """Peak speeds and depths at three points known to 1 %: the posterior fills a sliver of the prior box,
    so calibrate (inference "auto") fits the mode on the solver and reports its Laplace posterior, which
    holds the truth; posterior.json says which path was taken and why. "emulator" keeps the GP's."""
    from torchslide.calibration_config import load_calibration_config, make_evaluator

    pts = [(375.0, 150.0), (475.0, 150.0), (575.0, 150.0)]
    obs = "".join(f'\n[[observations]]\nkind = "{k}"\nname = "{k}_{i}"\nx = {x}\ny = {y}\nvalue = 1.0\nsigma = 1.0\n'
                  for i, (x, y) in enumerate(pts) for k in ("max_velocity", "max_height"))
    ev = make_evaluator(load_calibration_config(write(tmp_path, BASE + PRIOR + obs + CAL)))
    _, y = ev.evaluate(np.array([[0.2, 1000.0]]))
    y = y[0].numpy()
    assert np.all(y > 0.1)
    obs = "".join(f'\n[[observations]]\nkind = "{k}"\nname = "{k}_{i}"\nx = {x}\ny = {yy}\nvalue = {v:.10g}\n'
                  f'sigma = {0.01 * v:.10g}\n' for (i, (x, yy)), k, v in
                  zip([(i, p) for i, p in enumerate(pts) for _ in range(2)], ["max_velocity", "max_height"] * 3, y))
    for inference in ("auto", "emulator"):
        cfg = write(tmp_path, BASE + PRIOR + obs + CAL + f'inference = "{inference}"\n')
        out = tmp_path / inference
        assert main(["calibrate", str(cfg), "--out", str(out), "--quiet"]) == 0
        post = json.loads((out / "posterior.json").read_text())
        inf = post["inference"]
        if inference == "emulator":
            assert inf["path"] == "emulator" and inf["why"] == 'inference = "emulator"'
            continue
        assert inf["path"] == "local" and inf["box_fraction"] < 0.05 and "of the prior box" in inf["why"]
        assert inf["n_runs"] > 0 and np.isfinite(inf["log_evidence_emulator"])
        assert post["n_runs"] == 10 and post["stopped_reason"].startswith("laplace")
        for n, t in (("mu", 0.2), ("xi", 1000.0)):
            lo, hi = post["hdr90"][n]
            assert lo <= t <= hi and (hi - lo) < 0.1 * (PRIOR_BOX[n][1] - PRIOR_BOX[n][0])
        assert (out / "posterior.png").exists()
        assert max(abs(o["standardised_residual"]) for o in post["best_run_fit"]["observations"]) < 1.0
        cap = capsys.readouterr()
        assert "inference: local" in cap.out and "misses" not in cap.err


PRIOR_BOX = {"mu": (0.05, 0.5), "xi": (200.0, 2000.0)}
