"""A mixed team's dynamics: each agent steps, projects and references with its own (lifted) model.

:class:`TeamNominal` and :class:`TeamSystem` stand where a
:class:`~torch_gpmpc.dynamics.systems.NominalModel` and a
:class:`~torch_gpmpc.dynamics.systems.TrueSystem` stand for a team of one model, for tensors whose
leading dimension is the team's K agents (in agent order). The models are lifted to common sizes
(:mod:`~torch_gpmpc.config.team`), so every agent's state has n and its input m entries.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from typing import Callable

import torch
from torch import Tensor

from torch_gpmpc.config.team import TeamSpec
from torch_gpmpc.dynamics.systems import (
    NominalModel, SpecSizes, TrueSystem, VortexWind, make_system, system_from_config,
)
from torch_gpmpc.errors import GpmpcError


def by_group(members: list[Tensor], parts: list[Tensor]) -> Tensor:
    """Rows of each group (``parts[g]``, leading dimension ``len(members[g])``) put back in agent
    order: the (K, ...) tensor whose row ``members[g][i]`` is ``parts[g][i]``."""
    out = parts[0].new_empty((sum(len(m) for m in members), *parts[0].shape[1:]))
    for rows, part in zip(members, parts):
        out[rows] = part
    return out


class TeamNominal(SpecSizes):
    """The known models of a mixed team, one per agent (lifted to common sizes).

    Args:
        team: the team's models (:class:`~torch_gpmpc.config.team.TeamSpec`).

    Attributes:
        models: one :class:`NominalModel` per distinct (lifted) model.
        members: the agents of each model, int64 tensors.

    Examples:
        >>> import torch
        >>> from torch_gpmpc import ModelSpec
        >>> from torch_gpmpc.config.team import team_spec
        >>> f = TeamNominal(team_spec([ModelSpec.double_integrator(2), ModelSpec.single_integrator(2)]))
        >>> x = torch.tensor([[0.0, 0, 1, 0], [0.0, 0, 0, 0]], dtype=torch.float64)
        >>> f(x, torch.ones(2, 2, dtype=torch.float64)).round(decimals=4).tolist()  # drone, then robot: p + 0.1 u
        [[0.105, 0.005, 1.1, 0.1], [0.1, 0.1, 0.0, 0.0]]
    """

    def __init__(self, team: TeamSpec) -> None:
        self.team = team
        self.models = [NominalModel(spec) for spec in team.models]
        self.members = [torch.tensor(team.members(g), dtype=torch.long) for g in range(len(team.models))]
        #: agent 0's lifted model: the team's sizes n, m and the position (common to all) are its
        self.spec = team.agent_spec(0)

    def __repr__(self) -> str:
        return f"TeamNominal({[m.spec.name for m in self.models]}, n={self.dim}, m={self.input_dim})"

    @property
    def input_memory_rows(self) -> list[int]:
        """State rows that hold the last applied input in every model of the team."""
        common = set.intersection(*(set(m.input_memory_rows) for m in self.models))
        return sorted(common)

    def agent_model(self, k: int) -> NominalModel:
        """Agent k's (lifted) model."""
        return self.models[self.team.group_of[k]]

    def per_group(self, fn: Callable[..., Tensor], *rows: Tensor) -> Tensor:
        """``fn(model, *group_rows)`` for every model on its agents' rows of ``rows`` (each (K, ...)),
        put back in agent order."""
        return by_group(self.members, [fn(model, *(r[idx] for r in rows))
                                       for model, idx in zip(self.models, self.members)])

    def states_at(self, positions: Tensor) -> Tensor:
        """States at rest at ``positions`` (K, P) -> (K, n) (every other state 0, for every model)."""
        return self.models[0].states_at(positions)

    def momentum(self, num_agents: int) -> Tensor:
        """(K,) bool: whether each agent's model has momentum (``num_agents`` must be K)."""
        return torch.tensor([bool(self.agent_model(k).rate_states()) for k in range(num_agents)], dtype=torch.bool)

    def reference_states(self, path: Tensor) -> Tensor:
        """Each agent's state references from its position references: (K, S, P) -> (K, S, n)."""
        return self.per_group(NominalModel.reference_states, path)

    def project(self, u: Tensor) -> Tensor:
        """Each agent's inputs (K, m) projected onto its own model's bounds."""
        return self.per_group(NominalModel.project, u)

    def gp_targets(self, x: Tensor, u: Tensor, x_next: Tensor) -> tuple[list[Tensor], Tensor]:
        """Each agent's GP input (a list of K (1, Din_k) tensors) and residual ``[x' - A x - B u]_R``
        (K, R) of one transition: x, x_next (K, n), u (K, m)."""
        inputs, targets = [], []
        for k in range(x.shape[0]):
            model = self.agent_model(k)
            inp, y = model.gp_targets(x[k:k + 1], u[k:k + 1], x_next[k:k + 1])
            inputs.append(inp)
            targets.append(y[0])
        return inputs, torch.stack(targets)

    def __call__(self, x: Tensor, u: Tensor) -> Tensor:
        """Each agent's nominal next state: x (K, n), u (K, m) -> (K, n)."""
        return self.per_group(NominalModel.__call__, x, u)


@dataclass(frozen=True)
class TeamSystem:
    """The true system of a mixed team: each agent's model's :class:`TrueSystem` (same wind and noise).

    Attributes:
        team: the team's models. wind: the vortex wind. noise_std: the process noise level.
        turned: the wind turned 90 degrees (as :attr:`TrueSystem.turned`).
    """

    team: TeamSpec
    wind: VortexWind
    noise_std: float = 0.1
    turned: bool = False

    @cached_property
    def nominal(self) -> TeamNominal:
        """The team's known models."""
        return TeamNominal(self.team)

    @cached_property
    def systems(self) -> list[TrueSystem]:
        """One :class:`TrueSystem` per distinct model (in ``team.models`` order)."""
        return [TrueSystem(model, self.wind, self.noise_std, self.turned) for model in self.nominal.models]

    def step(self, x: Tensor, u: Tensor, noise: Tensor | None = None,
             generator: torch.Generator | None = None) -> Tensor:
        """One step of every agent: x (K, n), u (K, m), noise (K, R) standard normal (drawn from
        ``generator`` when ``None``) -> (K, n)."""
        if noise is None:
            noise = torch.randn((x.shape[0], len(self.team.models[0].residual)), generator=generator,
                                dtype=x.dtype, device=x.device)
        members = self.nominal.members
        return by_group(members, [system.step(x[idx], u[idx], noise=noise[idx])
                                  for system, idx in zip(self.systems, members)])


def team_system_from_config(cfg) -> TrueSystem | TeamSystem:
    """The true system of a run: a :class:`TeamSystem` for a mixed team (``models``), else
    :func:`~torch_gpmpc.dynamics.systems.system_from_config`.

    Raises:
        GpmpcError: a mixed team on a plant other than ``model``, or a model the wind cannot act on.
    """
    team = cfg.team()
    if team is None or not team.is_mixed:
        return system_from_config(cfg)
    if cfg.plant != "model":
        raise GpmpcError("config key 'models': a mixed team flies on plant=model only (RotorPy vehicles are "
                         "one model); set plant=model or give every agent the same model")
    for spec in team.models:  # each model's wind check
        make_system(spec, cfg.noise_std, cfg.wind_scale)
    return TeamSystem(team, VortexWind(scale=cfg.wind_scale), noise_std=cfg.noise_std)
