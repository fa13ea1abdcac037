"""`torchslide simulate`: bad input -> exit 2, one-line error, nothing written; a batch round trip."""
from __future__ import annotations

import json

import numpy as np
import pytest

from torchslide.cli import main
from torchslide.terrain import read_asc

from .conftest import cfg_text, write_case


def run_cli(argv, capsys):
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


@pytest.fixture
def case(tmp_path):
    write_case(tmp_path)
    return tmp_path


@pytest.mark.parametrize(
    "mutate,match",
    [
        (lambda t: t + "\n[modle]\nmu = 1\n", r"unknown section \[modle\]"),
        (lambda t: t.replace('rheology = "voellmy"', 'rheology = "bingham"'), "unknown rheology 'bingham'"),
        (lambda t: t.replace("mu = 0.2", "mu = 0.0"), "mu must be > 0"),
        (lambda t: t.replace("xi = 1000.0", "xi = -5.0"), "xi must be > 0"),
        (lambda t: t.replace("x = 300.0", "x = -50.0"), "is outside the DEM"),
        (lambda t: t.replace('"dem.asc"', '"missing.asc"'), "file not found"),
        (lambda t: t.replace("t_end = 20.0", "tend = 20.0"), r"unknown key 'tend' in \[run\]"),
    ],
)
def test_bad_config_exit_2(case, capsys, mutate, match):
    (case / "c.toml").write_text(mutate(cfg_text()))
    out = case / "out"
    code, _, err = run_cli(["simulate", case / "c.toml", "--out", out, "-q"], capsys)
    assert code == 2
    assert err.startswith("torchslide: error: ") and err.count("\n") == 1
    import re

    assert re.search(match, err)
    assert not out.exists()
    assert not [p for p in case.iterdir() if p.name.startswith(".torchslide")]


@pytest.mark.parametrize("kind", ["nan_dem", "neg_release", "grid"])
def test_bad_rasters_exit_2(tmp_path, capsys, kind):
    from torchslide.terrain import DEM

    if kind == "grid":
        write_case(tmp_path, release_dem=DEM(z=np.zeros((10, 35)), cellsize=20.0, yll=-20.0))
    else:
        write_case(tmp_path, **{kind: True})
    (tmp_path / "c.toml").write_text(cfg_text())
    code, _, err = run_cli(["simulate", tmp_path / "c.toml", "--out", tmp_path / "out", "-q"], capsys)
    assert code == 2 and err.startswith("torchslide: error: ")
    assert {"nan_dem": "nodata cells", "neg_release": "must be >= 0", "grid": "does not match the DEM grid"}[kind] in err
    assert not (tmp_path / "out").exists()


def test_missing_config_and_nonempty_out(tmp_path, capsys):
    code, _, err = run_cli(["simulate", tmp_path / "none.toml", "--out", tmp_path / "o"], capsys)
    assert code == 2 and "config file not found" in err
    write_case(tmp_path)
    (tmp_path / "c.toml").write_text(cfg_text())
    (tmp_path / "o").mkdir()
    (tmp_path / "o" / "keep.txt").write_text("x")
    code, _, err = run_cli(["simulate", tmp_path / "c.toml", "--out", tmp_path / "o"], capsys)
    assert code == 2 and "not empty" in err
    assert [p.name for p in (tmp_path / "o").iterdir()] == ["keep.txt"]


def test_no_command_and_help(capsys):
    assert main([]) == 2
    with pytest.raises(SystemExit) as e:
        main(["simulate", "--help"])
    assert e.value.code == 0
    assert "--out" in capsys.readouterr().out


MEMBER_KEYS = {"release_volume", "final_volume", "outflow_volume", "impact_area", "deposit_area", "deposit_volume",
               "steps", "t_final", "runtime_s", "gauges", "params", "failed"}


def test_simulate_batch_round_trip(case, capsys):
    pytest.importorskip("torchslide.solver")
    import torch

    from torchslide.config import load_config
    from torchslide.solver import simulate

    (case / "c.toml").write_text(cfg_text(mu="[0.2, 0.35]").replace("t_end = 20.0", "t_end = 8.0"))
    out = case / "results" / "run1"  # parent does not exist yet
    code, stdout, err = run_cli(["simulate", case / "c.toml", "--out", out, "-q"], capsys)
    assert code == 0, err
    assert sorted(p.name for p in out.iterdir()) == ["config.toml", "member-000", "member-001", "summary.json"]
    batch = json.loads((out / "summary.json").read_text())
    assert batch["batch_size"] == 2 and len(batch["members"]) == 2
    cfg = load_config(case / "c.toml")
    ref = simulate(**cfg.simulate_kwargs())
    for b in range(2):
        m = out / f"member-{b:03d}"
        for f in ("h_max.asc", "v_max.asc", "h_final.asc", "summary.json"):
            assert (m / f).is_file()
        s = json.loads((m / "summary.json").read_text())
        assert MEMBER_KEYS <= set(s)
        assert set(s["gauges"]["G1"]) >= {"h_max", "v_max", "h_final"}
        assert s["params"]["mu"] == [0.2, 0.35][b]
        dem = cfg.terrain.dem
        assert s["release_volume"] == pytest.approx(float((cfg.terrain.release * dem.surface_area()).sum()), rel=1e-6)
        # the raster reads back equal to the result (the solver is deterministic on CPU)
        back = read_asc(m / "h_max.asc")
        assert back.same_grid(cfg.terrain.dem)
        np.testing.assert_allclose(back.z, ref.h_max[b].numpy(), rtol=1e-12, atol=1e-12)
        assert float(torch.as_tensor(back.z).max()) > 0
    assert not [p for p in case.iterdir() if p.name.startswith(".torchslide")]


