"""Peak speeds against the energy line (docs/verification.md, case 7) on terrain with steps and roughness:
the flow must never be faster than a point mass sliding from the release with Coulomb friction (plus its
peak thickness as pressure head), and not much slower on a chute where that point mass is exact."""
from __future__ import annotations

import numpy as np
from scipy.ndimage import binary_dilation, gaussian_filter

from torchslide.bounds import energy_line_speed, free_fall_speed
from torchslide.physics import Params
from torchslide.solver import SolverConfig, simulate
from torchslide.terrain.grid import DEM


def _stepped_chute(dx=10.0, nx=300, ny=5):
    """Steps of 60 m alternating 40 and 10 degrees down to x = 2000 m, then flat (uniform across)."""
    x = (np.arange(nx) + 0.5) * dx
    slope = np.where((x // 60.0) % 2 == 0, np.tan(np.radians(40)), np.tan(np.radians(10)))
    slope = np.where(x > 2000, 0.0, slope)
    zf = -np.cumsum(slope) * dx
    return DEM(np.tile(zf - zf.min(), (ny, 1)), dx), x


def _rough_gully(dx=10.0, nx=160, ny=60, amp=5.0, seed=0):
    """A 35 degree slope with a V-shaped gully (sides 0.6) onto a gentle run-out, roughened by smoothed
    noise of ``amp`` m at the scale of one cell."""
    x = (np.arange(nx) + 0.5) * dx
    y = (np.arange(ny) + 0.5) * dx
    X, Y = np.meshgrid(x, y)
    yc = ny * dx / 2
    z = np.where(X < 1000, (1000 - X) * np.tan(np.radians(35)), -(X - 1000) * 0.05) + 0.6 * np.abs(Y - yc)
    noise = gaussian_filter(np.random.default_rng(seed).standard_normal((ny, nx)), 1.0)
    return DEM(z + amp * noise / noise.std(), dx), X, Y, yc


def test_a_stepped_chute_follows_its_energy_line():
    """On steps of 40 and 10 degrees a slab of 1 m with mu = 0.15 and almost no turbulent friction moves
    like a point mass: v^2 = 2 g (z0 - z - mu s). Every cell's peak speed stays under the energy line
    from the release and the track's speeds stay within 15 % of the point mass's (the bed's reaction at
    the steps once made them 1.9 times the point mass and 3.6 times the bound)."""
    dem, x = _stepped_chute()
    rel = np.zeros(dem.shape)
    rel[:, (x > 100) & (x < 300)] = 1.0
    mu = 0.15
    r = simulate(dem, rel, Params.make(mu=[mu], xi=[1e6]), t_end=200.0,
                 config=SolverConfig(stop_ke_fraction=1e-3), thickness="vertical")
    v, h = r.v_max[0].numpy(), r.h_max[0].numpy()
    bound = energy_line_speed(dem.z, dem.cellsize, rel, mu, h)
    track = (h > 0.05) & ~binary_dilation(rel > 0)    # the cell beside a release receives it at any speed
    assert track[2].sum() > 150
    assert (v[track] <= bound[track]).all(), float((v[track] / bound[track]).max())
    zc = dem.z[2]
    x0 = x[(x > 100) & (x < 300)].mean()
    point = np.sqrt(2 * 9.81 * np.clip(np.interp(x0, x, zc) - zc - mu * (x - x0), 0, None))
    along = track[2] & (x > 400) & (x < 1900)
    ratio = v[2][along] / point[along]
    assert 0.85 < ratio.mean() < 1.15, ratio.mean()


def test_peak_speeds_on_a_rough_gully_stay_under_the_energy_line_and_free_fall():
    """A 3 m release in a rough V gully (noise of 5 m at the cell scale): outside the release every
    cell's v_max is under the energy line with mu and free fall (they were 1.9 and 1.7 times above
    them when the momentum crossed cells as horizontal momentum with a curvature reaction), and the
    fastest cell is within 25 % of the point mass's speed at the foot of the slope."""
    dem, X, Y, yc = _rough_gully()
    rel = np.where((np.abs(X - 200) < 60) & (np.abs(Y - yc) < 60), 3.0, 0.0)
    mu = 0.2
    r = simulate(dem, rel, Params.make(mu=[mu], xi=[1e5]), t_end=120.0, thickness="vertical")
    v, h = r.v_max[0].numpy(), r.h_max[0].numpy()
    outside = (h > 0.05) & ~binary_dilation(rel > 0)
    assert outside.sum() > 500
    bound = energy_line_speed(dem.z, dem.cellsize, rel, mu, h)
    assert (v[outside] <= bound[outside]).all(), float((v[outside] / bound[outside]).max())
    assert (v[outside] <= free_fall_speed(dem.z, rel)[outside]).all()
    foot = np.sqrt(2 * 9.81 * ((1000 - 200) * np.tan(np.radians(35)) - mu * 800))
    assert 0.75 * foot < v.max() < 1.25 * foot, (v.max(), foot)
