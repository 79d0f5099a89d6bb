"""Unrolled ADMM: a fixed number of iterations with gradients through every local solve,
and the tensor residuals and distance penalty the objective is built from."""

from __future__ import annotations

import dataclasses

import warnings
from dataclasses import dataclass
import torch
from torch import Tensor
from torch_gpmpc.coordination.admm import ADMM, ADMMState, StepResult, adapt_state, initial_state
from torch_gpmpc.coordination.agent_step import edge_copies
from torch_gpmpc.errors import GpmpcError
from torch_gpmpc.coordination.graph import Graph


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
    """Run exactly ``warmup_iters`` (no gradient) + ``iters`` (differentiable) ADMM iterations.

    Args:
        admm: the ADMM (its config gives horizon, eps, r_safe, relinearize).
        x0: (K, D) states.
        xref: (K, T+1, D) reference window.
        graph: the communication graph.
        iters: unrolled iterations (>= 1).
        rho: 0-d tensor penalty.
        split: scalar or (K, K) risk split.
        warm: warm start (already shifted), or ``None`` for a cold start.
        warmup_iters: iterations run first under ``torch.no_grad`` at the same parameters.

    Returns:
        The :class:`UnrolledStep`.
    """
    if iters < 1:
        raise GpmpcError(f"unroll_admm: iters must be >= 1, got {iters}")
    state = initial_state(x0.detach(), admm.cfg.horizon, graph, admm.local.nominal.input_dim) if warm is None \
        else adapt_state(warm, graph)
    lin_plans, lin_inputs = state.plans, state.inputs  # relinearize=False keeps these
    if warmup_iters > 0:
        with torch.no_grad():
            res = admm.solve_step(x0.detach(), xref, graph, warm=state, rho=rho.detach(),
                                  risk_split=_detach(split), max_iter=warmup_iters, tol=0.0,
                                  safety_fallback=False)
        state = detached_state(res.state)
        if not admm.cfg.relinearize:
            state = dataclasses.replace(state, plans=lin_plans.detach(), inputs=lin_inputs.detach())
    adaptive = admm.cfg.rho_update == "adaptive"
    if adaptive:  # the tuned rho is every edge's start; residual balancing adapts it from there
        state = dataclasses.replace(state, rho=torch.as_tensor(rho, dtype=torch.float64).expand(graph.num_edges))
    primal, dual = [], []
    res = None
    for _ in range(iters):
        z_prev = state.z
        rho_used = state.rho if adaptive else rho
        with warnings.catch_warnings():  # solve_step logs float() of residuals that carry gradients
            warnings.filterwarnings("ignore", message="Converting a tensor with requires_grad=True")
            res = admm.solve_step(x0, xref, graph, warm=state, rho=rho, risk_split=split, max_iter=1, tol=0.0,
                                 safety_fallback=False)
        new = res.state
        if graph.num_edges:
            copies = edge_copies(res.solution, graph)  # (E, 2, 2, T+1, D)
            gap = copies - new.z.unsqueeze(1)
            primal.append(torch.sqrt(gap.pow(2).sum(dim=(2, 3, 4)).mean() + _SQRT_FLOOR))
            dual.append(torch.sqrt((rho_used * (new.z - z_prev).flatten(1).norm(dim=1)).pow(2).mean() + _SQRT_FLOOR))
        else:
            primal.append(x0.new_zeros(()))
            dual.append(x0.new_zeros(()))
        state = new if admm.cfg.relinearize else dataclasses.replace(new, plans=lin_plans, inputs=lin_inputs)
    res.state = new
    return UnrolledStep(result=res, primal=torch.stack(primal), dual=torch.stack(dual))


def _detach(x: Tensor | float) -> Tensor | float:
    return x.detach() if isinstance(x, Tensor) else x


def detached_state(s: ADMMState) -> ADMMState:
    return ADMMState(s.plans.detach(), s.inputs.detach(), s.edges, s.z.detach(), s.lam.detach(),
                     None if s.pvar is None else s.pvar.detach(), None if s.rho is None else s.rho.detach())


def distance_penalty(plans: Tensor, r_safe: float, width: float) -> Tensor:
    """Smooth penalty on planned pair distances below ``r_safe``.

    ``sum_{tau=1..T} sum_{k<j} width * softplus((r_safe - ||X_k^tau - X_j^tau||) / width)``
    divided by the number of pairs.

    Args:
        plans: (K, T+1, D) planned states.
        r_safe: safety radius.
        width: softplus width beta > 0.

    Returns:
        0-d tensor (0 for K < 2).
    """
    K = plans.shape[0]
    if K < 2:
        return plans.new_zeros(())
    i, j = torch.triu_indices(K, K, 1)
    diff = plans[i, 1:] - plans[j, 1:]  # (P, T, D)
    dist = torch.sqrt(diff.pow(2).sum(-1) + _SQRT_FLOOR)
    return width * torch.nn.functional.softplus((r_safe - dist) / width).sum() / i.numel()
