"""Plane coupling: neighbours agree on a separating plane per edge and horizon step, not on copies
of each other's trajectories (``admm_coupling = planes``).

With the step's frozen linearization, edge ``e = (lo, hi)``'s collision row at horizon step tau is
``n^T (p_lo - p_hi) >= d`` (``n`` the unit normal from hi towards lo, ``d`` the pair's distance plus
margins). It holds exactly when some offset ``w`` splits it::

    n^T p_lo >= w + d / 2      (lo's half, in lo's problem)
    n^T p_hi <= w - d / 2      (hi's half, in hi's problem)

so the team's problem is the agents' local problems, each with its own halves, coupled only by
one scalar ``w_{e,tau}`` per edge and step. Consensus ADMM on those scalars (Boyd et al. 2011,
§7.1): each end solves its local problem with its copy ``w_{e,a}`` pulled towards
``zeta_e - mu_{e,a} / rho_e``; then ``zeta_e = mean_a (w_{e,a} + mu_{e,a} / rho_e)`` and
``mu_{e,a} += rho_e (w_{e,a} - zeta_e)`` (unscaled duals, as :mod:`~.penalty` keeps them). The
optimum is the copies' (the same team problem: :func:`~.centralized.solve_centralized`); a
message is T numbers per neighbour instead of ``2 (T+1) n``.

Why: with copies, each agent's copy of a neighbour is free of the neighbour's dynamics and input
bound, and the neighbour's own plan is pulled towards the average of its neighbours' copies; in
a crowd an edge's residual then contracts slowly (README "Scale"). Here each agent enforces its
own half on its own plan, and the only thing averaged is where the plane lies. Measured on the
random-transition benchmark's first steps (N = 20, all 190 pairs coupled, one step replayed
from each state, steps 0-7): 26-73 iterations against 35-221 with copies, to the same plan cost.

The local problems are the copy formulation's with their neighbour copies re-read: the copy
``Y_{e,a}`` is pulled towards ``c n`` (``c`` the target offset), its row bound is ``d / 2``, and
its offset is ``w = n^T Y`` (the row only sees ``Y`` along ``n``); the own-copy term is off. So
every local solver serves both couplings unchanged.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import torch
from torch import Tensor

from torch_gpmpc.config.settings import ControllerSettings
from torch_gpmpc.control.problem import LocalProblemData, LocalSolution
from torch_gpmpc.control.solvers.repeated import RepeatedSolve
from torch_gpmpc.coordination.graph import Graph
from torch_gpmpc.coordination.penalty import (
    DUAL_TOL_FACTOR, EdgeResiduals, balance_penalty, unconverged_edges,
)
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


def lost_end_offsets(geometry: PlaneGeometry, plan: Tensor, edge: int, side: int, position: list[int]) -> Tensor:
    """The offsets (T,) a lost neighbour votes on edge ``edge`` at its end ``side``: where its half
    of the plane touches its last shared plan (T+1, n), which it is taken to follow as an obstacle
    (lo: ``n^T p - d / 2``; hi: ``n^T p + d / 2``)."""
    p = torch.zeros_like(plan[1:])
    p[..., position] = plan[1:][..., position]
    offset = (geometry.normals[edge] * p).sum(-1)
    half = geometry.distance[edge] / 2
    return offset - half if side == 0 else offset + half


def midpoint_planes(geometry: PlaneGeometry, plans: Tensor, graph: Graph, position: list[int]) -> Tensor:
    """Offsets (E, T) of the planes halfway between the pair's linearization plans (K, T+1, n) at
    tau = 1..T along each edge's normal (the start of a step's consensus)."""
    lo, hi = graph.edges[:, 0], graph.edges[:, 1]
    middle = torch.zeros_like(plans[lo, 1:])
    middle[..., position] = (plans[lo, 1:][..., position] + plans[hi, 1:][..., position]) / 2
    return (geometry.normals * middle).sum(dim=-1)


def plane_problem(data: LocalProblemData, geometry: PlaneGeometry, targets: Tensor, rho: Tensor) -> LocalProblemData:
    """The local problems with plane halves: each active slot's row bound ``d / 2`` on the edge's
    normal (negated for hi), its copy pulled towards ``targets`` along the normal with weight
    ``rho``, no own-copy term.

    Args:
        data: the assembled problems (batch K; their dynamics, costs and margins are kept).
        geometry: the step's :class:`PlaneGeometry`.
        targets: (E, 2, T) each end's target offset in lo's frame.
        rho: (E,) each edge's weight on its ends' copies.
    """
    g = geometry
    normals = torch.zeros_like(data.normals).index_put((g.agent, g.slot), g.sign[:, None, None] * g.normals[g.edge])
    bounds = torch.zeros_like(data.bounds).index_put((g.agent, g.slot), g.distance[g.edge] / 2)
    along = along_normals(g)
    pull = torch.zeros_like(data.z_nbr)
    pull = pull.index_put((g.agent, g.slot), torch.cat([torch.zeros_like(along[:, :1]),
                                                        targets[g.edge, g.side][..., None] * along], dim=1))
    weight = data.bounds.new_zeros(data.active.shape).index_put((g.agent, g.slot), rho[g.edge])
    zero = torch.zeros_like(data.z_own)
    return dataclasses.replace(data, normals=normals, bounds=bounds, rho=data.bounds.new_zeros(()),
                               rho_nbr=weight, z_own=zero, lam_own=zero, z_nbr=pull, lam_nbr=zero)


def along_normals(geometry: PlaneGeometry) -> Tensor:
    """(S, T, n) each active slot's edge normal over its squared length, ``n / |n|^2``: the copy
    ``c n / |n|^2`` has offset ``n^T Y = c`` (the normals are unit, except an all-zero one)."""
    normals = geometry.normals[geometry.edge]
    return normals / normals.square().sum(-1, keepdim=True).clamp_min(1e-300)


def plane_offsets(solution: LocalSolution, geometry: PlaneGeometry, fallback: Tensor) -> Tensor:
    """Each end's offset ``w_{e,a} = n^T Y`` (E, 2, T) in lo's frame from the local solutions; ends
    whose solve failed vote ``fallback`` (E, T), the current consensus."""
    g = geometry
    offsets = (g.normals[g.edge] * solution.Y[g.agent, g.slot, 1:]).sum(-1)
    if solution.ok is not None:
        offsets = torch.where(solution.ok[g.agent, None], offsets, fallback[g.edge])
    return fallback.new_zeros(fallback.shape[0], 2, fallback.shape[1]).index_put((g.edge, g.side), offsets)


def plane_consensus(offsets: Tensor, planes: Tensor, duals: Tensor, rho: Tensor
                    ) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Consensus and dual updates of every edge's plane.

    Args:
        offsets: (E, 2, T) both ends' offsets. planes: (E, T) the previous consensus.
        duals: (E, 2, T) unscaled duals. rho: (E,) penalties.

    Returns:
        ``(planes_new (E, T), duals_new (E, 2, T), primal (E, 2), dual (E,))`` with
        ``primal[e, a] = max_tau |w_{e,a} - zeta_e|`` and ``dual[e] = rho_e ||zeta_e - zeta_e_prev||``.
    """
    r = rho[:, None, None]
    new = (offsets + duals / r).mean(dim=1)
    gap = offsets - new[:, None]
    return new, duals + r * gap, gap.abs().amax(dim=2), rho * (new - planes).norm(dim=1)


