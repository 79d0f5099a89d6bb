"""The ADMM iterate of one control step and what a step returns.

:class:`ADMMState` is what is warm-started from step to step (plans, consensus ``z`` and
duals ``lam`` per edge); :class:`IterationStats` is what one ADMM iteration reports;
:class:`StepResult` is the outcome of one step's ADMM (n states, m inputs per agent).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import torch
from torch import Tensor

from torch_gpmpc.control.problem import FAILURE_KINDS, LocalProblemData, LocalSolution
from torch_gpmpc.coordination.graph import Graph


@dataclass
class ADMMState:
    """Warm-startable iterate of one time step.

    Attributes:
        plans: (K, T+1, n) each agent's own planned states (also the linearization points).
        inputs: (K, T, m) each agent's planned inputs.
        edges: (E, 2) the edges ``z`` and ``lam`` belong to.
        z: (E, 2, T+1, n) consensus trajectories ``[X_lo; X_hi]`` per edge.
        lam: (E, 2, 2, T+1, n) duals; ``lam[e, a]`` is held by the edge's end ``a``
            (0 = lo, 1 = hi) and has the shape of ``z_e``.
        pvar: (E, 2, T) each end's variance along the edge's collision normal at tau = 1..T,
            as that end last reported it (what the ``sum`` and ``joint`` pair margins exchange);
            NaN or ``None`` where not known yet.
        rho: (E,) each edge's ADMM penalty (adapted by residual balancing); ``None``: the
            step's starting rho on every edge.
        risk_left: (K,) each agent's unspent mission risk (``risk_mode = mission``), carried
            from step to step; ``None``: not in use, or a fresh mission.
        applied: (K, m) each agent's first planned input of the step before :meth:`shifted` (the
            input it applied last: ``U_{-1}`` of the input-rate term); ``None``: not known.
        solver_point: the local solver's points of the last iteration's solves (opaque, the fast
            solver's warm start: :attr:`~torch_gpmpc.control.problem.LocalSolution.solver_point`);
            kept by :meth:`shifted` (the next step's first solve starts from its active sets);
            ``None``: none yet.
        planes: (E, T) each edge's agreed plane offset per horizon step with ``admm_coupling =
            planes`` (:mod:`~torch_gpmpc.coordination.planes`); ``None`` at a step's start (the first
            iteration starts from the planes halfway between the linearization plans) or with copies.
        plane_gradient: (E, T) the team cost's derivative in each plane offset at the step's last
            iteration (:func:`~torch_gpmpc.coordination.planes.plane_gradient`); ``None`` at a step's
            start or with copies.
        plane_rho: (E, T) each plane coordinate's step penalty (its inverse step size), adapted within
            a step; ``None`` at a step's start or with copies.

    Examples:
        >>> import torch
        >>> from torch_gpmpc.coordination.graph import communication_graph
        >>> from torch_gpmpc.coordination.state import initial_state
        >>> x0 = torch.tensor([[0.0, 0.0], [1.0, 0.0]], dtype=torch.float64)
        >>> state = initial_state(x0, horizon=4, graph=communication_graph(x0, None))
        >>> tuple(state.plans.shape), tuple(state.z.shape), tuple(state.lam.shape)
        ((2, 5, 2), (1, 2, 5, 2), (1, 2, 2, 5, 2))
        >>> tuple(state.shifted().plans.shape)      # the next step's warm start
        (2, 5, 2)
    """

    plans: Tensor
    inputs: Tensor
    edges: Tensor
    z: Tensor
    lam: Tensor
    pvar: Tensor | None = None
    rho: Tensor | None = None
    risk_left: Tensor | None = None
    applied: Tensor | None = None
    solver_point: Any = None
    planes: Tensor | None = None
    plane_gradient: Tensor | None = None
    plane_rho: Tensor | None = None

    def detached(self) -> "ADMMState":
        """The same iterate with every tensor detached from the autograd graph."""
        return ADMMState(self.plans.detach(), self.inputs.detach(), self.edges, self.z.detach(), self.lam.detach(),
                         None if self.pvar is None else self.pvar.detach(),
                         None if self.rho is None else self.rho.detach(),
                         None if self.risk_left is None else self.risk_left.detach(),
                         None if self.applied is None else self.applied.detach(), self.solver_point,
                         None if self.planes is None else self.planes.detach(),
                         None if self.plane_gradient is None else self.plane_gradient.detach(),
                         None if self.plane_rho is None else self.plane_rho.detach())

    def shifted(self) -> "ADMMState":
        """Shift everything one step forward in time (drop the first point, hold the last); the
        dropped first inputs become ``applied``; the planes are found again from the next step's
        linearization (each edge keeps its penalty)."""
        return ADMMState(
            plans=shift_in_time(self.plans, dim=1),
            inputs=shift_in_time(self.inputs, dim=1),
            edges=self.edges,
            z=shift_in_time(self.z, dim=2),
            lam=shift_in_time(self.lam, dim=3),
            pvar=None if self.pvar is None else shift_in_time(self.pvar, dim=2),
            rho=self.rho,
            risk_left=self.risk_left,
            applied=self.inputs[:, 0],
            solver_point=self.solver_point,
        )


@dataclass
class StepResult:
    """Outcome of ADMM at one time step.

    Attributes:
        plans: (K, T+1, n) final planned states.
        inputs: (K, T, m) final planned inputs (apply ``inputs[:, 0]``).
        state: the final :class:`ADMMState` (shift it to warm-start the next step).
        iterations: ADMM iterations run.
        converged: whether the stopping criterion was met.
        primal_residuals: per iteration, largest ``||y_{e,k} - z_e||``.
        dual_residuals: per iteration, largest ``rho ||z_e - z_e_prev||``.
        unconverged_edges: per iteration, the edges that have not met the stopping test yet
            (:attr:`IterationStats.unconverged_edges`); empty where not counted (the distributed
            backend). A stop at the cap held by a handful of edges reads very differently from one
            where the whole team disagrees.
        slack_max: largest collision slack of the final iterate.
        state_slack_max: how far the final plans leave the soft state constraints (state box,
            rows, norm bound, workspace), the largest over agents and steps (0 inside).
        infeasible_solves: local solves with active slack or failure, summed over iterations.
        failed_solves: local solves that failed (fallback plan used), summed over iterations.
        failed_by_kind: ``failed_solves`` split by kind, ``{kind: count}`` for every kind
            in :data:`~torch_gpmpc.control.problem.FAILURE_KINDS` (exception, non-finite, inaccurate).
        solve_time_s: seconds spent in local solves.
        max_margin: largest chance margin of the final iterate (0 for deterministic methods).
        messages: (K,) numbers each agent sends per iteration.
        solution: the final :class:`LocalSolution` (kept for gradients and diagnostics).
        lost_agents: agents a distributed run has lost (they follow their last plans).
        fallback: ADMM stopped unconverged and some agents re-planned (inside their buffered
            Voronoi cells towards neighbours that can stop at once, against the latest plans of
            neighbours with momentum as fixed obstacles;
            :func:`~torch_gpmpc.coordination.fallback.fallback_problem`).
        unsafe_plan: after any fallback, some pair's applied plans are closer at tau = 1 than
            their collision rows require (``r_safe`` plus the pair's margin, less ``admm_tol``).
        pair_separation: (K, K) the applied plans' distance at tau = 1 per pair (NaN off edges).
        pair_required: (K, K) the larger of the pair's two tau = 1 row bounds (NaN off edges).
        pair_risk: (K, K) the bound on each pair's probability of colliding at the next sample,
            from the applied plans and the agents' variances at tau = 1 (NaN off edges; ``None``
            for methods without margins; :func:`~torch_gpmpc.coordination.mission_risk.pair_risk_bounds`).
        obstacle_risk: (K,) each agent's summed bound on hitting an obstacle of its rows at the
            next sample (``None`` without obstacles or margins;
            :func:`~torch_gpmpc.coordination.mission_risk.obstacle_risk_bounds`).
        problem: the agents' local problems of the last iteration (its convexification; what
            :func:`~torch_gpmpc.coordination.centralized.solve_centralized` solves jointly).

    Examples:
        >>> import torch
        >>> from torch_gpmpc import Controller, ControllerSettings, ModelSpec
        >>> ctrl = Controller(ModelSpec.single_integrator(2), settings=ControllerSettings(method="nominal"))
        >>> x0 = torch.tensor([[-1.0, 0.0], [1.0, 0.0]], dtype=torch.float64)
        >>> result = ctrl.step(x0, x0.flip(0)[:, None].expand(2, 14, 2))
        >>> tuple(result.inputs.shape), result.converged, result.failed_solves
        ((2, 13, 2), True, 0)
    """

    plans: Tensor
    inputs: Tensor
    state: ADMMState
    iterations: int
    converged: bool
    primal_residuals: list[float] = field(default_factory=list)
    dual_residuals: list[float] = field(default_factory=list)
    unconverged_edges: list[int] = field(default_factory=list)
    slack_max: float = 0.0
    state_slack_max: float = 0.0
    infeasible_solves: int = 0
    failed_solves: int = 0
    failed_by_kind: dict[str, int] = field(default_factory=lambda: dict.fromkeys(FAILURE_KINDS, 0))
    solve_time_s: float = 0.0
    max_margin: float = 0.0
    messages: Tensor | None = None
    solution: LocalSolution | None = None
    lost_agents: list[int] = field(default_factory=list)
    fallback: bool = False
    unsafe_plan: bool = False
    pair_separation: Tensor | None = None
    pair_required: Tensor | None = None
    pair_risk: Tensor | None = None
    obstacle_risk: Tensor | None = None
    problem: LocalProblemData | None = None

    def record(self, stats: IterationStats) -> None:
        """Add one iteration's report (counts, residual history, last solution and problem)."""
        self.iterations += 1
        self.primal_residuals.append(float(stats.primal.detach()))
        self.dual_residuals.append(float(stats.dual.detach()))
        self.unconverged_edges.append(stats.unconverged_edges)
        self.solve_time_s += stats.solve_time_s
        self.failed_solves += stats.failed_solves
        for kind, count in stats.failed_by_kind.items():
            self.failed_by_kind[kind] += count
        self.infeasible_solves += stats.infeasible_solves
        self.solution, self.problem, self.max_margin = stats.solution, stats.problem, stats.max_margin

    def record_counts(self, primal: float, dual: float, unconverged_edges: int, infeasible_solves: int,
                      solve_time_s: float) -> None:
        """Add the report of a compiled iteration (:mod:`~torch_gpmpc.coordination.steady`): its
        residuals and counts (it had no failed solve); the solution and problem stay those of the
        last iteration through :meth:`~.admm.ADMM.iterate` (a step always ends with one)."""
        self.iterations += 1
        self.primal_residuals.append(primal)
        self.dual_residuals.append(dual)
        self.unconverged_edges.append(unconverged_edges)
        self.solve_time_s += solve_time_s
        self.infeasible_solves += infeasible_solves


