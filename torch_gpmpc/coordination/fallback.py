"""The safety fallback: what an agent re-plans when ADMM stops on plans not known to be safe, and
the rule that decides who re-plans.

A pair of agents that can both stop at once keeps to buffered Voronoi cells (Zhou et al. 2017,
:func:`cell_slots`): an agent re-plans when its own row of such a pair is short at tau = 1, and,
again and again, when its plan leaves its cell towards an agent that re-plans
(:func:`fallback_agents`). An agent in a pair with momentum re-plans when that pair is unsafe at
tau = 1. A re-plan keeps to the cells of its agent's cell pairs and treats its other neighbours'
latest plans as fixed obstacles; the rest keep their plans. Both backends apply the same rule
(:func:`fallback_agents`; the distributed world closes the agents' seeds over the graph,
:func:`replanning_from_seeds`), each agent with the bounds it knows: in process both rows of a
pair, in the distributed backend its own (a pair with momentum whose two bounds differ can then be
judged differently). A re-plan's slack is priced by how far each pair has eaten into its margin
(:func:`danger_weights`), so an agent squeezed between pairs already inside their bounds opens
the closest pair first.
"""

from __future__ import annotations

import dataclasses

import torch
from torch import Tensor

from torch_gpmpc.control.problem import LocalProblemData
from torch_gpmpc.coordination.agent_step import on_positions
from torch_gpmpc.coordination.graph import Graph


#: Penalty that pins the neighbour copies to the neighbours' plans in the safety fallback:
#: moving a copy by d costs FIXED_OBSTACLE_RHO d^2 / 2, far above the collision slack's price.
FIXED_OBSTACLE_RHO = 1e6


def obstacle_problem(data: LocalProblemData, nbr_plans: Tensor) -> LocalProblemData:
    """The local problems with the neighbours' plans as fixed obstacles (no consensus pull on
    the own plan).

    Args:
        data: the last iteration's problems (their linearization, normals and full margins).
        nbr_plans: the neighbours' latest own plans per slot, shape (B, M, T+1, D).
    """
    zero = torch.zeros_like(data.z_own)
    return dataclasses.replace(data, rho=torch.zeros_like(torch.as_tensor(data.rho)).detach(),
                               rho_nbr=torch.full_like(data.active, FIXED_OBSTACLE_RHO, dtype=torch.float64),
                               z_own=zero, lam_own=zero, z_nbr=nbr_plans.detach(), lam_nbr=zero)


def cell_planes(own_plans: Tensor, nbr_plans: Tensor, position: list[int]) -> tuple[Tensor, Tensor]:
    """Each pair's buffered Voronoi plane at the agents' measured positions (tau = 0 of their plans).

    Agent k's cell towards neighbour j is ``n^T p >= m + b / 2`` with ``n`` the unit vector from
    j's position to k's and ``m = n^T (p_k + p_j) / 2``; j's cell, with ``-n``, is the other side
    (Zhou et al., "Fast, on-line collision avoidance for dynamic vehicles using buffered Voronoi
    cells", 2017). Coincident positions (never in a safe team) take the first axis.

    Args:
        own_plans: (B, T+1, D) the agents' plans. nbr_plans: (B, M, T+1, D) their neighbours'.
        position: the state indices of the position.

    Returns:
        ``(n (B, M, P), m (B, M))``.
    """
    diff = own_plans[:, None, 0, position] - nbr_plans[:, :, 0, position]
    length = torch.linalg.vector_norm(diff, dim=-1, keepdim=True)
    axis = torch.zeros_like(diff)
    axis[..., 0] = 1.0
    n = torch.where(length > 1e-9, diff / length.clamp_min(1e-300), axis)
    m = (n * 0.5 * (own_plans[:, None, 0, position] + nbr_plans[:, :, 0, position])).sum(-1)
    return n, m


