"""experiments/hidden_physics/boundary_inflow.py on the harness terrain the old transmissive edge fed."""
from __future__ import annotations

import pytest


def test_the_resolved_terrain_gains_volume_through_an_open_edge_and_none_through_the_outflow_edge():
    """On 40 m cells the resolved terrain's null run gained ~4.5 % of its release through the open edge
    (the artefact the outflow edge removes); with the default outflow edge nothing comes in."""
    from experiments.hidden_physics.boundary_inflow import measure

    r = measure("resolved", 40.0, scenarios=["null"])["null"]
    assert r["inflow_open_fraction"] == pytest.approx(0.045, abs=0.01)
    assert r["inflow_outflow"] == 0.0
    assert r["max_abs_dh_final"] > 0.1