@dataclass
class IterationStats:
    """What one ADMM iteration reports (:meth:`~torch_gpmpc.coordination.admm.ADMM.iterate`).

    Attributes:
        solution: the agents' local solutions (failed agents replaced by their previous plans).
        problem: the local problems solved.
        primal: largest per-edge primal residual ``||y_{e,k} - z_e||``, 0-d (keeps gradients).
        dual: largest per-edge dual residual ``rho_e ||z_e - z_e_prev||``, 0-d (keeps gradients).
        primal_ratio, dual_ratio: the largest residual over its stopping tolerance (< 1: met).
        unconverged_edges: edges whose own residuals have not met the stopping test
            (:func:`~torch_gpmpc.coordination.penalty.unconverged_edges`); 0 without edges.
        max_margin: largest chance margin of an active row.
        solve_time_s: seconds in the local solves.
        failed_solves, failed_by_kind: failed local solves, split by kind.
        infeasible_solves: solves with an active slack or a failure.
    """

    solution: LocalSolution
    problem: LocalProblemData
    primal: Tensor
    dual: Tensor
    primal_ratio: float = 0.0
    dual_ratio: float = 0.0
    unconverged_edges: int = 0
    max_margin: float = 0.0
    solve_time_s: float = 0.0
    failed_solves: int = 0
    failed_by_kind: dict[str, int] = field(default_factory=lambda: dict.fromkeys(FAILURE_KINDS, 0))
    infeasible_solves: int = 0