def cell_problem(data: LocalProblemData, own_plans: Tensor, nbr_plans: Tensor,
                 position: list[int]) -> LocalProblemData:
    """The safety fallback's re-plan: the local problems with each collision row replaced by the
    agent's buffered Voronoi cell at every step, ``n^T p_tau >= m + b_tau / 2`` (:func:`cell_planes`;
    ``b_tau`` the row's bound, chance margin included), and no consensus pull.

    At tau = 1 two agents of a pair keep ``(b_k + b_j) / 2`` between them whether one or both
    re-plan, as long as an agent that does not re-plan is inside its cell towards one that does
    (:func:`fallback_agents`) and no re-plan needs slack. Staying where it is lies inside the
    cell, so an agent that can stop at once (no velocity state) always has a re-plan without slack,
    wind permitting.

    Args:
        data: the last iteration's problems (dynamics, margins); its collision normals are replaced.
        own_plans: (B, T+1, D) the agents' latest plans (tau = 0: the measured states).
        nbr_plans: (B, M, T+1, D) their neighbours' latest plans.
        position: the state indices of the position.
    """
    n, m = cell_planes(own_plans.detach(), nbr_plans.detach(), position)
    T, D = data.normals.shape[2], data.normals.shape[3]
    normals = on_positions(n, position, D)[:, :, None].expand(-1, -1, T, -1)
    # a virtual neighbour at m - b/2 along n turns the row n^T (X - Y) >= b into n^T X >= m + b / 2
    anchor = (m[..., None, None] - 0.5 * data.bounds.detach()[..., None]) * normals
    obstacles = torch.cat([anchor[:, :, :1], anchor], dim=2)  # tau = 0 has no row
    return obstacle_problem(dataclasses.replace(data, normals=normals), obstacles)


def priced_by_danger(problem: LocalProblemData, w: Tensor) -> LocalProblemData:
    """The problems with each collision row's slack priced ``w`` (B, M) times higher: the row
    scaled by ``w``, and the copies' pin by ``w^2`` so that moving a copy relieves the row no more
    than before."""
    return dataclasses.replace(problem, normals=problem.normals * w[..., None, None],
                               bounds=problem.bounds * w[..., None], rho_nbr=problem.rho_nbr * w ** 2)


#: The largest factor by which a row's slack in a re-plan with cells is priced above the others'.
MAX_DANGER_WEIGHT = 10.0


def danger_weights(own_plans: Tensor, nbr_plans: Tensor, bounds: Tensor, contact: Tensor | float,
                   position: list[int]) -> Tensor:
    """How much more each row's slack in a re-plan with cells should cost, (B, M):
    ``(b - c) / (d - c)`` clipped to ``[1, MAX_DANGER_WEIGHT]``, with ``d`` the pair's measured
    distance, ``b`` its tau = 1 bound and ``c`` its contact distance (the largest weight where
    ``d <= c``; 1, no change, where ``d >= b``).
    Rows of pairs already inside their bounds cannot all be met at once in a jam; with equal
    prices an agent squeezed between a neighbour at 0.3 m and one at 0.8 m is indifferent between
    them (the L1 slack trades one for the other) and tracking decides. Pricing by how far a pair
    has eaten into its margin makes the re-plan open the closest pair first.

    Args:
        own_plans: (B, T+1, D). nbr_plans: (B, M, T+1, D). bounds: (B, M) tau = 1 bounds.
        contact: (B, M, 1) or a number: the distance the pair's rows ask before margins.
        position: the state indices of the position.
    """
    d = torch.linalg.vector_norm(own_plans[:, None, 0, position] - nbr_plans[:, :, 0, position], dim=-1)
    c = contact[..., 0] if torch.is_tensor(contact) else contact
    ratio = torch.where(d > c, (bounds - c) / (d - c).clamp_min(1e-12), torch.full_like(d, MAX_DANGER_WEIGHT))
    return ratio.clamp(1.0, MAX_DANGER_WEIGHT)


