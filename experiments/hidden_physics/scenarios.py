"""Blind hidden-physics scenarios: recordings from a finer grid with a hidden term, noise and a release error.

Terrains (``SITES``; select with :func:`terrain_variant`, the harness' ``--terrain``):

* ``"narrow"`` (the default): a short S-bend channel (torchslide.terrain.synthetic.channel_with_bends,
  1200 m slope + 500 m run-out, 600 m wide) of half-width 40 m with a sharp slope-to-run-out kink and
  a release of radius 60 m, i.e. two 40 m cells across the channel; the solver's runs on it agree
  between grids only from 10 m cells on.
* ``"resolved"``: the same channel of half-width 100 m, the kink replaced by a 300 m parabolic
  transition, a release of radius 120 m, and gauge g2 at x = 1150 m (in the transition) instead of
  1300 m (at the deposit's front): a terrain that a 40 m grid resolves.
* ``"fan"``: a steep channel with one 60 deg bend onto a fan, an erodible reach through the bend
  (torchslide.terrain.synthetic.bend_to_fan), three gauges (above the bend, below it, on the fan's head)
  and the low-friction patch through the bend.

The inversion grid has ``cellsize`` m cells; the recordings are made on a grid of ``cellsize /
fine_factor`` (same analytic surface), their deposit map block-averaged onto the inversion grid.
The true release volume differs from the nominal one by a factor U(0.9, 1.1) (RELEASE_FACTOR; its
final_volume sigma is 10 % of the nominal volume, the draw itself unknown to the inversion, its sd
RELEASE_VOLUME_SD); the ``release_volume`` scenario makes it (1 + 0.25 x strength) times that.
"""
from __future__ import annotations

from collections.abc import Callable
from contextlib import contextmanager
from dataclasses import dataclass, replace

import numpy as np
import torch

from torchslide.observe import Observation
from torchslide.observe_series import SeriesObservation, interp_series
from torchslide.physics import Params
from torchslide.terrain.grid import DEM
from torchslide.solver import SolverConfig, simulate
from torchslide.terrain import synthetic
from torchslide.terrain.synthetic import _bends, channel_with_bends, release_from_shape

TRUE_BASE = {"mu": 0.25, "xi": 500.0}
V_NOMINAL = 2.0e5
RELEASE_FACTOR = (0.9, 1.1)
"""Range of the uniform factor between the true and the stated release volume."""
RELEASE_VOLUME_SD = 0.0577
"""The relative sd of that factor, (1.1 - 0.9) / sqrt(12) to three figures: the release's error as a user who
knows it states it ([diagnose] release_volume_sd)."""
T_END = 90.0
DT_OBS = 2.0
SOLVER = dict(stop_ke_fraction=2e-3, stop_quiet_time=0.0, output_interval=1.0)   # the thresholds' stop rule
# gauge quantity -> (the likelihood's sigma, the sd of the noise drawn), and the deposit map's noise sd (its
# likelihood sigma is make_recording's map_sigma, 0.5 m): the harness states errors larger than it draws
GAUGE_ERRORS = {"h": (0.5, 0.2), "speed": (2.0, 0.5)}
DEPOSIT_NOISE = 0.3

# scenario -> (true library term, None, "outside" (a friction patch) or "release_volume" (a release 25 % larger than
# stated, an input error: not the harness' library's), hidden parameters at strength 1)
SCENARIOS = {
    "null": (None, {}),
    "entrainment": ("entrainment", {"kappa": 0.0015}),
    "curvature": ("curvature", {"curvature": 1.0}),
    "earth_pressure": ("earth_pressure", {"earth_pressure": 1.0, "phi_int": 35.0}),
    "yield_stress": ("yield_stress", {"tau_y": 3.0}),
    "mu_i": ("mu_i", {"mu_i": 0.2}),
    "low_friction_patch": ("outside", {}),
    "release_volume": ("release_volume", {"release_scale": 0.25}),
}
SWITCH = {"entrainment": "kappa", "curvature": "curvature", "earth_pressure": "earth_pressure",
          "yield_stress": "tau_y", "mu_i": "mu_i"}
PATCH_MU_SCALE = 0.55   # the out-of-library patch: mu x this inside it


@dataclass(frozen=True)
class Site:
    """One harness terrain. surface: cellsize m -> DEM (the same analytic surface at every cell size);
    release_centre (x, y) m and release_radius m of the paraboloid-cap release; gauges ((name, x, y), ...);
    erodible: (X, Y) cell centres (ny, nx) m -> erodible depth (ny, nx) m; patch: (X, Y) -> (ny, nx) bool,
    where the out-of-library scenario lowers mu."""

    surface: Callable
    release_centre: tuple
    release_radius: float
    gauges: tuple
    erodible: Callable
    patch: Callable


