"""torch_gpmpc: cooperative Gaussian-process MPC for safe multi-agent navigation.

Public API: ``Transitions``, ``ResidualGP``, ``fit_residual_gp``,
``LocalMPC``, ``ADMM``, ``simulate``, ``Rollout``, ``compute_metrics``, ``Config``.
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
    "LocalMPC": "control.solvers.conic",
    "ADMM": "coordination.admm",
    "simulate": "sim.closed_loop",
    "Rollout": "sim.rollout",
    "compute_metrics": "sim.metrics",
    "NominalModel": "dynamics.systems",
    "VortexWind": "dynamics.systems",
    "TrueSystem": "dynamics.systems",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str) -> Any:
    if name in _EXPORTS:
        module = importlib.import_module(f".{_EXPORTS[name]}", __name__)
        return getattr(module, name)
    raise AttributeError(f"module 'torch_gpmpc' has no attribute {name!r}")
