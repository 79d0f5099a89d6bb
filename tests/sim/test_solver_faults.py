"""Solver faults at one ADMM iteration: a local solver that raises (every agent of that batched
solve fails), or returns NaN or an inaccurate answer for one agent. The failed agents fall back
to their previous plans and the run finishes, for the single integrator and for models whose
input size differs from their state size (the double integrator, the Crazyflie model file), in
process and distributed (one process per agent).

What is checked: the run finishes with finite states and inputs of the model's sizes, and the
metrics count exactly the injected failures, by kind.
"""

from __future__ import annotations

import importlib.util
import json
import logging
import os
import textwrap
from pathlib import Path

import numpy as np
import pytest

from torch_gpmpc.cli import main
from torch_gpmpc.config import Config
from torch_gpmpc.sim.closed_loop import simulate
from torch_gpmpc.sim.metrics import compute_metrics

ROOT = Path(__file__).resolve().parents[2]
CRAZYFLIE = str(ROOT / "examples" / "crazyflie" / "model.toml")

#: model -> config keys of a short crossing
MODELS = {
    "single-integrator": {},
    "double-integrator": {"model": "double-integrator", "scenario": "circle", "num_agents": 3},
    "crazyflie": {"model": CRAZYFLIE, "scenario": "circle", "num_agents": 3, "circle_radius": 1.0,
                  "wind_scale": 0.0},
}
SHORT = {"method": "nominal", "max_steps": 4, "admm_max_iter": 6, "horizon": 6, "noise_std": 0.0}

#: the solver call (counted per process, 1-based) that fails
FAILING_CALL = 3

#: fault -> the failure kind the metrics count it under
KINDS = {"exception": "exception", "nan": "non-finite", "inaccurate": "inaccurate"}

# written to a file so that the agent processes import the same injector
FAULTS = '''
import dataclasses

import torch

from torch_gpmpc.control.problem import FAIL_INACCURATE, FAIL_NONFINITE


def faulty_solver(real, fault, fail_call):
    """The real local solver, except at call ``fail_call`` (counted per process): it raises
    (``exception``), or returns row 0 as NaN (``nan``) or moved off the dynamics
    (``inaccurate``), flagged as the solvers' acceptance rule flags such answers."""
    calls = [0]

    def call(data):
        calls[0] += 1
        if calls[0] != fail_call:
            return real(data)
        if fault == "exception":
            raise RuntimeError("injected solver exception")
        sol = real(data)
        X, ok = sol.X.clone(), sol.ok.clone()
        failure = torch.zeros(ok.shape, dtype=torch.int64)
        X[0] = float("nan") if fault == "nan" else X[0] + 1.0
        ok[0] = False
        failure[0] = FAIL_NONFINITE if fault == "nan" else FAIL_INACCURATE
        return dataclasses.replace(sol, X=X, ok=ok, failure=failure)
    return call


def install(fault, fail_call):
    """Every per-agent step built from now on gets faulty solvers, and no rescue of inaccurate rows
    by the reference path (as when that fails too), so the failure reaches the fallback."""
    import torch_gpmpc.coordination.agent_step as agent_step

    real_factory = agent_step.make_local_solver
    agent_step.make_local_solver = lambda *a, **k: faulty_solver(real_factory(*a, **k), fault, fail_call)
    agent_step.LocalStep.rescue_inaccurate = lambda self, data, sol: sol
'''

SITECUSTOMIZE = '''
# test-only: every agent process of this run gets local solvers with one fault
import os

import gpmpc_test_faults

gpmpc_test_faults.install(os.environ["GPMPC_TEST_FAULT"], int(os.environ["GPMPC_TEST_FAILING_CALL"]))
'''


