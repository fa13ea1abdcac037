"""`torchslide sweep`: the brute-force reference posterior over the prior box, resume, and its bad input."""
from __future__ import annotations

import json

import numpy as np
import pytest

from torchslide.cli import main
from torchslide.commands.sweep import interpolate_density
from torchslide.posterior import cell_volume, grid_axes

from .conftest import CALIBRATE_BASE as BASE, CALIBRATE_CAL as CAL, CALIBRATE_OBS as OBS, CALIBRATE_PRIOR as PRIOR, truth_velocity, write_config as write

SMALL = CAL.replace("batch_size = 2", "batch_size = 2\nmax_batch = 4")


@pytest.fixture(scope="module")
def case(tmp_path_factory):
    d = tmp_path_factory.mktemp("sweep")
    v = truth_velocity(d)
    return d, write(d, BASE + PRIOR + OBS.format(value=v, sigma=0.1 * v) + SMALL)


def test_sweep_reference_posterior_and_tv_to_a_calibration(case, capsys):
    d, cfg = case
    assert main(["calibrate", str(cfg), "--out", str(d / "cal"), "--quiet"]) == 0
    assert main(["sweep", str(cfg), "--out", str(d / "sw"), "--n", "4", "--calibration", str(d / "cal"),
                 "--quiet"]) == 0
    info = json.loads((d / "sw" / "sweep.json").read_text())
    assert info["n_runs"] == 16 and info["n_failed"] == 0 and np.isfinite(info["log_evidence"])
    assert 0.0 <= info["tv_to_calibration"] <= 1.0
    npz = np.load(d / "sw" / "sweep.npz")
    axes = [npz["axis_0"], npz["axis_1"]]
    assert npz["density"].shape == (4, 4)
    assert npz["density"].sum() * cell_volume(axes) == pytest.approx(1.0)
    rows = np.genfromtxt(d / "sw" / "sweep.csv", delimiter=",", names=True)
    assert rows.shape == (16,) and np.allclose(np.sort(np.unique(rows["mu"])), axes[0])
    # the grid's z are the evaluator's: the density is exp(z - log Z) at each node
    z = rows["z"].reshape(4, 4)
    assert np.allclose(np.log(npz["density"]), z - info["log_evidence"])
    assert (d / "sw" / "posterior.png").is_file()


def test_sweep_resumes_without_repeating_runs(case, capsys, monkeypatch):
    d, cfg = case
    from torchslide.evaluator import LandslideEvaluator

    calls = []
    real = LandslideEvaluator.evaluate

    def counting(self, x):
        calls.append(len(x))
        if len(calls) == 2:
            raise KeyboardInterrupt  # interrupted after the first solver call
        return real(self, x)

    monkeypatch.setattr(LandslideEvaluator, "evaluate", counting)
    assert main(["sweep", str(cfg), "--out", str(d / "r"), "--n", "3", "--quiet"]) == 130  # Ctrl-C
    assert "interrupted" in capsys.readouterr().err
    assert calls == [4, 4] and (d / "r" / "sweep_checkpoint.npz").is_file()
    code = main(["sweep", str(cfg), "--out", str(d / "r"), "--n", "3", "--quiet"])
    assert code == 2 and "pass --resume" in capsys.readouterr().err
    calls.clear()
    monkeypatch.setattr(LandslideEvaluator, "evaluate", lambda self, x: (calls.append(len(x)), real(self, x))[1])
    assert main(["sweep", str(cfg), "--out", str(d / "r"), "--n", "3", "--quiet", "--resume"]) == 0
    assert calls == [4, 1]  # nodes 5-9 only: the first four were kept
    assert main(["sweep", str(cfg), "--out", str(d / "whole"), "--n", "3", "--quiet"]) == 0
    a = np.load(d / "r" / "sweep.npz")["z"]
    b = np.load(d / "whole" / "sweep.npz")["z"]
    np.testing.assert_allclose(a, b, rtol=1e-12)
    code = main(["sweep", str(cfg), "--out", str(d / "r"), "--n", "4", "--quiet", "--resume"])
    assert code == 2 and "other nodes" in capsys.readouterr().err


@pytest.mark.parametrize("args,match", [(["--n", "1"], "--n must be >= 2"),
                                        (["--n", "400"], "is 160000 runs")])
def test_sweep_bad_input(case, capsys, tmp_path, args, match):
    d, cfg = case
    code = main(["sweep", str(cfg), "--out", str(tmp_path / "s"), "--quiet", *args])
    err = capsys.readouterr().err
    assert code == 2 and match in err and err.count("\n") == 1
    assert not (tmp_path / "s").exists()


def test_interpolate_density_keeps_a_linear_density():
    fine = grid_axes(np.array([[0.0, 0.0], [1.0, 2.0]]), 50)
    coarse = grid_axes(np.array([[0.0, 0.0], [1.0, 2.0]]), 7)
    dens = (1.0 + fine[0])[:, None] * np.ones(50)[None, :]
    q = interpolate_density(fine, dens, coarse)
    want = (1.0 + coarse[0])[:, None] * np.ones(7)[None, :]
    want /= want.sum() * cell_volume(coarse)
    np.testing.assert_allclose(q, want, rtol=1e-9)
    same = interpolate_density(fine, dens / (dens.sum() * cell_volume(fine)), fine)
    np.testing.assert_allclose(same, dens / (dens.sum() * cell_volume(fine)), rtol=1e-12)
