"""Consensus ADMM over the neighbour graph (paper §3.3-3.5, Algorithm 1): the paper's copies
(``admm_coupling = copies``, below) or separating planes (``planes``, the default; last paragraphs).

Per edge ``e = (lo, hi)`` the shared vector is ``z_e = [X_lo; X_hi]`` (eq. 18),
shape (2, T+1, D). Agent k keeps a copy ``y_{e,k}`` of it: its own plan in its own
half and its copy of the neighbour's plan in the other. One iteration:

1. linearize: dynamics around each agent's own plan, collision rows around the plans of
   both agents of the pair: once per control step at the warm start (default), or at every
   iterate with ``relinearize = true`` (Algorithm 1, step 9; the moving convexification then
   keeps ADMM from settling: measured on the six-agent circle with admm_rel_tol = 0, 42.5
   instead of 28.4 iterations per step and 17 steps at the iteration cap);
2. local solves: all K local problems (27) as **one batched** local-solver call;
3. consensus ``z_e = (y_{e,lo} + y_{e,hi}) / 2`` (eq. 28);
4. duals ``lam_{e,k} += rho_e (y_{e,k} - z_e)`` (eq. 29);
5. with ``rho_update = adaptive`` (default), each edge's ``rho_e`` by residual balancing.

Stopping (:mod:`~torch_gpmpc.coordination.penalty`): with ``admm_stop = primal-dual``
(default) every edge's primal residual ``||y_{e,k} - z_e||`` and dual residual
``rho_e ||z_e - z_e_prev||`` are below their absolute-plus-relative tolerances (Boyd et al.
2011 §3.3.1); with ``primal`` (the paper's rule) the primal one below ``admm_tol`` (and the
dual one below ``admm_dual_tol`` if set); or ``admm_max_iter``. The primal-only rule at a
fixed rho stops on a feasible consensus that is not yet optimal.

With ``admm_coupling = planes`` (the default; :mod:`~torch_gpmpc.coordination.planes`) neighbours
share instead one separating plane per edge and horizon step, each keeping its own half, and move it
by primal decomposition: the same team problem, T numbers per message, and plans that keep every pair at any
iteration, so a capped step applies its last safe iterate rather than falling back.

Messages: per iteration agent k sends its copy ``y_{e,k}`` (``2 (T+1) n`` numbers, n the
model's state size) and, with the ``sum``/``joint`` margins, its T projected variances to each
neighbour. The paper counts
``2 D_x T |N_k|`` because its T indexes the T+1 points ``t..t+T`` as T vectors; we
report ours.

Everything is torch: with gradients enabled, an unrolled ADMM is differentiable in
rho, the risk split and the problem data (used by ``gpmpc tune``). One iteration is
:meth:`ADMM.iterate`; a control step (:meth:`ADMM.solve_step`) is that loop plus the stopping
test and the safety check; the tuner's unroll is the same loop without stopping. Within
:meth:`ADMM.solve_step`, the iterations after a step's second (its first where no variances are
exchanged), whose problems change only in their consensus terms, run on the kept problems where
nothing needs gradients (``admm_compiled``: :mod:`~torch_gpmpc.coordination.steady`,
:class:`~torch_gpmpc.coordination.planes.PlaneIterations`): the same plans, bit for bit. The edges'
update after the solves is written once per coupling (:mod:`~torch_gpmpc.coordination.consensus`,
:mod:`~torch_gpmpc.coordination.planes`) and shared with the distributed agents.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor, nn

from torch_gpmpc.config.settings import ControllerSettings
from torch_gpmpc.control.problem import LocalProblemData, LocalSolution
from torch_gpmpc.coordination.bodies import edge_distances, slot_distances
from torch_gpmpc.coordination.consensus import consensus_update, copies_update
from torch_gpmpc.coordination.agent_step import (
    LocalStep, edge_copies, edge_variances, fall_back_to_previous, slot_risks,
)
from torch_gpmpc.coordination.fallback import fallback_agents, fallback_problem, pair_safety
from torch_gpmpc.coordination.graph import Graph
from torch_gpmpc.coordination.mission_risk import (
    RISK_FLOOR, agent_charges, direction_risk_bounds, edge_allotments, edge_separations, obstacle_risk_bounds,
    pair_matrix, pair_risk_bounds, row_allotments, slot_risks_from_edges, starting_budgets,
)
from torch_gpmpc.coordination.planes import (
    PlaneIterations, SafeIterates, end_multipliers, midpoint_planes, plane_geometry, plane_iteration, plane_problem,
)
from torch_gpmpc.coordination.penalty import should_stop, starting_penalties, unconverged_edges
from torch_gpmpc.coordination.state import ADMMState, IterationStats, StepResult, adapt_state, initial_state
from torch_gpmpc.coordination.steady import SteadyIterations, repeatable
from torch_gpmpc.dynamics.systems import NominalModel
from torch_gpmpc.errors import GpmpcError

__all__ = ["ADMM", "ADMMState", "IterationStats", "StepContext", "StepResult", "adapt_state", "consensus_update",
           "initial_state"]


@dataclass
class StepContext:
    """The data one control step's ADMM iterations share (built by :meth:`ADMM.prepare`).

    Attributes:
        x0: (K, n) measured states. xref: (K, T+1, n) reference windows.
        graph: the communication graph of the step.
        rho: the penalty, 0-d (with ``rho_update = adaptive``: the start of new edges).
        eps_self: (K, M) each agent's own risk per slot. eps_nbr: (K, M) its neighbour's.
        eps_edge: (E, 2) the step's risk of each end of each edge under a mission budget
            (``None``: ``risk_mode = pair_step``).
        eps_obstacle: (K,) the step's risk of each of an agent's obstacle rows under a mission
            budget (``None``: ``settings.obstacle_eps``).
        lin_plans, lin_inputs: (K, T+1, n) and (K, T, m) linearization points (the warm start);
            ``None`` with ``relinearize``, where every iterate is its own.
        layer: the batched local solver for the graph's slot count.
        tol: absolute primal tolerance of the stopping test.
        linearization: the dynamics linearization at ``lin_plans`` once computed (reused by
            every iteration of the step: it is most of an iteration's cost).
        u_prev: (K, m) the inputs applied at the previous step (the input-rate term's
            ``U_{-1}``), from the warm start; ``None``: 0 (a cold start).
        convexification: the last iterate's convexification (its obstacle rows are charged to a
            mission budget).
        planes_posed: with ``admm_coupling = planes``, the last iteration's plane problems and their
            :class:`~.planes.PlaneGeometry` (what the compiled plane iterations keep).
    """

    x0: Tensor
    xref: Tensor
    graph: Graph
    rho: Tensor
    eps_self: Tensor
    eps_nbr: Tensor
    eps_edge: Tensor | None
    lin_plans: Tensor | None
    lin_inputs: Tensor | None
    layer: nn.Module
    tol: float
    linearization: Any = None
    u_prev: Tensor | None = None
    eps_obstacle: Tensor | None = None
    convexification: Any = None
    planes_posed: Any = None


class ADMM:
    r"""Consensus ADMM for K agents' local MPC problems (Algorithm 1, all agents batched).

    Per edge ``e = (k, j)`` both agents hold a copy ``y_{e,k} = [X_k; Y_{k,j}]`` of the
    shared trajectories ``z_e = [X_k; X_j]``. One control step solves::

        minimize   sum_k J_k(X_k, U_k)   subject to   y_{e,k} = z_e  for every edge end,

    with ``J_k`` agent k's local MPC cost and constraints (dynamics, input bound, collision
    rows), by iterating, with penalty rho and duals ``lam_{e,k}``:

    1. local step (every agent, in parallel; :class:`~.agent_step.LocalStep`)::

           y_k = argmin J_k + sum_{e in N_k} lam_{e,k}^T (y_{e,k} - z_e) + rho/2 ||y_{e,k} - z_e||^2

    2. consensus ``z_e = (y_{e,k} + y_{e,j}) / 2`` (eq. 28);
    3. duals ``lam_{e,k} += rho (y_{e,k} - z_e)`` (eq. 29).

    Residuals: primal ``r_e = max_k ||y_{e,k} - z_e||``, dual ``s_e = rho_e ||z_e - z_e^prev||``.
    Stopping and the adaptation of ``rho_e`` follow :mod:`~torch_gpmpc.coordination.penalty`;
    the linearization points are the warm start's plans, or the current plans every
    iteration with ``relinearize`` (Algorithm 1, step 9).

    Args:
        step: the per-agent step (:class:`~.agent_step.LocalStep`, or a mixed team's
            :class:`~.team_step.TeamStep`), which knows the model, the method, the GPs, the cost and
            the settings.

    Examples:
        >>> import torch
        >>> from torch_gpmpc import ADMM, ControllerSettings, LocalStep, ModelSpec
        >>> from torch_gpmpc.coordination.graph import communication_graph
        >>> step = LocalStep(ControllerSettings(method="nominal", horizon=5), ModelSpec.single_integrator(2))
        >>> admm = ADMM(step)
        >>> x0 = torch.tensor([[-1.0, 0.0], [1.0, 0.0]], dtype=torch.float64)
        >>> xref = x0.flip(0)[:, None].expand(2, 6, 2)              # swap places
        >>> ctx, state = admm.prepare(x0, xref, communication_graph(x0, None))
        >>> state, stats = admm.iterate(ctx, state)               # one pure iteration
        >>> tuple(state.plans.shape), stats.primal.ndim
        ((2, 6, 2), 0)
    """

    def __init__(self, step: LocalStep) -> None:
        if not hasattr(step, "assemble"):
            raise GpmpcError(f"ADMM takes the per-agent step (LocalStep(settings, model, method, wind, gps)), got "
                             f"{type(step).__name__}")
        #: the per-agent step every iteration runs (its settings, model, method and GPs)
        self.agent_step = step
        self.settings = step.settings

    @property
    def nominal(self) -> NominalModel:
        """The agents' known model."""
        return self.agent_step.nominal

    @property
    def gps(self) -> list | None:
        """The agents' residual models (indexed by agent id), or ``None``."""
        return self.agent_step.gps

    def with_settings(self, **changes: Any) -> "ADMM":
        """The same agents under settings with ``changes`` applied (keys of :class:`ControllerSettings`)."""
        return ADMM(self.agent_step.with_settings(self.settings.replace(**changes)))

    def prepare(self, x0: Tensor, xref: Tensor, graph: Graph, warm: ADMMState | None = None,
                rho: float | Tensor | None = None, risk_split: float | Tensor | None = None,
                tol: float | None = None) -> tuple[StepContext, ADMMState]:
        """The step's shared data and its first iterate (warm or cold start).

        Args:
            x0: (K, n) measured states. xref: (K, T+1, n) reference windows.
            graph: communication graph at this step.
            warm: previous step's state, already shifted (cold start if ``None``).
            rho: penalty (default ``settings.rho``); a tensor keeps gradients. With
                ``rho_update = adaptive`` it is the start of every edge the warm state does not
                carry a penalty for (edges carried over keep their adapted one).
            risk_split: scalar or (K, K) split (default ``settings.risk_split``).
            tol: absolute primal tolerance of the stopping test (default ``settings.admm_tol``).
        """
        s = self.settings
        rho_t = torch.as_tensor(s.rho if rho is None else rho, dtype=x0.dtype)
        state = initial_state(x0, s.horizon, graph, self.nominal.input_dim) if warm is None \
            else adapt_state(warm, graph)
        if state.planes is not None:  # a step's planes start from its own linearization
            state = dataclasses.replace(state, planes=None, plane_gradient=None, plane_rho=None)
        eps_edge = eps_obstacle = None
        if s.risk_mode == "mission":
            remaining = starting_budgets(graph.num_agents, s.risk_budget, x0) if state.risk_left is None \
                else state.risk_left
            state = dataclasses.replace(state, risk_left=remaining)
            rows = mission_obstacle_rows(s)
            eps_edge = edge_allotments(remaining, graph, s.risk_pacing, rows)
            eps_obstacle = row_allotments(remaining, graph, s.risk_pacing, rows) if rows else None
            eps_self, eps_nbr = slot_risks_from_edges(graph, eps_edge)
        else:
            eps_self = slot_risks(graph, s.eps, s.risk_split if risk_split is None else risk_split)
            eps_nbr = s.eps - eps_self
        if s.rho_update == "adaptive":
            state = dataclasses.replace(state, rho=starting_penalties(state.rho, rho_t, graph.num_edges))
        lin_plans, lin_inputs = (None, None) if s.relinearize else (state.plans, state.inputs)
        ctx = StepContext(x0, xref, graph, rho_t, eps_self, eps_nbr, eps_edge, lin_plans, lin_inputs,
                          self.agent_step.solver(graph.num_slots), s.admm_tol if tol is None else tol,
                          u_prev=None if warm is None else warm.applied, eps_obstacle=eps_obstacle)
        return ctx, state

    def iterate(self, ctx: StepContext, state: ADMMState) -> tuple[ADMMState, IterationStats]:
        """One ADMM iteration: local solves (failed agents keep their previous plans), consensus,
        duals, penalty update. Returns the next iterate and what the iteration measured."""
        s, graph = self.settings, ctx.graph
        if s.admm_coupling == "planes" and graph.num_edges:
            return self._iterate_planes(ctx, state)
        assembled = self._assemble(ctx, state)
        _, sol, stats = self._local_solves(ctx, state, assembled.data, assembled)
        z_new, lam, rho_next = state.z, state.lam, state.rho
        if graph.num_edges:
            rho_now = state.rho if s.rho_update == "adaptive" else ctx.rho
            update = copies_update(edge_copies(sol, graph), state.z, state.lam, rho_now, s, ctx.tol)
            z_new, lam, rho_next = update.z, update.lam, update.rho
            stats.primal, stats.dual = update.residuals.primal.max(), update.residuals.dual.max()
            stats.primal_ratio = float(update.stop.primal_ratio.max().detach())
            stats.dual_ratio = float(update.stop.dual_ratio.max().detach())
            stats.unconverged_edges = unconverged_edges(update.stop, s)
        pvar = state.pvar
        if assembled.own_variance is not None:
            pvar = edge_variances(assembled.own_variance, graph, state.pvar)
        return ADMMState(sol.X, sol.U, graph.edges, z_new, lam, pvar, rho_next, state.risk_left,
                         solver_point=sol.solver_point), stats

    def _assemble(self, ctx: StepContext, state: ADMMState) -> Any:
        """The iteration's local problems (:meth:`~.agent_step.LocalStep.assemble`) at the step's
        linearization (computed once and kept in ``ctx``), or at ``state`` with ``relinearize``."""
        s, graph = self.settings, ctx.graph
        adaptive = s.rho_update == "adaptive"
        lin_state = state if ctx.lin_plans is None else \
            dataclasses.replace(state, plans=ctx.lin_plans, inputs=ctx.lin_inputs)
        rho_slots = state.rho[graph.slot_edge] if adaptive and graph.num_edges else ctx.rho
        assembled = self.agent_step.assemble(ctx.x0, ctx.xref, lin_state, graph, rho_slots, ctx.eps_self,
                                             linearization=ctx.linearization, eps_nbr=ctx.eps_nbr,
                                             u_prev=ctx.u_prev, eps_obstacle=ctx.eps_obstacle)
        if ctx.lin_plans is not None:
            ctx.linearization = assembled.linearization
        ctx.convexification = assembled.linearization
        return assembled

    def _local_solves(self, ctx: StepContext, state: ADMMState, posed: LocalProblemData,
                      assembled: Any) -> tuple[LocalSolution, LocalSolution, IterationStats]:
        """Solve the batch ``posed`` and account for it: ``(solution, the same with failed agents on
        their previous plans, the iteration's stats)``; the stats report the assembled problems."""
        step = self.agent_step
        t0 = time.perf_counter()
        sol = step.solve(ctx.layer, posed, state.solver_point)
        stats = IterationStats(solution=sol, problem=assembled.data, primal=ctx.x0.new_zeros(()),
                               dual=ctx.x0.new_zeros(()), max_margin=float(assembled.max_margin.detach()),
                               solve_time_s=time.perf_counter() - t0)
        step.count_failures(sol, stats)
        kept = fall_back_to_previous(sol, state, ctx.graph)
        stats.solution = kept
        stats.infeasible_solves = int((kept.slack_active | ~kept.ok).sum())
        return sol, kept, stats

    def _iterate_planes(self, ctx: StepContext, state: ADMMState) -> tuple[ADMMState, IterationStats]:
        """:meth:`iterate` with ``admm_coupling = planes`` (:mod:`~.planes`): local solves on plane
        halves at the agreed offsets, then each edge's plane step. The iteration reports the assembled
        problems (full rows: what the safety check and a centralized solve use)."""
        s, graph = self.settings, ctx.graph
        if state.planes is None:  # the step's first iteration: its rows read the step's own variances
            state = self._with_step_variances(ctx, state)
        assembled = self._assemble(ctx, state)
        data = assembled.data
        geometry = plane_geometry(data, graph)
        planes = state.planes if state.planes is not None else \
            midpoint_planes(geometry, state.plans if ctx.lin_plans is None else ctx.lin_plans, graph,
                            self.nominal.position)
        posed = plane_problem(data, geometry, planes)
        ctx.planes_posed = (posed, geometry)
        _, sol, stats = self._local_solves(ctx, state, posed, assembled)
        mu = end_multipliers(sol.multipliers, sol.Y, sol.ok, geometry, planes)
        step, res, stop = plane_iteration(mu, sol.X, geometry, planes, state.plane_rho, state.plane_gradient, ctx.rho,
                                          s, ctx.tol)
        stats.primal, stats.dual = res.primal.max(), res.dual.max()
        stats.primal_ratio = float(stop.primal_ratio.max().detach())
        stats.dual_ratio = float(stop.dual_ratio.max().detach())
        stats.unconverged_edges = unconverged_edges(stop, s)
        pvar = state.pvar
        if assembled.own_variance is not None:
            pvar = edge_variances(assembled.own_variance, graph, state.pvar)
        nxt = ADMMState(sol.X, sol.U, graph.edges, state.z, state.lam, pvar, state.rho, state.risk_left,
                        solver_point=sol.solver_point, planes=step.planes, plane_gradient=step.gradient,
                        plane_rho=step.rho)
        return nxt, stats

    def _with_step_variances(self, ctx: StepContext, state: ADMMState) -> ADMMState:
        """``state`` with every edge end's projected variance (``pvar``, (E, 2, T)) from this step's
        linearization rather than the last step's reports, where the margins read the neighbours'.

        With planes the pair rows then hold from the step's first iteration to its last (the frozen
        linearization fixes the variances), so the planes' geometry (their normals and distances) is
        the step's, and the distributed backend's agents can agree on it once per step."""
        if not self.agent_step.exchanges_variance:
            return state
        own = self._assemble(ctx, state).own_variance
        return dataclasses.replace(state, pvar=edge_variances(own, ctx.graph, state.pvar))

    def solve_step(
        self,
        x0: Tensor,
        xref: Tensor,
        graph: Graph,
        warm: ADMMState | None = None,
        rho: float | Tensor | None = None,
        risk_split: float | Tensor | None = None,
        max_iter: int | None = None,
        tol: float | None = None,
        safety_fallback: bool = True,
    ) -> StepResult:
        """Run ADMM for one time step: :meth:`iterate` until the stopping test or the cap,
        then the safety check.

        Args:
            x0: (K, n) measured states.
            xref: (K, T+1, n) reference window.
            graph: communication graph at this step.
            warm: previous step's state, already shifted (cold start if ``None``).
            rho, risk_split: see :meth:`prepare` (tensors keep gradients).
            max_iter: iteration cap (defaults to ``settings.iteration_cap``).
            tol: absolute primal tolerance of the stopping rule (defaults to ``settings.admm_tol``;
                0 never stops early). Penalty balancing always uses the configured tolerances.
            safety_fallback: when ADMM stops on plans not known to be jointly safe, re-plan the
                agents :func:`~.fallback.fallback_agents` names: in pairs of agents that can both
                stop at once, those with a row short at tau = 1 and the agents whose plans leave
                their buffered Voronoi cells towards them, and the agents of unsafe pairs with
                momentum; inside their cells, against neighbours with momentum as fixed
                obstacles (:func:`~.fallback.fallback_problem`).
        """
        s = self.settings
        ctx, state = self.prepare(x0, xref, graph, warm, rho, risk_split, tol)
        max_iter = s.iteration_cap if max_iter is None else max_iter
        result = StepResult(plans=state.plans, inputs=state.inputs, state=state, iterations=0, converged=False)
        steady: SteadyIterations | None = None
        planes = s.admm_coupling == "planes" and graph.num_edges
        safe = SafeIterates()  # with planes, the iterates whose halves held near
        deadline = None if s.admm_time_budget_ms is None else time.perf_counter() + s.admm_time_budget_ms / 1000
        for it in range(max_iter):
            # the step's last iteration goes through the torch path, which reports the solution
            last = it == max_iter - 1 or (deadline is not None and it > 0 and time.perf_counter() > deadline)
            if steady is not None and not last:
                t0 = time.perf_counter()
                fast = steady.iterate(state)
                if fast is not None and not should_stop(fast.primal_ratio, fast.dual_ratio, s):
                    result.record_counts(fast.primal, fast.dual, fast.unconverged_edges, fast.infeasible_solves,
                                         time.perf_counter() - t0)
                    state = fast.state
                    safe.record(fast.dual_ratio, state.plans, state.inputs)
                    continue
                # anything unusual goes through the torch path too, which reports the failures
            state, stats = self.iterate(ctx, state)
            result.record(stats)
            if planes:
                safe.record(stats.dual_ratio, state.plans, state.inputs)
            if should_stop(stats.primal_ratio, stats.dual_ratio, s):
                result.converged = True
                break
            if last:
                break
            # the problems change only in their consensus terms from the second iteration on (from the
            # first where no variances are exchanged, the margins then not reading the neighbours', or
            # with planes, whose first iteration reads the step's own variances)
            if it == 1 or (it == 0 and (not self.agent_step.exchanges_variance or s.admm_coupling == "planes")):
                steady = self._steady_iterations(ctx, state, stats)
        applied = safe.best() if planes else None
        if applied is not None:
            state = dataclasses.replace(state, plans=applied[0], inputs=applied[1])
        if graph.num_edges and result.iterations:
            # with planes every iterate whose halves held is jointly safe: only a step without one re-plans
            unsafe_stop = applied is None if planes else not result.converged
            state = self._check_safety(state, result.problem, graph, ctx.layer, result,
                                       safety_fallback and unsafe_stop)
        if result.iterations:
            state = self._account_risk(state, result, graph, ctx)
        result.plans, result.inputs, result.state = state.plans, state.inputs, state
        result.slack_max = float(result.solution.slack.detach().max()) if result.solution.slack.numel() else 0.0
        result.state_slack_max = state_slack_max(result.solution)
        result.messages = self.agent_step.message_size * graph.degrees()
        return result

    def _steady_iterations(self, ctx: StepContext, state: ADMMState,
                           stats: IterationStats) -> SteadyIterations | PlaneIterations | None:
        """The step's compiled iterations (:mod:`~.steady`; :class:`~.planes.PlaneIterations` with
        ``admm_coupling = planes``) from the iteration after ``state``, ``stats`` on, or ``None`` where
        they do not apply: ``admm_compiled`` off, a linearization per iterate,
        no edge, a solver other than ``fast`` with warm starts, a failed solve, gradients wanted, or
        tensors not float64 on the CPU."""
        if not self.settings.admm_compiled or ctx.lin_plans is None \
                or not ctx.graph.num_edges or stats.failed_solves:
            return None
        layer = ctx.layer
        if not repeatable(layer, (state.z, state.plans, state.lam, state.rho, ctx.rho)):
            return None
        if self.settings.admm_coupling == "planes":
            posed, geometry = ctx.planes_posed
            solve = layer.repeated(posed)
            return None if solve is None else PlaneIterations(self.settings, ctx.graph, geometry, ctx.rho, ctx.tol,
                                                              solve)
        solve = layer.repeated(stats.problem)
        return None if solve is None else SteadyIterations(self.settings, ctx.graph, stats.problem, ctx.rho, ctx.tol,
                                                           solve)

    def _check_safety(self, state: ADMMState, data, graph: Graph, layer, result: StepResult,
                      fallback: bool) -> ADMMState:
        """Judge the applied plans at tau = 1 (own plans, not copies); with ``fallback`` (a stop on
        plans not known to be safe), re-plan (:func:`~.fallback.fallback_problem`) the agents
        :func:`~.fallback.fallback_agents` names: agents with a short row of a cell pair at
        tau = 1 and the agents whose plans leave their cells towards them, and every agent in an
        unsafe pair with momentum."""
        bounds = data.bounds[:, :, 0].detach()
        position = self.nominal.position
        unsafe, sep, req = pair_safety(state.plans.detach(), graph, bounds, self.settings.admm_tol, position)
        replan = torch.zeros_like(unsafe)
        if fallback:
            replan, cells = fallback_agents(state.plans.detach(), graph, bounds, self.settings.admm_tol, position,
                                            self.nominal.momentum(graph.num_agents), self.settings.safety_fallback)
        if bool(replan.any()):
            rows = replan.nonzero().flatten()
            with torch.no_grad():
                contact = slot_distances(self.settings, torch.arange(graph.num_agents), graph.slot_nbr)
                posed = fallback_problem(data, state.plans, state.plans[graph.slot_nbr], position, cells, contact)
                sol = self.agent_step.solve_agents(layer, posed, rows)
            solved = sol.ok.nonzero().flatten()
            if solved.numel():
                use = rows[solved]
                state = dataclasses.replace(state, plans=state.plans.index_put((use,), sol.X[solved]),
                                            inputs=state.inputs.index_put((use,), sol.U[solved]))
                result.fallback = True
                unsafe, sep, req = pair_safety(state.plans.detach(), graph, bounds, self.settings.admm_tol, position)
        result.unsafe_plan = bool(unsafe.any())
        result.pair_separation, result.pair_required = sep, req
        return state

    def _account_risk(self, state: ADMMState, result: StepResult, graph: Graph, ctx: StepContext) -> ADMMState:
        """The pairs' and the obstacle rows' probability bounds of the applied plans
        (``result.pair_risk``, ``result.obstacle_risk``) and, under a mission budget, each agent's
        remaining risk less its charge."""
        bounds = None
        with torch.no_grad():
            result.obstacle_risk = self._obstacle_risk(state.plans.detach(), ctx.convexification)
            if graph.num_edges and state.pvar is not None:
                sep = edge_separations(state.plans.detach(), result.problem.normals.detach(), graph)
                var = state.pvar.detach()[:, :, 0].sum(dim=1)
                bounds = pair_risk_bounds(sep, var, edge_distances(self.settings, graph.edges))
                cov = self._next_position_covariances(ctx.convexification, graph.num_agents)
                # the pair's own direction: tighter where the plans left the normals (both bounds are
                # NaN together, on NaN plans or variances, so fmin never turns an uncounted NaN into a charge)
                if cov is not None:
                    positions = state.plans.detach()[:, 1, self.nominal.position]
                    distance = edge_distances(self.settings, graph.edges)
                    bounds = torch.fmin(bounds, direction_risk_bounds(positions, cov, graph.edges, distance))
                result.pair_risk = pair_matrix(bounds, graph)
        if ctx.eps_edge is None:
            return state
        charges = state.risk_left.new_zeros(graph.num_agents) if bounds is None else \
            agent_charges(bounds, ctx.eps_edge.detach(), graph)
        if result.obstacle_risk is not None:
            charges = charges + result.obstacle_risk
        return dataclasses.replace(state, risk_left=(state.risk_left - charges).clamp_min(RISK_FLOOR))

    def _per_model(self, conv: Any) -> list[tuple[Any, Any]]:
        """The last iterate's convexification ``conv`` with the agents it covers: one pair per model
        of a mixed team (its ``members``), else ``[(conv, slice(None))]``."""
        parts = conv if isinstance(conv, tuple) else (conv,)
        return list(zip(parts, getattr(self.agent_step, "members", [slice(None)])))

    def _next_position_covariances(self, conv: Any, num_agents: int) -> Tensor | None:
        """(K, P, P) every agent's position covariance at tau = 1 from the last iterate's
        convexification (one per model in a mixed team), or ``None`` without margins."""
        models = self._per_model(conv)
        if any(getattr(c, "next_position_cov", None) is None for c, _ in models):
            return None
        P = models[0][0].next_position_cov.shape[-1]
        cov = models[0][0].next_position_cov.new_zeros(num_agents, P, P)
        for c, idx in models:
            cov[idx] = c.next_position_cov.detach()
        return cov

    def _obstacle_risk(self, plans: Tensor, conv: Any) -> Tensor | None:
        """(K,) each agent's summed bound on hitting an obstacle of its rows at the next sample
        (:func:`~.mission_risk.obstacle_risk_bounds`), or ``None`` without obstacle rows or margins.

        Args:
            plans: (K, T+1, n) the applied plans.
            conv: the last iterate's convexification; a mixed team's is one per model.
        """
        models = self._per_model(conv)
        if any(getattr(c, "obstacle_std", None) is None for c, _ in models):
            return None
        pos = self.nominal.position
        risk = plans.new_zeros(plans.shape[0])
        for c, idx in models:
            risk[idx] = obstacle_risk_bounds(plans[idx][..., pos], c.obstacle_normals[..., pos], c.obstacle_bounds,
                                             c.obstacle_std)
        return risk


def mission_obstacle_rows(settings: ControllerSettings) -> int:
    """L, the obstacle rows an agent carries at a horizon step that a mission budget pays for:
    ``obstacle_rows``, or fewer when there are fewer obstacles (0 without obstacles)."""
    obstacles = settings.obstacles
    return min(settings.obstacle_rows, len(obstacles)) if obstacles is not None else 0


def state_slack_max(solution) -> float:
    """The largest state-constraint slack of a :class:`LocalSolution` (0 if none or not computed)."""
    slack = getattr(solution, "state_slack", None)
    if slack is None or not slack.numel():
        return 0.0
    return float(torch.nan_to_num(slack.detach(), nan=0.0).max())
