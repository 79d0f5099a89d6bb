"""The copies' consensus (``admm_coupling = copies``): one ADMM iteration's arithmetic around the
local solves, written once for the torch path (:meth:`~.admm.ADMM.iterate`), the compiled
iterations (:mod:`~.steady`) and the distributed agents (:mod:`~.distributed.agent`).

Before the solves, each slot's consensus terms (:func:`slot_consensus`: its halves of the edge's
consensus ``z_e`` and this agent's duals); after them, :func:`copies_update`: the consensus (eq. 28)
and dual (eq. 29) updates of every edge, its residuals and tolerances (:mod:`~.penalty`), and, with
``rho_update = adaptive``, its next penalty by residual balancing.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from torch_gpmpc.config.settings import ControllerSettings
from torch_gpmpc.coordination.graph import Graph
from torch_gpmpc.coordination.penalty import EdgeResiduals, balance_penalty, edge_residuals


@dataclass
class SlotConsensus:
    """Each slot's consensus terms of the selected agents, shapes (B, M, T+1, n).

    Attributes:
        z_own, z_nbr: the slot's edge consensus: the agent's own half and its neighbour's.
        lam_own, lam_nbr: the agent's duals on those halves.
    """

    z_own: Tensor
    z_nbr: Tensor
    lam_own: Tensor
    lam_nbr: Tensor


def slot_consensus(z: Tensor, lam: Tensor, graph: Graph, rows: slice | Tensor = slice(None)) -> SlotConsensus:
    """The consensus terms of agents ``rows`` (B of them), slot by slot.

    Args:
        z: (E, 2, T+1, n) consensus. lam: (E, 2 [holder], 2 [half], T+1, n) duals.
        graph: the communication graph. rows: which agents (default all).
    """
    slot_edge, side = graph.slot_edge[rows], graph.slot_side[rows]
    r = torch.arange(slot_edge.shape[0])[:, None]
    c = torch.arange(graph.num_slots)[None, :]
    z_slot = z[slot_edge]  # (B, M, 2, T+1, n)
    lam_mine = lam[slot_edge][r, c, side]  # (B, M, 2, T+1, n): this agent's duals
    return SlotConsensus(z_slot[r, c, side], z_slot[r, c, 1 - side], lam_mine[r, c, side], lam_mine[r, c, 1 - side])


def consensus_update(copies: Tensor, z: Tensor, lam: Tensor, rho: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Consensus (eq. 28) and dual (eq. 29) updates of every edge.

    Args:
        copies: (E, 2 [holder], 2 [half], T+1, n) both ends' copies ``y_{e,a}`` of ``z_e``.
        z: (E, 2, T+1, n) previous consensus.
        lam: (E, 2, 2, T+1, n) previous duals, ``lam[e, a]`` held by end ``a``.
        rho: ADMM penalty: a scalar, or (E,) one per edge.

    Returns:
        ``(z_new (E, 2, T+1, n), lam_new (E, 2, 2, T+1, n), primal (E, 2), dual (E,))`` with
        ``primal[e, a] = ||y_{e,a} - z_new_e||`` and ``dual[e] = rho ||z_new_e - z_e||``.
    """
    z_new = copies.mean(dim=1)
    gap = copies - z_new.unsqueeze(1)
    rho_e = rho.reshape(-1, 1, *[1] * (z.dim() - 1)) if rho.dim() == 1 else rho  # per edge: (E, 1, 1, 1, 1)
    lam_new = lam + rho_e * gap
    primal = gap.flatten(2).norm(dim=2)
    dual = rho * (z_new - z).flatten(1).norm(dim=1)
    return z_new, lam_new, primal, dual


@dataclass
class CopiesUpdate:
    """One iteration's update of every edge (:func:`copies_update`).

    Attributes:
        z: (E, 2, T+1, n) consensus. lam: (E, 2, 2, T+1, n) duals.
        rho: (E,) the next penalties with ``rho_update = adaptive``, else ``None``.
        gaps: (E, 2) ``||y_{e,a} - z_e||``. dual: (E,) ``rho_e ||z_e - z_e_prev||``.
        residuals: the residuals with the configured tolerances (what balancing reads).
        stop: the same with the stopping test's tolerance.
    """

    z: Tensor
    lam: Tensor
    rho: Tensor | None
    gaps: Tensor
    dual: Tensor
    residuals: EdgeResiduals
    stop: EdgeResiduals


def copies_update(copies: Tensor, z: Tensor, lam: Tensor, rho: Tensor, settings: ControllerSettings,
                  tol: float | None = None, ends: tuple[Tensor, Tensor] | None = None) -> CopiesUpdate:
    """The consensus, duals, residuals and next penalties of every edge from both ends' copies.

    Args:
        copies: (E, 2, 2, T+1, n) both ends' copies. z, lam: the previous consensus and duals.
        rho: the penalty the iteration solved with: (E,) with ``rho_update = adaptive``, else 0-d.
        settings: tolerances, stopping and penalty rules.
        tol: the stopping test's absolute primal tolerance (default ``settings.admm_tol``).
        ends: ``(edges, holders)``, int64 each: the edge ends whose duals' norms the dual tolerances
            read (both ends of an edge have the same norm, :func:`~.penalty.edge_residuals`); default
            end 0 of every edge. A distributed agent knows only its own ends' (other edges: 0).
    """
    z_new, lam_new, gaps, dual = consensus_update(copies, z, lam, rho)
    if ends is None:
        lam_norm = lam_new[:, 0].flatten(1).norm(dim=1)
    else:
        lam_norm = lam_new.new_zeros(lam_new.shape[0])
        lam_norm[ends[0]] = lam_new[ends[0], ends[1]].flatten(1).norm(dim=1)
    res = edge_residuals(copies, z_new, lam_norm, gaps, dual, settings)
    stop = res if tol is None or tol == settings.admm_tol else \
        edge_residuals(copies, z_new, lam_norm, gaps, dual, settings, tol)
    rho_next = balance_penalty(rho, res) if settings.rho_update == "adaptive" else None
    return CopiesUpdate(z_new, lam_new, rho_next, gaps, dual, res, stop)
