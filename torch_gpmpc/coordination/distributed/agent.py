"""One agent's side of the distributed ADMM: its state, its GP, its local step and updates.

No communication happens here; the hosting process (:mod:`.agent_process`) moves the
messages. Each agent sees its neighbourhood as a *star graph* over the global agent ids
(only its own edges) and keeps an :class:`~torch_gpmpc.coordination.state.ADMMState`
over all K ids in which only its own row and its neighbours' plan rows are meaningful;
that lets it call the batched per-agent step (:mod:`~torch_gpmpc.coordination.agent_step`)
unchanged, so it computes exactly the in-process ADMM's row k.

Each agent computes ``z_e`` (eq. 28; both ends compute the same mean of the same two
copies) and its *own* ``lambda_{e,k}`` (eq. 29). No agent ever receives another agent's
covariance, GP or data. A lost neighbour is treated as an obstacle following its last
shared plan: its missing copy is replaced by ``[own plan; last shared plan]``.

With ``admm_coupling = planes`` an agent agrees with its neighbours once per step on the step's
variances and collision rows (:meth:`AgentController.step_variances`,
:meth:`AgentController.plane_rows`), sends the T multipliers of its half per iteration, and its
plan after the stop decision; both ends of an edge compute the plane's step from the same two
multipliers, as :mod:`~torch_gpmpc.coordination.planes` does for the whole team.

In a mixed team (config key ``models``) an agent plans with its own model's step, lifted to the
team's state size (:mod:`~torch_gpmpc.coordination.team_step`): the rows it solves are the ones
the in-process :class:`~torch_gpmpc.coordination.team_step.TeamStep` gives its model's step, and
its messages carry the same lifted states.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from typing import Any

import torch
from torch import Tensor

from torch_gpmpc.config.schema import Config
from torch_gpmpc.control.problem import FAILURE_KINDS, LocalSolution
from torch_gpmpc.coordination.consensus import copies_update
from torch_gpmpc.coordination.penalty import starting_penalties
from torch_gpmpc.coordination.bodies import slot_distances
from torch_gpmpc.coordination.agent_step import edge_copies, fall_back_to_previous, slot_risks
from torch_gpmpc.coordination.fallback import fallback_cells, fallback_problem, fallback_seeds, pair_safety
from torch_gpmpc.coordination.controller import make_agent_step
from torch_gpmpc.gp.offset import OffsetCorrected
from torch_gpmpc.gp.online import OnlineLearning, run_models
from torch_gpmpc.coordination.distributed.protocol import DTYPE, TELEMETRY_KEYS, Telemetry, replan_seeds_size
from torch_gpmpc.coordination.graph import graph_from_edges
from torch_gpmpc.coordination.planes import (
    PlaneTerms, SafeIterates, agent_rows, end_multipliers, midpoint_planes, plane_iteration, plane_problem,
    rows_geometry,
)
from torch_gpmpc.coordination.state import ADMMState, StepResult, adapt_state, initial_state
from torch_gpmpc.coordination.steady import repeatable, solve_or_hand_back
from torch_gpmpc.coordination.team_step import TeamStep
from torch_gpmpc.dynamics.team import team_system_from_config

log = logging.getLogger(__name__)


def reference_window(path: Tensor, t: int, horizon: int) -> Tensor:
    """Points ``t..t+T`` of a reference path (R, D), holding its last point; shape (T+1, D)."""
    steps = torch.arange(int(t), int(t) + int(horizon) + 1).clamp(max=path.shape[0] - 1)
    return path[steps]


def rows_like(v: Tensor, num_rows: int) -> Tensor:
    """An uninitialised (num_rows, *v.shape[1:]) tensor whose rows have ``v[0]``'s memory layout.

    The layer returns plans in a column-major layout, and some torch kernels (e.g. the
    norm in :func:`~torch_gpmpc.control.risk.collision_normals`) round differently in the last
    bit for other layouts; keeping the layer's layout keeps the agent's arithmetic
    identical to the in-process backend's.
    """
    inner = v[0]
    order = sorted(range(inner.dim()), key=lambda d: inner.stride(d), reverse=True)
    buf = v.new_empty((num_rows, *[inner.shape[d] for d in order]))
    return buf.permute(0, *[order.index(d) + 1 for d in range(inner.dim())])


def embed_row(sol: LocalSolution, k: int, state: ADMMState) -> LocalSolution:
    """Place a batch-1 solution in row k of a K-row solution (other rows: the known plans,
    ``ok``), so the batched per-agent step functions apply to the agent's view.

    Args:
        sol: the agent's own solution (batch 1).
        k: its id.
        state: its view of the iterate (K rows).
    """
    num_agents = state.plans.shape[0]
    values: dict[str, Any] = {}
    for f in dataclasses.fields(LocalSolution):
        v = getattr(sol, f.name)
        if not isinstance(v, Tensor):
            values[f.name] = v
            continue
        full = rows_like(v, num_agents)
        if f.name == "X":
            full.copy_(state.plans)
        elif f.name == "U":
            full.copy_(state.inputs)
        elif f.name == "ok":
            full.fill_(True)
        else:
            full.zero_()
        full[k] = v[0]
        values[f.name] = full
    return LocalSolution(**values)


class AgentController:
    """One agent's side of Algorithm 1: its state, its GP, its local solve and updates.

    No communication happens here; the hosting process moves the messages.

    Args:
        k: agent id.
        num_agents: K (ids are global).
        cfg: run configuration.
        reference: the agent's own reference path, shape (R, D): the window at step t is
            points ``t..t+T``, holding the last point (as the scenario's reference window).
        gp: the agent's own residual GP (or ``None`` if the method needs none).
    """

    def __init__(self, k: int, num_agents: int, cfg: Config, reference: Tensor, gp=None) -> None:
        self.k, self.num_agents, self.cfg = k, num_agents, cfg
        self.reference = torch.as_tensor(reference, dtype=DTYPE)
        system = team_system_from_config(cfg)
        #: this agent's residual model as the in-process run wraps it (online copy, offset estimate)
        self.gp = None if gp is None else run_models([gp], cfg)[0]
        # indexed by agent id; this process holds only its own GP
        gps = None if self.gp is None else [self.gp if j == k else None for j in range(self.num_agents)]
        step = make_agent_step(cfg, system, gps)
        #: the team's known models (a mixed team's :class:`~torch_gpmpc.dynamics.team.TeamNominal`):
        #: which pairs can both stop at once (the fallback's cells) depends on their models
        self.team_nominal = step.nominal
        #: this agent's per-agent step (the same object the in-process ADMM iterates; in a mixed
        #: team its model's step, as the in-process TeamStep uses for its rows)
        self.local = step.groups[step.team.group_of[k]] if isinstance(step, TeamStep) else step
        #: the online GP's and the offset estimate's updates, as the in-process loop makes them for every agent
        self.learning = OnlineLearning([self.gp], self.local.nominal, cfg.gp_online, cfg.gp_online_max_input_change) \
            if cfg.gp_online or isinstance(self.gp, OffsetCorrected) else None
        self.rho = torch.as_tensor(cfg.rho, dtype=DTYPE)
        #: neighbours agree on separating planes (admm_coupling = planes), not on copies
        self.planes = cfg.admm_coupling == "planes"
        self.state: ADMMState | None = None
        self.known = torch.zeros(num_agents, dtype=torch.bool)
        self.nbrs: list[int] = []
        self.dead: set[int] = set()
        self.graph = graph_from_edges(num_agents, [])
        self.counters = dict.fromkeys(TELEMETRY_KEYS, 0.0)

    # --- step set-up
    def begin_step(self, t: int, x0: Tensor, nbr_ids: list[int], xref: Tensor | None = None) -> list[int]:
        """Take the measurement; return the neighbours new to this agent (plan exchange).

        Args:
            t: step.
            x0: own measured state, shape (D,).
            nbr_ids: ids of agents in communication range.
            xref: this step's reference states (T+1, D) as the closed loop shaped them (routes,
                detours); ``None``: the window of the agent's own reference path.
        """
        cfg, k, K = self.cfg, self.k, self.num_agents
        nominal = self.local.nominal
        self._learn_from_last_step(x0)
        self.x0 = x0
        if xref is None:
            xref = nominal.reference_states(reference_window(self.reference, t, cfg.horizon))
        self.xref = xref[None]
        #: the input this agent applied last (the input-rate term's U_{-1}; None on a cold start)
        self.u_prev = None if self.state is None or self.state.applied is None else self.state.applied[k:k + 1]
        if self.state is None:  # cold start: the plan is to stay (initial_state's rule)
            D, Du = nominal.dim, nominal.input_dim
            own = initial_state(x0[None], cfg.horizon, graph_from_edges(1, []), Du)
            plans = x0.new_zeros(K, cfg.horizon + 1, D)
            inputs = x0.new_zeros(K, cfg.horizon, Du)
            plans[k], inputs[k] = own.plans[0], own.inputs[0]
            self.state = ADMMState(plans, inputs, torch.zeros(0, 2, dtype=torch.long),
                                   x0.new_zeros(0, 2, cfg.horizon + 1, D),
                                   x0.new_zeros(0, 2, 2, cfg.horizon + 1, D))
        else:
            self.state = ADMMState(self.state.plans.clone(), self.state.inputs, self.state.edges,
                                   self.state.z, self.state.lam, self.state.pvar, self.state.rho,
                                   solver_point=self.state.solver_point)
        self.known[k] = True
        self._next_nbrs = sorted(int(j) for j in nbr_ids if int(j) != k)
        return [j for j in self._next_nbrs if j not in self.nbrs]

    def _learn_from_last_step(self, x0: Tensor) -> None:
        """Learn from the transition this agent just made (x0 (D,), its measured state, after the
        input it applied last from the state of the step before) through
        :class:`~torch_gpmpc.gp.online.OnlineLearning`, as the in-process loop does for every agent:
        its online GP (``gp_online``) and its offset estimate."""
        if self.learning is None or self.state is None or self.state.applied is None:
            return
        u = self.local.nominal.project(self.state.applied[self.k:self.k + 1])
        self.learning.observe(self.x0[None], u, x0[None])

    def own_plan(self) -> Tensor:
        """The warm-start plan sent to new neighbours, shape (T+1, D)."""
        return self.state.plans[self.k]

    def set_neighbour_plan(self, j: int, plan: Tensor) -> None:
        """Store neighbour j's plan (T+1, D) (from a plan message or its copy's own half)."""
        self.state.plans[j] = plan
        self.known[j] = True

    def finish_setup(self) -> None:
        """Build the star graph of this step, carry z/lambda over (``adapt_state``)."""
        cfg, k = self.cfg, self.k
        nbrs = []
        for j in self._next_nbrs:
            if j in self.dead and not bool(self.known[j]):
                log.warning("agent %d: agent %d is in range but lost and never shared a plan; ignored", k, j)
                continue
            nbrs.append(j)
        self.nbrs = nbrs
        self.graph = graph_from_edges(self.num_agents, [(k, j) for j in nbrs])
        self.state = adapt_state(self.state, self.graph)
        self.adaptive = cfg.rho_update == "adaptive"
        if self.adaptive:
            self.state = dataclasses.replace(
                self.state, rho=starting_penalties(self.state.rho, self.rho, self.graph.num_edges))
        self.eps_self = slot_risks(self.graph, cfg.eps, cfg.risk_split)[k:k + 1]
        self.layer = self.local.solver(self.graph.num_slots)
        self.frozen = (self.state.plans, self.state.inputs)  # linearization points unless relinearizing
        self.linearization = None
        self.result = StepResult(plans=self.state.plans, inputs=self.state.inputs, state=self.state,
                                 iterations=0, converged=False)
        m = torch.arange(self.graph.num_slots)
        self.slot_e = self.graph.slot_edge[k, m]
        self.slot_a = self.graph.slot_side[k, m]
        self.geometry = self.own_rows = None  # the step's planes (admm_coupling = planes), by take_plane_rows
        self.plane_terms: PlaneTerms | None = None  # the step's kept plane problem (compiled solves), if any
        self._safe = SafeIterates()  # the iterates whose halves held near (planes)
        self.fallback_possible = False  # set by check_safety: whether this step may re-plan (the team knows)
        self.kept_rows: tuple = (None, None)  # its half-space rows (the plans' state slack)

    # --- one ADMM iteration
    @property
    def message_size(self) -> int:
        """Numbers of one iteration's message to a neighbour: the copy ``y_{kj,k}`` (2 (T+1) D) and,
        for the ``sum``/``joint`` margins, the T projected variances along the edge's normal; with
        planes the T offsets alone."""
        return self.local.message_size

    def _assemble(self) -> Any:
        """This agent's local problem at the step's linearization (computed on the first call and
        kept unless relinearizing), with its neighbours' variances as last reported."""
        cfg, k, state = self.cfg, self.k, self.state
        lin_state = state if cfg.relinearize else \
            dataclasses.replace(state, plans=self.frozen[0], inputs=self.frozen[1])
        rho = state.rho[self.graph.slot_edge[k:k + 1]] if self.adaptive and self.graph.num_edges else self.rho
        assembled = self.local.assemble(self.x0[None], self.xref, lin_state, self.graph, rho,
                                        self.eps_self, rows=slice(k, k + 1), linearization=self.linearization,
                                        u_prev=self.u_prev)
        if not cfg.relinearize:
            self.linearization = assembled.linearization
        self.assembled = assembled
        return assembled

    def _solve_local(self, data: Any) -> LocalSolution:
        """Solve this agent's problem ``data`` (batch 1) and account for it; returns the raw solution
        and keeps, as ``self.solution``, its K-row view with a failed solve on the previous plan."""
        k, state = self.k, self.state
        t0 = time.perf_counter()
        sol = self.local.solve(self.layer, data, state.solver_point)
        self.result.solve_time_s += time.perf_counter() - t0
        full = embed_row(sol, k, state)
        self.local.count_failures(full, self.result)
        full = fall_back_to_previous(full, state, self.graph)
        self.result.infeasible_solves += int((full.slack_active | ~full.ok)[k])
        self.result.max_margin = float(self.assembled.max_margin)
        self.solution = full
        return sol

    def solve(self) -> dict[int, Tensor]:
        """Local solve (27) and fallback; returns the message per neighbour: the own copy
        ``y_{kj,k}`` (2, T+1, D), flattened, then the projected variances when exchanged (with
        planes, :meth:`plane_solve`'s offsets)."""
        if self.planes:
            return self.plane_solve()
        assembled = self._assemble()
        self._solve_local(assembled.data)
        full = self.solution
        self.copies = edge_copies(full, self.graph) if self.graph.num_edges else None
        out = {}
        for m, j in enumerate(self.nbrs):
            parts = [self.copies[self.slot_e[m], self.slot_a[m]].flatten()]
            if self.local.exchanges_variance:
                parts.append(assembled.own_variance[0, m])
            out[j] = torch.cat(parts)
        return out

    def update(self, received: dict[int, Tensor | None]) -> tuple[float, float, float, float]:
        """Consensus (28) and own duals (29) from the neighbours' copies.

        Args:
            received: neighbour id -> its message (:meth:`solve`'s format), or ``None`` if lost.

        Returns:
            ``(primal, dual, primal ratio, dual ratio)``: the largest ``||y_{e,k} - z_e||`` over
            own edges, the largest ``rho ||z_e - z_e_prev||``, and the largest of each over its
            tolerance (:mod:`~torch_gpmpc.coordination.penalty`).
        """
        if self.planes:
            return self.plane_update(received)
        k, state, sol = self.k, self.state, self.solution
        plans = sol.X.clone()  # row k: own plan; neighbour rows are overwritten below (same layout)
        inputs = state.inputs.clone()
        inputs[k] = sol.U[k]
        pvar = state.pvar
        if self.graph.num_edges:
            copies = self.copies
            pvar = self._own_variances()
            n_copy = copies[0, 0].numel()
            for m, j in enumerate(self.nbrs):
                e, a = self.slot_e[m], self.slot_a[m]
                msg = received.get(j)
                if msg is None:  # lost neighbour: an obstacle following its last shared plan
                    copy = torch.empty_like(copies[e, a])
                    copy[a], copy[1 - a] = sol.X[k], state.plans[j]
                else:
                    copy = msg[:n_copy].view_as(copies[e, a])
                    plans[j] = copy[1 - a]
                    if pvar is not None and msg.numel() > n_copy:
                        pvar[e, 1 - a] = msg[n_copy:]
                copies[e, 1 - a] = copy
            rho_now = state.rho if self.adaptive else self.rho
            # both ends balance the same residuals (an end's duals have the edge's norm): the same rho_e
            update = copies_update(copies, state.z, state.lam, rho_now, self.cfg, ends=(self.slot_e, self.slot_a))
            z_new, lam, rho_next, res = update.z, update.lam, update.rho, update.residuals
            lam[self.slot_e, 1 - self.slot_a] = 0.0  # the neighbour's dual is the neighbour's
            primal = update.gaps[self.slot_e, self.slot_a].max()
            dual = update.dual.max()
            ratios = (float(res.primal_ratio.max()), float(res.dual_ratio.max()))
        else:
            z_new, lam, rho_next = state.z, state.lam, None
            primal = dual = self.x0.new_zeros(())
            ratios = (0.0, 0.0)
        self.state = ADMMState(plans, inputs, self.graph.edges, z_new, lam, pvar, rho_next,
                               solver_point=sol.solver_point)
        self.result.iterations += 1
        self.counters["iterations_total"] += 1
        return float(primal), float(dual), *ratios

    # --- plane coupling (admm_coupling = planes): the step's rows once, then T offsets per iteration
    def step_variances(self) -> dict[int, Tensor]:
        """Where the margins read the neighbours' variances: this step's own projected variance
        along each edge's normal at tau = 1..T, (T,) per neighbour (sent once per step; the in-process
        :meth:`~torch_gpmpc.coordination.admm.ADMM.iterate` gives every end these at a step's start)."""
        own = self._assemble().own_variance
        return {j: own[0, m] for m, j in enumerate(self.nbrs)}

    def take_step_variances(self, received: dict[int, Tensor | None]) -> None:
        """Every end's variance of this step (``state.pvar``, (E, 2, T)) from :meth:`step_variances`
        and the neighbours' (a lost neighbour keeps its last report)."""
        pvar = self._own_variances()
        for m, j in enumerate(self.nbrs):
            if received.get(j) is not None:
                pvar[self.slot_e[m], 1 - self.slot_a[m]] = received[j]
        self.state = dataclasses.replace(self.state, pvar=pvar)

    def plane_rows(self) -> dict[int, Tensor]:
        """This step's collision rows (the problem assembled with the step's variances), per
        neighbour: the slot's bounds (T,) then its normals (T, D), flattened (sent once per step)."""
        data = self._assemble().data
        return {j: torch.cat([data.bounds[0, m], data.normals[0, m].flatten()]) for m, j in enumerate(self.nbrs)}

    def take_plane_rows(self, received: dict[int, Tensor | None]) -> None:
        """The step's planes from both ends' rows (a lost neighbour's: this agent's, mirrored): their
        :class:`~torch_gpmpc.coordination.planes.PlaneGeometry` and the starting offsets halfway
        between the linearization plans."""
        data, graph, k, T = self.assembled.data, self.graph, self.k, self.cfg.horizon
        if not graph.num_edges:
            return
        normals = data.normals.new_zeros(self.num_agents, *data.normals.shape[1:])
        bounds = data.bounds.new_zeros(self.num_agents, *data.bounds.shape[1:])
        normals[k], bounds[k] = data.normals[0], data.bounds[0]
        for m, j in enumerate(self.nbrs):
            slot = int(torch.nonzero(graph.active[j] & (graph.slot_nbr[j] == k))[0])
            msg = received.get(j)
            if msg is None:
                bounds[j, slot], normals[j, slot] = data.bounds[0, m], -data.normals[0, m]
            else:
                bounds[j, slot], normals[j, slot] = msg[:T], msg[T:].view_as(normals[j, slot])
        self.geometry = rows_geometry(normals, bounds, graph)
        self.own_rows = agent_rows(self.geometry, k)
        planes = midpoint_planes(self.geometry, self.frozen[0], graph, self.local.nominal.position)
        self.state = dataclasses.replace(self.state, planes=planes, plane_gradient=None, plane_rho=None)

    def plane_solve(self) -> dict[int, Tensor]:
        """The local solve on this agent's plane halves; returns its multiplier of each half (T,) per
        neighbour (:func:`~torch_gpmpc.coordination.planes.end_multipliers`).

        The step's rows are fixed, so after its first solve only the copies' targets change: later
        solves write them into the kept problem and solve it warm (compiled, as the
        in-process :class:`~torch_gpmpc.coordination.planes.PlaneIterations` do; the same bits), and
        anything unusual goes through the torch path."""
        state = self.state
        if not self.graph.num_edges:
            self._solve_local(self._assemble().data)
            return {}
        raw = self._solve_kept(state.planes) if self.plane_terms is not None else None
        if raw is None:
            # the step's rows, as plane_rows assembled them (their weights are plane_problem's own)
            posed = plane_problem(self.assembled.data, self.own_rows, state.planes)
            failed = self.result.failed_solves
            raw = self._solve_local(posed)
            if self.plane_terms is None and self.result.failed_solves == failed and self.cfg.admm_compiled \
                    and repeatable(self.layer, (state.plans, state.planes)):
                kept = self.layer.repeated(posed)
                self.plane_terms = None if kept is None else PlaneTerms(self.own_rows, kept)
                self.kept_rows = (posed.halfspace_normals, posed.halfspace_bounds)  # for the plans' state slack
        sol, k = self.solution, self.k
        self.multipliers = end_multipliers(None if sol.multipliers is None else sol.multipliers[k:k + 1],
                                           sol.Y[k:k + 1], sol.ok[k:k + 1], self.own_rows, state.planes)
        return {j: self.multipliers[self.slot_e[m], self.slot_a[m]] for m, j in enumerate(self.nbrs)}

    def _solve_kept(self, planes: Tensor) -> LocalSolution | None:
        """The kept plane problem solved at new offsets ``planes`` (E, T) (compiled), accounted as
        :meth:`_solve_local` accounts a solve; ``None`` hands the solve to the torch path."""
        k, state, kept = self.k, self.state, self.plane_terms.solve
        t0 = time.perf_counter()
        self.plane_terms.write(planes)
        sol = solve_or_hand_back(kept, state.solver_point)
        self.result.solve_time_s += time.perf_counter() - t0
        if sol is None:
            return None
        raw = LocalSolution(X=sol.X, U=sol.U, Y=sol.Y, slack=sol.slack,
                            slack_active=torch.tensor([sol.slack_active > 0]), ok=torch.ones(1, dtype=torch.bool),
                            cost=sol.X.new_full((1,), float("nan")),  # not computed here; nothing reads it
                            state_slack=self.layer.constraints.state_violation(sol.X, *self.kept_rows),
                            solver_point=sol.point, multipliers=sol.multipliers)
        self.solution = embed_row(raw, k, state)
        self.result.infeasible_solves += int(sol.slack_active > 0)
        return raw

    def plane_update(self, received: dict[int, Tensor | None]) -> tuple[float, float, float, float]:
        """Each own edge's plane step from both ends' multipliers (a lost neighbour's plane stays where
        it is: its last shared plan keeps its half); both ends compute the same.

        Returns:
            ``(primal, dual, primal ratio, dual ratio)`` over this agent's edges (both ends), as
            :func:`~torch_gpmpc.coordination.planes.plane_residuals` measures them.
        """
        k, state, sol = self.k, self.state, self.solution
        inputs = state.inputs.clone()
        inputs[k] = sol.U[k]
        rho_next, planes, gradient = state.plane_rho, state.planes, state.plane_gradient
        out = (0.0, 0.0, 0.0, 0.0)
        if self.graph.num_edges:
            mu = self.multipliers.clone()
            for m, j in enumerate(self.nbrs):
                e, a = self.slot_e[m], self.slot_a[m]
                msg = received.get(j)
                mu[e, 1 - a] = msg if msg is not None else mu[e, a]  # a lost neighbour's plane stays
            step, res, _ = plane_iteration(mu, sol.X[k:k + 1], self.own_rows, state.planes, state.plane_rho,
                                           state.plane_gradient, self.rho, self.cfg)
            out = (float(res.primal.max()), float(res.dual.max()), float(res.primal_ratio.max()),
                   float(res.dual_ratio.max()))
            planes, gradient, rho_next = step.planes, step.gradient, step.rho
        self.state = dataclasses.replace(state, plans=sol.X.clone(), inputs=inputs, solver_point=sol.solver_point,
                                         planes=planes, plane_gradient=gradient, plane_rho=rho_next)
        self.result.iterations += 1
        self.counters["iterations_total"] += 1
        return out

    def keep_safe_plan(self, decision: Tensor) -> None:
        """With planes, the world's decision on the iteration :meth:`plane_update` just ran: note this
        agent's plan under the team's safety level (its dual residual, the largest over the team), and
        at the stop apply the plan :class:`~torch_gpmpc.coordination.planes.SafeIterates` picks (the
        in-process :meth:`~torch_gpmpc.coordination.admm.ADMM.solve_step`'s rule)."""
        if not self.planes or not self.graph.num_edges:
            return
        k = self.k
        self._safe.record(float(decision[1]), self.state.plans[k].clone(), self.state.inputs[k].clone())
        best = self._safe.best()
        if float(decision[2]) > 0.5 and best is not None:
            plans, inputs = self.state.plans.clone(), self.state.inputs.clone()
            plans[k], inputs[k] = best
            self.state = dataclasses.replace(self.state, plans=plans, inputs=inputs)

    def take_final_plans(self, received: dict[int, Tensor | None]) -> None:
        """The neighbours' plans (T+1, D): with planes at the step's last iteration (what the safety
        check reads), and after a step that may have re-planned, the plans they apply (what the next
        step's warm start holds, as in process); a lost neighbour keeps its last."""
        plans = self.state.plans.clone()
        for j, plan in received.items():
            if plan is not None:
                plans[j] = plan.view_as(plans[j])
        self.state = dataclasses.replace(self.state, plans=plans)

    def residual_message(self, residuals: tuple[float, float, float, float]) -> Tensor:
        """The residual message (:func:`~.protocol.residual_size` numbers) of the iteration
        :meth:`update` just ran: its ``residuals``."""
        return torch.tensor(residuals, dtype=DTYPE)

    def _own_variances(self) -> Tensor | None:
        """``state.pvar`` with this agent's own ends set from its latest assembly."""
        own = self.assembled.own_variance
        if own is None:
            return self.state.pvar
        pvar = self.state.pvar
        if pvar is None:
            pvar = own.new_full((self.graph.num_edges, 2, own.shape[-1]), float("nan"))
        pvar = pvar.clone()
        for m in range(len(self.nbrs)):
            pvar[self.slot_e[m], self.slot_a[m]] = own[0, m]
        return pvar

    def check_safety(self, settle: bool) -> None:
        """Judge the own plan at tau = 1 against the neighbours' latest plans; with ``settle`` (the
        world's word that the step stopped on plans not known to be safe) also prepare
        :meth:`replan_seeds`, the agent's part of the team's decision who re-plans (the in-process
        :class:`~torch_gpmpc.coordination.admm.ADMM`'s rule, :func:`~.fallback.fallback_agents`;
        here each agent sees only its own pairs and its neighbours' plans before their own
        fallback; their re-planned plans arrive by :meth:`take_applied_plans`)."""
        self.fallback_possible = False
        self._seeds = torch.zeros(replan_seeds_size(self.num_agents), dtype=DTYPE)
        self._fallback_cells = None
        if not self.graph.num_edges or not self.result.iterations:
            return
        self.fallback_possible = settle
        k, state, tol = self.k, self.state, self.cfg.admm_tol
        position = self.local.nominal.position
        bounds = self.assembled.data.bounds[:, :, 0].detach()
        self._judged_bounds = bounds.new_full((self.num_agents, bounds.shape[1]), float("-inf"))
        self._judged_bounds[k] = bounds[0]
        unsafe, _, _ = pair_safety(state.plans, self.graph, self._judged_bounds, tol, position)
        self.counters["unsafe_plan"] = float(bool(unsafe[k]))
        if not settle:
            return
        cells = fallback_cells(self.team_nominal.momentum(self.num_agents), self.graph, self.cfg.safety_fallback)
        seeds, exits = fallback_seeds(state.plans, self.graph, self._judged_bounds, tol, position, cells)
        self._fallback_cells = cells
        self._seeds[0] = float(seeds[k])
        self._seeds[1 + self.graph.slot_nbr[k][exits[k]]] = 1.0

    def replan_seeds(self) -> Tensor:
        """The agent's fallback message to the world, prepared by :meth:`check_safety`
        (:func:`~torch_gpmpc.coordination.distributed.protocol.replan_seeds_size` numbers)."""
        return self._seeds

    def replan(self, decided: bool) -> None:
        """Re-plan (inside its buffered Voronoi cell towards its cell pairs, against its other
        neighbours' plans as fixed obstacles) when the team ``decided`` it must."""
        if not decided or self._fallback_cells is None:
            return
        k, state = self.k, self.state
        position = self.local.nominal.position
        contact = slot_distances(self.local.settings, torch.tensor([k]), self.graph.slot_nbr[k:k + 1])
        data = fallback_problem(self.assembled.data, state.plans[k:k + 1], state.plans[self.graph.slot_nbr[k:k + 1]],
                                position, self._fallback_cells[k:k + 1], contact)
        sol = self.local.solve(self.layer, data)
        if bool(sol.ok[0]):
            plans, inputs = state.plans.clone(), state.inputs.clone()
            plans[k], inputs[k] = sol.X[0], sol.U[0]
            self.state = dataclasses.replace(state, plans=plans, inputs=inputs)
            self.counters["fallback"] = 1.0
            unsafe, _, _ = pair_safety(self.state.plans, self.graph, self._judged_bounds, self.cfg.admm_tol, position)
            self.counters["unsafe_plan"] = float(bool(unsafe[k]))

    def take_applied_plans(self, received: dict[int, Tensor | None]) -> None:
        """After a step that may have re-planned (:attr:`fallback_possible`), the plans the neighbours
        apply: the next step's warm start holds them, as the in-process one does, and the own plan is
        judged against them."""
        self.take_final_plans(received)
        unsafe, _, _ = pair_safety(self.state.plans, self.graph, self._judged_bounds, self.cfg.admm_tol,
                                   self.local.nominal.position)
        self.counters["unsafe_plan"] = float(bool(unsafe[self.k]))

    def end_step(self) -> Telemetry:
        """The step's telemetry (input, plan, counters); shifts the state for the next warm start."""
        k, res, c = self.k, self.result, self.counters
        slack = self.solution.slack[k] if hasattr(self, "solution") else torch.zeros(0)
        c["slack_max"] = float(slack.max()) if slack.numel() else 0.0
        state_slack = getattr(self.solution, "state_slack", None) if hasattr(self, "solution") else None
        c["state_slack_max"] = 0.0 if state_slack is None else float(torch.nan_to_num(state_slack[k]).max())
        c["infeasible"], c["failed"] = res.infeasible_solves, res.failed_solves
        for kind in FAILURE_KINDS:
            c[f"failed_{kind}"] = res.failed_by_kind.get(kind, 0)
        c["solve_time"], c["max_margin"] = res.solve_time_s, res.max_margin
        record = Telemetry(self.state.inputs[k, 0].clone(), self.state.plans[k].clone(),
                           self.state.inputs[k].clone(), dict(c))
        c["fallback"] = c["unsafe_plan"] = 0.0  # per-step flags
        self.state = self.state.shifted()
        return record
