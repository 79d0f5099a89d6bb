"""Closed loops with general linear models: the double integrator end to end, the distributed
backend on it, and the user's chain collect -> fit-gp -> run with a hand-written model file."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from torch_gpmpc.cli import main
from torch_gpmpc.config import load_config
from torch_gpmpc.sim.closed_loop import simulate
from torch_gpmpc.sim.distributed import simulate_distributed
from torch_gpmpc.sim.metrics import compute_metrics
from tests.helpers import lag_model

#: The Models page's hand-written model file.
HAND_WRITTEN = (Path(__file__).resolve().parents[2] / "examples" / "models" / "double_integrator_2d.toml").read_text()


def test_double_integrator_pair_swaps_places_safely():
    """Two 2D double integrators cross through the centre (noiseless, learned wind)."""
    cfg = load_config(None, {"model": "double-integrator", "scenario": "circle", "num_agents": 2,
                             "circle_radius": 1.5, "noise_std": 0.0, "max_steps": 60, "gp_iters": 20})
    rollout = simulate(cfg)
    metrics = compute_metrics(rollout)
    assert rollout.states.shape[1:] == (2, 4) and rollout.inputs.shape[1:] == (2, 2)
    assert rollout.plans.shape[2:] == (cfg.horizon + 1, 4)
    assert metrics["arrival_step_max"] is not None
    assert metrics["min_pair_distance"] >= cfg.r_safe - 0.01
    # the velocity states move: the agents are not single integrators in disguise
    assert np.abs(rollout.states[1:, :, 2:]).max() > 0.3


@pytest.mark.parametrize("model, n", [("double-integrator", 4), (lag_model(), 6)], ids=["double", "with-last-command"])
def test_distributed_double_integrator_equals_inprocess(model, n):
    cfg = load_config(None, {"model": model, "method": "gp-chance", "max_steps": 3,
                             "admm_max_iter": 5, "gp_iters": 5})
    rollout, report = simulate_distributed(cfg, agents_per_process=2, timeout_s=60)
    ref = simulate(cfg)
    assert not report.lost_agents
    assert rollout.states.shape == ref.states.shape == (4, 3, n)
    assert np.abs(rollout.states - ref.states).max() <= 1e-9
    assert rollout.input_memory == ref.input_memory == (None if n == 4 else [4, 5])


def _chain(tmp_path, samples: int, run_sets: list[str]) -> dict:
    model = tmp_path / "di.toml"
    model.write_text(HAND_WRITTEN)
    data, gp, out = tmp_path / "t.npz", tmp_path / "gp.pt", tmp_path / "run"
    assert main(["collect", "--model", str(model), "--out", str(data), "--samples", str(samples)]) == 0
    assert main(["fit-gp", "--model", str(model), "--transitions", str(data), "--out", str(gp), "--iters", "20"]) == 0
    sets = [f"model={model}", "noise_std=0", *run_sets]
    assert main(["run", "--gp-model", str(gp), "--out", str(out), *[a for s in sets for a in ("--set", s)]]) == 0
    with np.load(out / "rollout.npz") as r:
        assert r["states"].shape[1:] == (3, 4)
    return json.loads((out / "metrics.json").read_text())


def test_model_file_chain_short(tmp_path):
    metrics = _chain(tmp_path, 30, ["max_steps=4", "admm_max_iter=10"])
    assert metrics["steps"] == 4 and metrics["violations"] == 0


@pytest.mark.slow
def test_model_file_chain_arrives_keeping_r_safe(tmp_path):
    metrics = _chain(tmp_path, 100, [])
    assert metrics["reached"] and metrics["min_pair_distance"] >= 0.495


def test_tuning_objective_on_a_double_integrator_has_finite_gradients():
    from torch_gpmpc.coordination.controller import Controller
    from torch_gpmpc.dynamics.systems import system_from_config
    from torch_gpmpc.gp import fit_agent_gps
    from torch_gpmpc.tuning import TuningObjective, make_instances
    import torch

    cfg = load_config(None, {"model": "double-integrator", "gp_iters": 5})
    system = system_from_config(cfg)
    admm = Controller.for_run(cfg, system, fit_agent_gps(cfg, system, 3)).admm
    instances = make_instances(cfg, [0])
    assert instances[0].x0.shape == (3, 4) and instances[0].noise.shape[-1] == 2
    rho = torch.tensor(20.0, dtype=torch.float64, requires_grad=True)
    value = TuningObjective(admm, instances, admm_iters=3, mpc_steps=2, system=system)(rho=rho)
    value.loss.backward()
    assert torch.isfinite(value.loss) and torch.isfinite(rho.grad) and rho.grad != 0


BOX_AND_SPEED = """name = "box-bounded double integrator"
dt = 0.1
A = [[1, 0, 0, 0.1, 0, 0], [0, 1, 0, 0, 0.1, 0], [0, 0, 1, 0, 0, 0.1], [0, 0, 0, 1, 0, 0], [0, 0, 0, 0, 1, 0],
     [0, 0, 0, 0, 0, 1]]