def plane_residuals(primal: Tensor, dual: Tensor, duals: Tensor, cfg: ControllerSettings,
                    tol: float | None = None) -> EdgeResiduals:
    """The planes' stopping residuals (the copies' are :func:`~.penalty.edge_residuals`).

    The primal test is absolute and per horizon step: every end's offset within ``tol / 2`` of the
    consensus (``tol`` default ``admm_tol``), so the two halves of a pair overlap by at most ``tol``
    and the pair keeps its distance less ``tol`` (``pair_buffer = admm_tol`` keeps all of it). An
    offset's size depends on where the origin is, so there is no relative part. The dual test is the
    copies' (:mod:`~.penalty`).

    Args:
        primal: (E, 2) each end's largest ``|w_{e,a} - zeta_e|``. dual: (E,) ``rho_e ||zeta_e - zeta_e_prev||``.
        duals: (E, 2, T) the duals after the update.
        cfg: ``admm_tol``, ``admm_dual_tol``, ``admm_rel_tol``, ``admm_stop``.
    """
    tol = cfg.admm_tol if tol is None else tol
    rel = cfg.admm_rel_tol if cfg.admm_stop == "primal-dual" else 0.0
    dual_abs = cfg.admm_dual_tol if cfg.admm_dual_tol is not None else DUAL_TOL_FACTOR * tol
    with torch.no_grad():
        eps_primal = torch.full_like(dual, tol / 2)
        eps_dual = dual_abs + rel * duals[:, 0].norm(dim=1)
    return EdgeResiduals(primal.amax(dim=1), dual, eps_primal, eps_dual)


