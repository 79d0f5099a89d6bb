"""Mixed teams: agents of different models planned as one batch, each model lifted to a common state.

A team of double-integrator drones (state ``[p, v]``, n = 4 in 2D) and single-integrator ground
robots (state ``p``, n = 2) plans in one batched local problem and one consensus ADMM: every model
is *lifted* to the team's largest state and input sizes ``(n, m)`` by padding. The padded states
have zero rows in A and B (they start at 0 and stay 0), the padded inputs zero columns in B (the
control-effort term drives them to 0). The model's own state keeps its indices, so the position,
the residual rows, the GP input columns and the state constraints carry over unchanged; the
lifted model's plans restricted to its first ``n_k`` states are exactly the model's plans.

Why lift rather than exchange positions only: the collision rows read positions only, but the
consensus, the warm starts, the safety fallback and the recorded rollouts all work on one state
tensor; lifting keeps every one of them (and the compiled solver) as it is, at the price of
messages of the largest model's size. An agent still plans with its own dynamics, input bound,
state constraints, GP and uncertainty model (one solver per model).

Requirements (checked, each error names the fix): the same sampling time ``dt``, the same position
indices, and the same number of residual rows (the process noise and the learned-model report
are per residual row).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Sequence

from torch_gpmpc.config.model_spec import ModelSpec
from torch_gpmpc.errors import GpmpcError


def lift_spec(spec: ModelSpec, n: int, m: int) -> ModelSpec:
    """``spec`` padded to n states and m inputs (zero rows and columns; a padded input's box is 1).

    Examples:
        >>> from torch_gpmpc import ModelSpec
        >>> si = lift_spec(ModelSpec.single_integrator(2), 4, 2)
        >>> si.state_dim, si.A[2], si.B[0], si.position, si.residual
        (4, (0.0, 0.0, 0.0, 0.0), (0.1, 0.0), (0, 1), (0, 1))
    """
    n0, m0 = spec.state_dim, spec.input_dim
    if (n0, m0) == (n, m):
        return spec
    if n0 > n or m0 > m:
        raise GpmpcError(f"lift_spec: model {spec.name!r} has (n, m) = ({n0}, {m0}), more than ({n}, {m})")
    A = tuple(tuple(spec.A[i][j] if i < n0 and j < n0 else 0.0 for j in range(n)) for i in range(n))
    B = tuple(tuple(spec.B[i][j] if i < n0 and j < m0 else 0.0 for j in range(m)) for i in range(n))
    box = None if spec.input_box is None else spec.input_box + (1.0,) * (m - m0)
    G = None if spec.state_rows_G is None else tuple(row + (0.0,) * (n - n0) for row in spec.state_rows_G)
    return replace(spec, A=A, B=B, input_box=box, state_rows_G=G)


@dataclass(frozen=True)
class TeamSpec:
    """The models of a team, lifted to common sizes.

    Attributes:
        models: the distinct agent models, lifted to ``(n, m)``, in order of first appearance.
        group_of: agent k's index into ``models``, length K.
        own_dims: each model's own ``(n_k, m_k)`` before lifting (same order as ``models``).

    Examples:
        >>> from torch_gpmpc import ModelSpec
        >>> di, si = ModelSpec.double_integrator(2), ModelSpec.single_integrator(2)
        >>> team = team_spec([di, di, si])
        >>> team.group_of, team.members(1), team.own_dims, team.is_mixed
        ((0, 0, 1), [2], ((4, 2), (2, 2)), True)
    """

    models: tuple[ModelSpec, ...]
    group_of: tuple[int, ...]
    own_dims: tuple[tuple[int, int], ...]

    @property
    def num_agents(self) -> int:
        """K."""
        return len(self.group_of)

    @property
    def is_mixed(self) -> bool:
        """More than one model."""
        return len(self.models) > 1

    def members(self, group: int) -> list[int]:
        """The agents of model ``group``, in increasing order."""
        return [k for k, g in enumerate(self.group_of) if g == group]

    def agent_spec(self, k: int) -> ModelSpec:
        """Agent k's lifted model."""
        return self.models[self.group_of[k]]


def team_spec(specs: Sequence[ModelSpec], where: str = "config key 'models'") -> TeamSpec:
    """The :class:`TeamSpec` of one model per agent.

    Raises:
        GpmpcError: naming ``where``, when the models differ in ``dt``, in their position indices
            or in their number of residual rows.
    """
    if not specs:
        raise GpmpcError(f"{where}: give one model per agent (a non-empty list)")
    distinct: list[ModelSpec] = []
    for spec in specs:
        if spec not in distinct:
            distinct.append(spec)
    first = distinct[0]
    for spec in distinct[1:]:
        if spec.dt != first.dt:
            raise GpmpcError(f"{where}: models {first.name!r} (dt {first.dt}) and {spec.name!r} (dt {spec.dt}) "
                             "must share one sampling time; set dt in the model files (or --set dt=...)")
        if spec.position != first.position:
            raise GpmpcError(f"{where}: models {first.name!r} and {spec.name!r} have position indices "
                             f"{list(first.position)} and {list(spec.position)}; order every model's state "
                             "so that the position has the same indices (e.g. the position first)")
        if len(spec.residual) != len(first.residual):
            raise GpmpcError(f"{where}: models {first.name!r} and {spec.name!r} have {len(first.residual)} and "
                             f"{len(spec.residual)} residual rows; a mixed team needs the same number")
    n = max(s.state_dim for s in distinct)
    m = max(s.input_dim for s in distinct)
    return TeamSpec(models=tuple(lift_spec(s, n, m) for s in distinct),
                    group_of=tuple(distinct.index(s) for s in specs),
                    own_dims=tuple((s.state_dim, s.input_dim) for s in distinct))
