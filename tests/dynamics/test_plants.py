"""The Plant protocol: today's true system as a plant, and a stub plant through the closed loop."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from torch_gpmpc import Config, compute_metrics, simulate
from torch_gpmpc.config import load_config
from torch_gpmpc.coordination.controller import Controller
from torch_gpmpc.dynamics.plants import ModelPlant, Plant, plant_from_config
from torch_gpmpc.dynamics.systems import make_system, system_from_config
from torch_gpmpc.errors import GpmpcError
from torch_gpmpc.sim.closed_loop import ADMMPlanner, run_closed_loop
from torch_gpmpc.sim.scenarios import make_scenario


class DriftPlant:
    """The nominal model plus a constant drift; the planner is shown the true state plus a bias."""

    def __init__(self, nominal, drift, bias):
        self.nominal, self.drift, self.bias = nominal, drift, bias
        self.seen = []

    @property
    def true_states(self):
        return self._x

    def reset(self, starts):
        self._x = self.nominal.states_at(starts)
        return self._x + self.bias

    def step(self, t, x, u, noise=None):
        self.seen.append(x.clone())
        self._x = self.nominal(self._x, u) + self.drift
        return self._x + self.bias


def _run(cfg, plant):
    system = system_from_config(cfg)
    return run_closed_loop(cfg, make_scenario(cfg), plant, ADMMPlanner(Controller.for_run(cfg, system, None)))


def test_model_plant_is_the_true_system():
    system = make_system(2, noise_std=0.1, wind_scale=0.1)
    plant = ModelPlant(system)
    assert isinstance(plant, Plant)
    x0 = plant.reset(torch.tensor([[0.5, -1.0], [2.0, 0.3]], dtype=torch.float64))
    u = torch.tensor([[1.0, 0.0], [0.0, -1.0]], dtype=torch.float64)
    w = torch.randn(2, 2, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    assert torch.equal(plant.step(0, x0, u, noise=w), system.step(x0, u, noise=w))
    assert torch.equal(plant.true_states, system.step(x0, u, noise=w))


def test_closed_loop_on_a_true_system_or_its_plant_is_identical():
    cfg = Config(method="nominal", max_steps=4)
    system = system_from_config(cfg)
    a = _run(cfg, system)
    b = _run(cfg, plant_from_config(cfg, system))
    np.testing.assert_array_equal(a.states, b.states)


def test_stub_plant_through_the_closed_loop():
    """Rollout states are the plant's true states, the planner sees the measured ones, and
    plan_tracking_rmse is the drift's RMS (the nominal plan predicts no drift)."""
    cfg = Config(method="nominal", max_steps=5, noise_std=0.0)
    nominal = system_from_config(cfg).nominal
    drift = torch.tensor([0.01, 0.0], dtype=torch.float64)
    bias = torch.tensor([0.0, 0.02], dtype=torch.float64)
    plant = DriftPlant(nominal, drift, bias)
    rollout = _run(cfg, plant)
    S = rollout.num_steps
    assert S == 5
    np.testing.assert_allclose(rollout.states[-1], plant.true_states.numpy())
    np.testing.assert_allclose(rollout.plans[:, :, 0], torch.stack(plant.seen).numpy())  # plans start at x
    np.testing.assert_allclose(rollout.states[1:] - rollout.plans[:, :, 1] + bias.numpy(), np.broadcast_to(
        drift.numpy(), rollout.states[1:].shape), atol=1e-12)
    # planned next state = A (x_true + bias) + B u; flown = A x_true + B u + drift
    expected = np.sqrt(np.mean((drift.numpy() - bias.numpy()) ** 2))
    assert abs(compute_metrics(rollout)["plan_tracking_rmse"] - expected) < 1e-12


