"""torch_gpmpc: cooperative Gaussian-process MPC for safe multi-agent navigation.

Public API. Build a controller from tensors: ``ModelSpec`` (the agent model),
``ResidualGP`` (``fit_residual_gp``, ``ResidualGP.from_gpytorch`` for your own GPyTorch models;
the ``ResidualModel`` protocol; ``OffsetCorrected`` for offset-free tracking),
``ControllerSettings``, ``Controller`` (``step``). Its parts:
``LocalStep`` (the per-agent step), ``ADMM`` (``prepare``/``iterate``/``solve_step``),
``make_local_solver`` with the ``LocalProblemData`` -> ``LocalSolution`` contract and the
backends ``InteriorPointMPC`` (default, compiled), ``CvxpyLayerMPC`` (reference; ``LocalMPC`` is
its name in the design's API contract) and ``DirectClarabelMPC``, the problem's cost ``QuadraticCost``. Runs: ``Config``,
``simulate``, ``Rollout``, ``compute_metrics``; data: ``Transitions``.
Imports are lazy so that ``gpmpc --help`` and light modules stay fast. Importing the
package changes no global state: every tensor the package creates is float64 explicitly.
"""

from __future__ import annotations

import importlib
from typing import Any

__version__ = "0.1.0"

_EXPORTS = {
    "Config": "config.schema",
    "load_config": "config.load",
    "GpmpcError": "errors",
    "Transitions": "data.transitions",
    "ResidualGP": "gp.model",
    "fit_residual_gp": "gp.fit",
    "CvxpyLayerMPC": "control.solvers.conic",
    "InteriorPointMPC": "control.solvers.interior_point",
    "DirectClarabelMPC": "control.solvers.direct_clarabel",
    "make_local_solver": "control.solvers",
    "LocalProblemData": "control.problem",
    "LocalSolution": "control.problem",
    "QuadraticCost": "control.cost",
    "ADMM": "coordination.admm",
    "ADMMState": "coordination.state",
    "StepResult": "coordination.state",
    "LocalStep": "coordination.agent_step",
    "Controller": "coordination.controller",
    "ControllerSettings": "config.settings",
    "ModelSpec": "config.model_spec",
    "ResidualModel": "gp.protocol",
    "GPyTorchResidual": "gp.gpytorch_models",
    "OffsetCorrected": "gp.offset",
    "simulate": "sim.closed_loop",
    "Rollout": "sim.rollout",
    "compute_metrics": "sim.metrics",
    "NominalModel": "dynamics.systems",
    "VortexWind": "dynamics.systems",
    "TrueSystem": "dynamics.systems",
}

#: Names of the design's API contract that name an export above.
_CONTRACT_NAMES = {"LocalMPC": "CvxpyLayerMPC"}

__all__ = sorted([*_EXPORTS, *_CONTRACT_NAMES])


def __getattr__(name: str) -> Any:
    name = _CONTRACT_NAMES.get(name, name)
    if name in _EXPORTS:
        module = importlib.import_module(f".{_EXPORTS[name]}", __name__)
        return getattr(module, name)
    raise AttributeError(f"module 'torch_gpmpc' has no attribute {name!r}")
