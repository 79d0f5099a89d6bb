"""The per-agent part of one ADMM iteration, shared by the in-process ADMM and a
distributed agent: assemble the local problems, solve them with failures isolated, fall
back to the previous plan where a solve failed, and form the copies sent to neighbours.

Every function works on a batch of agents (rows of the graph); a distributed agent
passes its own row, the in-process :class:`~torch_gpmpc.coordination.admm.ADMM` all rows,
so both compute the same thing.
"""

from __future__ import annotations

import dataclasses
import logging
import warnings
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor, nn

from torch_gpmpc.config.model_spec import ModelSpec
from torch_gpmpc.config.schema import Config
from torch_gpmpc.config.settings import ControllerSettings
from torch_gpmpc.control.cost import QuadraticCost
from torch_gpmpc.control.linearize import linearize_plan
from torch_gpmpc.control.obstacle_rows import obstacle_rows
from torch_gpmpc.control.problem import (
    FAIL_EXCEPTION, FAIL_INACCURATE, FAIL_NONFINITE, FAILURE_KINDS, LocalProblemData, LocalSolution, select_problems,
)
from torch_gpmpc.control.risk import (
    chance_quantile, collision_normals, lqr_gain, pair_margins, pair_risks, projected_variances, safe_sqrt,
    state_covariances,
)
from torch_gpmpc.control.constraints import LocalConstraints
from torch_gpmpc.control.solvers import make_local_solver
from torch_gpmpc.coordination.bodies import body_radii, slot_distances
from torch_gpmpc.coordination.consensus import slot_consensus
from torch_gpmpc.coordination.graph import Graph
from torch_gpmpc.coordination.rescue import SolveRescue
from torch_gpmpc.coordination.state import ADMMState, IterationStats, StepResult
from torch_gpmpc.dynamics.methods import Method
from torch_gpmpc.dynamics.systems import NominalModel, VortexWind
from torch_gpmpc.errors import GpmpcError

log = logging.getLogger(__name__)


def slot_risks(graph: Graph, eps: float | Tensor, risk_split: float | Tensor) -> Tensor:
    """Each agent's own risk ``eps_k`` on each of its edges (eq. 21).

    Args:
        graph: the communication graph.
        eps: total risk per pair.
        risk_split: share of the lower-indexed agent; a scalar or a (K, K) tensor whose
            entry ``[lo, hi]`` is used for edge ``(lo, hi)``.

    Returns:
        (K, M) risk of agent k on slot m (padding slots get ``eps / 2``).
    """
    split = torch.as_tensor(risk_split, dtype=torch.float64)
    if split.dim() == 2:
        lo, hi = graph.edges[graph.slot_edge, 0], graph.edges[graph.slot_edge, 1]
        split = split[lo, hi] if graph.num_edges else split.new_full(graph.active.shape, 0.5)
    eps_lo, eps_hi = pair_risks(torch.as_tensor(eps, dtype=split.dtype), split)
    eps_lo = eps_lo.expand(graph.active.shape)
    eps_hi = eps_hi.expand(graph.active.shape)
    return torch.where(graph.slot_side == 0, eps_lo, eps_hi)


def _wrapped_interrupt(exc: BaseException) -> BaseException | None:
    """The KeyboardInterrupt (or other non-``Exception``) in ``exc``'s cause/context chain, if any.

    C extensions can turn a signal that arrives while they call back into Python into an
    ordinary error (CPython: "SystemError: ... returned a result with an exception set").
    """
    seen: set[int] = set()
    while exc is not None and id(exc) not in seen:
        seen.add(id(exc))
        if not isinstance(exc, Exception):
            return exc
        exc = exc.__cause__ or exc.__context__
    return None


@dataclass
class Assembled:
    """The local problems of a batch of agents and what the iteration reports about them.

    Attributes:
        data: the problems (batch B).
        max_margin: largest chance margin of an active row, 0-d.
        own_variance: (B, M, T) each agent's variance along each slot's normal at tau = 1..T
            (what it sends its neighbours for ``sum``/``joint`` margins); ``None`` without margins.
        linearization: the :class:`Convexification` used (reused by the caller while the
            linearization points stay fixed within a step).
    """

    data: LocalProblemData
    max_margin: Tensor
    own_variance: Tensor | None = None
    linearization: Any = None


