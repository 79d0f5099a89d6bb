"""The per-agent step of a mixed team: one :class:`~.agent_step.LocalStep` per model, one batch.

Each model's agents assemble and solve their local problems with their own step (dynamics, input
bound, state constraints, GP, uncertainty model, compiled solver); the problems and solutions are
put back in agent order, so the consensus ADMM, the safety check and the recorder see one team of
K agents of the common (lifted) state size (:mod:`~torch_gpmpc.config.team`). Messages between
agents carry the lifted state: ``2 (T+1) n`` numbers with n the largest model's state size.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import torch
from torch import Tensor

from torch_gpmpc.config.schema import Config
from torch_gpmpc.config.settings import ControllerSettings
from torch_gpmpc.config.team import TeamSpec
from torch_gpmpc.control.problem import (
    SHARED_SCALARS, LocalProblemData, LocalSolution, select_problems, select_solution,
)
from torch_gpmpc.coordination.agent_step import Assembled, LocalStep, as_settings, call_layer
from torch_gpmpc.coordination.graph import Graph
from torch_gpmpc.coordination.state import ADMMState, IterationStats, StepResult
from torch_gpmpc.dynamics.methods import Method
from torch_gpmpc.dynamics.systems import NominalModel, VortexWind
from torch_gpmpc.dynamics.team import TeamNominal, by_group
from torch_gpmpc.errors import GpmpcError

def merge_problems(parts: list[LocalProblemData], members: list[Tensor], models: list[NominalModel]) -> LocalProblemData:
    """One batch in agent order from each model's problems (``parts[g]`` holds agents ``members[g]``);
    a part without ``dyn_B`` gets its model's B (``models[g]``, (n, m)) at every step when another
    part has one."""
    if any(p.dyn_B is not None for p in parts):
        parts = [p if p.dyn_B is not None else dataclasses.replace(
            p, dyn_B=model.B(p.dyn_A.dtype, p.dyn_A.device).expand(*p.dyn_A.shape[:2], -1, -1))
            for p, model in zip(parts, models)]
    merged = {}
    for f in dataclasses.fields(LocalProblemData):
        values = [getattr(p, f.name) for p in parts]
        if all(v is None for v in values):
            merged[f.name] = None
        elif f.name in SHARED_SCALARS and values[0].dim() == 0:
            merged[f.name] = values[0]
        else:
            merged[f.name] = by_group(members, values)
    return LocalProblemData(**merged)


def merge_solutions(parts: list[LocalSolution], members: list[Tensor]) -> LocalSolution:
    """One :class:`LocalSolution` in agent order from each model's (``parts[g]``: agents ``members[g]``)."""
    def merged(name: str) -> Tensor | None:
        values = [getattr(p, name) for p in parts]
        return None if any(v is None for v in values) else by_group(members, values)

    detail = next((p.failure_detail for p in parts if p.failure_detail), None)
    return LocalSolution(X=merged("X"), U=merged("U"), Y=merged("Y"), slack=merged("slack"),
                         slack_active=merged("slack_active"), ok=merged("ok"), cost=merged("cost"),
                         failure=merged("failure"), failure_detail=detail, state_slack=merged("state_slack"),
                         multipliers=merged("multipliers"))


class TeamLayer:
    """The batched local solvers of a mixed team: model g's layer solves agents ``members[g]``."""

    #: takes a ``guess`` (one per model) as the fast solver does (:func:`~.agent_step.call_layer`)
    accepts_guess = True

    def __init__(self, layers: list, members: list[Tensor]) -> None:
        self.layers, self.members = layers, members

    def __call__(self, data: LocalProblemData, guess: tuple | None = None) -> LocalSolution:
        """Solve every agent's problem with its model's solver; data and solution in agent order
        (``guess``: the last solution's ``solver_point``, one per model, or ``None``)."""
        guesses = guess or (None,) * len(self.layers)
        parts = [call_layer(layer, select_problems(data, rows), g) for layer, rows, g in zip(self.layers, self.members, guesses)]
        return dataclasses.replace(merge_solutions(parts, self.members),
                                   solver_point=tuple(p.solver_point for p in parts))


