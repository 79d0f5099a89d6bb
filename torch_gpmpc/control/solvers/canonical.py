"""The fast solver's problem data: :class:`~torch_gpmpc.control.problem.LocalProblemData` in the
solver's variables (torch, differentiable): the dynamics condensed (``X_{1..T} = G U + h``), so only
the inputs, the neighbour copies and the row slacks remain (:class:`CanonicalData`), with the soft
state rows appended as slots without a copy. :mod:`~torch_gpmpc.control.solvers.interior_point` hands
the result to the compiled kernels."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from torch_gpmpc.control.constraints import LocalConstraints
from torch_gpmpc.control.cost import horizon_weights
from torch_gpmpc.control.problem import ConsensusTerms, LocalProblemData


def condense_dynamics(x0: Tensor, dyn_A: Tensor, dyn_c: Tensor, dyn_B: Tensor) -> tuple[Tensor, Tensor]:
    """Eliminate the dynamics: ``X_{1..T} = G U + h`` (differentiable).

    With ``X_0 = x0`` and ``X_{t+1} = A_t X_t + B_t U_t + c_t``, block row ``t`` of ``G``
    is ``A_{t-1} ... A_{k+1} B_k`` in block column ``k < t`` and ``B_{t-1}`` for ``k = t - 1``.

    Args:
        x0: initial states, shape (B, D).
        dyn_A: state matrices, shape (B, T, D, D).
        dyn_c: offsets, shape (B, T, D).
        dyn_B: input matrices, shape (B, T, D, Du), or one (D, Du) matrix for every step.

    Returns:
        ``(G, h)`` with G of shape (B, T*D, T*Du) and h of shape (B, T*D), states and
        inputs flattened time-major (index ``t * D + d``, ``t * Du + j``).
    """
    batch, horizon, dim = dyn_c.shape
    dyn_B = dyn_B.expand(batch, horizon, *dyn_B.shape[-2:])
    du = dyn_B.shape[-1]
    n = horizon * du
    # What step t adds to the augmented block row [G_t | h_t]: B_t in block column t and
    # c_t in the last column; shape (B, T, D, n + 1).
    eye = torch.eye(horizon, dtype=dyn_c.dtype, device=dyn_c.device)
    blocks = torch.einsum("ts,btdj->btdsj", eye, dyn_B).reshape(batch, horizon, dim, n)
    inject = torch.cat([blocks, dyn_c[..., None]], dim=3)
    row = torch.cat([x0.new_zeros(batch, dim, n), x0[:, :, None]], dim=2)
    rows = []
    for t in range(horizon):
        row = torch.baddbmm(inject[:, t], dyn_A[:, t], row)  # A_t [G_{t-1} | h_{t-1}] + inject_t
        rows.append(row)
    stacked = torch.cat(rows, dim=1)  # (B, n, n + 1)
    return stacked[:, :, :n], stacked[:, :, n]


@dataclass
class CanonicalData:
    """The local problem in the solver's variables (all differentiable functions of the data).

    Objective (up to constants) over ``u = vec(U)``, ``Y_{j,1..T}`` and ``s``::

        c_X ||G u + h||^2 - l_X . (G u + h) + alpha ||u||^2 + beta ||D u||^2 + g_u . u + 1/2 u^T H_cost u
        + sum_j (rho_y_j / 2 ||Y_j||^2 - w_y_j . Y_j) + slack_penalty * sum(s)

    (``beta ||D u||^2 + g_u . u`` is the input-rate term ``beta sum_t ||U_t - U_{t-1}||^2`` up to a
    constant; D takes first differences, ``g_u = -2 beta U_{-1}`` on U_0. A stated cost
    (:mod:`~torch_gpmpc.control.cost`) adds what differs from ``||X - Xref||^2 + alpha ||U||^2``:
    its Hessian in ``H_cost`` and its linear part in ``g_u``; see :func:`stated_cost_terms`.)

    Attributes:
        G: condensed input-to-state map, shape (B, T*D, T*Du).
        h: condensed free response, shape (B, T*D).
        c_x: quadratic weight of the states, ``1 + sum_{active j} rho_j / 2``, shape (B,).
        l_x: linear weight of X_{1..T}, ``2 Xref + sum_{active j} (rho_j z_own_j - lam_own_j)``,
            shape (B, T*D).
        rho_y: weight of the neighbour copies (1 on inactive slots), shape (B, M).
        w_y: linear weight of Y_{j,1..T}, ``rho_j z_nbr_j - lam_nbr_j`` (0 inactive),
            shape (B, M, T, D).
        y0: the closed-form copies at step 0, ``w_y / rho_y`` at tau = 0, shape (B, M, D).
        normals: collision normals (0 inactive), shape (B, M, T, D); after
            :func:`with_state_rows` also the soft state rows, (B, M + L, T, D).
        bounds: collision bounds (-1 inactive), shape (B, M, T) (then (B, M + L, T)).
        g_u: linear input weight (the input-rate term's and a stated cost's), shape (B, T*Du).
        H_cost: a stated cost's Hessian beyond ``2 G^T G + 2 alpha I`` (0 without one), (B, T*Du, T*Du).
    """

    G: Tensor
    h: Tensor
    c_x: Tensor
    l_x: Tensor
    rho_y: Tensor
    w_y: Tensor
    y0: Tensor
    normals: Tensor
    bounds: Tensor
    g_u: Tensor
    H_cost: Tensor

    def kernel_inputs(self) -> tuple[Tensor, ...]:
        """The fields a solver reads, in the compiled kernels' order (:data:`KERNEL_FIELDS`)."""
        return tuple(getattr(self, name) for name in KERNEL_FIELDS)


