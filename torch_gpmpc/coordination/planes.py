"""Plane coupling: neighbours share one separating plane per edge and horizon step, each keeping its
own half, instead of agreeing on copies of each other's trajectories (``admm_coupling = planes``).

With the step's frozen linearization, edge ``e = (lo, hi)``'s collision row at horizon step tau is
``n^T (p_lo - p_hi) >= d`` (``n`` the unit normal from hi towards lo, ``d`` the pair's distance plus
margins). It holds whenever both ends keep their halves of one offset ``c``::

    n^T p_lo >= c + d / 2      (lo's half, in lo's problem)
    n^T p_hi <= c - d / 2      (hi's half, in hi's problem)

so the team's problem is the agents' local problems with their halves, coupled only by ``c_{e,tau}``,
and the same as the copies' (:func:`~.centralized.solve_centralized`). One iteration (primal
decomposition): every agent solves with its halves at the current offsets (:func:`plane_problem`),
reports its halves' multipliers (:func:`end_multipliers`; T numbers per neighbour), and both ends move
each offset against the team cost's derivative ``mu_lo - mu_hi`` (:func:`plane_update`).

Why: every iterate's plans keep every pair's row wherever their halves held, whatever the iteration,
so a control step may stop at any budget and apply its last such iterate (:class:`SafeIterates`,
graded by :func:`unsafe_ends`); the safety fallback is left for a step without one. Consensus on
copies is safe only once it has converged, which a crowd's steps rarely do within a budget.

The local problems are the copy formulation's with each neighbour copy pinned to the plane: the
copy ``Y_{e,a}`` is held at ``c n`` by the weight :data:`PLANE_PIN`, its row bound is ``d / 2`` (the
row only sees ``Y`` along ``n``), and the own-copy term is off. So every local solver serves both
couplings unchanged.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import torch
from torch import Tensor

from torch_gpmpc.config.settings import ControllerSettings
from torch_gpmpc.control.problem import LocalProblemData
from torch_gpmpc.control.solvers.repeated import RepeatedSolve
from torch_gpmpc.coordination.graph import Graph
from torch_gpmpc.coordination.penalty import RHO_BOUNDS, EdgeResiduals, unconverged_edges
from torch_gpmpc.coordination.state import ADMMState
from torch_gpmpc.coordination.steady import SteadyResult, solve_or_hand_back


@dataclass(frozen=True)
class PlaneGeometry:
    """The step's planes: which slot holds which edge end, and each edge's normals and distances.

    Attributes:
        agent, slot: (S,) the active slots ``(agent, slot)`` of the graph.
        edge, side: (S,) the edge each slot holds and the slot's end (0 = lo, 1 = hi).
        sign: (S,) float, +1 for lo's slots, -1 for hi's (lo's frame to the slot's).
        normals: (E, T, n) each edge's unit normal from hi towards lo (lo's slot normal).
        distance: (E, T) the larger of the two ends' row bounds ``d`` (sound for both).
    """

    agent: Tensor
    slot: Tensor
    edge: Tensor
    side: Tensor
    sign: Tensor
    normals: Tensor
    distance: Tensor


def plane_geometry(data: LocalProblemData, graph: Graph) -> PlaneGeometry:
    """The planes of the assembled problems ``data`` (batch K, every agent of ``graph``; at least
    one edge): lo's normals (hi's rows use their negation) and each edge's larger bound."""
    return rows_geometry(data.normals, data.bounds, graph)


def rows_geometry(normals: Tensor, bounds: Tensor, graph: Graph) -> PlaneGeometry:
    """:func:`plane_geometry` from the rows alone: ``normals`` (K, M, T, n) and ``bounds`` (K, M, T)
    of every active slot of ``graph`` (a distributed agent fills its neighbours' slots with the rows
    they sent)."""
    agent, slot = torch.nonzero(graph.active, as_tuple=True)
    edge, side = graph.slot_edge[agent, slot], graph.slot_side[agent, slot]
    E, T, n = graph.num_edges, normals.shape[2], normals.shape[3]
    lo_slot = side == 0
    edge_normals = normals.new_zeros(E, T, n).index_put((edge[lo_slot],), normals[agent[lo_slot], slot[lo_slot]])
    ends = bounds.new_zeros(E, 2, T).index_put((edge, side), bounds[agent, slot])
    sign = torch.where(lo_slot, 1.0, -1.0).to(bounds.dtype)
    return PlaneGeometry(agent, slot, edge, side, sign, edge_normals, ends.amax(dim=1))


