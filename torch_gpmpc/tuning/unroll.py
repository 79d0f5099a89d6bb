"""Unrolled ADMM: a fixed number of iterations with gradients through every local solve,
and the tensor residuals and distance penalty the objective is built from."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Sequence

import torch
from torch import Tensor

from torch_gpmpc.coordination.admm import ADMM, ADMMState, StepResult
from torch_gpmpc.coordination.agent_step import edge_copies
from torch_gpmpc.coordination.graph import Graph
from torch_gpmpc.errors import GpmpcError


#: Added under square roots of residuals (keeps gradients finite at an exact consensus).
_SQRT_FLOOR = 1e-24


@dataclass
class UnrolledStep:
    """ADMM at one time step, unrolled for a fixed number of iterations.

    Attributes:
        result: the last iteration's :class:`StepResult` (``result.solution`` and
            ``result.state`` carry gradients).
        primal: per unrolled iteration, ``r_p`` (see the module docstring), shape (I,).
        dual: per unrolled iteration, ``r_d``, shape (I,).
    """

    result: StepResult
    primal: Tensor
    dual: Tensor


def unroll_admm(
    admm: ADMM,
    x0: Tensor,
    xref: Tensor,
    graph: Graph,
    iters: int,
    rho: Tensor,
    split: Tensor | float,
    warm: ADMMState | None = None,
    warmup_iters: int = 0,
) -> UnrolledStep:
    """Run exactly ``warmup_iters`` (no gradient) + ``iters`` (differentiable) ADMM iterations:
    the step's loop of :meth:`ADMM.iterate` with no stopping test and no safety fallback.

    Args:
        admm: the ADMM (its settings give horizon, eps, r_safe, relinearize).
        x0: (K, n) states.
        xref: (K, T+1, n) reference window.
        graph: the communication graph.
        iters: unrolled iterations (>= 1).
        rho: 0-d tensor penalty (with ``rho_update = adaptive``: every edge's start).
        split: scalar or (K, K) risk split.
        warm: warm start (already shifted), or ``None`` for a cold start.
        warmup_iters: iterations run first under ``torch.no_grad`` at the same parameters.

    Returns:
        The :class:`UnrolledStep`.
    """
    if iters < 1:
        raise GpmpcError(f"unroll_admm: iters must be >= 1, got {iters}")
    ctx, state = admm.prepare(x0, xref, graph, warm, rho, split)
    if warmup_iters > 0:
        with torch.no_grad():
            for _ in range(warmup_iters):
                state, _ = admm.iterate(ctx, state)
        state = state.detached()
        ctx.linearization = None  # computed without gradients: recompute in the unrolled iterations
    if admm.settings.rho_update == "adaptive":  # the tuned rho is every edge's start
        state = dataclasses.replace(state, rho=torch.as_tensor(rho, dtype=torch.float64).expand(graph.num_edges))
    result = StepResult(plans=state.plans, inputs=state.inputs, state=state, iterations=0, converged=False)
    primal, dual = [], []
    for _ in range(iters):
        z_prev, rho_used = state.z, state.rho if state.rho is not None else ctx.rho
        state, stats = admm.iterate(ctx, state)
        result.record(stats)
        if graph.num_edges:
            copies = edge_copies(stats.solution, graph)  # (E, 2, 2, T+1, n)
            gap = copies - state.z.unsqueeze(1)
            primal.append(torch.sqrt(gap.pow(2).sum(dim=(2, 3, 4)).mean() + _SQRT_FLOOR))
            dual.append(torch.sqrt((rho_used * (state.z - z_prev).flatten(1).norm(dim=1)).pow(2).mean()
                                   + _SQRT_FLOOR))
        else:
            primal.append(x0.new_zeros(()))
            dual.append(x0.new_zeros(()))
    result.plans, result.inputs, result.state = state.plans, state.inputs, state
    return UnrolledStep(result=result, primal=torch.stack(primal), dual=torch.stack(dual))


def distance_penalty(plans: Tensor, r_safe: float, width: float, radii: Sequence[float] | None = None) -> Tensor:
    """Smooth penalty on planned pair distances below ``r_safe`` (``r_k + r_j`` with ``radii``).

    ``sum_{tau=1..T} sum_{k<j} width * softplus((r_safe - ||X_k^tau - X_j^tau||) / width)``
    divided by the number of pairs.

    Args:
        plans: (K, T+1, D) planned states.
        r_safe: safety radius.
        width: softplus width beta > 0.
        radii: each agent's body radius (K), or ``None`` (every pair keeps ``r_safe``).

    Returns:
        0-d tensor (0 for K < 2).
    """
    K = plans.shape[0]
    if K < 2:
        return plans.new_zeros(())
    i, j = torch.triu_indices(K, K, 1)
    diff = plans[i, 1:] - plans[j, 1:]  # (P, T, D)
    dist = torch.sqrt(diff.pow(2).sum(-1) + _SQRT_FLOOR)
    if radii is not None:
        body = torch.as_tensor(radii, dtype=dist.dtype, device=dist.device)
        r_safe = (body[i] + body[j])[:, None]  # (P, 1): each pair's distance, every step
    return width * torch.nn.functional.softplus((r_safe - dist) / width).sum() / i.numel()
