"""``torchslide example bondo|msh2021 --out DIR [--cellsize M]``: a complete case to start from.

Writes the files a user brings, for the built-in Bondo-like valley (torchslide.terrain.synthetic.bondo_like):

    DIR/dem.asc          the terrain, ESRI ASCII, m
    DIR/release.asc      the release thickness normal to the slope, m (3e6 m^3)
    DIR/simulate.toml    two friction values run as one batch, gauges L1-L3 on the flow path, the
                         valley's thalweg as a run-out path
    DIR/calibrate.toml   a prior over (mu, xi) and one recording: the maximum speed at L1

The recording is a synthetic one (mu = 0.23, xi = 1000 m/s^2 with 10 % noise, on 60 m cells): 63.4 m/s.
The README's tour runs ``simulate``, ``calibrate``, ``predict`` and ``sweep`` on these files.

``msh2021`` writes a real event, the December 2021 landslide near Mount St. Helens (landlab's
MassWastingRunout tutorial data, MIT licence; SOURCE.md and LICENSE.md beside the files):

    DIR/dem.asc            the pre-event terrain, 10 m cells (one column of nodata)
    DIR/failure_depth.asc  the failure depths of the 30 source cells, negative, vertical m: the release,
                           ``release = { failure_depth = "failure_depth.asc" }`` (the bed is lowered by them
                           and the thickness converted to normal by torchslide)
    DIR/dod.asc            the surveyed DEM of difference of the runout (+ deposition, - erosion, vertical m;
                           nodata off the 224 mapped cells): an ``elevation_change`` observation
    DIR/source.asc         the mapped source (1 at the 30 cells)
    DIR/hillshade.asc      a 2 m hillshade for figures
    DIR/erodible.asc       a regolith 1.2 m deep (the depth landlab's tutorial uses), for the entrainment candidate
    DIR/footprint.asc      the mapped outline: 1 on the 224 changed cells, 0 within 50 m around them (a
                           ``footprint`` observation), nodata beyond
    DIR/simulate.toml, calibrate.toml (the mapped impact and deposit areas, the outline, the run-out from the
    release's crown to the farthest changed cell and the DoD), diagnose.toml
"""
from __future__ import annotations

import argparse
import math
from pathlib import Path

import numpy as np

from ..config import ConfigError

HELP = "write an example case (DEM, release, configs) to start from"

EXAMPLES = ("bondo", "msh2021")

MSH_FILES = {"dem.asc": "pre_runout_DEM.asc", "failure_depth.asc": "landslide_depth.asc",
             "dod.asc": "DEM_of_Difference.asc", "source.asc": "landslide_polygon.asc",
             "hillshade.asc": "pre_runout_DEM_hillshade.asc", "SOURCE.md": "SOURCE.md", "LICENSE.md": "LICENSE.md"}
"""Files of the msh2021 example and the shipped files they copy (torchslide/data/msh2021)."""

MSH_TERRAIN = """[terrain]
dem = "dem.asc"
release = { failure_depth = "failure_depth.asc" }   # negative vertical depths: the bed is lowered by them
thickness = "normal"

[model]
rheology = "voellmy"
mu = 0.3
xi = 1000.0

[run]
t_end = 300.0
"""

MSH_CALIBRATE = """
[prior]
mu = [0.05, 0.6]
xi = [100.0, 3000.0]

[[observations]]
kind = "impact_area"       # the mapped runout, source included: 224 cells of 100 m^2
name = "impact"
value = 22400.0
sigma = 2240.0
threshold = 0.1

[[observations]]
kind = "deposit_area"      # cells where the survey found deposition
name = "deposit"
value = 13000.0
sigma = 1300.0
threshold = 0.1

[[observations]]
kind = "footprint"         # the mapped outline (footprint.asc: 1 mapped, 0 within 50 m around it), against
name = "outline"           # the smooth reach h_max^2 / (h_max^2 + threshold^2) of each cell
file = "footprint.asc"
sigma = 0.3
corr_length = 20.0
threshold = 0.1

[[observations]]
kind = "runout_length"     # the survey's run-out: the farthest changed cell of the DoD from the release's crown
name = "runout"            # (horizontal m; a [[paths]] entry with path = "name" measures it along a path instead)
map = "dod.asc"
sigma = 20.0               # two cells
threshold = 0.1

[[observations]]
kind = "elevation_change"  # the surveyed DEM of difference, vertical m (+ deposition, - erosion)
name = "dod"
file = "dod.asc"
sigma = 0.5
corr_length = 20.0

[calibration]
n_initial = 20
n_total = 40
batch_size = 10
"""