def agent_rows(geometry: PlaneGeometry, k: int) -> PlaneGeometry:
    """The part of ``geometry`` agent ``k`` poses: its own slots, with ``agent`` 0 (its problems as
    a batch of one, as a distributed agent solves them); the edges' normals and distances whole."""
    own = geometry.agent == k
    return dataclasses.replace(geometry, agent=torch.zeros_like(geometry.agent[own]), slot=geometry.slot[own],
                               edge=geometry.edge[own], side=geometry.side[own], sign=geometry.sign[own])


def midpoint_planes(geometry: PlaneGeometry, plans: Tensor, graph: Graph, position: list[int]) -> Tensor:
    """Offsets (E, T) of the planes halfway between the pair's linearization plans (K, T+1, n) at
    tau = 1..T along each edge's normal (the start of a step's consensus)."""
    lo, hi = graph.edges[:, 0], graph.edges[:, 1]
    middle = torch.zeros_like(plans[lo, 1:])
    middle[..., position] = (plans[lo, 1:][..., position] + plans[hi, 1:][..., position]) / 2
    return (geometry.normals * middle).sum(dim=-1)


#: The weight that pins each end's copy to the agreed offset: a half whose multiplier is ``mu``
#: moves its copy by ``mu / PLANE_PIN``, so the halves hold to micrometres.
PLANE_PIN = 1e6


def plane_problem(data: LocalProblemData, geometry: PlaneGeometry, planes: Tensor) -> LocalProblemData:
    """The local problems with plane halves at the agreed offsets: each active slot's row bound
    ``d / 2`` on the edge's normal (negated for hi), its copy pinned to ``planes`` along the normal
    (weight :data:`PLANE_PIN`), no own-copy term.

    Args:
        data: the assembled problems (batch K; their dynamics, costs and margins are kept).
        geometry: the step's :class:`PlaneGeometry`.
        planes: (E, T) each edge's offset in lo's frame.
    """
    g = geometry
    normals = torch.zeros_like(data.normals).index_put((g.agent, g.slot), g.sign[:, None, None] * g.normals[g.edge])
    bounds = torch.zeros_like(data.bounds).index_put((g.agent, g.slot), g.distance[g.edge] / 2)
    along = along_normals(g)
    pull = torch.zeros_like(data.z_nbr)
    pull = pull.index_put((g.agent, g.slot), torch.cat([torch.zeros_like(along[:, :1]),
                                                        planes[g.edge][..., None] * along], dim=1))
    weight = data.bounds.new_zeros(data.active.shape).index_put(
        (g.agent, g.slot), data.bounds.new_full(g.agent.shape, PLANE_PIN))
    zero = torch.zeros_like(data.z_own)
    return dataclasses.replace(data, normals=normals, bounds=bounds, rho=data.bounds.new_zeros(()),
                               rho_nbr=weight, z_own=zero, lam_own=zero, z_nbr=pull, lam_nbr=zero)


def along_normals(geometry: PlaneGeometry) -> Tensor:
    """(S, T, n) each active slot's edge normal over its squared length, ``n / |n|^2``: the copy
    ``c n / |n|^2`` has offset ``n^T Y = c`` (the normals are unit, except an all-zero one)."""
    normals = geometry.normals[geometry.edge]
    return normals / normals.square().sum(-1, keepdim=True).clamp_min(1e-300)


