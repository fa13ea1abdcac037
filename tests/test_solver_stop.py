"""When a run ends: the rule of torchslide.solver.stop (SolverConfig.stop_quiet_time, the default)
against the kinetic-energy rule alone and a run to t_end."""
from __future__ import annotations

import torch

from torchslide.physics import Params
from torchslide.solver import SolverConfig, simulate

from .conftest import chute_case

P = Params.make(mu=[0.2, 0.35, 0.25], xi=[300.0, 1500.0, 800.0])


def _last_arrival(r) -> torch.Tensor:
    a = r.arrival_time
    return torch.where(torch.isinf(a), torch.zeros_like(a), a).amax(dim=(1, 2))


def test_a_run_ends_once_its_footprint_is_quiet_with_the_maps_of_a_run_to_t_end():
    dem, rel = chute_case()
    full = simulate(dem, rel, P, t_end=200.0, config=SolverConfig(stop_ke_fraction=0.0, stop_quiet_time=0.0))
    ke = simulate(dem, rel, P, t_end=200.0, config=SolverConfig(stop_quiet_time=0.0))
    r = simulate(dem, rel, P, t_end=200.0)
    assert bool(r.stopped.all()) and bool((r.t_final < 0.5 * full.t_final).all())
    assert float(r.t_final.sum()) < 0.7 * float(ke.t_final.sum())        # the slow creep is not waited for
    # it ended after 10 s without a newly reached cell, with the kinetic energy below 1 % of its peak
    # (and the deposit changing by less than 1 % of the volume in those 10 s)
    assert bool((r.t_final - _last_arrival(r) >= 10.0).all())
    assert bool((r.ke_history[:, -1] < 0.01 * r.ke_history.amax(dim=1)).all())   # samples after the end repeat it
    # the maps a user reads: peak speeds as at t_end, the footprint within 1 %
    assert torch.equal(r.v_max.amax(dim=(1, 2)), full.v_max.amax(dim=(1, 2)))
    reached = r.h_max > 0.1
    assert torch.equal(r.v_max[reached], full.v_max[reached])
    # the deposit within 5 % of the volume (L1) of the one at t_end
    moved = (r.h_final - full.h_final).abs().sum(dim=(1, 2)) / full.h_final.sum(dim=(1, 2))
    assert bool((moved < 0.05).all())
    a, b = (r.h_max > 0.1).sum(dim=(1, 2)), (full.h_max > 0.1).sum(dim=(1, 2))
    assert bool(((b - a).abs() <= 0.01 * b).all())
    # switched off, the kinetic-energy rule alone decides
    off = simulate(dem, rel, P, t_end=200.0, config=SolverConfig(stop_quiet_time=0.0))
    assert torch.equal(off.t_final, ke.t_final)


def test_the_footprint_rule_waits_while_the_front_advances():
    """A flow still reaching new cells (a long slope, t_end before it stops) is never ended by the rule."""
    dem, rel = chute_case()
    r = simulate(dem, rel, P, t_end=15.0)
    assert not bool(r.stopped.any()) and bool((r.t_final == 15.0).all())
