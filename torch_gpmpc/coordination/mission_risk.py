"""A collision-risk budget for the whole mission (``risk_mode = mission``), spent pair-step by pair-step.

The promise: the probability that any pair collides at any applied step of the run is at
most ``delta = risk_budget``. The argument (Boole's inequality twice, Blackmore and Ono's
joint chance constraints made receding-horizon):

1. Agent k starts with ``R_k = delta / K``; the team's budgets sum to delta.
2. At every control step, agent k allots ``a_k = R_k / risk_pacing`` and gives each of its
   d_k edges and each of its L obstacle rows the risk ``eps_k = a_k / (d_k + L)``
   (:func:`row_allotments`, :func:`edge_allotments`); the pair's rows carry the sound margin of
   ``eps_k + eps_j`` (``pair_margin = sum`` or ``joint``), for which the agents exchange these
   numbers (one per edge and step), and each obstacle row the margin of ``eps_k`` alone.
3. After the step is applied, the pair's collision probability at the next sample is
   bounded by ``p = Phi(-(n^T (x_k - x_j) - r_safe) / sqrt(s_k + s_j))`` on the applied plans at
   tau = 1 (:func:`pair_risk_bounds`): the collision disc lies beyond the linearized half-space
   ``n^T (p_k - p_j) >= r_safe`` (n a unit vector), and ``n^T (x_k - x_j)`` is Gaussian with the
   two agents' projected variances. Whenever the pair's row holds, ``p <= eps_k + eps_j``.
   The same bound along the pair's own direction at tau = 1 (:func:`direction_risk_bounds`) is
   valid too, and the smaller of the two is charged: plans the rows did not pose (a fallback's
   re-plan in its Voronoi cell) are charged what they risk, not what the stale normal suggests.
   Likewise an obstacle row ``n^T p_k >= b`` (a supporting half-space of the convex obstacle
   grown by the body radius) bounds the agent's probability of hitting it by
   ``Phi(-(n^T x_k - b) / sqrt(s_k))`` (:func:`obstacle_risk_bounds`), at most ``eps_k`` when
   the row holds.
4. Each agent is charged its share ``p eps_k / (eps_k + eps_j)`` of each pair's bound (<= eps_k
   when the row holds; :func:`agent_charges`) and its obstacle rows' bounds, so ``R_k`` shrinks
   by at most ``a_k`` a step and never reaches 0.
5. Then P(any collision or obstacle hit) <= sum over steps, pairs and obstacle rows of p = sum
   of the charges <= sum_k R_k(0) = delta, for any run length.

Assumptions: each agent's one-step deviation from its plan is Gaussian with the variance its
GP predicts (latent plus learned noise), independent between agents; the GP mean's
linearization gives the plan's next state. Pairs outside the communication radius carry no
rows and are charged nothing: the radius must exceed what two agents can close in one step;
likewise the obstacles beyond an agent's ``obstacle_rows`` nearest must be out of one step's reach.
When a row is violated anyway (slack, an unconverged ADMM stop), the charge exceeds the
allotment and the budget is overspent; ``risk_spent`` in the metrics shows it. ``gpmpc
calibrate --mission`` tests the whole chain by Monte Carlo.
"""

from __future__ import annotations

import torch
from torch import Tensor

from torch_gpmpc.coordination.graph import Graph

#: The smallest risk an agent keeps (its quantile Phi^-1(1 - 1e-12) = 7.0 keeps margins finite
#: after an overspent step).
RISK_FLOOR = 1e-12


def starting_budgets(num_agents: int, risk_budget: float, like: Tensor | None = None) -> Tensor:
    """Each agent's share of the mission budget, ``delta / K``, shape (K,), float64."""
    dtype = torch.float64 if like is None else like.dtype
    return torch.full((num_agents,), risk_budget / num_agents, dtype=dtype)


def row_allotments(remaining: Tensor, graph: Graph, pacing: int, obstacle_rows: int = 0) -> Tensor:
    """This step's risk of each of an agent's rows: ``remaining_k / (pacing (d_k + L))``.

    Args:
        remaining: (K,) each agent's unspent budget.
        graph: the communication graph (degrees d_k).
        pacing: ``risk_pacing``: a step spends at most ``1 / pacing`` of what remains.
        obstacle_rows: L, the obstacle rows each agent carries at a horizon step.

    Returns:
        (K,) the risk of one of agent k's edges or obstacle rows.
    """
    shares = (graph.degrees() + obstacle_rows).clamp_min(1).to(remaining.dtype)
    return remaining.clamp_min(RISK_FLOOR) / (pacing * shares)


def edge_allotments(remaining: Tensor, graph: Graph, pacing: int, obstacle_rows: int = 0) -> Tensor:
    """This step's risk of each end of each edge (:func:`row_allotments`).

    Returns:
        (E, 2) risk of the edge's lower- and higher-indexed end.
    """
    per_edge = row_allotments(remaining, graph, pacing, obstacle_rows)
    return per_edge[graph.edges] if graph.num_edges else remaining.new_zeros(0, 2)


def slot_risks_from_edges(graph: Graph, eps_edge: Tensor) -> tuple[Tensor, Tensor]:
    """Per-slot risks of the agent and of its neighbour from per-edge risks.

    Args:
        graph: the communication graph.
        eps_edge: (E, 2) risk of each end of each edge.

    Returns:
        ``(eps_self, eps_nbr)``, each (K, M); padding slots get 0.25 (their rows are inactive).
    """
    if not graph.num_edges:
        pad = eps_edge.new_full(graph.active.shape, 0.25)
        return pad, pad
    own = eps_edge[graph.slot_edge, graph.slot_side]
    other = eps_edge[graph.slot_edge, 1 - graph.slot_side]
    pad = torch.full_like(own, 0.25)
    return torch.where(graph.active, own, pad), torch.where(graph.active, other, pad)