class TeamStep:
    """What each agent of a mixed team does at one ADMM iteration (the
    :class:`~.agent_step.LocalStep` interface the in-process ADMM uses), for all K agents.

    Args:
        settings: the controller settings (a run configuration is converted).
        team: the team's models, lifted (:class:`~torch_gpmpc.config.team.TeamSpec`).
        method: the controller method (default the settings').
        wind: the known wind (``nonlinear`` methods), else ``None``.
        gps: one residual model per agent (each fitted on its own model's residual rows), or ``None``.

    Attributes:
        groups: one :class:`~.agent_step.LocalStep` per model (``team.models`` order).
        nominal: the team's models (:class:`~torch_gpmpc.dynamics.team.TeamNominal`).
        uncertainty: agent 0's covariance model (each model resolves ``auto`` for itself).

    Examples:
        >>> import torch
        >>> from torch_gpmpc import ADMM, ControllerSettings, ModelSpec
        >>> from torch_gpmpc.config.team import team_spec
        >>> from torch_gpmpc.coordination.graph import communication_graph
        >>> team = team_spec([ModelSpec.double_integrator(2), ModelSpec.single_integrator(2)])
        >>> admm = ADMM(TeamStep(ControllerSettings(method="nominal", horizon=5), team))
        >>> x0 = torch.tensor([[-1.0, 0, 0, 0], [1.0, 0, 0, 0]], dtype=torch.float64)
        >>> res = admm.solve_step(x0, x0.flip(0)[:, None].expand(2, 6, 4), communication_graph(x0[:, :2], None))
        >>> tuple(res.plans.shape), bool(res.plans[1, :, 2:].abs().max() == 0)   # the robot has no velocity
        ((2, 6, 4), True)
    """

    def __init__(self, settings: ControllerSettings | Config, team: TeamSpec, method: str | Method | None = None,
                 wind: VortexWind | None = None, gps: list | None = None) -> None:
        self.settings = as_settings(settings)
        self.method = Method.parse(method or self.settings.method)
        self.team, self.wind, self.gps = team, wind, gps
        self.nominal = TeamNominal(team)
        self.members = self.nominal.members
        self.groups = [LocalStep(self.settings, spec, self.method, wind, gps) for spec in team.models]
        self.uncertainty = self.groups[team.group_of[0]].uncertainty
        self._layers: dict[int, TeamLayer] = {}

    def with_settings(self, settings: ControllerSettings | Config) -> "TeamStep":
        """The same team (models, method, wind, GPs) under other settings."""
        return TeamStep(settings, self.team, self.method, self.wind, self.gps)

    @property
    def exchanges_variance(self) -> bool:
        """Whether neighbours exchange projected variances."""
        return self.groups[0].exchanges_variance

    @property
    def message_size(self) -> int:
        """Numbers one agent sends one neighbour per ADMM iteration (lifted state size)."""
        return self.groups[0].message_size

    def solver(self, num_slots: int) -> TeamLayer:
        """The team's batched local solvers for ``num_slots`` neighbour slots (built once per size)."""
        if num_slots not in self._layers:
            self._layers[num_slots] = TeamLayer([g.solver(num_slots) for g in self.groups], self.members)
        return self._layers[num_slots]

    def assemble(self, x0: Tensor, xref: Tensor, state: ADMMState, graph: Graph, rho: Tensor, eps_self: Tensor,
                 rows: slice | Tensor = slice(None), linearization: Any = None, eps_nbr: Tensor | None = None,
                 u_prev: Tensor | None = None, eps_obstacle: Tensor | None = None) -> Assembled:
        """Every agent's local problem, assembled by its model's step (arguments as
        :meth:`LocalStep.assemble <torch_gpmpc.coordination.agent_step.LocalStep.assemble>`, for all
        K agents; ``linearization`` is a previous call's, one per model)."""
        if not (isinstance(rows, slice) and rows == slice(None)):
            raise GpmpcError("a mixed team plans in one process (all agents at once); the distributed backend "
                             "needs one model for every agent")
        rho = torch.as_tensor(rho)
        parts = []
        for g, (step, idx) in enumerate(zip(self.groups, self.members)):
            parts.append(step.assemble(
                x0[idx], xref[idx], state, graph, rho[idx] if rho.dim() == 2 else rho, eps_self[idx], rows=idx,
                linearization=None if linearization is None else linearization[g],
                eps_nbr=None if eps_nbr is None else eps_nbr[idx], u_prev=None if u_prev is None else u_prev[idx],
                eps_obstacle=None if eps_obstacle is None else eps_obstacle[idx]))
        data = merge_problems([p.data for p in parts], self.members, [step.nominal for step in self.groups])
        own_var = None if parts[0].own_variance is None else by_group(self.members, [p.own_variance for p in parts])
        return Assembled(data, torch.stack([p.max_margin for p in parts]).max(), own_var,
                         tuple(p.linearization for p in parts))

    def solve(self, layer: TeamLayer, data: LocalProblemData, guess: tuple | None = None) -> LocalSolution:
        """Every agent's local solve with its model's solver, failures isolated per model
        (``guess``: the last solution's ``solver_point``, one per model, or ``None``)."""
        guesses = guess or (None,) * len(self.groups)
        parts = [step.solve(sub, select_problems(data, rows), g)
                 for step, sub, rows, g in zip(self.groups, layer.layers, self.members, guesses)]
        return dataclasses.replace(merge_solutions(parts, self.members),
                                   solver_point=tuple(p.solver_point for p in parts))

    def solve_agents(self, layer: TeamLayer, data: LocalProblemData, rows: Tensor) -> LocalSolution:
        """The cold local solves of agents ``rows`` (int64 (B',)): every agent is solved and ``rows``
        are kept (mixed teams are small: splitting ``rows`` by model would save little)."""
        return select_solution(self.solve(layer, data), rows)

    def count_failures(self, sol: LocalSolution, result: StepResult | IterationStats) -> None:
        """Add failed solves to ``result`` and warn once per kind (see ``LocalStep.count_failures``)."""
        self.groups[0].count_failures(sol, result)
