"""Models whose state holds the last command (``w' = u``, a tracking-lag model): which rows count, what the
default cost, the plants and the plan-tracking metric do with them."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from torch_gpmpc import Config, ModelSpec, compute_metrics, simulate
from torch_gpmpc.coordination.team_step import TeamStep
from torch_gpmpc.sim.metrics import plan_tracking_rmse
from torch_gpmpc.sim.rollout import Rollout
from tests.helpers import lag_model


def test_the_rows_that_hold_the_last_input_are_found_and_only_those():
    assert ModelSpec.load("examples/rotorpy/crazyflie_lag.toml").input_memory == ((6, 0), (7, 1), (8, 2))
    assert ModelSpec.from_table(lag_model()).input_memory == ((4, 0), (5, 1))
    for spec in (ModelSpec.load("examples/rotorpy/crazyflie.toml"), ModelSpec.double_integrator(3),
                 ModelSpec.single_integrator(2)):
        assert spec.input_memory == ()
    table = lag_model()
    table["A"][4][0] = 0.5          # the row also reads the position: a state, not the last input
    table["B"][5][0] = 0.5          # the row mixes two inputs
    assert ModelSpec.from_table(table).input_memory == ()
    table = lag_model()
    table["A"][0][4] = 0.1          # the position reads it: a velocity set by the command, the robot's state
    assert ModelSpec.from_table(table).input_memory == ((5, 1),)
    table = lag_model()
    table["B"][4][0] = 2.0          # twice the input: not the input itself
    table["residual"] = [2, 3, 5]   # a residual row is learned, not known
    assert ModelSpec.from_table(table).input_memory == ()


def test_a_lag_model_flies_the_closed_loop_with_the_commands_in_its_state(tmp_path):
    """Through the model's own true system the last-command rows equal the inputs applied, exactly (the
    process noise acts on the residual rows), the rollout keeps them through a save, and the
    plan-tracking metric leaves them out."""
    cfg = Config(model=lag_model(), scenario="circle", num_agents=2, circle_radius=1.5, max_steps=6,
                 gp_iters=5)
    rollout = simulate(cfg)
    assert rollout.states.shape[1:] == (2, 6) and rollout.input_memory == [4, 5]
    assert np.array_equal(rollout.states[1:, :, 4:], rollout.inputs)
    assert np.array_equal(rollout.states[0, :, 4:], np.zeros((2, 2)))
    path = tmp_path / "rollout.npz"
    rollout.save(path)
    loaded = Rollout.load(path)
    assert loaded.input_memory == [4, 5]
    metrics = compute_metrics(loaded)
    p, s = rollout.plans[:, :, 1, :4], rollout.states[1:, :, :4]
    assert metrics["plan_tracking_rmse"] == pytest.approx(float(np.sqrt(np.mean((p - s) ** 2))), rel=1e-12)
    json.dumps(metrics)


def test_plan_tracking_without_memory_rows_is_over_every_state():
    plans = np.zeros((1, 1, 2, 3))
    states = np.zeros((2, 1, 3))
    states[1, 0] = [0.3, 0.0, 4.0]
    kw = dict(inputs=np.zeros((1, 1, 1)), plans=plans, targets=np.zeros((1, 1)), adjacency=np.zeros((1, 1, 1)),
              admm_iterations=np.ones(1), converged=np.ones(1, bool), primal_residuals=np.zeros((1, 1)),
              dual_residuals=np.zeros((1, 1)), slack_max=np.zeros(1), infeasible_solves=np.zeros(1),
              solve_time=np.zeros(1), chance_margin=np.zeros(1), wall_time_s=0.0, method="nominal", seed=0)
    assert plan_tracking_rmse(Rollout(states, **kw)) == pytest.approx(np.sqrt((0.09 + 16.0) / 3))
    assert plan_tracking_rmse(Rollout(states, **kw, input_memory=[2])) == pytest.approx(np.sqrt(0.09 / 2))


def test_a_mixed_team_weighs_each_agent_by_its_own_model(tmp_path):
    path = tmp_path / "lag.json"
    path.write_text(json.dumps(lag_model()))
    cfg = Config(method="nominal", scenario="circle", num_agents=2, models=[str(path), "double-integrator"])
    steps = TeamStep(cfg, cfg.team()).groups
    assert torch.diagonal(steps[0].cost_weights[0][0]).tolist() == [1.0, 1.0, 1.0, 1.0, 0.0, 0.0]
    assert torch.diagonal(steps[1].cost_weights[0][0]).tolist() == [1.0] * 6