@dataclass
class Convexification:
    """What the linearization points of a step fix in the local problems (computed once per step
    when they stay fixed: the GP linearization, covariance propagation and normals were most of
    an ADMM iteration's assembly).

    Attributes:
        lin: the dynamics linearization (:func:`~torch_gpmpc.control.linearize.linearize_plan`).
        normals: collision normals, shape (B, M, T, D).
        own_var: each agent's projected variance along each slot's normal, (B, M, T), or ``None``.
        obstacle_normals, obstacle_bounds: the agent's obstacle rows ``n^T x_tau >= b`` without
            chance margins, shapes (B, L, T, D) and (B, L, T), or ``None`` (no obstacles).
        obstacle_std: the agent's standard deviation along each obstacle row, (B, L, T), or
            ``None`` (no obstacles, or a method without margins).
        next_position_cov: the agent's position covariance at tau = 1, (B, P, P), or ``None``
            (a method without margins): what bounds a pair's risk along any direction.
    """

    lin: Any
    normals: Tensor
    own_var: Tensor | None = None
    obstacle_normals: Tensor | None = None
    obstacle_bounds: Tensor | None = None
    obstacle_std: Tensor | None = None
    next_position_cov: Tensor | None = None

    def obstacle_bounds_with_margins(self, eps: float | Tensor) -> Tensor | None:
        """The obstacle rows' bounds with the chance margin ``Phi^{-1}(1 - eps) std``.

        Args:
            eps: the risk of one row: a number, or (B,) one per agent (a mission budget's).

        Returns:
            (B, L, T) bounds, or ``None`` without obstacles.
        """
        if self.obstacle_bounds is None or self.obstacle_std is None:
            return self.obstacle_bounds
        quantile = chance_quantile(torch.as_tensor(eps, dtype=self.obstacle_bounds.dtype))
        quantile = quantile[:, None, None] if quantile.dim() else quantile
        return self.obstacle_bounds + quantile * self.obstacle_std


def exchanges_variance(settings: ControllerSettings, method: str | Method | None = None) -> bool:
    """Whether the agents send their T projected variances with every copy (the ``sum`` and
    ``joint`` pair margins of chance-constrained methods; ``method`` defaults to ``settings.method``)."""
    return Method.parse(method or settings.method).chance and settings.pair_margin != "own"


def message_size(settings: ControllerSettings, state_dim: int, method: str | Method | None = None) -> int:
    """Numbers one agent sends one neighbour per ADMM iteration: its copy ``y_{e,k}``
    (``2 (T+1) n``, n the model's state dimension) and, when exchanged, its T projected variances;
    with ``admm_coupling = planes`` its T plane offsets alone (the variances and the rows are agreed
    once per step)."""
    T = settings.horizon
    if settings.admm_coupling == "planes":
        return T
    return 2 * (T + 1) * state_dim + (T if exchanges_variance(settings, method) else 0)


def as_settings(settings: ControllerSettings | Config) -> ControllerSettings:
    """The controller settings of a run configuration (settings pass through)."""
    return settings.controller_settings() if isinstance(settings, Config) else settings