def cell_exits(plans: Tensor, graph: Graph, bounds: Tensor, tol: float, position: list[int]) -> Tensor:
    """Where the agents' own plans leave their buffered Voronoi cells (:func:`cell_planes`) at
    tau = 1 (the step applied) by more than ``tol``, per neighbour slot.

    Args:
        plans: (K, T+1, D) the agents' own plans (tau = 0: the measured states).
        graph: the communication graph.
        bounds: (K, M) each agent's collision bound per slot at tau = 1 (``-inf``: ignore the slot).
        tol: allowance.
        position: the state indices of the position.

    Returns:
        (K, M) bool: agent k's plan crosses its cell's face towards slot m's neighbour.
    """
    n, m = cell_planes(plans, plans[graph.slot_nbr], position)  # (K, M, P), (K, M)
    height = (n * plans[:, None, 1, position]).sum(-1)
    return (height < m + 0.5 * bounds - tol) & graph.active


def own_rows_unsafe(plans: Tensor, graph: Graph, bounds: Tensor, tol: float, position: list[int]) -> Tensor:
    """(K,) bool: agents whose plan at tau = 1 is closer to a neighbour's than the agent's *own* row
    bound for that pair asks, less ``tol``. A pair that neither end flags is as far apart as the
    larger of its two bounds asks (:func:`pair_safety`'s test), and each agent decides it alone.

    Args: as :func:`cell_exits`.
    """
    return ((slot_gaps(plans, graph, position) < bounds - tol) & graph.active).any(dim=1)


def slot_gaps(plans: Tensor, graph: Graph, position: list[int]) -> Tensor:
    """(K, M): the distance at tau = 1 between each agent's plan (K, T+1, D) and each of its slot
    neighbours' (entries of empty slots mean nothing)."""
    p = plans[:, 1, position]
    return torch.linalg.vector_norm(p[:, None] - p[graph.slot_nbr], dim=-1)


def pair_bounds(bounds: Tensor, graph: Graph) -> Tensor:
    """(K, M): the larger of each pair's two row bounds per slot (``bounds`` (K, M); a bound an
    agent does not know is ``-inf``, and NaN counts as unknown)."""
    K = bounds.shape[0]
    k_idx, m_idx = torch.nonzero(graph.active, as_tuple=True)
    by_id = bounds.new_full((K, K), float("-inf"))
    by_id[k_idx, graph.slot_nbr[k_idx, m_idx]] = bounds[k_idx, m_idx]
    return torch.fmax(by_id, by_id.T).gather(1, graph.slot_nbr)


def replanning_closure(seeds: Tensor, exits: Tensor, graph: Graph) -> Tensor:
    """The smallest set of agents that holds ``seeds`` and every agent whose plan leaves its cell
    towards a member (``exits`` (K, M), :func:`cell_exits`).

    Args:
        seeds: (K,) bool, the agents that must re-plan.
        exits: (K, M) bool. graph: the communication graph.

    Returns:
        (K,) bool. Grows by at least one agent per round, so it ends within K rounds.
    """
    members = seeds.clone()
    while True:
        grown = members | (exits & members[graph.slot_nbr]).any(dim=1)
        if torch.equal(grown, members):
            return members
        members = grown


def replanning_from_seeds(seeds: Tensor, exits_by_id: Tensor, graph: Graph) -> Tensor:
    """:func:`replanning_closure` from the distributed agents' messages to the world, whose exits
    are by agent id: ``exits_by_id`` (K, K), agent k's plan leaving its cell towards agent j."""
    return replanning_closure(seeds, exits_by_id.gather(1, graph.slot_nbr) & graph.active, graph)


