"""torch_gpmpc: cooperative Gaussian-process MPC for safe multi-agent navigation.

Public API (design.md §2): ``Transitions``, ``ResidualGP``, ``fit_residual_gp``,
``LocalMPC``, ``ADMM``, ``simulate``, ``Rollout``, ``compute_metrics``, ``Config``.
Imports are lazy so that ``gpmpc --help`` and light modules stay fast.
"""

from __future__ import annotations

import importlib
from typing import Any

import torch

__version__ = "0.1.0"

# float64 by default: the MPC data, GP solves and finite-difference checks need it.
torch.set_default_dtype(torch.float64)

_EXPORTS = {
    "Config": "config",
    "load_config": "config",
    "GpmpcError": "errors",
    "Transitions": "data",
    "ResidualGP": "gp",
    "fit_residual_gp": "gp",
    "LocalMPC": "mpc",
    "ADMM": "admm",
    "simulate": "sim",
    "Rollout": "rollout",
    "compute_metrics": "metrics",
    "NominalModel": "systems",
    "VortexWind": "systems",
    "TrueSystem": "systems",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str) -> Any:
    if name in _EXPORTS:
        module = importlib.import_module(f".{_EXPORTS[name]}", __name__)
        return getattr(module, name)
    raise AttributeError(f"module 'torch_gpmpc' has no attribute {name!r}")