def cost_weights(cost: QuadraticCost | list[QuadraticCost] | None, settings: ControllerSettings,
                 nominal: NominalModel) -> tuple[Tensor, Tensor, Tensor, Tensor] | None:
    """The tracking cost's weights ``(Q, R, P, u_ref)`` with a leading agent axis (1 row for a cost shared
    by all, else one per agent id), or ``None`` for the paper's cost (no cost stated, ``terminal_cost =
    stage``, no rows that hold the last input): see :class:`LocalStep`'s ``cost``. A cost without P gets
    the terminal weight of ``settings.terminal_cost``; the default cost is :func:`default_state_weights`'s
    Q and ``R = alpha I``.

    Raises:
        GpmpcError: a cost given both ways, not a :class:`QuadraticCost`, or weights that do not fit the model.
    """
    table = settings.cost
    if cost is not None and table is not None:
        raise GpmpcError("the cost is given twice, as the settings' cost table and as cost=QuadraticCost(...); "
                         "keep one")
    if cost is None and table is None:
        state_weights = default_state_weights(nominal)
        if state_weights is None and settings.terminal_cost == "stage":
            return None
        costs = [QuadraticCost(Q=1.0 if state_weights is None else state_weights, R=settings.alpha)]
        where = ["the default cost (Q = I, R = alpha I): " if state_weights is None else
                 "the default cost (Q = I but 0 on the rows that hold the last input, R = alpha I): "]
    elif cost is None:
        costs = [QuadraticCost(Q=table.Q, R=table.R, P=table.P, u_ref=table.u_ref)]
        where = ["config key 'cost', entry "]
    else:
        costs = [cost] if isinstance(cost, QuadraticCost) else list(cost) if isinstance(cost, (list, tuple)) else None
        if costs is None or not costs or not all(isinstance(c, QuadraticCost) for c in costs):
            raise GpmpcError(f"cost must be a QuadraticCost or a list of them (one per agent), got "
                             f"{type(cost).__name__}; a table {{Q, R, P, u_ref}} goes in the settings' cost")
        where = ["QuadraticCost."] if len(costs) == 1 else [f"the cost of agent {k}: QuadraticCost."
                                                              for k in range(len(costs))]
    resolved = []
    for c, at in zip(costs, where):
        if c.P is None and settings.terminal_cost == "stage":
            c = dataclasses.replace(c, P=c.Q)
        resolved.append(c.resolve(nominal, at))
    return tuple(torch.stack(ws) for ws in zip(*resolved))  # type: ignore[return-value]


def default_state_weights(nominal: NominalModel) -> Tensor | None:
    """The default cost's diagonal Q, (n,): 1 on every state but the rows that hold the last input
    (:attr:`~torch_gpmpc.config.model_spec.ModelSpec.input_memory`: the input cost weighs them already);
    ``None`` for a model without such rows (Q = I). A mixed team's models each have their own step,
    so each gets its own."""
    rows = nominal.input_memory_rows
    if not rows:
        return None
    q = torch.ones(nominal.dim, dtype=torch.float64)
    q[rows] = 0.0
    return q


def cost_version(cost: QuadraticCost | list[QuadraticCost] | None) -> tuple | None:
    """What identifies a stated cost's current values: its tensors' identities and versions (an in-place
    change is seen), or ``None`` when gradients must reach them (resolve anew, into a new graph)."""
    costs = [] if cost is None else [cost] if isinstance(cost, QuadraticCost) else list(cost)
    tensors = [v for c in costs if isinstance(c, QuadraticCost) for v in (c.Q, c.R, c.P, c.u_ref)
               if isinstance(v, Tensor)]
    if torch.is_grad_enabled() and any(t.requires_grad for t in tensors):
        return None
    return tuple(id(c) for c in costs) + tuple((id(t), t._version) for t in tensors)


def as_nominal(model: NominalModel | ModelSpec) -> NominalModel:
    """The tensor form of an agent model (a :class:`NominalModel` passes through)."""
    return model if isinstance(model, NominalModel) else NominalModel(model)


def on_positions(normals_p: Tensor, position: list[int], state_dim: int) -> Tensor:
    """Row normals on the positions (..., P) as normals on the state (..., n): the rows act on the
    position states only."""
    normals = normals_p.new_zeros(*normals_p.shape[:-1], state_dim)
    normals[..., position] = normals_p
    return normals


def select_rows(items: list, rows: slice | Tensor) -> list:
    """The entries ``rows`` (a slice, or an int64 tensor of agent ids) of a per-agent list."""
    return items[rows] if isinstance(rows, slice) else [items[int(k)] for k in rows]


def _reported_variances(state: ADMMState, slot_edge: Tensor, side: Tensor, own: Tensor) -> Tensor:
    """The neighbours' last reported projected variances per slot (B, M, T); the agent's own
    where none has been reported yet (a symmetric first guess)."""
    if state.pvar is None or state.pvar.shape[0] == 0:
        return own
    reported = state.pvar[slot_edge, 1 - side]
    return torch.where(torch.isnan(reported), own, reported)


