"""A local solver that raises at one ADMM iteration: every agent of that solve falls back to its
previous plan and the run finishes, for models whose input size differs from their state size
too (the double integrator, the Crazyflie model file), in process and distributed.

Independent answer: the same run without the exception (its plans after the failed iteration
are the previous iterate's, so the run may differ, but it must finish with finite states and
count exactly the failed solves).
"""

from __future__ import annotations

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

#: model -> config keys of a short crossing (the Crazyflie model has no vortex wind rows of its own scale)
MODELS = {
    "single-integrator": {},
    "double-integrator": {"model": "double-integrator", "scenario": "circle", "num_agents": 3},
    "crazyflie": {"model": CRAZYFLIE, "scenario": "circle", "num_agents": 3, "circle_radius": 1.0,
                  "wind_scale": 0.0},
}
SHORT = {"method": "nominal", "max_steps": 4, "admm_max_iter": 6, "horizon": 6, "noise_std": 0.0}

#: the solver call (counted per process, 1-based) that raises
FAILING_CALL = 3


class RaisingSolver:
    """Calls the real solver, except call number ``fail`` (counted across all instances), which raises."""

    calls = 0

    def __init__(self, real, fail: int):
        self.real, self.fail = real, fail

    def __call__(self, data):
        RaisingSolver.calls += 1
        if RaisingSolver.calls == self.fail:
            raise RuntimeError("injected solver exception")
        return self.real(data)


def raise_at(monkeypatch, fail: int) -> None:
    """Make the per-agent step's solvers raise at solver call ``fail``."""
    import torch_gpmpc.coordination.agent_step as agent_step

    real = agent_step.make_local_solver
    RaisingSolver.calls = 0
    monkeypatch.setattr(agent_step, "make_local_solver", lambda *a, **k: RaisingSolver(real(*a, **k), fail))


@pytest.mark.parametrize("model", list(MODELS))
def test_solver_exception_falls_back_and_the_run_finishes_in_process(model, monkeypatch, caplog):
    cfg = Config(**{**SHORT, **MODELS[model]})
    raise_at(monkeypatch, FAILING_CALL)
    with caplog.at_level(logging.WARNING):
        rollout = simulate(cfg)
    m = compute_metrics(rollout)
    assert rollout.num_steps == cfg.max_steps
    assert m["failed_local_solves_by_kind"]["exception"] == cfg.num_agents  # one batched call, every agent
    assert m["failed_local_solves"] == cfg.num_agents
    assert np.isfinite(rollout.states).all() and np.isfinite(rollout.inputs).all()
    assert rollout.states.shape[-1] == cfg.state_dim and rollout.inputs.shape[-1] == cfg.input_dim
    assert "injected solver exception" in caplog.text


SITECUSTOMIZE = """
# test-only: every agent process of this run gets a local solver that raises at one call
import os
import torch_gpmpc.coordination.agent_step as agent_step

_real = agent_step.make_local_solver
_fail = int(os.environ["GPMPC_TEST_FAILING_CALL"])
_calls = [0]


def _raising(*args, **kwargs):
    real = _real(*args, **kwargs)

    def call(data):
        _calls[0] += 1
        if _calls[0] == _fail:
            raise RuntimeError("injected solver exception")
        return real(data)
    return call


agent_step.make_local_solver = _raising
"""


@pytest.mark.parametrize("model", ["double-integrator", "crazyflie"])
def test_solver_exception_falls_back_and_the_run_finishes_distributed(model, tmp_path, monkeypatch):
    """Each agent process's own solver raises at its third call: every agent falls back once."""
    hook = tmp_path / "hook"
    hook.mkdir()
    (hook / "sitecustomize.py").write_text(textwrap.dedent(SITECUSTOMIZE))
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join([str(hook), str(ROOT), os.environ.get("PYTHONPATH", "")]))
    monkeypatch.setenv("GPMPC_TEST_FAILING_CALL", str(FAILING_CALL))
    out = tmp_path / "dist"
    args = ["run", "--backend", "distributed", "--timeout", "120", "--no-figures", "--out", str(out)]
    for key, value in {**SHORT, **MODELS[model]}.items():
        args += ["--set", f"{key}={value}"]
    assert main(args) == 0
    m = json.loads((out / "metrics.json").read_text())
    cfg = Config(**{**SHORT, **MODELS[model]})
    assert m["steps"] == cfg.max_steps
    assert m["failed_local_solves_by_kind"]["exception"] == cfg.num_agents  # once in each agent process
    states = np.load(out / "rollout.npz")["states"]
    assert np.isfinite(states).all() and states.shape[-1] == cfg.state_dim