#: The :class:`CanonicalData` fields the solvers read, in the compiled kernels' argument order.
KERNEL_FIELDS = ("G", "h", "c_x", "l_x", "rho_y", "w_y", "normals", "bounds", "g_u", "H_cost")


def finite_problems(arrays: list[np.ndarray], y0: Tensor) -> np.ndarray:
    """Which problems have finite canonical data (``arrays``: :meth:`CanonicalData.kernel_inputs` as
    NumPy arrays, and the step-0 copies y0 (B, M, D)) and ``rho > 0`` on every slot, (B,) bool (NumPy,
    on the arrays the kernel reads: a few calls, where the same test in torch cost more than a warm
    solve)."""
    B = arrays[1].shape[0]
    total = y0.detach().cpu().numpy().reshape(B, -1).sum(1)
    for a in arrays:
        total = total + a.reshape(B, -1).sum(1)
    valid = np.isfinite(total)
    rho_y = arrays[KERNEL_FIELDS.index("rho_y")]
    if rho_y.size:
        valid &= (rho_y > 0).all(1)
    return valid


def stated_cost_terms(data: LocalProblemData, G: Tensor, h: Tensor, alpha: float) -> tuple[Tensor, Tensor]:
    """What a stated cost adds to the default one, in the condensed variables (differentiable).

    With ``X_{1..T} = G u + h``, the state weight ``W = blockdiag(Q, .., Q, P)`` of X_1..X_T and
    ``Rbar = blockdiag(R, .., R)``, the stated cost minus ``||X - Xref||^2 + alpha ||u||^2`` is, up to
    a constant, ``1/2 u^T H u + g . u`` with::

        H = 2 G^T (W - I) G + 2 (Rbar - alpha I),   g = 2 G^T (W - I) (h - Xref) - 2 Rbar u_ref

    Returns:
        ``(H (B, n, n), g (B, n))``, n = T Du; zeros when ``data`` states no cost.
    """
    batch, n = G.shape[0], G.shape[2]
    if not data.has_cost:
        return G.new_zeros(batch, n, n), G.new_zeros(batch, n)
    T, D = data.xref.shape[1] - 1, data.xref.shape[2]
    Du = n // T
    eye_x, eye_u = torch.eye(D, dtype=G.dtype, device=G.device), torch.eye(Du, dtype=G.dtype, device=G.device)
    W = horizon_weights(data.cost_Q.to(G), data.cost_P.to(G), T) - eye_x  # (B, T, D, D)
    Gt = G.view(batch, T, D, n)
    WG = torch.einsum("btde,bten->btdn", W, Gt).reshape(batch, T * D, n)
    err = (h - data.xref[:, 1:].reshape(batch, T * D)).view(batch, T, D)
    Werr = torch.einsum("btde,bte->btd", W, err).reshape(batch, T * D)
    dR = data.cost_R.to(G) - alpha * eye_u  # (B, Du, Du)
    eye_t = torch.eye(T, dtype=G.dtype, device=G.device)
    Rbar = torch.einsum("ts,bij->btisj", eye_t, dR).reshape(batch, n, n)  # blockdiag(dR, .., dR)
    H = 2.0 * G.mT @ WG + 2.0 * Rbar
    g = 2.0 * (G.mT @ Werr[..., None])[..., 0]
    if data.u_ref is not None:
        g = g - 2.0 * (data.cost_R.to(G) @ data.u_ref.to(G)[..., None])[..., 0].repeat(1, T)
    return 0.5 * (H + H.mT), g