def cell_slots(momentum: Tensor, graph: Graph) -> Tensor:
    """(K, M) bool: the pairs whose safety fallback uses buffered Voronoi cells: both agents can stop
    at once (``momentum`` (K,) bool: a velocity state). A cell's guarantee needs the other agent to
    keep to its own cell, which a vehicle with momentum cannot promise (a cell can trap it
    mid-flight), so pairs with momentum keep the fixed-obstacle re-plan."""
    return graph.active & ~momentum[:, None] & ~momentum[graph.slot_nbr]


def fallback_cells(momentum: Tensor, graph: Graph, rule: str) -> Tensor:
    """(K, M) bool: the pairs kept to cells under the ``safety_fallback`` ``rule``:
    :func:`cell_slots` for ``cells``, none for ``obstacles``."""
    slots = cell_slots(momentum, graph)
    return slots if rule == "cells" else torch.zeros_like(slots)


def unsafe_slots(plans: Tensor, graph: Graph, bounds: Tensor, tol: float, position: list[int]) -> Tensor:
    """(K, M) bool: the pairs whose plans at tau = 1 are closer than the larger of the pair's two
    row bounds asks, less ``tol`` (:func:`pair_safety`'s test per slot; a bound an agent does not
    know is ``-inf``). Arguments as :func:`cell_exits`."""
    return (slot_gaps(plans, graph, position) < pair_bounds(bounds, graph) - tol) & graph.active


def fallback_seeds(plans: Tensor, graph: Graph, bounds: Tensor, tol: float, position: list[int],
                   cells: Tensor) -> tuple[Tensor, Tensor]:
    """What each agent knows alone before the team settles who re-plans: ``(seeds (K,), exits
    (K, M))``. An agent is a seed when one of its own rows of a cell pair is not kept at tau = 1
    (:func:`own_rows_unsafe`), or when one of its other pairs is unsafe (:func:`unsafe_slots`);
    ``exits`` are its :func:`cell_exits` towards its cell pairs. Arguments as
    :func:`fallback_agents`."""
    cell_bounds = torch.where(cells, bounds, torch.full_like(bounds, float("-inf")))
    other_unsafe = (unsafe_slots(plans, graph, bounds, tol, position) & ~cells).any(dim=1)
    seeds = own_rows_unsafe(plans, graph, cell_bounds, tol, position) | other_unsafe
    exits = cell_exits(plans, graph, bounds, tol, position) & cells
    return seeds, exits


def fallback_agents(plans: Tensor, graph: Graph, bounds: Tensor, tol: float, position: list[int],
                    momentum: Tensor, rule: str) -> tuple[Tensor, Tensor]:
    """Who re-plans after a stop on plans not known to be safe, and how (the rule both backends apply).

    The agents that re-plan are :func:`replanning_closure` of the seeds (:func:`fallback_seeds`):
    an agent whose own row of a cell pair (:func:`cell_slots`; none under the ``obstacles`` rule) is
    not kept at tau = 1, or one of whose other pairs is unsafe at tau = 1, and, again and again, an
    agent whose plan leaves its cell towards an agent of its cell pairs that re-plans. Every other
    agent keeps its plan. A re-plan keeps to the agent's cells towards its cell pairs and treats
    its other neighbours' plans as fixed obstacles (:func:`fallback_problem`). A cell pair is then
    safe at tau = 1 as long as no re-plan needs slack: both keep (no row of theirs was short),
    both re-plan (each inside its cell), or one re-plans inside its cell and the other's plan is
    inside its own cell towards it (else it would re-plan too). Staying keeps every cell row; a
    re-plan with rows towards neighbours with momentum too may need slack, shared by danger.

    Args:
        plans: (K, T+1, D) the agents' own plans. graph: the communication graph.
        bounds: (K, M) collision bounds at tau = 1 (``-inf``: unknown). tol: allowance.
        position: the state indices of the position. momentum: (K,) bool.
        rule: the ``safety_fallback`` setting, ``cells`` or ``obstacles``.

    Returns:
        ``(replan (K,), cells (K, M))`` bool.
    """
    cells = fallback_cells(momentum, graph, rule)
    seeds, exits = fallback_seeds(plans, graph, bounds, tol, position, cells)
    return replanning_closure(seeds, exits, graph), cells


