"""Shared small terrains for the solver tests (plus a smoke test of the shared cases)."""
from __future__ import annotations

import torch

from torchslide.physics import Params
from torchslide.solver import simulate

from .conftest import chute_case


def test_chute_smoke():
    dem, rel = chute_case()
    r = simulate(dem, rel, Params.make(mu=0.3, xi=500.0), t_end=120.0)
    assert not bool(r.failed.any())
    assert bool(r.stopped.all())
    # the deposit lies beyond the slope break, the release area is (mostly) left behind
    X = torch.as_tensor(dem.x_centres())
    com = float((r.h_final[0].sum(0) * X).sum() / r.h_final[0].sum())
    assert com > 250.0


def test_progress_reports_the_simulated_time_during_the_call(capsys):
    """progress=True: a bar of the slowest member's simulated time that moves during the call."""
    import re

    dem, rel = chute_case()
    simulate(dem, rel, Params.make(mu=[0.3, 0.35], xi=500.0), t_end=60.0, progress=True)
    err = capsys.readouterr().err
    done = [int(m) for m in re.findall(r"(\d+)/60 s simulated", err)]
    assert "simulate 2 members" in err and any(0 < d < 60 for d in done) and done[-1] == 60