def end_multipliers(multipliers: Tensor | None, copies: Tensor, ok: Tensor | None, geometry: PlaneGeometry,
                    planes: Tensor) -> Tensor:
    """(E, 2, T) each end's multiplier of its half at every step: the solver's row multipliers, or
    read off the pinned copies (a half that binds holds its copy ``mu / PLANE_PIN`` off the agreed
    offset) where the solver reports none (the cvxpylayers reference) or gradients are wanted (the
    copies carry them); 0 for an end whose solve failed. The two readings agree to the solver's
    tolerance times PLANE_PIN; the solver's keeps the batched and the distributed agents' steps equal
    to rounding.

    Args:
        multipliers: (K, M, T) the solves' collision-row multipliers, or ``None``.
        copies: (K, M, T+1, n) the solves' copies ``Y``. ok: (K,) bool, or ``None``: all accepted.
        geometry: the step's :class:`PlaneGeometry`. planes: (E, T) the offsets the solves were pinned to.
    """
    g = geometry
    offsets = (g.normals[g.edge] * copies[g.agent, g.slot, 1:]).sum(-1)
    pinned = PLANE_PIN * (g.sign[:, None] * (planes[g.edge] - offsets)).clamp_min(0.0)
    if multipliers is None or copies.requires_grad:  # the solver's multipliers carry no gradient
        mu = pinned
    else:
        mu = torch.where(torch.isnan(multipliers[g.agent, g.slot]), pinned, multipliers[g.agent, g.slot])
    if ok is not None:
        mu = torch.where(ok[g.agent, None], mu, torch.zeros_like(mu))
    return mu.new_zeros(planes.shape[0], 2, planes.shape[1]).index_put((g.edge, g.side), mu)


@dataclass
class PlaneUpdate:
    """One iteration's new planes (:func:`plane_update`).

    Attributes:
        planes: (E, T) the next offsets. gradient: (E, T) this iteration's ``mu_lo - mu_hi``.
        rho: (E, T) the step penalties of the move.
        move: (E,) each edge's largest move over the horizon at the starting penalty (the stopping
            residual).
    """

    planes: Tensor
    gradient: Tensor
    rho: Tensor
    move: Tensor


#: How a coordinate's step penalty changes: times PLANE_BACKOFF where its gradient changed sign (the
#: last move overshot), divided by PLANE_SPEEDUP where it kept its sign.
PLANE_BACKOFF, PLANE_SPEEDUP = 2.0, 1.25
#: A gradient below this is the solver's tolerance, not a direction: it does not turn a step.
GRADIENT_FLOOR = 1e-9
#: The largest move of an offset in one iteration, as a fraction of its pair's distance.
PLANE_MAX_MOVE = 0.25


def plane_update(multipliers: Tensor, planes: Tensor, rho: Tensor | None, previous_gradient: Tensor | None,
                 distance: Tensor, start_rho: Tensor) -> PlaneUpdate:
    """The planes' primal-decomposition step: every offset moves against the team cost's derivative
    ``mu_lo - mu_hi``, towards the end whose half costs less, ``c <- c - (mu_lo - mu_hi) / (2 rho)``.

    Each coordinate's ``rho`` (its inverse step) adapts: times :data:`PLANE_BACKOFF` where the
    gradient changed sign since the last iteration (the move overshot), eased back towards the
    starting rho where it kept it (never below: a step never grows past the starting one); the
    factor is detached, so gradients reach the starting rho.
    No offset moves more than :data:`PLANE_MAX_MOVE` of its pair's distance in one iteration: a half
    that needs slack prices its row at the slack penalty, which would fling the plane.

    Args:
        multipliers: (E, 2, T) both ends' multipliers (:func:`end_multipliers`). planes: (E, T) the
            offsets the solves were pinned to. rho: (E, T) the penalties of the last move, or ``None``
            at a step's first iteration (``start_rho`` everywhere).
        previous_gradient: (E, T) the last iteration's gradient, or ``None`` at a step's first.
        distance: (E, T) the pairs' distances (:attr:`PlaneGeometry.distance`).
        start_rho: 0-d, the step's starting penalty: the stopping residual is the move it would make,
            ``max_tau |mu_lo - mu_hi| / (2 start_rho)`` (a grown ``rho`` would stop a step early).
    """
    gradient = multipliers[:, 0] - multipliers[:, 1]
    if rho is None:
        rho = start_rho.expand(planes.shape)
    if previous_gradient is not None:
        with torch.no_grad():
            turn = torch.where(gradient.abs() > GRADIENT_FLOOR, gradient, 0.0) * previous_gradient
            factor = torch.where(turn < 0, PLANE_BACKOFF, torch.where(turn > 0, 1 / PLANE_SPEEDUP, 1.0))
            factor = (rho.detach() * factor).clamp(min=start_rho.detach(), max=RHO_BOUNDS[1]) / rho.detach()
        rho = rho * factor
    limit = PLANE_MAX_MOVE * distance
    step = torch.minimum(torch.maximum(-gradient / (2 * rho), -limit), limit)
    return PlaneUpdate(planes + step, gradient, rho, gradient.detach().abs().amax(dim=1) / (2 * start_rho.detach()))