def fallback_problem(data: LocalProblemData, own_plans: Tensor, nbr_plans: Tensor, position: list[int],
                     cells: Tensor, contact: Tensor | float | None = None) -> LocalProblemData:
    """The safety fallback's re-plan of each agent: inside its buffered Voronoi cell towards each
    cell pair (:func:`cell_problem`; ``cells``, :func:`cell_slots`), against its other neighbours'
    latest plans as fixed obstacles (:func:`obstacle_problem`).

    Args:
        data: the last iteration's problems. own_plans: (B, T+1, D). nbr_plans: (B, M, T+1, D).
        position: the state indices of the position. cells: (B, M) bool.
        contact: the distance each pair's rows ask before margins, (B, M, 1) or a number
            (:func:`~torch_gpmpc.coordination.bodies.slot_distances`: ``r_k + r_j`` or ``r_safe``, plus
            ``pair_buffer``): the rows of an agent with cell rows are then priced by
            :func:`danger_weights`; ``None``: every row at the solver's one price.
    """
    if not bool(cells.any()):
        return obstacle_problem(data, nbr_plans)
    posed = cell_problem(data, own_plans, nbr_plans, position)
    if not bool((cells | ~data.active).all()):  # empty slots are ignored
        fixed, rows = obstacle_problem(data, nbr_plans), cells[:, :, None, None]
        posed = dataclasses.replace(fixed, normals=torch.where(rows, posed.normals, fixed.normals),
                                    bounds=torch.where(cells[:, :, None], posed.bounds, fixed.bounds),
                                    rho_nbr=torch.where(cells, posed.rho_nbr, fixed.rho_nbr),
                                    z_nbr=torch.where(rows, posed.z_nbr, fixed.z_nbr))
    if contact is None:
        return posed
    # an agent with cell rows prices all its rows on one danger scale, else a squeeze between a
    # cell and a neighbour with momentum would always give way towards the latter
    w = danger_weights(own_plans.detach(), nbr_plans.detach(), data.bounds.detach()[:, :, 0], contact, position)
    return priced_by_danger(posed, torch.where(cells.any(dim=1, keepdim=True), w, torch.ones_like(w)))


def pair_safety(plans: Tensor, graph: Graph, bounds: Tensor, tol: float,
                position: list[int] | None = None) -> tuple[Tensor, Tensor, Tensor]:
    """Are the agents' own plans safe at tau = 1 (the step they apply)?

    A pair (k, j) is unsafe when ``||X_k^1 - X_j^1||`` is below the larger of its two rows'
    bounds (``r_safe`` plus the pair's margin) by more than ``tol`` (the consensus tolerance:
    copies agree with the plans only that well at convergence).

    Args:
        plans: (K, T+1, D) the agents' own plans.
        graph: the communication graph.
        bounds: (K, M) each agent's tau = 1 collision bound per slot.
        tol: allowance below the bound.
        position: the state indices of the position (``None``: every state).

    Returns:
        ``(unsafe (K,) bool, separation (K, K), required (K, K))``; off-edge entries are NaN.
    """
    position = list(range(plans.shape[-1])) if position is None else position
    gaps, need = slot_gaps(plans, graph, position), pair_bounds(bounds, graph)
    K = plans.shape[0]
    sep = torch.full((K, K), float("nan"), dtype=plans.dtype)
    req = torch.full((K, K), float("nan"), dtype=plans.dtype)
    k_idx, m_idx = torch.nonzero(graph.active, as_tuple=True)
    j_idx = graph.slot_nbr[k_idx, m_idx]
    sep[k_idx, j_idx], req[k_idx, j_idx] = gaps[k_idx, m_idx], need[k_idx, m_idx]
    return ((gaps < need - tol) & graph.active).any(dim=1), sep, req
