"""What the closed loop steps: the :class:`Plant` protocol, and today's true system as one plant.

A plant holds the true state of every vehicle. Each control step the closed loop hands it the
states the planner used and the first planned input of every agent; the plant advances one
sampling time ``dt`` and returns the states the planner sees next (a measurement of the planning
state). Collisions and metrics are judged on :attr:`Plant.true_states`.

- :class:`ModelPlant`: the model's own true system ``x' = A x + B u + g(p) + w`` (the paper's world);
  what it returns is exact.
- :class:`~torch_gpmpc.dynamics.rotorpy_plant.RotorPyPlant`: simulated multirotors (RotorPy) that
  track each step's plan with a geometric controller at a high rate.

Shapes: K vehicles, D planning states, Du inputs, P positions, R residual rows.
"""

from __future__ import annotations

import dataclasses
from typing import Protocol, runtime_checkable

from torch import Tensor

from torch_gpmpc.dynamics.systems import NominalModel, TrueSystem


@runtime_checkable
class Plant(Protocol):
    """A team of K vehicles stepped one sampling time at a time.

    Attributes:
        nominal: the planning model (its ``dt`` is the plant's step).
        true_states: the vehicles' true planning states now, (K, D).

    Examples:
        >>> import torch
        >>> from torch_gpmpc.dynamics.plants import ModelPlant, Plant
        >>> from torch_gpmpc.dynamics.systems import make_system
        >>> plant = ModelPlant(make_system(2, noise_std=0.0, wind_scale=0.0))
        >>> x = plant.reset(torch.zeros(1, 2, dtype=torch.float64))
        >>> plant.step(0, x, torch.ones(1, 2, dtype=torch.float64)).tolist(), isinstance(plant, Plant)
        ([[0.1, 0.1]], True)
    """

    nominal: NominalModel

    @property
    def true_states(self) -> Tensor: ...

    def reset(self, starts: Tensor) -> Tensor:
        """Place the vehicles at rest at ``starts`` (K, P); returns the first measured states (K, D)."""
        ...

    def step(self, t: int, x: Tensor, u: Tensor, noise: Tensor | None = None) -> Tensor:
        """Fly control step ``t``: apply inputs ``u`` (K, Du) planned from the measured states ``x`` (K, D)
        for one ``dt``. ``noise`` (K, R) are the run's standard-normal process-noise draws of this step
        (a plant with its own physics may ignore them). Returns the next measured states (K, D); rows
        that hold the last input (:attr:`~torch_gpmpc.config.model_spec.ModelSpec.input_memory`) must
        be ``u``."""
        ...


class ModelPlant:
    """The model's true system as a plant: exact states, process noise on the residual rows.

    Args:
        system: the :class:`~torch_gpmpc.dynamics.systems.TrueSystem` (nominal model, vortex wind,
            noise level).
        wind_change_step: from this control step on, the wind is turned 90 degrees about the
            vertical axis (``(g_1, g_2, g_3) -> (-g_2, g_1, g_3)``; ``None``: never).
    """

    def __init__(self, system: TrueSystem, wind_change_step: int | None = None) -> None:
        self.system = system
        self.turned = dataclasses.replace(system, turned=True)
        self.wind_change_step = wind_change_step
        self.nominal = system.nominal
        #: (K, D), what :meth:`reset` or :meth:`step` returned last (``None`` before :meth:`reset`)
        self.true_states: Tensor | None = None

    def reset(self, starts: Tensor) -> Tensor:
        """States at rest at ``starts`` (K, P) -> (K, D)."""
        self.true_states = self.nominal.states_at(starts)
        return self.true_states

    def step(self, t: int, x: Tensor, u: Tensor, noise: Tensor | None = None) -> Tensor:
        """``x' = A x + B u + g(p) + s w`` from the true states (the measured ones are the same)."""
        changed = self.wind_change_step is not None and t >= self.wind_change_step
        self.true_states = (self.turned if changed else self.system).step(self.true_states, u, noise=noise)
        return self.true_states


def plant_from_config(cfg, system: TrueSystem) -> Plant:
    """The plant of a run: ``plant = model`` steps ``system``; ``plant = rotorpy`` flies RotorPy
    vehicles (:class:`~torch_gpmpc.dynamics.rotorpy_plant.RotorPyPlant`) under ``system``'s planning model."""
    if cfg.plant == "model":
        return ModelPlant(system, cfg.wind_change_step)
    from torch_gpmpc.dynamics.rotorpy_plant import PlantSettings, RotorPyPlant

    return RotorPyPlant(system.nominal, PlantSettings.from_config(cfg))