B = [[0.005, 0, 0], [0, 0.005, 0], [0, 0, 0.005], [0.1, 0, 0], [0, 0.1, 0], [0, 0, 0.1]]
position = [0, 1, 2]
residual = [3, 4, 5]
gp_inputs = ["x0", "x1"]
[input_bound]
box = [1.5, 1.5, 1.0]
[state_box]
indices = [3, 4, 5]
lower = [-1.2, -1.2, -0.5]
upper = [1.2, 1.2, 0.5]
"""


@pytest.mark.parametrize("distributed", [False, True])
def test_an_acceleration_box_and_a_workspace_run_on_the_fast_solver(tmp_path, distributed):
    """The random-transition benchmark's constraints (per-axis acceleration box, a workspace box,
    here also per-axis speed limits) on ``solver=fast``, in process and one process per agent: four
    3D double integrators cross a flat workspace whose floor and ceiling bind on the straight paths."""
    model = tmp_path / "box.toml"
    model.write_text(BOX_AND_SPEED)
    scenario = tmp_path / "cross.json"
    scenario.write_text(json.dumps({
        "starts": [[-2, 0, 0.0], [2, 0, 0.0], [0, -2, 0.3], [0, 2, -0.3]],
        "targets": [[2, 0, 0.6], [-2, 0, -0.6], [0, 2, -0.3], [0, -2, 0.3]],
        "workspace": {"min": [-3, -3, -0.4], "max": [3, 3, 0.4]}}))
    out = tmp_path / "run"
    sets = {"admm_coupling": "copies", "model": str(model), "solver": "fast", "method": "nominal", "noise_std": 0.0, "wind_scale": 0.0,
            "max_steps": 25 if distributed else 60, "admm_max_iter": 40}
    args = ["run", "--scenario", str(scenario), "--out", str(out), *[a for k, v in sets.items() for a in
                                                                      ("--set", f"{k}={v}")]]
    if distributed:  # two agents per process: half the process start-ups
        args += ["--backend", "distributed", "--agents-per-process", "2"]
    assert main(args) == 0
    metrics = json.loads((out / "metrics.json").read_text())
    with np.load(out / "rollout.npz") as r:
        states, inputs = r["states"], r["inputs"]
    assert metrics["failed_local_solves"] == 0
    assert np.abs(inputs).max(axis=(0, 1)) == pytest.approx([1.5, 1.5, 1.0], abs=1e-6) or \
        (np.abs(inputs) <= np.array([1.5, 1.5, 1.0]) + 1e-9).all()
    assert (np.abs(states[..., 2]) <= 0.4 + 1e-3).all()  # the workspace's floor and ceiling hold
    assert (np.abs(states[..., 3:5]) <= 1.2 + 1e-3).all() and (np.abs(states[..., 5]) <= 0.5 + 1e-3).all()
    assert metrics["state_slack_max"] is not None and metrics["state_slack_max"] < 1e-3
    # kept up to ADMM's consensus tolerance (admm_tol 1e-3 + admm_rel_tol 1e-4 x the plans' size ~4)
    assert metrics["min_pair_distance"] >= 0.5 - 1.5e-3
    if not distributed:  # across in the plane; agents 0 and 1 end on the ceiling and the floor
        assert np.abs(states[-1, :, :2] - np.array([[2, 0], [-2, 0], [0, 2], [0, -2]])).max() < 0.1
        assert states[-1, 0, 2] == pytest.approx(0.4, abs=0.02) and states[-1, 1, 2] == pytest.approx(-0.4, abs=0.02)
