"""The README's tour as written: its commands from ``torchslide example`` to ``sweep`` run in order on the
example files (coarser cells and smaller budgets), and its TOML blocks are what the example writes."""
from __future__ import annotations

import re
import shlex
from pathlib import Path

import pytest

from torchslide.cli import main

README = Path(__file__).resolve().parents[1] / "README.md"


def tour() -> str:
    text = README.read_text()
    return text[text.index("## A tour"): text.index("**Diagnose.**")]


def tour_commands() -> list[list[str]]:
    """The indented command lines of the tour (comments dropped), as argument lists."""
    cmds = []
    for line in tour().splitlines():
        if line.startswith("    ") and not line.startswith("     "):
            cmds.append(shlex.split(line.strip(), comments=True))
    return cmds


def toml_blocks() -> list[list[str]]:
    """The tour's TOML blocks as lines without comments or blank lines."""
    blocks = re.findall(r"```toml\n(.*?)```", tour(), re.S)
    return [[ln.split("#")[0].rstrip() for ln in b.splitlines() if ln.split("#")[0].strip()] for b in blocks]


SMALL = {"--n": "3"}                 # posterior draws and sweep nodes per axis
BUDGET = {"n_initial": "4", "n_total": "6", "batch_size": "2"}


def test_readme_tour_runs_as_written(tmp_path, monkeypatch, capsys):
    cmds = tour_commands()
    names = [c[0] if c[0] != "torchslide" else f"torchslide {c[1]}" for c in cmds]
    assert names[:2] == ["torchslide example", "cd"] and "torchslide sweep" in names
    simulate_block, calibrate_block = toml_blocks()
    monkeypatch.chdir(tmp_path)
    for cmd in cmds:
        if cmd[0] == "cd":
            monkeypatch.chdir(tmp_path / cmd[1])
            continue
        if cmd[0] != "torchslide":         # tensorboard
            continue
        args = [SMALL.get(prev, a) if prev in SMALL else a for prev, a in zip([""] + cmd[1:], cmd[1:])]
        if args[0] == "example":
            assert main(args + ["--cellsize", "300"]) == 0
            case = tmp_path / args[args.index("--out") + 1]
            sim, cal = (case / "simulate.toml").read_text(), (case / "calibrate.toml").read_text()
            assert all(line in sim.splitlines() for line in simulate_block), "README simulate.toml block drifted"
            assert all(line in cal.splitlines() for line in calibrate_block), "README calibrate.toml block drifted"
            for k, v in BUDGET.items():
                cal = re.sub(rf"^{k} = .*$", f"{k} = {v}", cal, flags=re.M)
            (case / "calibrate.toml").write_text(cal)
            continue
        capsys.readouterr()
        rc = main(args + ["--quiet"])
        err = capsys.readouterr().err
        assert rc == 0, (args, err)
        assert "Traceback" not in err and "never reached" not in err and "no run reaches" not in err, (args, err)
    case = Path.cwd()
    assert (case / "run1" / "member-001" / "h_max.asc").exists()
    assert (case / "cal1" / "posterior.json").exists() and (case / "pred1" / "predictive.json").exists()
    assert (case / "sweep1" / "sweep.json").exists()


@pytest.mark.parametrize("where", ["gauge", "observation"])
def test_points_off_the_flow_path_are_named(tmp_path, capsys, where):
    """A gauge the flow never reaches (simulate) and a point observation no run reaches (calibrate) are
    named in a warning, with their coordinates."""
    assert main(["example", "bondo", "--out", str(tmp_path / "case"), "--cellsize", "300"]) == 0
    case = tmp_path / "case"
    capsys.readouterr()
    if where == "gauge":
        cfg = case / "simulate.toml"
        cfg.write_text(cfg.read_text().replace("y = 1086.6", "y = 1950.0").replace("t_end = 300.0", "t_end = 60.0"))
        assert main(["simulate", str(cfg), "--out", str(tmp_path / "run"), "--quiet"]) == 0
        assert "gauge L1 at (1700, 1950) is never reached" in capsys.readouterr().err
    else:
        cfg = case / "calibrate.toml"
        text = cfg.read_text().replace("y = 1086.6", "y = 1950.0").replace("t_end = 300.0", "t_end = 60.0")
        for k, v in BUDGET.items():
            text = re.sub(rf"^{k} = .*$", f"{k} = {v}", text, flags=re.M)
        cfg.write_text(text)
        assert main(["calibrate", str(cfg), "--out", str(tmp_path / "cal"), "--quiet"]) == 0
        assert "no run reaches observation v_L1 at (1700, 1950)" in capsys.readouterr().err
