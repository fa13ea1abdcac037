"""Bad input through the command line, in-process: every config and raster below is refused before any
run with one line ``torchslide: error: ...`` naming what is wrong, exit code 2, never a traceback."""
from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from torchslide.cli import main

SIM, CAL = "simulate.toml", "calibrate.toml"

# (config file, the edit: (pattern, replacement) on its text or a callable on the case folder, what the
# error line must name)
EDITS = [
    (SIM, ("mu = [0.2, 0.25]", 'mu = "0.2"'), "mu"),
    (SIM, ("mu = [0.2, 0.25]", "mu = -0.2"), "mu"),
    (SIM, ("mu = [0.2, 0.25]", "mu = [0.2, nan]"), "mu"),
    (SIM, ("xi = 1000.0", "xi = 0.0"), "xi"),
    (SIM, ("xi = 1000.0", "xi = [1000.0, 500.0, 200.0]"), "equal lengths"),
    (SIM, ("t_end = 300.0", "t_end = -1.0"), "t_end"),
    (SIM, ("t_end = 300.0", "t_end = 1e9"), "output times"),
    (SIM, ("t_end = 300.0", 't_end = "long"'), "t_end"),
    (SIM, ('dtype = "float64"', 'dtype = "float16"'), "dtype"),
    (SIM, ('device = "cpu"', 'device = "tpu"'), "device"),
    (SIM, ('boundary = "outflow"', 'boundary = "wall"'), "boundary"),
    (SIM, ('rheology = "voellmy"', 'rheology = "bingham"'), "rheology"),
    (SIM, ("x = 1700.0", "x = 1.0e7"), "L1"),
    (SIM, ('name = "L2"', 'name = "L1"'), "L1"),
    (SIM, ('dem = "dem.asc"', 'dem = "missing.asc"'), "missing.asc"),
    (SIM, ('release = "release.asc"', 'release = { centre = [1.0, 2.0, 3.0], radii = [50.0, 50.0] }'), "centre"),
    (SIM, ('release = "release.asc"', 'release = { centre = [500.0, 1000.0], radii = [50.0, 50.0], volume = "3e6" }'),
     "volume"),
    (SIM, ('release = "release.asc"', 'release = { centre = [500.0, 1000.0], radii = [-5.0] }'), "radii"),
    (SIM, ("[model]", "[modell]"), "modell"),
    (SIM, ("[run]", "[run]\ncfl = 3.0"), "cfl"),
    (SIM, ("[run]", "[run]\nspeed = 3.0"), "speed"),
    (SIM, ("[terrain]", "[terrain]\nsynthetic = \"bondo_like\""), "synthetic"),
    (SIM, ('name = "L1"', "name = 3"), "name"),
    (SIM, ('mu = [0.2, 0.25]', 'mu = [0.2, 0.25'), SIM),
    (CAL, ("mu = [0.02, 0.3]", "mu = [0.3, 0.02]"), "mu"),
    (CAL, ("mu = [0.02, 0.3]", "mu = [-0.1, 0.3]"), "mu"),
    (CAL, ("mu = [0.02, 0.3]", "kappa = [0.0, 0.1, 0.2]"), "kappa"),
    (CAL, ("xi = [100.0, 2200.0]", 'xi = { dist = "cauchy", low = 100.0, high = 2200.0 }'), "cauchy"),
    (CAL, ("xi = [100.0, 2200.0]", "zeta = [100.0, 2200.0]"), "zeta"),
    (CAL, ("value = 63.4", "value = -63.4"), "v_L1"),
    (CAL, ("sigma = 6.34", "sigma = 0.0"), "sigma"),
    (CAL, ('kind = "max_velocity"', 'kind = "max_speed"'), "max_speed"),
    (CAL, ("y = 1086.6\n", ""), "x, y"),
    (CAL, ('name = "v_L1"\nx = 1700.0\ny = 1086.6\n', "x = 1700.0\n"), "x, y"),     # no y and no name
    (CAL, ("n_initial = 30", "n_initial = 1"), "n_initial"),
    (CAL, ("n_total = 70", "n_total = 10"), "n_total"),
    (CAL, ("batch_size = 10", "batch_size = 0"), "batch_size"),
    (CAL, ("batch_size = 10", 'batch_size = 10\nacquisition = "ucb"'), "acquisition"),
    (CAL, ("mu = 0.23", "mu = [0.2, 0.25]"), "single values"),
    (CAL, ("[prior]", "[prior]\nmu = [0.02, 0.3]"), CAL),
]