def test_model_plant_turns_its_wind_at_the_change_step():
    system = make_system(3, noise_std=0.0, wind_scale=0.1)
    plant = ModelPlant(system, wind_change_step=2)
    x = plant.reset(torch.tensor([[0.7, -0.4, 0.2]], dtype=torch.float64))
    u = torch.zeros(1, 3, dtype=torch.float64)
    x1 = plant.step(1, x, u)
    assert torch.equal(x1, system.step(x, u, noise=torch.zeros(1, 3, dtype=torch.float64)))
    g = system.residual(x1)
    x2 = plant.step(2, x1, u)
    torch.testing.assert_close(x2 - x1, torch.stack([-g[:, 1], g[:, 0], g[:, 2]], dim=-1), rtol=0, atol=1e-15)


def test_online_gp_learns_the_turned_wind_and_the_frozen_one_does_not():
    """The short end-to-end version of the wind-change case: the paper's agents, the vortex turned at
    step 5; the online GPs' one-step prediction error after the change is well below the frozen GPs'."""
    base = Config(max_steps=30, wind_change_step=5, wind_scale=0.3, noise_std=0.01, gp_iters=10)
    frozen = compute_metrics(simulate(base))
    online = compute_metrics(simulate(base.replace(gp_online=True, gp_online_budget=100)))

    assert online["online_prediction_rmse_after_change"] < 0.7 * frozen["online_prediction_rmse_after_change"]
    assert online["gp_update_s_per_step"] > 0 and frozen["gp_update_s_per_step"] == 0
    # the online run also judges its GPs as fitted on its own transitions, which cannot foresee the turn
    assert online["frozen_prediction_rmse_after_change"] > online["online_prediction_rmse_after_change"]
    assert frozen["frozen_prediction_rmse_after_change"] is None
    assert 0 < online["online_prediction_rmse_at_change"] and frozen["online_prediction_rmse_at_change"] > 0


def test_an_online_run_records_its_fitted_gps_errors_on_its_own_transitions():
    """``frozen_prediction_error`` of an online run equals the fitted GPs' prediction of the
    transitions the run made, recomputed from its rollout (no offset estimate here)."""
    from torch_gpmpc.gp.fit import fit_agent_gps

    cfg = Config(max_steps=8, wind_change_step=3, wind_scale=0.3, noise_std=0.01, gp_iters=10,
                 gp_online=True, gp_online_budget=100)
    system = system_from_config(cfg)
    gps = fit_agent_gps(cfg, system, cfg.num_agents)
    rollout = simulate(cfg, gps=gps)
    x, u = torch.as_tensor(rollout.states), torch.as_tensor(rollout.inputs)
    expected = []
    for t in range(rollout.num_steps):
        inputs, y = system.nominal.gp_targets(x[t], u[t], x[t + 1])
        expected.append(torch.stack([y[k] - gps[k].predict(inputs[k:k + 1])[0][0] for k in range(len(gps))]))
    np.testing.assert_allclose(rollout.frozen_prediction_error, torch.stack(expected).numpy(), rtol=0, atol=1e-12)
    metrics = compute_metrics(rollout)
    assert metrics["frozen_prediction_rmse"] == pytest.approx(float(np.sqrt(np.mean(torch.stack(expected).numpy() ** 2))))


def test_a_rotorpy_run_does_not_build_the_vortex_wind(tmp_path):
    """With plant = rotorpy the model's own world is not flown: a planning model with GPs on more
    rows than the position (here the Crazyflie planner learning positions too) needs no wind_scale = 0."""
    text = (Path(__file__).resolve().parents[2] / "examples" / "rotorpy" / "crazyflie.toml").read_text()
    assert "residual = [3, 4, 5]" in text
    model = tmp_path / "crazyflie_all_rows.toml"
    model.write_text(text.replace("residual = [3, 4, 5]", "residual = [0, 1, 2, 3, 4, 5]"))
    with pytest.raises(GpmpcError, match="wind_scale=0"):
        system_from_config(load_config(None, {"model": str(model), "wind_scale": 0.1}))
    system = system_from_config(load_config(None, {"model": str(model), "wind_scale": 0.1, "plant": "rotorpy"}))
    assert system.wind.scale == 0.0 and len(system.nominal.residual) == 6