def test_simulate_single_member_layout(case, capsys):
    pytest.importorskip("torchslide.solver")
    (case / "c.toml").write_text(cfg_text().replace("t_end = 20.0", "t_end = 4.0"))
    out = case / "single"
    code, _, err = run_cli(["simulate", case / "c.toml", "--out", out, "-q"], capsys)
    assert code == 0, err
    names = {p.name for p in out.iterdir()}
    assert {"h_max.asc", "v_max.asc", "h_final.asc", "summary.json", "config.toml"} <= names
    s = json.loads((out / "summary.json").read_text())
    assert MEMBER_KEYS <= set(s)


def test_failure_during_run_leaves_nothing(case, capsys, monkeypatch):
    pytest.importorskip("torchslide.solver")
    import torchslide.solver as solver

    def boom(*a, **k):
        raise RuntimeError("solver exploded")

    monkeypatch.setattr(solver, "simulate", boom)
    (case / "c.toml").write_text(cfg_text())
    with pytest.raises(RuntimeError, match="exploded"):
        main(["simulate", str(case / "c.toml"), "--out", str(case / "o"), "-q"])
    assert not (case / "o").exists()
    assert not [p for p in case.iterdir() if p.name.startswith(".torchslide")]


def test_overwrite(case, capsys):
    pytest.importorskip("torchslide.solver")
    (case / "c.toml").write_text(cfg_text().replace("t_end = 20.0", "t_end = 2.0"))
    out = case / "o"
    out.mkdir()
    (out / "old.txt").write_text("x")
    code, _, err = run_cli(["simulate", case / "c.toml", "--out", out, "-q", "--overwrite"], capsys)
    assert code == 0, err
    assert not (out / "old.txt").exists() and (out / "h_max.asc").is_file()


SHORT_PLANE = """
[terrain]
synthetic = "inclined_plane"
cellsize = 50.0
options = {{ theta_deg = 30.0, slope_length = 500.0, runout_length = {runout}, width = {width} }}
release = {{ centre = [250.0, {yc}], radii = [120.0, 100.0], volume = 1.0e5 }}

[model]
rheology = "voellmy"
mu = 0.15
xi = 1000.0

[run]
t_end = 60.0
"""


@pytest.mark.parametrize("runout, width, warned", [(100.0, 300.0, True), (1500.0, 1000.0, False)])
def test_simulate_warns_when_the_flow_leaves_the_dem(tmp_path, capsys, runout, width, warned):
    """A DEM cut short below the slope: the run loses part of its release through the edge, which the
    summary counts (outflow_volume) and a warning names; with a long and wide run-out zone no warning."""
    (tmp_path / "c.toml").write_text(SHORT_PLANE.format(runout=runout, width=width, yc=width / 2))
    code, _, err = run_cli(["simulate", tmp_path / "c.toml", "--out", tmp_path / "o", "-q"], capsys)
    assert code == 0, err
    s = json.loads((tmp_path / "o" / "summary.json").read_text())
    assert (s["outflow_volume"] > 0.01 * s["release_volume"]) == warned
    assert ("of its release through the DEM edge" in err) == warned
    if warned:
        assert f"lost {100 * s['outflow_volume'] / s['release_volume']:.1f} %" in err


def test_simulate_writes_peak_pressure_and_states_the_conventions(case, capsys):
    """p_max = density v_max^2 (kPa) with [model] density; every summary names what its numbers measure."""
    (case / "c.toml").write_text(cfg_text().replace("t_end = 20.0", "t_end = 5.0").replace("[model]\n", "[model]\ndensity = 1500.0\n"))
    out = case / "out"
    code, _, err = run_cli(["simulate", case / "c.toml", "--out", out, "-q"], capsys)
    assert code == 0, err
    v, p = read_asc(out / "v_max.asc").z, read_asc(out / "p_max.asc").z
    assert v.max() > 1.0
    np.testing.assert_allclose(p, 1.5 * v**2, rtol=1e-9, atol=1e-12)
    s = json.loads((out / "summary.json").read_text())
    c = s["conventions"]
    assert c["input_thickness"] == "normal" and c["density_kg_m3"] == 1500.0
    assert "normal to the slope" in c["thickness"] and "along the surface" in c["speed"]
    assert s["max_p_max"] == pytest.approx(1.5 * s["max_v_max"] ** 2, rel=1e-9)
