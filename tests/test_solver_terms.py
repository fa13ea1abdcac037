"""Candidate terms: nested (switch 0 == plain Voellmy bitwise) and with the expected direction of effect."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from torchslide.diagnose.candidates import CANDIDATES
from torchslide.physics import Params
from torchslide.solver import SolverConfig, simulate

from .conftest import chute_case

from .conftest import TERMS_BASE as BASE, TERMS_ON as ON, TERMS_T_END as T_END

CFG = SolverConfig(output_interval=5.0)


@pytest.fixture(scope="module")
def case():
    dem, rel = chute_case()
    base = simulate(dem, rel, Params.make(**BASE), t_end=T_END, config=CFG)
    return dem, rel, base


def _runout(r, dem, b=0, thr=0.05):
    cols = (r.h_final[b] > thr).any(0).nonzero()
    return float(dem.x_centres()[int(cols.max())])


def _com(r, dem, b=0):
    X = torch.as_tensor(dem.x_centres())
    h = r.h_final[b]
    return float((h.sum(0) * X).sum() / h.sum())


@pytest.mark.parametrize("name", sorted(CANDIDATES))
def test_switch_zero_is_baseline_bitwise(case, name):
    """Member 0 has the switch at 0 while member 1 turns the term on (so the term's code runs):
    member 0 must equal the plain Voellmy run bitwise."""
    dem, rel, base = case
    cand = CANDIDATES[name]
    extra = {k: v for k, v in cand.fixed}
    p = Params.make(**BASE, **extra, **{cand.param: [cand.baseline, ON[cand.param]]})
    kw = {"erodible_depth": np.full(dem.shape, 1.0)} if cand.param == "kappa" else {}
    r = simulate(dem, rel, p, t_end=T_END, config=CFG, **kw)
    m0 = r.member(0)
    assert torch.equal(m0.h_final, base.h_final)
    assert torch.equal(m0.v_max, base.v_max)
    assert torch.equal(m0.steps, base.steps)
    assert not torch.equal(r.member(1).h_final, base.h_final)


def test_candidates_table():
    for name, c in CANDIDATES.items():
        assert c.baseline == 0.0 and c.prior[0] <= c.baseline < c.prior[1]
        assert c.param in Params.names()
        Params.make(mu=0.2, **dict(c.fixed), **{c.param: c.prior[1]})  # the prior box is valid


def test_yield_stress_shortens_runout_thicker_deposit(case):
    dem, rel, base = case
    r = simulate(dem, rel, Params.make(**BASE, tau_y=[0.0, 150.0]), t_end=T_END, config=CFG)
    assert _com(r, dem, 1) < _com(r, dem, 0) - 5.0
    assert float(r.h_final[1].max()) > float(r.h_final[0].max())


def test_entrainment_increases_volume(case):
    dem, rel, base = case
    r = simulate(dem, rel, Params.make(**BASE, kappa=[0.0, 0.004]), t_end=T_END, config=CFG,
                 erodible_depth=np.full(dem.shape, 1.0))
    assert float(r.final_volume[1]) > 1.05 * float(r.final_volume[0])
    assert float(r.bed_change[1].min()) < 0 and float(r.bed_change[0].abs().max()) == 0.0


def test_mu_i_adds_friction(case):
    dem, rel, base = case
    r = simulate(dem, rel, Params.make(**BASE, mu_i=[0.0, 0.3]), t_end=T_END, config=CFG)
    assert float(r.v_max[1].max()) < float(r.v_max[0].max())
    assert _com(r, dem, 1) < _com(r, dem, 0)


def test_deposition_leaves_mass_behind(case):
    dem, rel, base = case
    r = simulate(dem, rel, Params.make(**BASE, deposition=[0.0, 0.3]), t_end=T_END, config=CFG)
    assert _com(r, dem, 1) < _com(r, dem, 0)
    assert float(r.bed_change[1].max()) > 0
    bal = r.final_volume + r.outflow_volume - r.release_volume
    assert float(bal.abs().max()) < 1e-10 * float(r.release_volume[0])


def test_curvature_brakes_in_hollow(case):
    """The chute bends from slope to flat (a hollow, z_xx > 0 at the break): extra normal stress there
    means more friction, so the deposit stops earlier."""
    dem, rel, base = case
    r = simulate(dem, rel, Params.make(**BASE, curvature=[0.0, 1.0]), t_end=T_END, config=CFG)
    assert _com(r, dem, 1) < _com(r, dem, 0)


def test_earth_pressure_changes_spreading(case):
    dem, rel, base = case
    r = simulate(dem, rel, Params.make(**BASE, phi_int=35.0, earth_pressure=[0.0, 1.0]), t_end=T_END, config=CFG)
    # active k < 1 while spreading: less lateral push, the deposit is narrower or equal; passive k > 1
    # where it piles up at the stop: a flatter, longer deposit
    assert not torch.equal(r.h_final[0], r.h_final[1])
    assert _runout(r, dem, 1) != _runout(r, dem, 0) or float(r.h_final[1].max()) != float(r.h_final[0].max())
