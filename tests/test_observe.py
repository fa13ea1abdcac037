"""Observation operators against hand-made SimulationResults with known answers."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from torchslide import observe
from torchslide.observe import KINDS, Observation, register_kind
from torchslide.result import GaugeSeries, SimulationResult
from torchslide.terrain import DEM

CS = 10.0  # m; cell area 100 m^2


def make_result(h_max, h_final, v_max=None, dem=None) -> SimulationResult:
    h_max = torch.as_tensor(h_max, dtype=torch.float64)
    h_final = torch.as_tensor(h_final, dtype=torch.float64)
    B, ny, nx = h_max.shape
    dem = dem or DEM(z=np.zeros((ny, nx)), cellsize=CS, xll=1000.0, yll=2000.0)
    v_max = torch.zeros_like(h_max) if v_max is None else torch.as_tensor(v_max, dtype=torch.float64)
    area = torch.full((ny, nx), CS * CS, dtype=torch.float64)
    vol = (h_final * area).sum(dim=(-2, -1))
    z = torch.zeros(B, dtype=torch.float64)
    t = torch.linspace(0, 10, 3, dtype=torch.float64)
    g = GaugeSeries("G1", 1005.0, 2005.0, t, h=torch.tensor([[0.0, 2.0, 1.0]] * B, dtype=torch.float64),
                    u=torch.tensor([[0.0, 3.0, 0.0]] * B, dtype=torch.float64),
                    v=torch.tensor([[0.0, 4.0, 0.0]] * B, dtype=torch.float64))
    return SimulationResult(
        dem=dem, h_max=h_max, v_max=v_max, h_final=h_final, arrival_time=torch.full_like(h_max, float("inf")),
        cell_area=area, map_cell_area=CS * CS, release_volume=vol.clone(), final_volume=vol, outflow_volume=z, entrained_volume=z,
        steps=torch.zeros(B, dtype=torch.int64), t_final=z, stopped=torch.ones(B, dtype=torch.bool),
        history_t=t, mass_history=torch.zeros(B, 3, dtype=torch.float64), ke_history=torch.zeros(B, 3, dtype=torch.float64),
        gauges={"G1": g},
    )


@pytest.fixture
def res():
    # B = 2 on a 4 x 6 grid
    h_max = np.zeros((2, 4, 6))
    h_max[0, 1, 1:4] = [1.0, 0.6, 0.4]   # 2 cells > 0.5
    h_max[1, :, :] = 0.7                  # all 24 cells
    h_final = np.zeros((2, 4, 6))
    h_final[0, 1, 1:3] = [2.0, 0.3]       # 1 cell > 0.5, volume 200 m^3 above threshold, 230 total
    h_final[1, 2, 4] = 1.5
    v_max = np.zeros((2, 4, 6))
    v_max[:, 2, 3] = [5.0, 7.0]
    v_max[:, 2, 4] = [9.0, 11.0]
    return make_result(h_max, h_final, v_max)


def test_areas_and_volumes(res):
    assert observe.impact_area(res).tolist() == [200.0, 2400.0]
    assert observe.impact_area(res, threshold=0.0).tolist() == [300.0, 2400.0]
    assert observe.deposit_area(res).tolist() == [100.0, 100.0]
    assert observe.deposit_volume(res).tolist() == pytest.approx([200.0, 150.0])
    assert observe.deposit_volume(res, threshold=0.0).tolist() == pytest.approx([230.0, 150.0])
    assert observe.final_volume(res).tolist() == pytest.approx([230.0, 150.0])


def test_point_values(res):
    # cell (2, 3) spans x in [1030, 1040), y in [2020, 2030)
    assert observe.max_velocity(res, 1035.0, 2025.0).tolist() == [5.0, 7.0]
    assert observe.max_velocity(res, 1030.0, 2020.0).tolist() == [5.0, 7.0]  # lower-left edge belongs to the cell
    # bilinear halfway between the centres of (2, 3) and (2, 4)
    assert observe.max_velocity(res, 1040.0, 2025.0, method="bilinear").tolist() == pytest.approx([7.0, 9.0])
    assert observe.max_height(res, 1015.0, 2015.0).tolist() == [1.0, 0.7]
    assert observe.deposit_height(res, 1045.0, 2025.0).tolist() == [0.0, 1.5]
    with pytest.raises(ValueError, match="outside the DEM"):
        observe.max_velocity(res, 999.0, 2025.0)


def test_runout_length_straight_and_bent():
    # straight thalweg along row 1 from x = 1000: farthest wet cell centre of member 0 at x = 1035 -> 35 m
    h_max = np.zeros((2, 4, 6))
    h_max[0, 1, 0:4] = 1.0
    h_max[1, 3, 5] = 0.6       # off the path, projects to x = 1055 -> 55 m
    r = make_result(h_max, np.zeros_like(h_max))
    path = [(1000.0, 2015.0), (1060.0, 2015.0)]
    assert observe.runout_length(r, path).tolist() == pytest.approx([35.0, 55.0])
    assert observe.runout_length(r, path, max_offset=5.0).tolist() == pytest.approx([35.0, 0.0])
    assert observe.runout_length(r, path, threshold=2.0).tolist() == [0.0, 0.0]
    # an L-shaped path: up x to 1035 then up y; cell (3, 3) centre (1035, 2035) -> 35 + 20 = 55 m
    h2 = np.zeros((1, 4, 6))
    h2[0, 3, 3] = 1.0
    r2 = make_result(h2, np.zeros_like(h2))
    assert observe.runout_length(r2, [(1000.0, 2015.0), (1035.0, 2015.0), (1035.0, 2040.0)]).tolist() == pytest.approx([55.0])


def test_gauge_series(res):
    assert observe.gauge_series(res, "G1").shape == (2, 3)
    assert observe.gauge_series(res, "G1", "speed")[0].tolist() == [0.0, 5.0, 0.0]
    with pytest.raises(KeyError, match="G1"):
        observe.gauge_series(res, "nope")


def test_observation_predict_and_registry(res):
    known = {"impact_area", "deposit_area", "deposit_volume", "max_velocity", "deposit_height", "max_height",
             "runout_length", "final_volume"}
    assert known <= set(KINDS)
    o = Observation("impact_area", value=250.0, sigma=50.0)
    assert o.validate(res.dem) is o
    assert o.predict(res).tolist() == [200.0, 2400.0]
    o = Observation("max_velocity", value=6.0, sigma=1.0, x=1035.0, y=2025.0).validate(res.dem)
    assert o.predict(res).tolist() == [5.0, 7.0]
    o = Observation("runout_length", value=30.0, sigma=5.0, thalweg=[(1000.0, 2015.0), (1060.0, 2015.0)])
    assert o.validate(res.dem).predict(res).shape == (2,)
    # a new kind without editing observe.py
    register_kind("gauge_h_peak", lambda r, ob: observe.gauge_series(r, ob.options["gauge"]).amax(dim=1),
                  unit="m", overwrite=True)
    o = Observation("gauge_h_peak", value=2.0, sigma=0.5, options={"gauge": "G1"})
    assert o.validate(res.dem).predict(res).tolist() == [2.0, 2.0]
    assert Observation.from_dict({"kind": "deposit_area", "value": 1.0, "sigma": 1.0}).predict(res).shape == (2,)


@pytest.mark.parametrize(
    "kwargs,match",
    [
        (dict(kind="impact_aera", value=1.0, sigma=1.0), r"unknown observation kind 'impact_aera'; known kinds: .*impact_area"),
        (dict(kind="impact_area", value=1.0), "sigma .* is missing"),
        (dict(kind="impact_area", value=1.0, sigma=0.0), "sigma must be > 0"),
        (dict(kind="impact_area", value=1.0, sigma=-2.0), "sigma must be > 0"),
        (dict(kind="max_velocity", value=1.0, sigma=1.0), "needs a point x, y"),
        (dict(kind="max_velocity", value=1.0, sigma=1.0, x=0.0, y=0.0), "outside the DEM"),
        (dict(kind="runout_length", value=1.0, sigma=1.0), "needs a thalweg"),
        (dict(kind="impact_area", value=float("nan"), sigma=1.0), "value must be finite"),
    ],
)
def test_observation_validate_errors(res, kwargs, match):
    with pytest.raises(ValueError, match=match):
        Observation(**kwargs).validate(res.dem)


def test_from_dict_unknown_key():
    with pytest.raises(ValueError, match="unknown keys"):
        Observation.from_dict({"kind": "impact_area", "value": 1.0, "sigma": 1.0, "sigam": 2})