def _edit_raster(case: Path, name: str, fn) -> None:
    lines = (case / name).read_text().splitlines()
    head, body = lines[:6], [list(map(float, row.split())) for row in lines[6:]]
    a = np.asarray(body)
    a = fn(a)
    (case / name).write_text("\n".join(head + [" ".join(f"{v:.6f}" for v in row) for row in a]) + "\n")


RASTERS = [
    ("dem.asc", lambda a: np.where(np.arange(a.size).reshape(a.shape) == 7, np.nan, a), "non-finite"),
    ("dem.asc", lambda a: np.full_like(a, -9999.0), "every cell is nodata"),
    ("release.asc", lambda a: np.where(np.arange(a.size).reshape(a.shape) == 7, np.nan, a), "non-finite"),
    ("release.asc", lambda a: np.where(np.arange(a.size).reshape(a.shape) == 7, -1.0, a), "negative"),
    ("release.asc", lambda a: a[:-1], "release"),
    ("release.asc", lambda a: np.where(a > 0, np.inf, a), "release"),
    ("release.asc", lambda a: np.zeros_like(a), "release"),
]


@pytest.fixture(scope="module")
def example(tmp_path_factory) -> Path:
    case = tmp_path_factory.mktemp("fuzz") / "case"
    assert main(["example", "bondo", "--out", str(case), "--cellsize", "300"]) == 0
    return case


def _refused(case: Path, cfg: str, capsys, *extra) -> str:
    capsys.readouterr()
    out = case.parent / f"out_{abs(hash((cfg, case.name, extra))) % 10**8}"
    cmd = "simulate" if cfg == SIM else "calibrate"
    rc = main([cmd, str(case / cfg), "--out", str(out), "--quiet", *extra])
    err = capsys.readouterr().err
    assert rc == 2, err
    assert err.startswith("torchslide: error:") and len(err.strip().splitlines()) == 1, err
    assert not out.exists() or not any(p for p in out.iterdir() if p.name != "case.json"), "nothing half-written"
    return err


@pytest.mark.parametrize("cfg, edit, names", EDITS, ids=[f"{i}" for i in range(len(EDITS))])
def test_bad_config_is_one_line_before_any_run(example, tmp_path, capsys, cfg, edit, names):
    import shutil

    case = tmp_path / "case"
    shutil.copytree(example, case)
    text = (case / cfg).read_text()
    pattern, repl = edit
    assert pattern in text, pattern
    (case / cfg).write_text(text.replace(pattern, repl, 1))
    err = _refused(case, cfg, capsys)
    assert names in err, err


@pytest.mark.parametrize("raster, fn, names", RASTERS, ids=[f"{r[0]}-{i}" for i, r in enumerate(RASTERS)])
def test_bad_raster_is_one_line_before_any_run(example, tmp_path, capsys, raster, fn, names):
    import shutil

    case = tmp_path / "case"
    shutil.copytree(example, case)
    _edit_raster(case, raster, fn)
    err = _refused(case, SIM, capsys)
    assert re.search(names, err, re.I), err


def test_output_folder_that_cannot_be_one(example, tmp_path, capsys):
    """--out that is a file, lies under a file, or is the current folder: refused before any run."""
    (tmp_path / "afile").write_text("x")
    for cmd, cfg in (("simulate", SIM), ("calibrate", CAL), ("sweep", CAL), ("diagnose", CAL)):
        for out in (tmp_path / "afile", tmp_path / "afile" / "sub", ""):
            capsys.readouterr()
            extra = ["--n", "3"] if cmd == "sweep" else []
            assert main([cmd, str(example / cfg), "--out", str(out), *extra]) == 2
            err = capsys.readouterr().err
            assert err.startswith("torchslide: error:") and len(err.strip().splitlines()) == 1, err