MSH_DIAGNOSE = """
[diagnose]
candidates = ["entrainment", "curvature", "earth_pressure", "yield_stress", "mu_i", "release_volume"]
model_error_runs = 6         # the grid's error from 6 run pairs on 10 m and 5 m cells (12 by default)
"""

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
    p.add_argument("--cellsize", type=float, default=None, help="bondo: DEM cell size, m (default 60)")


def gauge_tables(points: dict) -> str:
    return "".join(f'[[gauges]]\nname = "{k}"\nx = {x:.1f}\ny = {y:.1f}\n\n' for k, (x, y) in points.items())


def run(args: argparse.Namespace) -> int:
    from ..output_folder import run_locked

    return run_locked(args.out, _run, args)


def _run(args: argparse.Namespace) -> int:
    if args.name == "msh2021":
        return _msh2021(args)
    return _bondo(args)


def _msh2021(args: argparse.Namespace) -> int:
    import shutil
    from importlib import resources

    from ..output_folder import check_output, staged_output

    if args.cellsize is not None:
        raise ConfigError("--cellsize is for the bondo example; msh2021 is the survey's 10 m grid "
                          "(resample with [terrain] cellsize)")
    out = Path(args.out)
    anc = check_output(out, overwrite=False)
    data = resources.files("torchslide") / "data" / "msh2021"
    with staged_output(out, anc, "example") as tmp:
        for name, shipped in MSH_FILES.items():
            with resources.as_file(data / shipped) as f:
                shutil.copyfile(f, tmp / name)
        (tmp / "simulate.toml").write_text(MSH_TERRAIN)
        (tmp / "calibrate.toml").write_text(MSH_TERRAIN + MSH_CALIBRATE)
        _erodible(tmp)
        _footprint(tmp)
        terrain = MSH_TERRAIN.replace('thickness = "normal"\n', 'thickness = "normal"\n'
                                      'erodible = "erodible.asc"    # the regolith, 1.2 m deep (landlab\'s tutorial)\n')
        (tmp / "diagnose.toml").write_text(terrain + MSH_CALIBRATE.replace("[calibration]", MSH_DIAGNOSE
                                                                           + "\n[calibration]"))
    print(f"wrote {out}: the 2021 Mount St. Helens landslide ({', '.join(MSH_FILES)}, erodible.asc, footprint.asc), simulate.toml, "
          "calibrate.toml, diagnose.toml; data from the landlab project, MIT licence (SOURCE.md, LICENSE.md)")
    return 0


def _footprint(folder: Path, ring: int = 5) -> None:
    """folder/footprint.asc: the mapped runout as an outline raster: 1 on the surveyed cells that changed
    (the DoD's), 0 on the ``ring`` cells around them (mapped as not reached), nodata beyond."""
    from scipy.ndimage import binary_dilation

    from ..terrain.io import read_asc, read_asc_array, write_asc

    dem = read_asc(folder / "dem.asc", nodata="outside")
    dod = read_asc_array(folder / "dod.asc")[0]
    mapped = np.isfinite(dod) & (dod != 0)
    near = binary_dilation(mapped, iterations=ring)
    if dem.outside is not None:
        near &= ~dem.outside
    write_asc(folder / "footprint.asc", np.where(mapped, 1.0, np.where(near, 0.0, np.nan)), dem, fmt="%.0f")


def _erodible(folder: Path, depth: float = 1.2) -> None:
    """folder/erodible.asc: a regolith of ``depth`` m over the DEM's domain (the entrainment candidate's bed)."""
    from ..terrain.io import read_asc, write_asc

    dem = read_asc(folder / "dem.asc", nodata="outside")
    inside = np.ones(dem.shape, dtype=bool) if dem.outside is None else ~dem.outside
    write_asc(folder / "erodible.asc", np.where(inside, depth, 0.0), dem, fmt="%.3f")


def _bondo(args: argparse.Namespace) -> int:
    from ..output_folder import check_output, staged_output
    from ..terrain.io import write_asc
    from ..terrain.synthetic import bondo_like

    if args.cellsize is None:
        args.cellsize = 60.0
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