def plane_iteration(multipliers: Tensor, plans: Tensor, geometry: PlaneGeometry, planes: Tensor,
                    rho: Tensor | None, previous_gradient: Tensor | None, start_rho: Tensor,
                    cfg: ControllerSettings, tol: float | None = None
                    ) -> tuple[PlaneUpdate, EdgeResiduals, EdgeResiduals]:
    """What one iteration makes of its solves, the same on every path (the torch path, the compiled
    :class:`PlaneIterations`, a distributed agent): the plane step (:func:`plane_update`), the
    iterate's safety grade (:func:`unsafe_ends`) and the residuals of :func:`plane_residuals`.

    Args:
        multipliers: (E, 2, T) both ends' multipliers. plans: (K, T+1, n) the plans the solves gave
            (only the agents ``geometry`` poses are graded: a distributed agent grades its own ends).
        geometry: the step's :class:`PlaneGeometry`. planes: (E, T) the offsets the solves were pinned to.
        rho, previous_gradient, start_rho: as :func:`plane_update` takes them.
        cfg: the settings (``admm_tol`` grades and balances). tol: the stopping test's tolerance
            (default ``admm_tol``).

    Returns:
        ``(step, residuals at admm_tol, residuals of the stopping test)``.
    """
    step = plane_update(multipliers, planes, rho, previous_gradient, geometry.distance, start_rho)
    unsafe = unsafe_ends(plans, geometry, planes, cfg.admm_tol)
    res = plane_residuals(step.move, unsafe, cfg)
    stop = res if tol is None or tol == cfg.admm_tol else plane_residuals(step.move, unsafe, cfg, tol)
    return step, res, stop


class SafeIterates:
    """A step's plans to apply: the latest iterate whose halves held at tau = 1 and 2
    (:data:`SAFE`), else the latest that held them at tau = 1 (:data:`SAFE_NOW`), else none (the
    safety fallback re-plans). Each iterate's plans are jointly safe at the levels it kept, whatever
    the iteration, so the step may stop anywhere. A distributed agent keeps its own plan's."""

    def __init__(self) -> None:
        self.latest: dict[float, tuple[Tensor, Tensor]] = {}

    def record(self, level: float, plans: Tensor, inputs: Tensor) -> None:
        """Note an iterate of team ``level`` (the largest :func:`unsafe_ends` level) and its plans."""
        if level < UNSAFE:
            self.latest[level] = (plans, inputs)

    def best(self) -> tuple[Tensor, Tensor] | None:
        """``(plans, inputs)`` to apply, or ``None``."""
        return self.latest.get(SAFE, self.latest.get(SAFE_NOW))


def plane_residuals(move: Tensor, unsafe: Tensor, cfg: ControllerSettings, tol: float | None = None) -> EdgeResiduals:
    """The planes' stopping residuals: each edge's largest move of its offsets at the step's starting
    penalty (E,) against ``tol / 2`` (``tol`` default ``admm_tol``), and as its dual residual its
    :func:`unsafe_ends` level (E,) against 1: a step does not stop on an iterate whose applied step
    may not keep its pairs. Every other iterate's plans are jointly safe, so stopping early costs
    cost, never safety."""
    tol = cfg.admm_tol if tol is None else tol
    return EdgeResiduals(move, unsafe.to(move.dtype), torch.full_like(move, tol / 2), torch.ones_like(move))


#: How unsafe an edge's end leaves an iterate (:func:`unsafe_ends`): it keeps its halves at tau = 1
#: and 2; only at tau = 1 (the step applied is safe, but the next step's first planes, halfway
#: between these plans shifted, may not be); not at tau = 1.
SAFE, SAFE_NOW, UNSAFE = 0.0, 0.5, 1.0