def input_rate_linear(data: LocalProblemData, beta: float, horizon: int, input_dim: int) -> Tensor:
    """``g_u = -2 beta U_{-1}`` on U_0 and 0 after it, shape (B, T*Du): the linear part of
    ``beta ||U_0 - U_{-1}||^2`` (``data.u_prev`` is U_{-1}; ``None``: 0)."""
    batch = data.x0.shape[0]
    g_u = data.x0.new_zeros(batch, horizon * input_dim)
    if beta != 0.0 and data.u_prev is not None:
        g_u = torch.cat([-2.0 * beta * data.u_prev, g_u[:, input_dim:]], dim=1)
    return g_u


class CondensedCache:
    """The last :func:`condense_dynamics` result, reused while its inputs are the same tensor
    objects, unmodified, under the same autograd mode: within one control step ADMM solves the
    same dynamics at every iteration (only the consensus terms change), and condensing them was
    a quarter of a 3D double-integrator iteration. Inference tensors (made under
    ``torch.inference_mode``, as the closed loop plans) keep no version counter: for them only the
    identity is compared (the planner never writes into its linearization in place)."""

    def __init__(self) -> None:
        self._key: tuple | None = None
        self._value: tuple[Tensor, Tensor] | None = None

    def __call__(self, x0: Tensor, dyn_A: Tensor, dyn_c: Tensor, dyn_B: Tensor) -> tuple[Tensor, Tensor]:
        """``condense_dynamics(x0, dyn_A, dyn_c, dyn_B)``, from the cache when it is the same input."""
        inputs = (x0, dyn_A, dyn_c, dyn_B)
        key = (torch.is_grad_enabled(), tuple(None if t.is_inference() else t._version for t in inputs))
        if self._key is not None and self._key[0] == key and all(a is b for a, b in zip(self._key[1], inputs)):
            return self._value
        self._value = condense_dynamics(*inputs)
        self._key = (key, inputs)  # holding the inputs keeps their identity unique
        return self._value


class CostTermsCache:
    """The last :func:`stated_cost_terms` result, reused while its inputs are the same tensor objects,
    unmodified, under the same autograd mode (as :class:`CondensedCache`): within a control step ADMM
    poses the same dynamics, reference and cost at every iteration."""

    def __init__(self) -> None:
        self._key: tuple | None = None
        self._value: tuple[Tensor, Tensor] | None = None

    def __call__(self, data: LocalProblemData, G: Tensor, h: Tensor, alpha: float) -> tuple[Tensor, Tensor]:
        """``stated_cost_terms(data, G, h, alpha)``, from the cache when it is the same input."""
        inputs = (G, h, data.xref, data.cost_Q, data.cost_R, data.cost_P, data.u_ref)
        key = (torch.is_grad_enabled(), alpha,
               tuple(None if t is None or t.is_inference() else t._version for t in inputs))
        if self._key is not None and self._key[0] == key and all(a is b for a, b in zip(self._key[1], inputs)):
            return self._value
        self._value = stated_cost_terms(data, G, h, alpha)
        self._key = (key, inputs)
        return self._value


