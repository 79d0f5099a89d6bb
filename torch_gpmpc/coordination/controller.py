"""The one place a controller is built from a configuration."""

from __future__ import annotations

from torch_gpmpc.config.schema import Config
from torch_gpmpc.coordination.admm import ADMM
from torch_gpmpc.dynamics.methods import Method
from torch_gpmpc.dynamics.systems import TrueSystem


def make_controller(cfg: Config, system: TrueSystem, gps: list | None = None,
                    method: str | Method | None = None) -> ADMM:
    """The consensus-ADMM controller of ``method`` (default ``cfg.method``).

    The method decides what the agents know: the ``nonlinear`` baselines get the true
    wind of ``system``, the ``gp`` and chance methods their residual GPs; the nominal
    model is ``system``'s.

    Args:
        cfg: run configuration.
        system: the true system (its nominal model and, for ``nonlinear``, its wind).
        gps: residual GPs indexed by agent id (ignored by methods that need none).
        method: overrides ``cfg.method``.
    """
    method = Method.parse(method or cfg.method)
    wind = system.wind if method.needs_wind else None
    return ADMM(cfg, method, system.nominal, wind, gps if method.needs_gp else None)
