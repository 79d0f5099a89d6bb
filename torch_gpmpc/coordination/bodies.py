"""Body sizes: how far apart a pair's centres must stay, and an agent's centre from an obstacle.

Without ``radii`` every agent is a disc (ball) of radius ``r_safe / 2``: a pair keeps ``r_safe``
and the scalar is used as is (so runs without radii are unchanged to the bit). With ``radii``
(one per agent, ``ControllerSettings.radii``) a pair (k, j) keeps ``r_k + r_j`` and agent k keeps
``r_k`` from every obstacle. A radius is a constant of the team, like an agent's id: the
distributed backend's mission message (the run configuration) carries them all, and no ADMM
message does.
"""

from __future__ import annotations

import torch
from torch import Tensor

from torch_gpmpc.config.settings import ControllerSettings, agent_radii


def body_radii(settings: ControllerSettings, agent_ids: Tensor) -> Tensor | float:
    """The body radius of each agent in ``agent_ids`` (B,) -> (B,) float64, or ``r_safe / 2``."""
    if settings.radii is None:
        return settings.r_safe / 2
    return torch.tensor(settings.radii, dtype=torch.float64)[agent_ids]


def slot_distances(settings: ControllerSettings, agent_ids: Tensor, slot_nbr: Tensor) -> Tensor | float:
    """The centre distance each slot's collision rows ask: ``r_k + r_j`` (or ``r_safe``) plus
    ``pair_buffer`` -> (B, M, 1) (broadcast over the horizon), or a number without radii.

    Args:
        agent_ids: (B,) the agents. slot_nbr: (B, M) their neighbour per slot (any id where inactive).
    """
    if settings.radii is None:
        return settings.r_safe + settings.pair_buffer
    radii = torch.tensor(settings.radii, dtype=torch.float64)
    return (radii[agent_ids][:, None] + radii[slot_nbr])[..., None] + settings.pair_buffer


def edge_distances(settings: ControllerSettings, edges: Tensor) -> Tensor | float:
    """The required centre distance of each edge ``(lo, hi)`` (E, 2) -> (E,), or ``r_safe``."""
    if settings.radii is None:
        return settings.r_safe
    radii = torch.tensor(settings.radii, dtype=torch.float64)
    return radii[edges[:, 0]] + radii[edges[:, 1]]


def pair_distances(radii: tuple[float, ...] | None, r_safe: float, num_agents: int) -> Tensor:
    """The required centre distance of every pair, (K, K) float64: ``r_k + r_j`` (``r_safe``
    without radii)."""
    r = torch.tensor(agent_radii(radii, r_safe, num_agents), dtype=torch.float64)
    return r[:, None] + r[None, :]
