"""Active-region cropping (SolverConfig.crop): a pure speed-up, bitwise equal to the whole-grid run."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from torchslide.physics import Params
from torchslide.solver import SolverConfig, simulate
from torchslide.solver import crop as crop_mod
from torchslide.terrain.synthetic import _bends, bondo_like, channel_with_bends, release_from_shape


def _channel():
    dem = channel_with_bends(40.0, slope_length=2000.0, runout_length=800.0, width=1200.0)
    rel = release_from_shape(dem, (250.0, 600.0), (120.0, 100.0), volume=2.0e5)
    return dem, rel


def _same(a, b):
    for name in ("h_final", "h_max", "v_max", "arrival_time", "steps", "t_final", "outflow_volume"):
        x, y = getattr(a, name), getattr(b, name)
        assert torch.equal(x, y), name
    for g in a.gauges:
        for f in ("h", "u", "v"):
            assert torch.equal(getattr(a.gauges[g], f), getattr(b.gauges[g], f)), (g, f)
    assert torch.allclose(a.mass_history, b.mass_history, rtol=1e-12, atol=0)


@pytest.mark.parametrize("crop_every", [1, 3])
def test_crop_equals_whole_grid(crop_every):
    """Voellmy batch with gauges far from the release (outside the first box) and one member that
    stops early (compaction while cropped)."""
    dem, rel = _channel()
    p = Params.make(mu=[0.25, 1.2, 0.3], xi=[800.0, 500.0, 2000.0])
    y_far = 600.0 + float(_bends(1300.0, 300.0, 1700.0, 150.0))  # on the channel axis
    gauges = [("up", 700.0, 600.0), ("far", 1300.0, y_far), ("corner", 20.0, 20.0)]
    kw = dict(t_end=60.0, gauges=gauges)
    rc = simulate(dem, rel, p, config=SolverConfig(output_interval=2.0, crop=True, crop_every=crop_every,
                                                   check_every=5), **kw)
    rf = simulate(dem, rel, p, config=SolverConfig(output_interval=2.0, crop=False, check_every=5), **kw)
    _same(rc, rf)
    assert float(rc.gauges["far"].h.max()) > 0  # the flow did reach the far gauge
    assert bool(rc.stopped[1])  # the high-friction member ended early and was compacted out


def test_crop_equals_whole_grid_with_source_terms():
    """Entrainment (bed evolves), deposition, earth pressure, curvature and a mu_scale raster."""
    dem, rel = _channel()
    ny, nx = dem.shape
    erod = np.full((ny, nx), 2.0)
    ms = np.ones((ny, nx))
    ms[:, nx // 2:] = 0.7
    p = Params.make(mu=[0.25, 0.25], xi=[800.0, 800.0], kappa=[0.0, 0.002], deposition=[0.0, 0.01],
                    earth_pressure=[1.0, 0.0], phi_int=[35.0, 35.0], curvature=[1.0, 0.0], tau_y=[0.0, 5.0],
                    mu_i=[0.1, 0.0])
    kw = dict(t_end=40.0, erodible_depth=erod, mu_scale=ms, gauges=[("g", 1500.0, 600.0)])
    rc = simulate(dem, rel, p, config=SolverConfig(output_interval=2.0, crop=True), **kw)
    rf = simulate(dem, rel, p, config=SolverConfig(output_interval=2.0, crop=False), **kw)
    _same(rc, rf)
    assert torch.equal(rc.bed_change, rf.bed_change)
    assert torch.equal(rc.entrained_volume, rf.entrained_volume)


def test_box_grows_from_the_release_and_stays_inside_the_grid():
    case = bondo_like(100.0)
    ny, nx = case.dem.shape
    h = torch.as_tensor(case.release).unsqueeze(0)
    box = crop_mod.grow(h, None, ny, nx, margin=7)
    rows, cols = np.nonzero(case.release > 0)
    # the release plus the margin (and the growth slack), clipped to the grid, is all that is stepped
    assert box.r0 <= rows.min() - 7 or box.r0 == 0
    assert box.c0 == 0 and box.c1 <= cols.max() + 1 + 14
    assert box.shape[1] < nx // 2
    # a box never shrinks, and an unchanged wet support keeps it as it is
    sub = h[:, box.r0:box.r1, box.c0:box.c1]
    assert crop_mod.grow(sub, box, ny, nx, margin=7) == box
    # a dry state keeps the current box (and the whole grid when there is none yet)
    assert crop_mod.grow(torch.zeros_like(sub), box, ny, nx, margin=7) == box
    assert crop_mod.grow(torch.zeros_like(h), None, ny, nx, margin=7).covers(ny, nx)


def test_crop_every_validated():
    with pytest.raises(ValueError, match="crop_every"):
        SolverConfig(crop_every=0).validate()


def test_max_steps_ends_the_member_while_cropped():
    """A member over max_steps is marked failed and stops advancing (its state stays at max_steps)."""
    dem, rel = _channel()
    p = Params.make(mu=[0.25, 0.3], xi=[800.0, 900.0])
    runs = [simulate(dem, rel, p, t_end=60.0, config=SolverConfig(crop=c, max_steps=10, check_every=5))
            for c in (True, False)]
    for r in runs:
        assert r.failed.tolist() == [True, True]
        assert r.steps.tolist() == [10, 10]
        assert "max_steps" in r.failure_reason[0]
        assert float(r.t_final[0]) < 60.0
    _same(*runs)