def _channel_site(halfwidth: float, transition: float, release_radius: float, g2_x: float) -> Site:
    geom = dict(slope_length=1200.0, runout_length=500.0, width=600.0, amplitude=80.0, channel_halfwidth=halfwidth,
                transition=transition)
    L = geom["slope_length"]
    yc = lambda x: 0.5 * geom["width"] + float(_bends(x, 0.15 * L, 0.85 * L, geom["amplitude"]))
    return Site(surface=lambda cs: channel_with_bends(cs, **geom), release_centre=(150.0, yc(150.0)),
                release_radius=release_radius, gauges=(("g1", 700.0, yc(700.0)), ("g2", g2_x, yc(g2_x))),
                erodible=lambda X, Y: np.where((X > 300) & (X < 1100), 2.0, 0.0),
                patch=lambda X, Y: (X > 650) & (X < 1000))


def _fan_site() -> Site:
    yc = lambda x: float(synthetic._fan_centreline(x))
    x0, x1, depth = synthetic.FAN_ERODIBLE
    return Site(surface=lambda cs: synthetic.bend_to_fan(cs).dem,
                release_centre=(synthetic.FAN_RELEASE["centre_x"], yc(synthetic.FAN_RELEASE["centre_x"])),
                release_radius=synthetic.FAN_RELEASE["radius"],
                gauges=tuple((k, x, yc(x) + dy) for k, (x, dy) in synthetic.FAN_POINTS.items()),
                erodible=lambda X, Y: np.where((X >= x0) & (X <= x1)
                                               & (np.abs(Y - synthetic._fan_centreline(X)) <= 100.0), depth, 0.0),
                patch=lambda X, Y: (X > 550) & (X < 900))


SITES = {
    "narrow": _channel_site(40.0, 0.0, 60.0, 1300.0),
    "resolved": _channel_site(100.0, 300.0, 120.0, 1150.0),
    "fan": _fan_site(),
}
TERRAINS = tuple(SITES)
TERRAIN = "narrow"
SITE = SITES[TERRAIN]


def use_terrain(name: str) -> str:
    """Make ``name`` (a key of ``SITES``) the terrain of every function of this module; returns the
    variant it replaces."""
    global TERRAIN, SITE
    if name not in SITES:
        raise ValueError(f"terrain: unknown variant {name!r} (known: {', '.join(SITES)})")
    previous = TERRAIN
    TERRAIN, SITE = name, SITES[name]
    return previous


@contextmanager
def terrain_variant(name: str):
    """``with terrain_variant("fan"): ...`` -- :func:`use_terrain` for the block, restored after."""
    previous = use_terrain(name)
    try:
        yield
    finally:
        use_terrain(previous)


def gauges():
    return list(SITE.gauges)


def _centres(dem):
    return np.meshgrid(dem.x_centres(), dem.y_centres())


def terrain(cellsize: float):
    """(DEM, erodible depth (ny, nx) m) of the current terrain on ``cellsize`` m cells."""
    dem = SITE.surface(cellsize)
    return dem, SITE.erodible(*_centres(dem))


def release(dem, volume: float):
    return release_from_shape(dem, SITE.release_centre, SITE.release_radius, volume=volume)


def mu_scale_patch(dem):
    return np.where(SITE.patch(*_centres(dem)), PATCH_MU_SCALE, 1.0)


