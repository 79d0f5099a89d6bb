"""The RotorPy plant: vehicles that track the planned steps (needs the ``rotorpy`` extra)."""

from __future__ import annotations

import sys

import numpy as np
import pytest
import torch

from torch_gpmpc import Config, compute_metrics, simulate
from torch_gpmpc.config.model_spec import ModelSpec
from torch_gpmpc.dynamics.rotorpy_plant import (PlantSettings, RotorPyPlant, TurningWind,
                                                check_planning_model, require_rotorpy)
from torch_gpmpc.dynamics.systems import NominalModel
from torch_gpmpc.errors import GpmpcError

MODEL = "examples/rotorpy/crazyflie.toml"


class _Constant:
    def update(self, t, position):
        return np.array([1.0, 0.0, 0.5])


def test_wind_turns_90_degrees_about_the_vertical_at_the_change():
    wind = TurningWind(_Constant(), change_time=1.0)
    np.testing.assert_allclose(wind.update(0.99, None), [1.0, 0.0, 0.5])
    np.testing.assert_allclose(wind.update(1.0, None), [0.0, 1.0, 0.5])


def test_planning_model_must_be_a_3d_double_integrator():
    check_planning_model(ModelSpec.double_integrator(dim=3, dt=0.1, u_max=2.0))
    check_planning_model(ModelSpec.load(MODEL))
    with pytest.raises(GpmpcError, match="3D double integrator"):
        check_planning_model(ModelSpec.double_integrator(dim=2, dt=0.1, u_max=2.0))
    with pytest.raises(GpmpcError, match="plant = rotorpy|plant"):
        Config(plant="gazebo")


def test_missing_rotorpy_says_how_to_install(monkeypatch):
    monkeypatch.setitem(sys.modules, "rotorpy", None)
    with pytest.raises(GpmpcError, match=r'pip install -e "\.\[rotorpy\]"'):
        require_rotorpy()


rotorpy = pytest.importorskip("rotorpy")


def _plant(**kw):
    return RotorPyPlant(NominalModel(ModelSpec.load(MODEL)), PlantSettings(**kw))


def test_hover_and_a_commanded_acceleration_are_tracked():
    plant = _plant()
    x = plant.reset(torch.tensor([[0.0, 0.0, 1.0], [2.0, 0.0, 1.0]], dtype=torch.float64))
    assert x.shape == (2, 6) and torch.equal(x[:, 3:], torch.zeros(2, 3, dtype=torch.float64))
    u = torch.tensor([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]], dtype=torch.float64)
    for t in range(10):
        x = plant.step(t, x, u)
    assert float((x[0, :3] - torch.tensor([0.0, 0.0, 1.0])).norm()) < 1e-3   # hover holds
    # 1 s at 1 m/s^2: v = 1, p = 2.5 for the double integrator; the vehicle falls a little short
    # (it must tilt first, about 0.2 s, and rotor drag grows with speed), never beyond
    assert 0.6 < float(x[1, 3]) < 1.0 and 2.2 < float(x[1, 0]) < 2.5
    assert plant.min_distance < 2.0 + 1e-9


def test_flights_are_reproducible_and_leave_numpy_alone():
    np.random.seed(123)
    before = np.random.get_state()[1].copy()
    runs = []
    for _ in range(2):
        plant = _plant(wind="dryden", wind_speed=(1.0, 0.0, 0.0), sensor_noise=0.01, seed=5)
        x = plant.reset(torch.zeros(1, 3, dtype=torch.float64))
        for t in range(3):
            x = plant.step(t, x, torch.zeros(1, 3, dtype=torch.float64))
        runs.append(x)
    assert torch.equal(runs[0], runs[1])
    np.testing.assert_array_equal(np.random.get_state()[1], before)
    assert float(runs[0][0, :3].norm()) > 0  # the gusts moved it


def test_wind_pushes_the_vehicle_downwind():
    plant = _plant(wind="constant", wind_speed=(3.0, 0.0, 0.0))
    x = plant.reset(torch.zeros(1, 3, dtype=torch.float64))
    for t in range(5):
        x = plant.step(t, x, torch.zeros(1, 3, dtype=torch.float64))
    assert float(x[0, 3]) > 0.01   # drifting along +x


@pytest.mark.parametrize("method", ["nominal", "gp-chance"])
def test_short_flight_through_the_closed_loop(method):
    """The GPs of gp-chance learn from excitation flights of the same vehicles in the same wind."""
    cfg = Config(model=MODEL, plant="rotorpy", plant_wind="constant", plant_wind_speed=[1.0, 0.0, 0.0],
                 scenario="circle", num_agents=2, method=method, max_steps=4,
                 **({} if method == "nominal" else {"gp_samples": 20, "gp_iters": 3}))
    rollout = simulate(cfg)
    metrics = compute_metrics(rollout)
    assert rollout.states.shape == (5, 2, 6) and np.isfinite(rollout.states).all()
    assert metrics["plan_tracking_rmse"] > 0 and metrics["violations"] == 0