def edge_variances(own_variance: Tensor, graph: Graph, previous: Tensor | None) -> Tensor:
    """Every edge end's reported projected variance (E, 2, T) after an iteration in which all
    agents of ``graph`` computed ``own_variance`` (K, M, T)."""
    T = own_variance.shape[-1]
    out = own_variance.new_full((graph.num_edges, 2, T), float("nan")) if previous is None else previous.clone()
    k_idx, m_idx = torch.nonzero(graph.active, as_tuple=True)
    return out.index_put((graph.slot_edge[k_idx, m_idx], graph.slot_side[k_idx, m_idx]), own_variance[k_idx, m_idx])


class LocalStep:
    """What each agent does at one ADMM iteration, for a batch of agents: the per-agent step.

    Everything model-dependent (state and input sizes, input bound, the ``auto`` uncertainty
    mode, the message size) comes from ``model``; everything else from ``settings``. The
    coordinator (:class:`~torch_gpmpc.coordination.admm.ADMM`, a distributed agent, tuning,
    the centralized planner) is handed this object. Its solvers belong to it.

    Args:
        settings: the controller settings (a run :class:`~torch_gpmpc.config.schema.Config` is
            converted with ``controller_settings()``).
        model: the known model f (a :class:`ModelSpec` is converted).
        method: the controller method (name or :class:`~torch_gpmpc.dynamics.methods.Method`;
            default ``settings.method``).
        wind: the known wind (``nonlinear`` methods), else ``None``.
        gps: residual models indexed by agent id (``gp`` and chance methods), else ``None``;
            a distributed agent holds ``None`` for every agent but itself.
        cost: the tracking cost: one :class:`~torch_gpmpc.control.cost.QuadraticCost` for every agent,
            a list indexed by agent id, or ``None``: the settings' ``cost`` table, else Q = I (0 on rows that hold the last input),
            R = alpha I, with the terminal weight of ``settings.terminal_cost`` (``lqr``: the model's
            LQR cost-to-go; ``stage``: P = Q, the paper's cost, solved as ``||X - Xref||^2 + alpha ||U||^2``).

    Examples:
        >>> import torch
        >>> from torch_gpmpc import ControllerSettings, LocalStep, ModelSpec
        >>> step = LocalStep(ControllerSettings(method="nominal"), ModelSpec.double_integrator(dim=3))
        >>> step.message_size, step.uncertainty   # T plane offsets' multipliers per neighbour and iteration
        (13, 'propagated')
        >>> step.with_settings(step.settings.replace(admm_coupling="copies")).message_size  # 2 (T+1) n: copies
        168
    """

    def __init__(self, settings: ControllerSettings | Config, model: NominalModel | ModelSpec,
                 method: str | Method | None = None, wind: VortexWind | None = None,
                 gps: list | None = None, cost: QuadraticCost | list[QuadraticCost] | None = None) -> None:
        self.settings = as_settings(settings)
        self.method = Method.parse(method or self.settings.method)
        self.nominal = as_nominal(model)
        self.wind = wind
        self.gps = gps
        self.cost = cost
        if cost is not None and self.settings.alpha != ControllerSettings.alpha \
                and self.settings.uncertainty != "feedback":
            warnings.warn("controller setting 'alpha' is ignored under cost=QuadraticCost(...): the cost's R "
                          "replaces alpha I", UserWarning, stacklevel=3)
        #: the cost's weights ``(Q, R, P, u_ref)``, one row per agent id (or one row for all), or
        #: ``None``: the default ``||X - Xref||^2 + alpha ||U||^2`` (refreshed by :meth:`cost_rows` when the
        #: cost's tensors change in place or need gradients)
        self.cost_weights = cost_weights(cost, self.settings, self.nominal)
        self._cost_key = cost_version(cost)
        self._cost_rows: dict = {}  # cost_rows' tensors of the last agents asked for
        #: the covariance model in use (``settings.uncertainty`` with ``auto`` resolved for the model)
        self.uncertainty = self.settings.uncertainty_for(self.nominal.spec)
        #: input bounds and soft state constraints (the model's, and the settings' workspace)
        self.constraints = LocalConstraints.of(self.nominal.spec, workspace=self.settings.workspace)
        #: obstacle rows per agent (L; 0 without obstacles)
        obstacles = self.settings.obstacles
        self.num_obstacle_rows = self.settings.obstacle_rows if obstacles is not None and len(obstacles) else 0
        #: B K of the ancillary LQR feedback (``uncertainty = feedback``), else None
        self.feedback = None
        if self.uncertainty == "feedback":
            A, B = self.nominal.A(dtype=torch.float64), self.nominal.B(dtype=torch.float64)
            self.feedback = B @ lqr_gain(A, B, 1.0, max(self.settings.alpha, 1e-9))
        self._solvers: dict[int, nn.Module] = {}
        #: the rescue of the fast solver's inaccurate solves (:meth:`rescue_inaccurate`)
        self.rescue = SolveRescue(self.build_solver)
        #: failure kinds already warned about (one warning per kind per run)
        self._warned: set[str] = set()

    def cost_rows(self, agent_ids: Tensor, like: Tensor) -> dict[str, Tensor]:
        """The :class:`~torch_gpmpc.control.problem.LocalProblemData` cost fields of agents ``agent_ids``
        (int64 (B,)) in ``like``'s dtype and device; empty for the default cost."""
        if self.cost_weights is None:
            return {}
        version = cost_version(self.cost)
        if version is None or version != self._cost_key:  # changed in place, or gradients wanted: resolve anew
            self.cost_weights, self._cost_key, self._cost_rows = cost_weights(self.cost, self.settings,
                                                                              self.nominal), version, {}
        # the same tensor objects for the same agents: the solver's caches key on them
        key = (tuple(agent_ids.tolist()), like.dtype, like.device)
        if key not in self._cost_rows or version is None:
            B = agent_ids.shape[0]
            rows = [w.expand(B, *w.shape[1:]) if w.shape[0] == 1 else w[agent_ids] for w in self.cost_weights]
            self._cost_rows = {key: dict(zip(("cost_Q", "cost_R", "cost_P", "u_ref"), (w.to(like) for w in rows)))}
        return self._cost_rows[key]

    def with_settings(self, settings: ControllerSettings | Config) -> "LocalStep":
        """The same agents (model, method, wind, GPs) under other settings."""
        return LocalStep(settings, self.nominal, self.method, self.wind, self.gps, self.cost)

    def solver(self, num_slots: int) -> nn.Module:
        """This step's batched local solver for ``num_slots`` neighbour slots (built once per size)."""
        if num_slots not in self._solvers:
            self._solvers[num_slots] = self.build_solver(num_slots, self.settings.solver)
        return self._solvers[num_slots]

    def build_solver(self, num_slots: int, solver: str, **stops: Any) -> nn.Module:
        """A new batched local solver ``solver`` (``fast``, ``clarabel``, ``reference`` or ``direct``) for
        ``num_slots`` neighbour slots, with this step's model, weights and constraints; ``stops``:
        the fast solver's ``tol`` and ``max_iter`` (:func:`~torch_gpmpc.control.solvers.make_local_solver`)."""
        s = self.settings
        return make_local_solver(
            horizon=s.horizon, dim=self.nominal.dim, num_neighbors=num_slots, nominal=self.nominal,
            u_max=None, alpha=s.alpha, slack_penalty=s.slack_penalty, solver=solver,
            constraints=self.constraints, num_halfspaces=self.num_obstacle_rows,
            input_rate_weight=s.input_rate_weight, warm_start=s.solver_warm, **stops,
        )

    @property
    def exchanges_variance(self) -> bool:
        """Whether neighbours exchange projected variances (T numbers per edge and iteration)."""
        return exchanges_variance(self.settings, self.method)

    @property
    def message_size(self) -> int:
        """Numbers one agent sends one neighbour per ADMM iteration (:func:`message_size`)."""
        return message_size(self.settings, self.nominal.dim, self.method)

    def assemble(
        self, x0: Tensor, xref: Tensor, state: ADMMState, graph: Graph, rho: Tensor, eps_self: Tensor,
        rows: slice | Tensor = slice(None), linearization: Any = None, eps_nbr: Tensor | None = None,
        u_prev: Tensor | None = None, eps_obstacle: Tensor | None = None,
    ) -> Assembled:
        """Linearize around the current plans and assemble the local problems of agents ``rows``.

        The collision rows carry the pair margins of ``settings.pair_margin``; the neighbour's
        projected variance is the one it last reported (``state.pvar``), or the agent's own
        before the first report.

        Args:
            x0, xref: measured states and reference windows of the selected agents,
                shapes (B, D) and (B, T+1, D).
            state: current iterate; ``plans`` must hold the selected agents and their neighbours.
            graph: communication graph.
            rho: ADMM penalty.
            eps_self: (B, M) own risk per slot of the selected agents.
            rows: which agents (B of them): all by default; an agent process passes its own row, a
                mixed team's step (:class:`~torch_gpmpc.coordination.team_step.TeamStep`) the agents
                of one model (an int64 tensor of ids).
                ``self.gps`` is indexed by agent id (an agent process may hold ``None`` for others).
            linearization: a previous call's ``Assembled.linearization`` (a :class:`Convexification`)
                at the same plans, inputs and rows, or a dynamics linearization alone; ``None``:
                compute it.
            eps_nbr: (B, M) the neighbour's risk per slot (default ``settings.eps - eps_self``:
                the pair's risk is ``eps``; a mission budget gives both ends their own).
            u_prev: (B, m) the selected agents' inputs applied at the previous step (the
                input-rate term's ``U_{-1}``; ``None``: 0).
            eps_obstacle: (B,) the risk of one obstacle row of each selected agent (a mission
                budget's; default ``settings.obstacle_eps``).
        """
        cfg = self.settings
        conv = linearization if isinstance(linearization, Convexification) else \
            self._convexify(state, graph, rows, linearization)
        lin, normals, own_var = conv.lin, conv.normals, conv.own_var
        slot_edge, side, active = graph.slot_edge[rows], graph.slot_side[rows], graph.active[rows]
        agent_ids = torch.arange(graph.num_agents)[rows]
        if self.method.chance:
            nbr_var = _reported_variances(state, slot_edge, side, own_var)
            margins = pair_margins(cfg.pair_margin, own_var, nbr_var, eps_self,
                                   cfg.eps - eps_self if eps_nbr is None else eps_nbr)
        else:
            margins = normals.new_zeros(normals.shape[:3])
        slots = slot_consensus(state.z, state.lam, graph, rows)
        data = LocalProblemData(
            x0=x0, xref=xref, dyn_A=lin.dyn_A, dyn_c=lin.dyn_c, dyn_B=lin.dyn_B, normals=normals,
            bounds=slot_distances(cfg, agent_ids, graph.slot_nbr[rows]) + margins, active=active, rho=rho,
            z_own=slots.z_own, z_nbr=slots.z_nbr, lam_own=slots.lam_own, lam_nbr=slots.lam_nbr,
            halfspace_normals=conv.obstacle_normals,
            halfspace_bounds=conv.obstacle_bounds_with_margins(cfg.obstacle_eps if eps_obstacle is None else eps_obstacle),
            u_prev=u_prev, **self.cost_rows(agent_ids, x0),
        )
        max_margin = margins[active].max() if bool(active.any()) else margins.new_zeros(())
        return Assembled(data, max_margin, own_var, conv)

    def _convexify(self, state: ADMMState, graph: Graph, rows: slice | Tensor, lin: Any = None) -> "Convexification":
        """The parts of the local problems fixed by the linearization points ``state.plans``
        (and inputs): the dynamics linearization (``lin`` if given), the collision normals and
        each agent's projected variances along them."""
        xbar = state.plans[rows]
        if lin is None:
            gps = None if self.gps is None else select_rows(self.gps, rows)
            lin = linearize_plan(self.method, xbar, self.nominal, self.wind, gps,
                                 include_noise=self.settings.margin_variance == "predictive",
                                 ubar=state.inputs[rows])
        slot_nbr = graph.slot_nbr[rows]
        agent_ids = torch.arange(graph.num_agents)[rows]
        pos = self.nominal.position
        normals = on_positions(collision_normals(xbar[..., pos], state.plans[slot_nbr][..., pos], agent_ids,
                                                 slot_nbr)[:, :, 1:], pos, xbar.shape[-1])
        own_var = sigma = position_cov = None
        if self.method.chance:
            sigma = state_covariances(self.uncertainty, lin.var, lin.dyn_A, self.feedback)[:, 1:]
            own_var = projected_variances(normals, sigma)
            position_cov = sigma[:, 0][:, pos][:, :, pos]
        return Convexification(lin, normals, own_var, *self._obstacle_rows(xbar, sigma, agent_ids),
                               next_position_cov=position_cov)

    def _obstacle_rows(self, xbar: Tensor, sigma: Tensor | None,
                       agent_ids: Tensor) -> tuple[Tensor | None, Tensor | None, Tensor | None]:
        """The agents' (``agent_ids`` (B,)) obstacle rows at the plans ``xbar`` (B, T+1, D) without
        margins, and the agents' standard deviations ``sqrt(n^T Sigma_tau n)`` along them when
        ``sigma`` (B, T, D, D) is given: ``(normals, bounds, std)``."""
        if not self.num_obstacle_rows:
            return None, None, None
        pos = self.nominal.position
        radius = body_radii(self.settings, agent_ids)
        radius = radius[:, None, None] if isinstance(radius, Tensor) else radius  # over (T, rows)
        normals_p, bounds = obstacle_rows(self.settings.obstacles, xbar[:, 1:, pos], radius, self.num_obstacle_rows)
        normals = on_positions(normals_p, pos, xbar.shape[-1])
        std = None if sigma is None else safe_sqrt(projected_variances(normals, sigma))
        return normals, bounds, std

    def solve_agents(self, layer: nn.Module, data: LocalProblemData, rows: Tensor) -> LocalSolution:
        """The cold local solves of agents ``rows`` (int64 (B',)) of the batch ``data`` only (a safety
        fallback's few re-plans in a crowd of a thousand), as :meth:`solve`; B' solutions."""
        return self.solve(layer, select_problems(data, rows))

    def solve(self, layer: nn.Module, data: LocalProblemData, guess: Any = None) -> LocalSolution:
        """One batched local solve (``guess``: the last solve's ``solver_point``, the fast solver's
        warm start, or ``None``); an exception escaping the layer fails every agent (kind
        ``exception``) instead of ending the run. Input errors (GpmpcError) still raise. With
        ``solver = fast``, problems the compiled solver leaves inaccurate (no convergence within
        its iteration cap: rare, on problems with heavily softened rows) are solved again
        (:meth:`rescue_inaccurate`)."""
        try:
            return self.rescue_inaccurate(data, call_layer(layer, data, guess))
        except GpmpcError:
            raise
        except Exception as exc:  # noqa: BLE001 - counted and warned by count_failures
            interrupt = _wrapped_interrupt(exc)
            if interrupt is not None:  # Ctrl-C that C code turned into an error: stop, do not fall back
                raise interrupt
            batch, T, D = data.xref.shape[0], data.xref.shape[1] - 1, data.xref.shape[2]
            M, Du = data.active.shape[1], self.nominal.input_dim
            nan = data.xref.new_full((), float("nan"))
            return LocalSolution(
                X=nan.expand(batch, T + 1, D).clone(), U=nan.expand(batch, T, Du).clone(),
                Y=nan.expand(batch, M, T + 1, D).clone(), slack=nan.expand(batch, M, T).clone(),
                slack_active=torch.zeros(batch, dtype=torch.bool), ok=torch.zeros(batch, dtype=torch.bool),
                cost=nan.expand(batch).clone(), failure=torch.full((batch,), FAIL_EXCEPTION),
                failure_detail=f"{type(exc).__name__}: {exc}")

    def rescue_inaccurate(self, data: LocalProblemData, sol: LocalSolution) -> LocalSolution:
        """``sol`` with the problems the fast solver left inaccurate solved again where a rescue
        succeeds (:class:`~.rescue.SolveRescue`); unchanged with another solver.

        Args:
            data: the B problems. sol: the fast solver's solution of them.
        """
        return self.rescue(data, sol) if self.settings.solver == "fast" else sol

    @property
    def rescued_solves(self) -> int:
        """Problems the fast solver left inaccurate and a rescue solved (a run's count)."""
        return self.rescue.rescued

    def count_failures(self, sol: LocalSolution, result: StepResult | IterationStats) -> None:
        """Add this iteration's failed solves to ``result`` (anything with ``failed_solves`` and
        ``failed_by_kind``) and warn once per kind per run."""
        bad = ~sol.ok
        if not bool(bad.any()):
            return
        if sol.failure is not None:
            codes = sol.failure
        else:  # a layer that does not report kinds: infer them
            finite = torch.isfinite(sol.X).flatten(1).all(1) & torch.isfinite(sol.U).flatten(1).all(1)
            codes = torch.where(finite, torch.full_like(bad, FAIL_INACCURATE, dtype=torch.int64),
                                torch.full_like(bad, FAIL_NONFINITE, dtype=torch.int64))
        result.failed_solves += int(bad.sum())
        for i, kind in enumerate(FAILURE_KINDS):
            agents = (bad & (codes == i + 1)).nonzero().flatten().tolist()
            if not agents:
                continue
            result.failed_by_kind[kind] += len(agents)
            if kind not in self._warned:
                self._warned.add(kind)
                detail = f" ({sol.failure_detail})" if kind == "exception" and sol.failure_detail else ""
                log.warning("local MPC solve failed (%s%s) for agent(s) %s; using their previous (shifted) "
                            "plans. Further %s failures are not logged again; they are counted in "
                            "metrics.json 'failed_local_solves'", kind, detail, agents, kind)
            else:
                log.debug("local MPC solve failed (%s) for agent(s) %s; previous plans used", kind, agents)