def block_average(a: np.ndarray, f: int) -> np.ndarray:
    ny, nx = a.shape
    return a[: ny // f * f, : nx // f * f].reshape(ny // f, f, nx // f, f).mean(axis=(1, 3))


@dataclass
class Recording:
    scenario: str
    seed: int
    strength: float
    truth: dict
    volume_factor: float
    observations: list
    fine_h_final: np.ndarray
    fine_h_max: np.ndarray | None = None


def make_recording(scenario: str, seed: int, cellsize: float = 40.0, strength: float = 1.0,
                   map_sigma: float = 0.5, map_corr: float | None = 60.0, noise: float = DEPOSIT_NOISE,
                   gauge_corr: float = 4.0, fine_factor: int = 2) -> Recording:
    """The recordings of one case: ``scenario``'s hidden term at ``strength`` x its nominal value, run on
    cells ``cellsize / fine_factor`` m (seed 1000 + ``seed`` draws the release error and the noise).
    The likelihood sigmas stated with them (gauge series: GAUGE_ERRORS' first values; deposit map:
    ``map_sigma`` m) are larger than the noise drawn (GAUGE_ERRORS' second values, ``noise`` m);
    :func:`noise_sigmas` states the noise as drawn."""
    term, hidden = SCENARIOS[scenario]
    rng = np.random.default_rng(1000 + seed)
    dem_c, erod_c = terrain(cellsize)
    dem_f, erod_f = terrain(cellsize / fine_factor)
    vf = float(rng.uniform(*RELEASE_FACTOR))
    vals = dict(TRUE_BASE)
    for k, v in hidden.items():
        vals[k] = v * strength if k != "phi_int" else v
    mu_scale = mu_scale_patch(dem_f) if term == "outside" else None
    if term == "outside" and strength != 1.0:
        mu_scale = 1.0 - (1.0 - mu_scale) * strength
    res = simulate(dem_f, release(dem_f, V_NOMINAL * vf), Params.make(**vals), t_end=T_END, gauges=gauges(),
                   config=SolverConfig(**SOLVER), erodible_depth=erod_f, mu_scale=mu_scale)
    hf = res.h_final[0].numpy()
    dep = block_average(hf, fine_factor)
    assert dep.shape == dem_c.shape, (dep.shape, dem_c.shape)
    obs = []
    dep_obs = dep + noise * rng.standard_normal(dep.shape)
    obs.append(SeriesObservation.from_array("deposit_map", dep_obs, dem_c, map_sigma, name="deposit",
                                            corr_length=map_corr))
    t = np.arange(DT_OBS, T_END + 1e-9, DT_OBS)
    for g in res.gauges.values():
        for q, (s, e) in GAUGE_ERRORS.items():
            y = (g.h if q == "h" else g.speed)
            yv = interp_series(g.t, y, torch.as_tensor(t))[0].numpy()
            yv = yv + e * rng.standard_normal(yv.shape)
            obs.append(SeriesObservation("gauge_series", yv, s, name=f"{g.name}:{q}", gauge=g.name, quantity=q,
                                         times=t.copy(), corr_length=gauge_corr))
    fv = float(res.final_volume[0])
    obs.append(Observation("final_volume", fv + 0.02 * V_NOMINAL * rng.standard_normal(), 0.1 * V_NOMINAL,
                           name="final_volume"))
    truth = {"term": term, **vals}
    return Recording(scenario, seed, strength, truth, vf, obs, hf, res.h_max[0].numpy())


SIGMAS = ("harness", "noise")   # the likelihood's sigmas: the harness' (make_recording) or noise_sigmas'


def noise_sigmas(observations) -> list:
    """The observations with each gauge series' and deposit map's sigma set to the sd of the noise the harness
    draws for it (GAUGE_ERRORS, DEPOSIT_NOISE: recordings whose errors are stated as they are, not 1.7-4 times
    larger); the others (the final volume, whose sigma is the release error's) unchanged."""
    out = []
    for o in observations:
        if getattr(o, "kind", None) == "gauge_series":
            o = replace(o, sigma=GAUGE_ERRORS[o.quantity][1])
        elif getattr(o, "kind", None) == "deposit_map":
            o = replace(o, sigma=DEPOSIT_NOISE)
        out.append(o)
    return out


def fine_terrain_grids(cellsize: float = 40.0) -> tuple:
    """(DEM, release depth (ny, nx) m, erodible depth (ny, nx) m) on cells half of ``cellsize``: the
    recording grid's surface with the nominal release and no hidden term, cut to twice the inversion
    grid's shape (the finer grid's extent rounds up by a cell), as a user who coarsened a finer DEM for the
    inversion would have it."""
    dem = terrain(cellsize)[0]
    dem_f, erod_f = terrain(cellsize / 2)
    ny, nx = 2 * dem.ny, 2 * dem.nx
    dem_f = DEM(dem_f.z[:ny, :nx], dem_f.cellsize, xll=dem_f.xll, yll=dem_f.yll)
    return dem_f, release(dem_f, V_NOMINAL), erod_f[:ny, :nx]


def make_evaluator(rec: Recording, cellsize: float = 40.0, max_batch: int = 16, fine_terrain: bool = False,
                   device: str = "cpu", compile_solver: bool = False):
    """The diagnosis' evaluator on ``cellsize`` m cells (nominal release volume), its solver runs on
    ``device`` ("cpu", "cuda", ...; the recordings are made on the CPU), compiled when
    ``compile_solver`` (SolverConfig.compile). ``fine_terrain``: give
    it the terrain on cells half as large (the recording grid's surface, nominal release, no hidden
    term) for the model error's finer runs, as a user coarsening a finer DEM for the inversion would."""
    from torchslide.bayes import Prior, Uniform
    from torchslide.diagnose import DiagnosisEvaluator
    from torchslide.diagnose.model_error import FineTerrain
    dem, erod = terrain(cellsize)
    prior = Prior({"mu": Uniform(0.12, 0.4), "xi": Uniform(150.0, 1500.0)})
    ft = None
    if fine_terrain:
        dem_f, rel_f, erod_f = fine_terrain_grids(cellsize)
        ft = FineTerrain(dem_f, rel_f, erodible_depth=erod_f)
    return DiagnosisEvaluator(dem=dem, release=release(dem, V_NOMINAL), observations=rec.observations, prior=prior,
                              t_end=T_END, gauges=gauges(), erodible_depth=erod,
                              solver_config=SolverConfig(**SOLVER, compile=compile_solver), max_batch=max_batch,
                              fine_terrain=ft,
                              device=device)
