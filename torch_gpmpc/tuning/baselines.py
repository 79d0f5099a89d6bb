"""Baselines the tuned values are compared with: a grid search over rho and the split that
equalizes the pair's margins."""

from __future__ import annotations

from typing import Any, Sequence
import torch
from torch import Tensor
from torch_gpmpc.tuning.objective import TuningObjective


def grid_search_rho(objective: TuningObjective, rhos: Sequence[float], split: Tensor | float | None = None
                    ) -> dict[str, Any]:
    """Evaluate the objective (no gradients) at each rho with a fixed split.

    Args:
        objective: the objective.
        rhos: candidate penalties.
        split: the split (default ``cfg.risk_split``).

    Returns:
        ``{"rhos": [...], "losses": [...], "best_rho": r, "best_loss": l, "evaluations": n}``.
    """
    losses = []
    with torch.no_grad():
        for rho in rhos:
            losses.append(float(objective(rho=torch.tensor(float(rho)), split=split).loss))
    best = min(range(len(losses)), key=losses.__getitem__)
    return {"rhos": [float(r) for r in rhos], "losses": losses, "best_rho": float(rhos[best]),
            "best_loss": losses[best], "evaluations": len(losses)}


def equalizing_split(sigma_lo: float, sigma_hi: float, eps: float, tol: float = 1e-14) -> float:
    """The split ``s`` with ``Phi^-1(1 - eps s) sigma_lo = Phi^-1(1 - eps (1 - s)) sigma_hi``.

    It minimizes the larger of the two agents' margins ``max_k Phi^-1(1 - eps_k) sigma_k``
    over splits with ``eps_lo + eps_hi = eps``: the lower agent's margin decreases in
    ``s`` and the higher one's increases, so the minimum of their max is where they meet
    (found by bisection; the ends are used if they never meet).

    Args:
        sigma_lo: the lower-indexed agent's standard deviation along the normal (>= 0).
        sigma_hi: the higher-indexed agent's (>= 0).
        eps: the pair's total risk, in (0, 1).
        tol: bisection tolerance on ``s``.
    """
    from statistics import NormalDist

    q = NormalDist().inv_cdf

    def excess(s: float) -> float:  # decreasing in s
        return q(1 - eps * s) * sigma_lo - q(1 - eps * (1 - s)) * sigma_hi

    lo, hi = 1e-15, 1 - 1e-15
    if excess(lo) <= 0:
        return lo
    if excess(hi) >= 0:
        return hi
    while hi - lo > tol:
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if excess(mid) > 0 else (lo, mid)
    return 0.5 * (lo + hi)