def edge_separations(plans: Tensor, normals: Tensor, graph: Graph) -> Tensor:
    """Each pair's planned separation along its collision normal at tau = 1,
    ``n^T (x_lo^1 - x_hi^1)`` with the lower-indexed end's normal.

    Args:
        plans: (K, T+1, D) the applied plans.
        normals: (K, M, T, D) the local problems' normals (zero off the position states).
        graph: the communication graph.

    Returns:
        (E,) separations.
    """
    sep = plans.new_full((graph.num_edges,), float("nan"))
    k, m = torch.nonzero(graph.active & (graph.slot_side == 0), as_tuple=True)
    e = graph.slot_edge[k, m]
    lo, hi = graph.edges[e, 0], graph.edges[e, 1]
    sep[e] = (normals[k, m, 0] * (plans[lo, 1] - plans[hi, 1])).sum(-1)
    return sep


def pair_risk_bounds(separation: Tensor, variance: Tensor, r_safe: float | Tensor) -> Tensor:
    """The bound on a pair's collision probability at the next sample,
    ``Phi(-(separation - r_safe) / sqrt(variance))``.

    Args:
        separation: (E,) planned separation along the normal at tau = 1.
        variance: (E,) ``s_k + s_j``, the two agents' variances along the normal.
        r_safe: the required centre distance: a number, or one per edge (E,) (``r_k + r_j``).

    Returns:
        (E,) probabilities (0 or 1 where the variance is 0; NaN where an input is).
    """
    gap = separation - r_safe
    std = variance.clamp_min(0.0).sqrt()
    random = std > 0
    tail = torch.special.ndtr(-gap / torch.where(random, std, torch.ones_like(std)))
    bound = torch.where(random, tail, (gap < 0).to(gap.dtype))  # no variance: certain either way
    return bound.masked_fill(gap.isnan() | variance.isnan(), float("nan"))


def direction_risk_bounds(positions: Tensor, covariances: Tensor, edges: Tensor, r_safe: float | Tensor) -> Tensor:
    """Each pair's collision bound at the next sample along the direction between its applied
    plans, ``n = (p_k - p_j) / |p_k - p_j|``: ``Phi(-(|p_k - p_j| - r_safe) / sqrt(n^T (S_k + S_j) n))``.

    Any unit vector fixed before the step's noise gives a valid bound (the collision disc lies
    beyond ``n^T (p_k - p_j) >= r_safe``), so the smaller of this and the row normal's bound is one
    too. It matters where the applied plans were not posed against the row normals: a safety
    fallback's re-plan in its Voronoi cell, or an earlier plane iterate, can leave a pair far
    apart and yet close along the stale normal.

    Args:
        positions: (K, P) the applied plans' positions at tau = 1.
        covariances: (K, P, P) the agents' position covariances at tau = 1.
        edges: (E, 2) the pairs.
        r_safe: the required centre distance: a number, or one per edge (E,).

    Returns:
        (E,) probabilities (:func:`pair_risk_bounds`).
    """
    lo, hi = edges[:, 0], edges[:, 1]
    diff = positions[lo] - positions[hi]
    distance = torch.linalg.vector_norm(diff, dim=-1)
    n = diff / distance.clamp_min(1e-12)[:, None]
    variance = torch.einsum("ep,epq,eq->e", n, covariances[lo] + covariances[hi], n)
    return pair_risk_bounds(distance, variance, r_safe)


def obstacle_risk_bounds(plans: Tensor, normals: Tensor, bounds: Tensor, std: Tensor) -> Tensor:
    """Each agent's bound on hitting each obstacle of its rows at the next sample,
    ``Phi(-(n^T x^1 - b) / s)``: the obstacle, grown by the body radius, lies beyond the row's
    half-space ``n^T x >= b``.

    Args:
        plans: (K, T+1, D) the applied plans.
        normals: (K, L, T, D) the obstacle rows' normals (zero off the position states).
        bounds: (K, L, T) their bounds without chance margins.
        std: (K, L, T) the agents' standard deviations along the normals (0: a certain state).

    Returns:
        (K,) the sum over each agent's L rows of the bound at tau = 1.
    """
    separation = (normals[:, :, 0] * plans[:, None, 1]).sum(-1)
    per_row = pair_risk_bounds(separation, std[:, :, 0].square(), bounds[:, :, 0])
    return torch.nan_to_num(per_row, nan=0.0).sum(dim=1)


def agent_charges(bounds: Tensor, eps_edge: Tensor, graph: Graph) -> Tensor:
    """What each agent is charged for a step: its share ``p eps_k / (eps_k + eps_j)`` of every
    edge's bound, summed over its edges.

    Args:
        bounds: (E,) the pairs' bounds (:func:`pair_risk_bounds`; NaN counts as 0).
        eps_edge: (E, 2) the step's risk of each end.
        graph: the communication graph.

    Returns:
        (K,) charges.
    """
    charge = torch.zeros(graph.num_agents, dtype=eps_edge.dtype)
    if not graph.num_edges:
        return charge
    share = torch.nan_to_num(bounds, nan=0.0)[:, None] * eps_edge / eps_edge.sum(dim=1, keepdim=True)
    return charge.index_add(0, graph.edges.reshape(-1), share.reshape(-1))


def pair_matrix(values: Tensor, graph: Graph) -> Tensor:
    """Per-edge values as a symmetric (K, K) matrix, NaN off the edges."""
    out = values.new_full((graph.num_agents, graph.num_agents), float("nan"))
    if graph.num_edges:
        lo, hi = graph.edges[:, 0], graph.edges[:, 1]
        out[lo, hi] = values
        out[hi, lo] = values
    return out