def unsafe_ends(plans: Tensor, geometry: PlaneGeometry, planes: Tensor, tol: float) -> Tensor:
    """(E,) each edge's :data:`UNSAFE` level: whether an end's plan leaves its half at tau = 1, or at
    tau = 2 only, by more than ``tol / 2``, so that the pair may be closer than its distance less
    ``tol`` (the safety check's allowance): a half the solve softened, a copy the pin let go under a
    large multiplier, or a failed solve's kept plan, which met the last planes, not these. Later
    steps are left to the next control steps, which plan them again.

    Args:
        plans: (K, T+1, n) the plans (a failed solve's kept plan); only the agents ``geometry``
            poses are read. geometry: the step's :class:`PlaneGeometry`. planes: (E, T) the offsets
            the plans were pinned to. tol: the allowance.
    """
    g = geometry
    near = min(2, planes.shape[1])
    height = (g.normals[g.edge, :near] * plans[g.agent, 1:near + 1]).sum(-1)
    short = g.sign[:, None] * (planes[g.edge, :near] - height) + g.distance[g.edge, :near] / 2 > tol / 2
    level = torch.where(short[:, 0], UNSAFE, torch.where(short.any(dim=1), SAFE_NOW, SAFE)).to(planes.dtype)
    return planes.new_zeros(planes.shape[0]).scatter_reduce(0, g.edge, level, "amax")


class PlaneTerms:
    """The copies' targets of kept plane problems, written in place for each new set of planes.

    A :class:`~torch_gpmpc.control.solvers.repeated.RepeatedSolve` starts with the posed problems'
    terms; of them only the active slots' targets change between a step's iterations (the weights
    stay :data:`PLANE_PIN`, the own terms 0, the copies' tau = 0 points 0, inactive slots neutral).
    :meth:`write` writes them as :func:`plane_problem` and
    :func:`~torch_gpmpc.control.solvers.canonical.canonicalize` would (the same bits).

    Args:
        geometry: the slots to write: a :class:`PlaneGeometry` whose ``agent`` indexes the kept batch.
        solve: the kept problems.
    """

    def __init__(self, geometry: PlaneGeometry, solve: RepeatedSolve) -> None:
        self.geometry, self.solve = geometry, solve
        self.along = along_normals(geometry)
        self.agent, self.slot = geometry.agent.numpy(), geometry.slot.numpy()

    def write(self, planes: Tensor) -> None:
        """Write each slot's target offsets ``planes`` (E, T)."""
        g, buf = self.geometry, self.solve.buffers
        buf.w_y[self.agent, self.slot] = (PLANE_PIN * (planes[g.edge][..., None] * self.along)).numpy()


class PlaneIterations:
    """A control step's later plane iterations on the kept problems (the planes' form of
    :class:`~.steady.SteadyIterations`): only the copies' targets change, so each iteration writes
    them (:class:`PlaneTerms`) into a :class:`~torch_gpmpc.control.solvers.repeated.RepeatedSolve`
    and solves warm; the plans, planes and penalties are the torch path's bit for bit. ``None`` from
    :meth:`iterate` hands the iteration to the torch path (as :class:`~.steady.SteadyIterations`
    does).

    Args:
        settings: the controller settings. graph: the step's graph.
        geometry: the step's :class:`PlaneGeometry`.
        rho: the step's penalty, 0-d (every edge's with ``rho_update = fixed``).
        tol: the stopping test's absolute primal tolerance.
        solve: the plane problems as last posed (batch K), as a :class:`RepeatedSolve`: only their
            copies' targets change.
    """

    def __init__(self, settings: ControllerSettings, graph: Graph, geometry: PlaneGeometry, rho: Tensor,
                 tol: float, solve: RepeatedSolve) -> None:
        self.settings, self.graph, self.geometry = settings, graph, geometry
        self.rho, self.tol, self.solve = rho, tol, solve
        self.terms = PlaneTerms(geometry, solve)

    def iterate(self, state: ADMMState) -> SteadyResult | None:
        """One iteration from ``state`` (the step's previous iterate), or ``None``."""
        g, s = self.geometry, self.settings
        self.terms.write(state.planes)
        sol = solve_or_hand_back(self.solve, state.solver_point)
        if sol is None:
            return None
        mu = end_multipliers(sol.multipliers, sol.Y, None, g, state.planes)
        step, res, stop = plane_iteration(mu, sol.X, g, state.planes, state.plane_rho, state.plane_gradient, self.rho,
                                          s, self.tol)
        nxt = dataclasses.replace(state, plans=sol.X, inputs=sol.U, solver_point=sol.point, planes=step.planes,
                                  plane_gradient=step.gradient, plane_rho=step.rho)
        return SteadyResult(nxt, float(res.primal.max()), float(res.dual.max()), float(stop.primal_ratio.max()),
                            float(stop.dual_ratio.max()), unconverged_edges(stop, s), sol.slack_active)