def canonicalize(data: LocalProblemData, B: Tensor, condense=condense_dynamics, beta: float = 0.0,
                 alpha: float = 0.0, cost_terms=stated_cost_terms) -> CanonicalData:
    """Map :class:`LocalProblemData` to :class:`CanonicalData` (differentiable).

    Inactive slots get ``rho = 1``, ``w = 0`` (so ``Y_j = 0``), normal 0 and bound -1,
    and contribute nothing to the state cost (as in :class:`~torch_gpmpc.control.solvers.conic.CvxpyLayerMPC`).
    ``B`` (D, Du) is the nominal input matrix, used when ``data.dyn_B`` is ``None``; ``condense``
    is :func:`condense_dynamics` or a :class:`CondensedCache`; ``beta`` is the input-rate weight and
    ``alpha`` the solver's effort weight (what a stated cost replaces); ``cost_terms`` is
    :func:`stated_cost_terms` or a :class:`CostTermsCache`.
    """
    terms = ConsensusTerms.of(data)
    c_x, l_x, rho_y, w_y, y0 = consensus_weights(terms, data.xref)
    G, h = condense(data.x0, data.dyn_A, data.dyn_c, B if data.dyn_B is None else data.dyn_B)
    T = data.xref.shape[1] - 1
    g_u = input_rate_linear(data, beta, T, G.shape[2] // T)
    H_cost, g_cost = cost_terms(data, G, h, alpha)
    if data.has_cost:
        g_u = g_u + g_cost
    return CanonicalData(G=G, h=h, c_x=c_x, l_x=l_x, rho_y=rho_y, w_y=w_y, y0=y0,
                         normals=terms.normals, bounds=terms.bounds, g_u=g_u, H_cost=H_cost)


def consensus_weights(terms: ConsensusTerms, xref: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """The consensus part of :class:`CanonicalData` from the problems' consensus terms and references
    ``xref`` (B, T+1, D): ``(c_x (B,), l_x (B, T D), rho_y (B, M), w_y (B, M, T, D), y0 (B, M, D))``.
    Also what ADMM's compiled iterations write into kept problems
    (:meth:`~torch_gpmpc.coordination.steady.SteadyIterations.write_terms`)."""
    l_x = (2.0 * xref[:, 1:] + terms.w_own[:, :, 1:].sum(dim=1)).flatten(1)
    y0 = terms.w_nbr[:, :, 0] / terms.rho_y[:, :, None]
    return terms.c_x, l_x, terms.rho_y, terms.w_nbr[:, :, 1:], y0


def with_state_rows(canon: CanonicalData, rows: list[tuple[Tensor, Tensor]]) -> CanonicalData:
    """``canon`` with soft state rows appended as slots without a neighbour copy (``rho_y = 1``,
    ``w_y = 0``, so their copies stay 0; the kernel's ``couple`` flag is 0 for them).

    Args:
        rows: ``(normals (B, L, T, D), bounds (B, L, T))`` blocks (per-problem half-spaces, the
            model's and workspace's constant rows expanded over B and T).
    """
    if not rows:
        return canon
    B, T, D = canon.h.shape[0], canon.normals.shape[2], canon.normals.shape[3]
    L = sum(n.shape[1] for n, _ in rows)
    return CanonicalData(
        G=canon.G, h=canon.h, c_x=canon.c_x, l_x=canon.l_x,
        rho_y=torch.cat([canon.rho_y, canon.rho_y.new_ones(B, L)], dim=1),
        w_y=torch.cat([canon.w_y, canon.w_y.new_zeros(B, L, T, D)], dim=1), y0=canon.y0,
        normals=torch.cat([canon.normals, *[n for n, _ in rows]], dim=1),
        bounds=torch.cat([canon.bounds, *[b for _, b in rows]], dim=1), g_u=canon.g_u, H_cost=canon.H_cost)


def state_row_blocks(data: LocalProblemData, constraints: LocalConstraints, num_halfspaces: int,
                     horizon: int, dim: int) -> list[tuple[Tensor, Tensor]]:
    """The soft state rows of ``data``'s B problems as slot blocks for :func:`with_state_rows`: the
    data's L half-spaces (when ``num_halfspaces``), then ``constraints``' constant rows expanded
    over B and the T = ``horizon`` steps; each block ``(normals (B, L', T, D), bounds (B, L', T))``."""
    rows = []
    if num_halfspaces:
        rows.append((data.halfspace_normals, data.halfspace_bounds))
    if constraints.num_rows:
        batch = data.x0.shape[0]
        normals, bounds = constraints.rows(dim, data.x0.dtype, data.x0.device)
        L = normals.shape[0]
        rows.append((normals[None, :, None].expand(batch, L, horizon, dim),
                     bounds[None, :, None].expand(batch, L, horizon)))
    return rows