def call_layer(layer: Any, data: LocalProblemData, guess: Any = None) -> LocalSolution:
    """``layer(data)``, with the warm start ``guess`` for a layer that declares ``accepts_guess``
    (the fast solver): any module mapping LocalProblemData to LocalSolution (a user's solver, a
    wrapper around the fast one) is still called with the data alone."""
    if guess is not None and getattr(layer, "accepts_guess", False):
        return layer(data, guess=guess)
    return layer(data)


def fall_back_to_previous(sol: LocalSolution, state: ADMMState, graph: Graph) -> LocalSolution:
    """Replace failed agents' solutions by their previous plans (a safe, feasible guess): at the
    first ADMM iteration of a step the last step's plan shifted (the warm start), later the previous iterate."""
    bad = ~sol.ok
    if not bool(bad.any()):
        return sol
    X = torch.where(bad[:, None, None], state.plans, sol.X)
    U = torch.where(bad[:, None, None], state.inputs, sol.U)
    nbr_prev = state.plans[graph.slot_nbr]
    Y = torch.where(bad[:, None, None, None], nbr_prev, sol.Y)
    return LocalSolution(X=X, U=U, Y=Y, slack=torch.where(bad[:, None, None], torch.zeros_like(sol.slack), sol.slack),
                         slack_active=sol.slack_active, ok=sol.ok, cost=sol.cost, failure=sol.failure,
                         failure_detail=sol.failure_detail,
                         state_slack=None if sol.state_slack is None else
                         torch.where(bad[:, None], torch.zeros_like(sol.state_slack), sol.state_slack),
                         solver_point=sol.solver_point,
                         multipliers=None if sol.multipliers is None else
                         torch.where(bad[:, None, None], float("nan"), sol.multipliers))


def edge_copies(sol: LocalSolution, graph: Graph) -> Tensor:
    """Each edge end's copy ``y_{e,a}`` of ``z_e`` (eq. 19): its own plan in its own half, its copy of
    the neighbour's plan in the other; shape (E, 2 [holder], 2 [half], T+1, D).

    Args:
        sol: the local solutions of all agents of ``graph`` (batch K).
        graph: the communication graph.
    """
    copies = sol.X.new_zeros(graph.num_edges, 2, 2, *sol.X.shape[1:])
    k_idx, m_idx = torch.nonzero(graph.active, as_tuple=True)
    e_idx = graph.slot_edge[k_idx, m_idx]
    a_idx = graph.slot_side[k_idx, m_idx]
    copies = copies.index_put((e_idx, a_idx, a_idx), sol.X[k_idx])
    copies = copies.index_put((e_idx, a_idx, 1 - a_idx), sol.Y[k_idx, m_idx])
    return copies
