"""What a tuning run writes and what a run reads back: the tuned.json payload and the
per-edge risk split."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Mapping, Sequence
import torch
from torch import Tensor
from torch_gpmpc.config.schema import Config
from torch_gpmpc.errors import GpmpcError
from torch_gpmpc.tuning.parameters import TuningParameters
from torch_gpmpc.tuning.tuner import Tuner


def tuned_payload(cfg: Config, params: TuningParameters, tuner: Tuner | None = None,
                  edges: Sequence[Sequence[int]] | None = None, extra: Mapping[str, Any] | None = None
                  ) -> dict[str, Any]:
    """The content of ``tuned.json``.

    ``config`` holds every flat config key with ``rho`` the tuned penalty and
    ``risk_split`` the mean tuned split over ``edges`` (``Config`` has one scalar
    split), so ``gpmpc run --config tuned.json`` accepts it; the per-edge splits are in
    ``risk_split_per_edge`` (``"lo_hi"`` keys; read them with :func:`load_risk_split`).
    """
    rho = float(params.rho().detach())
    mean_split = min(max(params.mean_split(edges), 1e-9), 1 - 1e-9)
    config = cfg.replace(rho=rho, risk_split=mean_split).to_dict()
    payload: dict[str, Any] = {
        "config": config,
        "risk_split_per_edge": params.split_per_edge(edges),
        "history": [r.to_dict() for r in tuner.history] if tuner is not None else [],
    }
    if extra:
        payload.update(extra)
    return payload


def load_risk_split(path: str | Path, num_agents: int) -> Tensor:
    """The per-edge split of a ``tuned.json`` as a (K, K) tensor for ``ADMM.solve_step``.

    Pairs missing from ``risk_split_per_edge`` get the file's scalar ``risk_split``.

    Raises:
        GpmpcError: unreadable file or a key naming an agent >= ``num_agents``.
    """
    try:
        data = json.loads(Path(path).read_text())
        default = float(data["config"]["risk_split"])
        per_edge = data.get("risk_split_per_edge", {})
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise GpmpcError(f"{str(path)!r} is not a tuned.json from gpmpc tune: {exc}") from exc
    out = torch.full((num_agents, num_agents), default, dtype=torch.float64)
    for key, value in per_edge.items():
        lo, hi = (int(v) for v in key.split("_"))
        if max(lo, hi) >= num_agents:
            raise GpmpcError(f"{str(path)!r}: risk_split_per_edge has pair {key} but the run has {num_agents} agents")
        out[lo, hi] = float(value)
    return out