def shift_in_time(x: Tensor, dim: int) -> Tensor:
    """Drop index 0 along ``dim`` and repeat the last entry: a plan one step later, holding its
    last point (the warm start of the next control step)."""
    if x.shape[dim] == 0:
        return x
    last = x.narrow(dim, x.shape[dim] - 1, 1)
    return torch.cat([x.narrow(dim, 1, x.shape[dim] - 1), last], dim=dim)


def initial_state(x0: Tensor, horizon: int, graph: Graph, input_dim: int | None = None) -> ADMMState:
    """Cold start: every agent plans to stay where it is; z from those plans, lam = 0.

    Args:
        x0: (K, n) current states.
        horizon: T.
        graph: the communication graph.
        input_dim: m (default n).
    """
    plans = x0.unsqueeze(1).expand(-1, horizon + 1, -1).clone()
    inputs = x0.new_zeros(x0.shape[0], horizon, x0.shape[1] if input_dim is None else input_dim)
    z = plans[graph.edges].clone() if graph.num_edges else x0.new_zeros(0, 2, horizon + 1, x0.shape[1])
    lam = x0.new_zeros(graph.num_edges, 2, 2, horizon + 1, x0.shape[1])
    return ADMMState(plans, inputs, graph.edges, z, lam)


def adapt_state(state: ADMMState, graph: Graph) -> ADMMState:
    """Carry ``z``/``lam`` (and the penalties and variances) over to a new graph: kept edges keep
    theirs, new edges start from the current plans with zero duals."""
    if torch.equal(state.edges, graph.edges):
        return state
    old = {tuple(e): i for i, e in enumerate(state.edges.tolist())}
    pairs = [(i, old[tuple(e)]) for i, e in enumerate(graph.edges.tolist()) if tuple(e) in old]
    kept, was = torch.tensor(pairs, dtype=torch.long).reshape(-1, 2).T  # new and old index of each kept edge
    z = state.plans[graph.edges].clone() if graph.num_edges else state.z[:0]
    z[kept] = state.z[was]
    lam = state.lam.new_zeros(graph.num_edges, *state.lam.shape[1:])
    lam[kept] = state.lam[was]
    pvar = rho = None
    if state.rho is not None:
        rho = state.rho.new_full((graph.num_edges,), float("nan")).index_put((kept,), state.rho[was])
    if state.pvar is not None:
        pvar = state.pvar.new_full((graph.num_edges, *state.pvar.shape[1:]), float("nan"))
        pvar[kept] = state.pvar[was]
    return ADMMState(state.plans, state.inputs, graph.edges, z, lam, pvar, rho, state.risk_left, state.applied,
                     state.solver_point)
