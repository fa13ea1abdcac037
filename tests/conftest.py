"""Shared cases and helpers of the test suite (terrains, configs, budgets); imported by the test modules."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from torchslide.cli import main
from torchslide.terrain import DEM, inclined_plane, release_from_shape, write_asc


# ------------------------------------------------------------------------ small terrains for the solver
def plane_dem(nx: int, ny: int, dx: float, tan_theta: float) -> DEM:
    """z = -x tan(theta) (flow towards +x)."""
    x = (np.arange(nx) + 0.5) * dx
    return DEM(np.tile(-x * tan_theta, (ny, 1)), dx)


def tilted_plane(n: int, dx: float, theta_deg: float, plan_deg: float = 0.0, half: float | None = None):
    """A user's DEM of a plane dipping at ``theta_deg`` towards the map direction ``plan_deg`` (0 = +x,
    counter-clockwise), on an n x n grid centred on the origin (or from -half to half).

    Returns (dem, X, Y, S, T): the cell centres in map m, S the map distance along the dip direction
    and T across it (so the slope coordinate along the surface is S / cos(theta))."""
    half = n * dx / 2 if half is None else half
    x = -half + (np.arange(n) + 0.5) * dx
    X, Y = np.meshgrid(x, x)
    a = np.radians(plan_deg)
    S = X * np.cos(a) + Y * np.sin(a)
    T = -X * np.sin(a) + Y * np.cos(a)
    dem = DEM(-S * np.tan(np.radians(theta_deg)), dx, xll=-half, yll=-half)
    return dem, X, Y, S, T


def chute_dem(nx: int = 60, ny: int = 24, dx: float = 10.0, slope_deg: float = 30.0, x_break: float = 300.0) -> DEM:
    """Inclined plane that turns into a flat run-out at x_break, with a gentle lateral trough."""
    x = (np.arange(nx) + 0.5) * dx
    y = (np.arange(ny) + 0.5) * dx
    zx = np.where(x < x_break, (x_break - x) * np.tan(np.radians(slope_deg)), 0.0)
    yc = y - y.mean()
    return DEM(zx[None, :] + 0.002 * yc[:, None] ** 2, dx)


def cap_release(dem: DEM, xc: float, yc: float, radius: float, height: float) -> np.ndarray:
    X, Y = np.meshgrid(dem.x_centres(), dem.y_centres())
    return np.clip(height * (1 - ((X - xc) ** 2 + (Y - yc) ** 2) / radius**2), 0, None)


def chute_case():
    dem = chute_dem()
    rel = cap_release(dem, 120.0, 120.0, 50.0, 8.0)
    return dem, rel



TERMS_T_END = 80.0


TERMS_BASE = dict(mu=0.25, xi=600.0)


TERMS_ON = {"kappa": 0.004, "curvature": 1.0, "earth_pressure": 1.0, "tau_y": 60.0, "mu_i": 0.3, "deposition": 0.3,
            "release_scale": 0.2}


def all_terms_case():
    """(dem, release, params, kwargs) of the chute with every candidate term: member 0 plain Voellmy, then one
    member per candidate (torchslide.diagnose.candidates) switched on at TERMS_ON (B = 1 + candidates);
    kwargs: an erodible bed 1 m deep and a gauge at the grid's centre."""
    from torchslide.diagnose.candidates import CANDIDATES
    from torchslide.physics import Params

    dem, rel = chute_case()
    names = sorted(CANDIDATES)
    vals: dict[str, list[float]] = {}
    fixed: dict[str, float] = {}
    for i, name in enumerate(names):
        c = CANDIDATES[name]
        fixed.update(dict(c.fixed))
        vals.setdefault(c.param, [c.baseline] * (len(names) + 1))[i + 1] = TERMS_ON[c.param]
    p = Params.make(**TERMS_BASE, **fixed, **vals)
    ny, nx = dem.shape
    gauges = [("G", float(dem.x_centres()[nx // 2]), float(dem.y_centres()[ny // 2]))]
    return dem, rel, p, dict(erodible_depth=np.full(dem.shape, 1.0), gauges=gauges)


def step_state(n: int, device="cpu", dtype=None):
    """(S, P, F) of the all-terms chute run (all_terms_case, torch step, no cropping) just before its n-th
    step: the state and parameter dicts and the StepFlags that a step function takes."""
    import importlib

    import torch

    from torchslide.solver import SolverConfig

    sim = importlib.import_module("torchslide.solver.simulate")
    get_step, taken = sim._get_step, {}

    def capture(F, kernel, device="cpu"):
        advance, calls = get_step(F, kernel, device), []

        def call(S, P, *args):
            calls.append(1)
            if len(calls) == n:
                taken.update(S={k: v.clone() if torch.is_tensor(v) else v for k, v in S.items()}, P=P, F=F)
            return advance(S, P, *args)
        return call

    dem, rel, p, kw = all_terms_case()
    dtype = dtype or torch.float64
    sim._get_step = capture
    try:
        sim.simulate(dem, rel, p.to(dtype=dtype), t_end=2.0, dtype=dtype, device=device,
                     config=SolverConfig(kernel="eager", crop=False), **kw)
    finally:
        sim._get_step = get_step
    return taken["S"], taken["P"], taken["F"]


def assert_steps_equal(ref: dict, new: dict) -> None:
    """Every field of two step results equal to the last bit, except the per-member sums (kinetic energy,
    mass, boundary outflow), whose order of summation may differ."""
    import torch

    for k, a in ref.items():
        if torch.is_tensor(a) and k not in ("ke", "ke_peak", "mass", "outflow"):
            assert torch.equal(a, new[k]), (k, float((a.double() - new[k].double()).abs().max()))
    assert float(ref["hu"].abs().max()) > 0



# --------------------------------------------------------------------------- config files (simulate)
def write_case(d, *, cellsize=20.0, release_dem=None, nan_dem=False, neg_release=False):
    """Small inclined plane DEM + release in folder d; returns (dem, release)."""
    dem = inclined_plane(30.0, cellsize=cellsize, slope_length=400, runout_length=300, width=200)
    rel = release_from_shape(dem, (150.0, 100.0), (60.0, 40.0), volume=2.0e4)
    z = dem.z.copy()
    if nan_dem:
        z[4, 5] = np.nan
    write_asc(d / "dem.asc", z, dem, fmt="%.17g")
    r = rel.copy()
    if neg_release:
        r[0, 0] = -1.0
    write_asc(d / "release.asc", r, release_dem or dem, fmt="%.17g")
    return dem, rel


CONFIG_BASE = """
[terrain]
dem = "dem.asc"
release = "release.asc"

[model]
rheology = "voellmy"
mu = {mu}
xi = {xi}

[run]
t_end = 20.0
dtype = "float64"
device = "cpu"

[[gauges]]
name = "G1"
x = {gx}
y = 100.0
"""


def cfg_text(mu="0.2", xi="1000.0", gx="300.0", extra=""):
    return CONFIG_BASE.format(mu=mu, xi=xi, gx=gx) + extra



# --------------------------------------------------------------------------- config files (calibrate)
CALIBRATE_BASE = """
[terrain]
synthetic = "inclined_plane"
cellsize = 50.0
options = { theta_deg = 30.0, slope_length = 500.0, runout_length = 700.0, width = 300.0 }
release = { centre = [250.0, 150.0], radii = [120.0, 100.0], volume = 1.0e5 }

[model]
rheology = "voellmy"
mu = 0.2
xi = 1000.0

[run]
t_end = 60.0
"""


CALIBRATE_PRIOR = """
[prior]
mu = [0.05, 0.5]
xi = [200.0, 2000.0]
"""


CALIBRATE_OBS = """
[[observations]]
kind = "max_velocity"
name = "v_plane"
x = 475.0
y = 150.0
value = {value}
sigma = {sigma}
"""


CALIBRATE_CAL = """
[calibration]
n_initial = 6
n_total = 10
batch_size = 2
seed = 3
grid_size = 30
truth = { mu = 0.2, xi = 1000.0 }
"""


def write_config(tmp_path: Path, text: str) -> Path:
    p = tmp_path / "cal.toml"
    p.write_text(text)
    return p


def truth_velocity(tmp_path: Path) -> float:
    cfg = write_config(tmp_path, CALIBRATE_BASE + '[[gauges]]\nname = "G"\nx = 475.0\ny = 150.0\n')
    assert main(["simulate", str(cfg), "--out", str(tmp_path / "truth"), "--quiet"]) == 0
    return json.loads((tmp_path / "truth" / "summary.json").read_text())["gauges"]["G"]["v_max"]



# ---------------------------------------------------------------------------- diagnosis configs, budgets
DIAGNOSE_BASE = """
[terrain]
synthetic = "inclined_plane"
cellsize = 50.0
options = {{ theta_deg = 30.0, slope_length = 500.0, runout_length = 700.0, width = 300.0 }}
release = {{ centre = [250.0, 150.0], radii = [120.0, 100.0], volume = 1.0e5 }}

[model]
rheology = "voellmy"
mu = 0.2
xi = 1000.0

[run]
t_end = 60.0

[[gauges]]
name = "G1"
x = 475.0
y = 150.0

[prior]
mu = [0.05, 0.5]
xi = [200.0, 2000.0]

[[observations]]
kind = "gauge_series"
file = "g1.csv"
gauge = "G1"
sigma = {{ h = 0.5, speed = 2.0 }}

[[observations]]
kind = "deposit_map"
file = "dep.asc"
sigma = 0.5

[diagnose]
candidates = {candidates}
"""


def setup_diagnose_case(tmp_path, csv="t,h,speed\n1,0,0\n2,1,3\n3,2,4\n", grid=(6, 24), candidates='["entrainment", "mu_i"]'):
    from torchslide.terrain.synthetic import inclined_plane
    (tmp_path / "g1.csv").write_text(csv)
    dem = inclined_plane(30.0, 50.0, slope_length=500.0, runout_length=700.0, width=300.0)
    other = DEM(z=np.zeros(grid), cellsize=50.0)
    write_asc(tmp_path / "dep.asc", np.zeros(grid), other)
    p = tmp_path / "diag.toml"
    p.write_text(DIAGNOSE_BASE.format(candidates=candidates))
    return p, dem


def tiny_budgets(extra: str = "") -> str:
    """The [diagnose] candidates value ["mu_i"] followed by tiny budgets (``extra``: more [diagnose] keys)
    and a tiny [calibration] section, for setup_diagnose_case(candidates=...)."""
    return ('["mu_i"]\nn_posterior_samples = 4\nn_posterior_samples_after = 4\nn_initial = 4\nn_total = 6\n'
            'n_total_max = 6\ntop_k = 1\nn_perm = 9\n'
            'model_error_runs = 2\ninference = "emulator"\n' + extra +
            '\n[calibration]\nn_initial = 4\nn_total = 6\nbatch_size = 2\ngrid_size = 40')


TINY_HARNESS_BUDGETS = dict(n_posterior_samples=8, n_posterior_samples_after=4, n_initial=6, n_total=8, n_total_max=8,
                            baseline_n_initial=6, baseline_n_total=8, batch_size=8, top_k=1,
                            n_perm=19, mcmc_steps=200, model_error_runs=0, release_volume_sd=0.0,
                            inference="emulator", detectability="linearised")



def cand(name, two_ln_bf, **kw):
    c = {"name": name, "log_bayes_factor": two_ln_bf / 2, "two_ln_bf_lower": two_ln_bf - 2, "ess": 6.0,
         "two_ln_bf_savage_dickey": 8.0, "delta_waic": 30.0, "misfit_after": 50.0,
         "located_rescored": {"items": [{"before": 9.0, "after": 1.0}], "max_after": 1.0, "explained_all": 0.9}}
    c.update(kw)
    return c



class Killed(BaseException):
    """What killed_after_write raises in place of a kill -9."""


def killed_after_write(monkeypatch, names, k: int, run) -> bool:
    """Call ``run()`` with os.replace patched so that right after the ``k``-th atomic write of a file named in
    ``names`` (torchslide.files writes every result through os.replace) the process "dies" (Killed); True
    when it did, False when ``run`` ended with fewer such writes."""
    import torchslide.files as files

    real_replace = files.os.replace
    count = [0]

    def replace(src, dst):
        real_replace(src, dst)
        if Path(dst).name in names:
            count[0] += 1
            if count[0] == k:
                raise Killed

    monkeypatch.setattr(files.os, "replace", replace)
    try:
        run()
        return False
    except Killed:
        return True
    finally:
        monkeypatch.setattr(files.os, "replace", real_replace)
