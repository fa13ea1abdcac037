"""``torchslide example bondo --out DIR [--cellsize M]``: a complete case to start from.

Writes the files a user brings, for the built-in Bondo-like valley (torchslide.terrain.synthetic.bondo_like):

    DIR/dem.asc          the terrain, ESRI ASCII, m
    DIR/release.asc      the release thickness normal to the slope, m (3e6 m^3)
    DIR/simulate.toml    two friction values run as one batch, gauges L1-L3 on the flow path, the
                         valley's thalweg as a run-out path
    DIR/calibrate.toml   a prior over (mu, xi) and one recording: the maximum speed at L1

The recording is a synthetic one (mu = 0.23, xi = 1000 m/s^2 with 10 % noise, on 60 m cells): 63.4 m/s.
The README's tour runs ``simulate``, ``calibrate``, ``predict`` and ``sweep`` on these files.
"""
from __future__ import annotations

import argparse
import math
from pathlib import Path

from ..config import ConfigError

HELP = "write an example case (DEM, release, configs) to start from"

EXAMPLES = ("bondo",)

TERRAIN = """[terrain]
dem = "dem.asc"
release = "release.asc"
thickness = "normal"
"""

SIMULATE = """
[model]
rheology = "voellmy"
mu = [0.2, 0.25]
xi = 1000.0
density = 2000.0

[run]
t_end = 300.0
dtype = "float64"
device = "cpu"
boundary = "outflow"

{gauges}[[paths]]
name = "thalweg"
points = {path}
"""

CALIBRATE = """
[model]
rheology = "voellmy"
mu = 0.23
xi = 1000.0

[run]
t_end = 300.0

[prior]
mu = [0.02, 0.3]
xi = [100.0, 2200.0]

[[observations]]
kind = "max_velocity"
name = "v_L1"
x = {x:.1f}
y = {y:.1f}
value = 63.4
sigma = 6.34

[calibration]
n_initial = 30
n_total = 70
batch_size = 10
"""


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("name", choices=EXAMPLES, help="which example")
    p.add_argument("--out", "-o", required=True, metavar="DIR", help="output folder (must not exist or be empty)")
    p.add_argument("--cellsize", type=float, default=60.0, help="DEM cell size, m (default 60)")


def gauge_tables(points: dict) -> str:
    return "".join(f'[[gauges]]\nname = "{k}"\nx = {x:.1f}\ny = {y:.1f}\n\n' for k, (x, y) in points.items())


def run(args: argparse.Namespace) -> int:
    from ..output_folder import run_locked

    return run_locked(args.out, _run, args)


def _run(args: argparse.Namespace) -> int:
    from ..output_folder import check_output, staged_output
    from ..terrain.io import write_asc
    from ..terrain.synthetic import bondo_like

    if not (math.isfinite(args.cellsize) and 5.0 <= args.cellsize <= 500.0):
        raise ConfigError(f"--cellsize must be between 5 and 500 m, got {args.cellsize}")
    out = Path(args.out)
    anc = check_output(out, overwrite=False)
    case = bondo_like(cellsize=args.cellsize)
    x, y = case.points["L1"]
    with staged_output(out, anc, "example") as tmp:
        write_asc(tmp / "dem.asc", case.dem.z, case.dem, fmt="%.6f")
        write_asc(tmp / "release.asc", case.release, case.dem, fmt="%.6f")
        path = "[" + ", ".join(f"[{px:.1f}, {py:.1f}]" for px, py in case.thalweg[::50]) + "]"
        (tmp / "simulate.toml").write_text(TERRAIN + SIMULATE.format(gauges=gauge_tables(case.points), path=path))
        (tmp / "calibrate.toml").write_text(TERRAIN + CALIBRATE.format(x=x, y=y))
    print(f"wrote {out}: dem.asc, release.asc ({case.dem.ny} x {case.dem.nx} cells of {args.cellsize:g} m), "
          f"simulate.toml, calibrate.toml")
    return 0