def load_faults(directory: Path):
    """Write the fault module (shared by this process and the agent processes) and import it."""
    path = directory / "gpmpc_test_faults.py"
    path.write_text(FAULTS)
    spec = importlib.util.spec_from_file_location("gpmpc_test_faults", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


#: ADMM variants the fault tests run: copies, plane coupling (the default)
ADMM_VARIANTS = {"copies": {"admm_coupling": "copies"}, "planes": {}}


@pytest.mark.parametrize("coupling", list(ADMM_VARIANTS))
@pytest.mark.parametrize("fault", list(KINDS))
@pytest.mark.parametrize("model", list(MODELS))
def test_solver_fault_falls_back_and_the_run_finishes_in_process(model, fault, coupling, tmp_path, monkeypatch,
                                                                  caplog):
    """(With the copies the failed agent's previous plan enters the consensus; with plane coupling
    the failed agent's ends report no multiplier and its edges grade the iterate unsafe, so the step
    applies an earlier safe one.)"""
    import torch_gpmpc.coordination.agent_step as agent_step

    cfg = Config(**{**SHORT, **MODELS[model]}, **ADMM_VARIANTS[coupling])
    monkeypatch.setattr(agent_step, "make_local_solver", agent_step.make_local_solver)  # restored afterwards
    monkeypatch.setattr(agent_step.LocalStep, "rescue_inaccurate", agent_step.LocalStep.rescue_inaccurate)
    load_faults(tmp_path).install(fault, FAILING_CALL)
    with caplog.at_level(logging.WARNING):
        rollout = simulate(cfg)
    m = compute_metrics(rollout)
    # a raising batched call fails every agent of the batch; NaN and inaccurate fail row 0
    n = cfg.num_agents if fault == "exception" else 1
    assert rollout.num_steps == cfg.max_steps
    assert m["failed_local_solves_by_kind"] == {k: (n if k == KINDS[fault] else 0) for k in KINDS.values()}
    assert m["failed_local_solves"] == n
    assert np.isfinite(rollout.states).all() and np.isfinite(rollout.inputs).all()
    assert rollout.states.shape[-1] == cfg.state_dim and rollout.inputs.shape[-1] == cfg.input_dim
    assert f"local MPC solve failed ({KINDS[fault]}" in caplog.text


@pytest.mark.parametrize("fault", list(KINDS))
def test_solver_fault_in_a_mixed_team_fails_only_that_models_agents(fault, tmp_path, monkeypatch):
    """Drones and a ground robot: one solver per model, each failing at its own third call; a raise
    fails every agent of that model's batch, NaN and inaccurate its row 0; the run finishes."""
    import torch_gpmpc.coordination.agent_step as agent_step

    cfg = Config(**{**SHORT, "scenario": "circle", "num_agents": 3,
                    "models": ["double-integrator", "single-integrator", "double-integrator"]})
    monkeypatch.setattr(agent_step, "make_local_solver", agent_step.make_local_solver)  # restored afterwards
    monkeypatch.setattr(agent_step.LocalStep, "rescue_inaccurate", agent_step.LocalStep.rescue_inaccurate)
    load_faults(tmp_path).install(fault, FAILING_CALL)
    rollout = simulate(cfg)
    m = compute_metrics(rollout)
    n = 3 if fault == "exception" else 2  # 2 drones + 1 robot; row 0 of each of the 2 batches
    assert rollout.num_steps == cfg.max_steps
    assert m["failed_local_solves_by_kind"] == {k: (n if k == KINDS[fault] else 0) for k in KINDS.values()}
    assert np.isfinite(rollout.states).all() and np.isfinite(rollout.inputs).all()
    assert rollout.states.shape[-1] == 4 and float(abs(rollout.states[:, 1, 2:]).max()) == 0.0


@pytest.mark.parametrize("model, fault, coupling", [
    ("double-integrator", "exception", "copies"), ("crazyflie", "exception", "copies"),
    ("single-integrator", "nan", "copies"), ("crazyflie", "inaccurate", "copies"), ("crazyflie", "nan", "planes"),
    ("crazyflie", "exception", "planes"), ("single-integrator", "nan", "planes")])
def test_solver_fault_falls_back_and_the_run_finishes_distributed(model, fault, coupling, tmp_path, monkeypatch):
    """Each agent process's own solver fails at its third call: each agent falls back once (with the
    copies and with plane coupling, where the fallen-back agent's ends report no multiplier and grade
    the iterate unsafe)."""
    hook = tmp_path / "hook"
    hook.mkdir()
    load_faults(hook)
    (hook / "sitecustomize.py").write_text(textwrap.dedent(SITECUSTOMIZE))
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join([str(hook), str(ROOT), os.environ.get("PYTHONPATH", "")]))
    monkeypatch.setenv("GPMPC_TEST_FAULT", fault)
    monkeypatch.setenv("GPMPC_TEST_FAILING_CALL", str(FAILING_CALL))
    out = tmp_path / "dist"
    args = ["run", "--backend", "distributed", "--timeout", "120", "--no-figures", "--out", str(out)]
    keys = {**SHORT, **MODELS[model], **ADMM_VARIANTS[coupling]}
    for key, value in keys.items():
        args += ["--set", f"{key}={value}"]
    assert main(args) == 0
    m = json.loads((out / "metrics.json").read_text())
    cfg = Config(**keys)
    assert m["steps"] == cfg.max_steps
    # an agent process solves its own row (batch 1): each agent fails once, whatever the fault
    assert m["failed_local_solves_by_kind"][KINDS[fault]] == cfg.num_agents
    assert m["failed_local_solves"] == cfg.num_agents
    states = np.load(out / "rollout.npz")["states"]
    assert np.isfinite(states).all() and states.shape[-1] == cfg.state_dim