def balance_plane_penalty(rho: Tensor, residuals: EdgeResiduals) -> Tensor:
    """(E,) the edges' next penalties: residual balancing with settled edges relaxed
    (:func:`~.penalty.balance_penalty`'s ``relax_settled``; their residuals are round-off)."""
    return balance_penalty(rho, residuals, relax_settled=True)


class PlaneTerms:
    """The copies' terms of kept plane problems, written in place for each new set of targets.

    A :class:`~torch_gpmpc.control.solvers.repeated.RepeatedSolve` starts with the posed problems'
    terms; of them only the active slots' weights and targets change between a step's iterations (the
    own terms stay 0, the copies' tau = 0 points 0, inactive slots neutral). :meth:`write` writes
    them as :func:`plane_problem` and :func:`~torch_gpmpc.control.solvers.canonical.canonicalize`
    would (the same bits).

    Args:
        geometry: the slots to write: a :class:`PlaneGeometry` whose ``agent`` indexes the kept batch.
        solve: the kept problems.
    """

    def __init__(self, geometry: PlaneGeometry, solve: RepeatedSolve) -> None:
        self.geometry, self.solve = geometry, solve
        self.along = along_normals(geometry)
        self.agent, self.slot = geometry.agent.numpy(), geometry.slot.numpy()

    def write(self, rho: Tensor, targets: Tensor) -> None:
        """Write each slot's weight ``rho`` (E,) and target offsets ``targets`` (E, 2, T)."""
        g, buf = self.geometry, self.solve.buffers
        weight = rho[g.edge]
        buf.rho_y[self.agent, self.slot] = weight.numpy()
        pull = targets[g.edge, g.side][..., None] * self.along
        buf.w_y[self.agent, self.slot] = (weight[:, None, None] * pull).numpy()


class PlaneIterations:
    """A control step's later plane iterations on the kept problems (the planes' form of
    :class:`~.steady.SteadyIterations`): only the copies' targets and weights change, so each
    iteration writes their terms (as :func:`~torch_gpmpc.control.solvers.canonical.canonicalize`
    computes them from :func:`plane_problem`) into a
    :class:`~torch_gpmpc.control.solvers.repeated.RepeatedSolve` and solves warm; the plans, planes,
    duals and penalties are the torch path's bit for bit. ``None`` from :meth:`iterate` hands the
    iteration to the torch path (as :class:`~.steady.SteadyIterations` does).

    Args:
        settings: the controller settings. graph: the step's graph.
        geometry: the step's :class:`PlaneGeometry`.
        rho: the step's penalty, 0-d (every edge's with ``rho_update = fixed``).
        tol: the stopping test's absolute primal tolerance.
        solve: the plane problems as last posed (batch K), as a :class:`RepeatedSolve`: only their
            copies' targets and weights change.
    """

    def __init__(self, settings: ControllerSettings, graph: Graph, geometry: PlaneGeometry, rho: Tensor,
                 tol: float, solve: RepeatedSolve) -> None:
        self.settings, self.graph, self.geometry = settings, graph, geometry
        self.adaptive = settings.rho_update == "adaptive"
        self.rho, self.tol, self.solve = rho, tol, solve
        self.terms = PlaneTerms(geometry, solve)

    def iterate(self, state: ADMMState) -> SteadyResult | None:
        """One iteration from ``state`` (the step's previous iterate), or ``None``."""
        g, s = self.geometry, self.settings
        rho = state.rho if self.adaptive else self.rho.expand(self.graph.num_edges)
        self.terms.write(rho, state.planes[:, None] - state.plane_duals / rho[:, None, None])
        sol = solve_or_hand_back(self.solve, state.solver_point)
        if sol is None:
            return None
        offsets = plane_offsets(LocalSolution(sol.X, sol.U, sol.Y, sol.slack, None, None, None), g, state.planes)
        planes, duals, gaps, dual_norms = plane_consensus(offsets, state.planes, state.plane_duals, rho)
        res = plane_residuals(gaps, dual_norms, duals, s)
        stop = res if self.tol == s.admm_tol else plane_residuals(gaps, dual_norms, duals, s, self.tol)
        rho_next = balance_plane_penalty(rho, res) if self.adaptive else None
        nxt = dataclasses.replace(state, plans=sol.X, inputs=sol.U, solver_point=sol.point, planes=planes,
                                  plane_duals=duals, rho=rho_next)
        return SteadyResult(nxt, float(res.primal.max()), float(res.dual.max()), float(stop.primal_ratio.max()),
                            float(stop.dual_ratio.max()), unconverged_edges(stop, s), sol.slack_active)
