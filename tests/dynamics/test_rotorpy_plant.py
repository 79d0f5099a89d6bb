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
LAG_MODEL = "examples/rotorpy/crazyflie_lag.toml"


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


def test_the_last_command_may_ride_along_as_states_6_to_8():
    check_planning_model(ModelSpec.load(LAG_MODEL))
    table = ModelSpec.load(LAG_MODEL).to_table()
    table["A"][3][6] = 0.05    # the velocity reads the last command: not what the vehicle's setpoint assumes
    with pytest.raises(GpmpcError, match=r"last command as states 6-8.*A\[3\]\[6\] = 0.05, expected 0"):
        check_planning_model(ModelSpec.from_table(table))
    table = ModelSpec.load(LAG_MODEL).to_table()
    table["residual"] = [3, 4, 5, 6]   # a GP on the last command, which is known exactly
    with pytest.raises(GpmpcError, match="velocity rows only"):
        check_planning_model(ModelSpec.from_table(table))


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


def test_a_lag_model_flies_the_same_vehicle_and_knows_the_command_it_gave():
    """States 0-5 of a lag model's flight are the double integrator's flight to the bit; states 6-8 are the
    command applied last, exactly (the sensor noise is on p and v only)."""
    gen = torch.Generator().manual_seed(0)
    commands = 2 * torch.rand(6, 1, 3, generator=gen, dtype=torch.float64) - 1
    flown = []
    for model in (MODEL, LAG_MODEL):
        plant = RotorPyPlant(NominalModel(ModelSpec.load(model)), PlantSettings(sensor_noise=0.01, seed=3))
        x = plant.reset(torch.zeros(1, 3, dtype=torch.float64))
        xs = [x]
        for t, u in enumerate(commands):
            x = plant.step(t, x, u)
            xs.append(x)
        flown.append(torch.cat(xs))
    plain, lag = flown
    assert lag.shape == (7, 9) and torch.equal(lag[:, :6], plain)
    assert torch.equal(lag[0, 6:], torch.zeros(3, dtype=torch.float64))
    assert torch.equal(lag[1:, 6:], commands[:, 0])
    assert torch.equal(plant.true_states[0, 6:], commands[-1, 0])


def test_the_previous_command_explains_what_the_current_one_cannot():
    """Why the lag model: under random commands, a least-squares fit of a step's acceleration error
    (velocity change over dt minus the command) on the velocity, the command and the previous one leaves
    less than a quarter of what the fit without the previous command leaves (the vehicle must tilt before
    it accelerates: measured 4-5 % against 27-30 % of the variance)."""
    plant = RotorPyPlant(NominalModel(ModelSpec.load(LAG_MODEL)), PlantSettings())
    gen = torch.Generator().manual_seed(1)
    x = plant.reset(torch.zeros(1, 3, dtype=torch.float64))
    rows, errors = [], []
    for t in range(60):
        u = torch.zeros(1, 3, dtype=torch.float64)
        u[0, :2] = 2 * torch.rand(2, generator=gen, dtype=torch.float64) - 1
        x_next = plant.step(t, x, u)
        rows.append(torch.cat([u[0, :2], x[0, 6:8], x[0, 3:5]]).numpy())
        errors.append(((x_next[0, 3:5] - x[0, 3:5]) / 0.1 - u[0, :2]).numpy())
        x = x_next
    F, e = np.array(rows)[10:], np.array(errors)[10:]

    def unexplained(columns):
        G = np.hstack([F[:, columns], np.ones((len(F), 1))])
        resid = e - G @ np.linalg.lstsq(G, e, rcond=None)[0]
        return resid.var(0) / e.var(0)

    without, with_lag = unexplained([0, 1, 4, 5]), unexplained([0, 1, 2, 3, 4, 5])
    assert (with_lag < 0.1).all() and (with_lag < 0.25 * without).all()


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


def test_short_flight_of_the_lag_model_through_the_closed_loop():
    """The lag model's GPs learn from excitation flights that log the last command too."""
    cfg = Config(model=LAG_MODEL, plant="rotorpy", plant_wind="constant", plant_wind_speed=[1.0, 0.0, 0.0],
                 scenario="circle", num_agents=2, max_steps=4, gp_samples=20, gp_iters=3)
    rollout = simulate(cfg)
    assert rollout.states.shape == (5, 2, 9) and rollout.input_memory == [6, 7, 8]
    assert np.array_equal(rollout.states[1:, :, 6:], rollout.inputs)
    assert compute_metrics(rollout)["violations"] == 0
