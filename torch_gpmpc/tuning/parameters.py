"""The tuned quantities: the global penalty rho and the per-edge risk split, and the objective's weights."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence
import torch
from torch import Tensor, nn
from torch_gpmpc.config.tune_settings import TuneSettings
from torch_gpmpc.errors import GpmpcError


@dataclass(frozen=True)
class ObjectiveWeights:
    """Weights of the tuning objective (see :mod:`torch_gpmpc.tuning`).

    Attributes:
        primal: weight of the final primal residual ``r_p``.
        dual: weight of the final dual residual ``r_d``.
        cost: weight of the mean planned cost per agent.
        distance: weight of the softplus penalty on planned distances below r_safe.
        distance_width: the softplus width beta (> 0).
    """

    primal: float = 1.0
    dual: float = 1.0
    cost: float = 0.01
    distance: float = 10.0
    distance_width: float = 0.05

    @classmethod
    def from_settings(cls, settings: TuneSettings) -> "ObjectiveWeights":
        """The weights of a run's :class:`~torch_gpmpc.config.tune_settings.TuneSettings`."""
        return cls(settings.w_primal, settings.w_dual, settings.w_cost, settings.w_distance,
                   settings.distance_width)


class TuningParameters(nn.Module):
    """The tuned quantities: ``log_rho`` () and per-edge split logits ``theta`` (K, K).

    Args:
        num_agents: K.
        rho: initial penalty (> 0).
        split: initial split of every edge, in (0, 1), or a (K, K) tensor (entry
            ``[lo, hi]`` per edge).
    """

    def __init__(self, num_agents: int, rho: float = 20.0, split: float | Tensor = 0.5) -> None:
        super().__init__()
        if rho <= 0:
            raise GpmpcError(f"rho must be > 0, got {rho}")
        split_t = torch.as_tensor(split, dtype=torch.float64).expand(num_agents, num_agents).clone()
        if not bool(((split_t > 0) & (split_t < 1)).all()):
            raise GpmpcError("risk split must be in (0, 1)")
        self.num_agents = int(num_agents)
        self.log_rho = nn.Parameter(torch.tensor(math.log(rho), dtype=torch.float64))
        self.theta = nn.Parameter(torch.logit(split_t))

    def rho(self) -> Tensor:
        """``exp(log_rho)``, a 0-d tensor."""
        return self.log_rho.exp()

    def split(self) -> Tensor:
        """``sigmoid(theta)``, shape (K, K): the lower-indexed agent's share per edge."""
        return torch.sigmoid(self.theta)

    def split_per_edge(self, edges: Sequence[Sequence[int]] | None = None) -> dict[str, float]:
        """``{"lo_hi": s}`` for the given edges (default: all pairs ``lo < hi``)."""
        split = self.split().detach()
        if edges is None:
            edges = [(i, j) for i in range(self.num_agents) for j in range(i + 1, self.num_agents)]
        return {f"{lo}_{hi}": float(split[lo, hi]) for lo, hi in edges}

    def mean_split(self, edges: Sequence[Sequence[int]] | None = None) -> float:
        """Mean split over the given edges (default all pairs); 0.5 for K < 2."""
        values = list(self.split_per_edge(edges).values())
        return float(sum(values) / len(values)) if values else 0.5
