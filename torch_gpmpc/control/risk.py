"""Chance-constrained collision margins (paper sections 3.1-3.3), pure and differentiable.

Agent k keeps its linearized distance to neighbour j above a tightened radius
(paper eq. 24)::

    n^T (x_k - x_j) >= r_safe + Phi^{-1}(1 - eps_k) * sqrt(n^T Sigma_k n),
    n = rbar / ||rbar||,  rbar = xbar_k - xbar_j,

where ``eps_k + eps_j = eps`` is the pair's risk budget (eq. 21) and ``Sigma_k`` is
agent k's *own* state covariance (eq. 22). That is the paper's margin (``pair_margin = own``);
it is not sound, because both agents deviate. The default (``sum``) adds the neighbour's
margin, computed from the T projected variances ``n^T Sigma_j n`` the neighbour sends with
its copy (:func:`pair_margins`); no covariance matrix leaves an agent. The controller computes
every margin on one path: :func:`state_covariances` -> :func:`projected_variances` ->
:func:`pair_margins`. Every function here is plain torch, so gradients reach the total risk
``eps``, the risk split and the covariances.
"""

from __future__ import annotations

import torch
from torch import Tensor

from torch_gpmpc.config.settings import UNCERTAINTY_MODES
from torch_gpmpc.errors import GpmpcError

#: Below this distance two linearization points count as coincident.
COINCIDENT_TOL = 1e-9

#: Variances below this give a zero margin (keeps sqrt's gradient finite).
_VAR_FLOOR = 1e-30


def pair_risks(eps: Tensor | float, split: Tensor | float) -> tuple[Tensor, Tensor]:
    """Split a pair's risk budget between its two agents (paper eq. 21).

    Args:
        eps: total collision risk of the pair, in (0, 1); any shape.
        split: share taken by the lower-indexed agent of the pair, in (0, 1);
            broadcastable with ``eps``.

    Returns:
        ``(eps_low, eps_high) = (eps * split, eps * (1 - split))``: the risks of the
        lower- and higher-indexed agent; they sum to ``eps``.
    """
    eps = torch.as_tensor(eps, dtype=torch.float64)
    split = torch.as_tensor(split, dtype=eps.dtype)
    return eps * split, eps * (1.0 - split)


def chance_quantile(eps_k: Tensor | float) -> Tensor:
    """Standard-normal quantile ``Phi^{-1}(1 - eps_k)`` (1.6449 for ``eps_k = 0.05``).

    Args:
        eps_k: an agent's risk level(s), in (0, 1); any shape.

    Returns:
        Quantiles, same shape as ``eps_k``.
    """
    eps_k = torch.as_tensor(eps_k, dtype=torch.float64)
    return torch.special.ndtri(1.0 - eps_k)


def state_covariances(mode: str, var: Tensor, dyn_A: Tensor, feedback: Tensor | None = None) -> Tensor:
    """Covariance of each planned state.

    ``pointwise`` (the paper): ``Sigma_tau = diag(var_tau)``, the GP variance at the
    linearization point ``xbar_tau`` alone.

    ``propagated`` (beyond the paper, cf. its discussion section): the state at
    ``tau = 0`` is measured, ``Sigma_0 = 0``, and the linearized dynamics
    ``x_{tau+1} = dyn_A_tau x_tau + B u_tau + dyn_c_tau + e_tau``, with independent
    ``e_tau ~ N(0, diag(var_tau))``, give
    ``Sigma_{tau+1} = dyn_A_tau Sigma_tau dyn_A_tau^T + diag(var_tau)``.

    ``feedback``: as ``propagated``, but the plan is tracked by an ancillary feedback
    ``u = u_plan + K (x - x_plan)`` (tube MPC, zero-order robust MPC), so deviations evolve
    by ``dyn_A_tau + B K``: ``Sigma_{tau+1} = (dyn_A_tau + B K) Sigma_tau (...)^T + diag(var_tau)``.
    With a stabilizing K this stays bounded; open loop it grows like tau with noise.

    Args:
        mode: ``"pointwise"``, ``"propagated"`` or ``"feedback"``.
        var: per-dimension variances at the linearization points, shape (B, T+1, D).
        dyn_A: linearized state matrices, shape (B, T, D, D) (used by ``propagated``, ``feedback``).
        feedback: ``B K``, shape (D, D) (required by ``feedback``; see :func:`lqr_gain`).

    Returns:
        Covariances, shape (B, T+1, D, D).

    Raises:
        GpmpcError: unknown ``mode`` or inconsistent shapes.
    """
    if mode not in UNCERTAINTY_MODES:
        raise GpmpcError(f"uncertainty: unknown mode {mode!r}; choose from {', '.join(UNCERTAINTY_MODES)}")
    if var.dim() != 3:
        raise GpmpcError(f"var must have shape (B, T+1, D), got {tuple(var.shape)}")
    if mode == "pointwise":
        return torch.diag_embed(var)
    batch, steps, dim = var.shape
    if dyn_A.shape != (batch, steps - 1, dim, dim):
        raise GpmpcError(
            f"dyn_A must have shape {(batch, steps - 1, dim, dim)} to match var {tuple(var.shape)}, "
            f"got {tuple(dyn_A.shape)}"
        )
    if mode == "feedback":
        if feedback is None or tuple(feedback.shape) != (dim, dim):
            raise GpmpcError(f"uncertainty=feedback needs the (D, D) matrix B K, got "
                             f"{None if feedback is None else tuple(feedback.shape)}")
        dyn_A = dyn_A + feedback.to(dyn_A.dtype)
    sigma = var.new_zeros(batch, dim, dim)
    out = [sigma]
    for tau in range(steps - 1):
        a = dyn_A[:, tau]
        sigma = a @ sigma @ a.transpose(-1, -2) + torch.diag_embed(var[:, tau])
        out.append(sigma)
    return torch.stack(out, dim=1)


def collision_normals(
    xbar_self: Tensor,
    xbar_nbr: Tensor,
    self_ids: Tensor | None = None,
    nbr_ids: Tensor | None = None,
) -> Tensor:
    """Unit normals of the linearized distance constraint (paper eq. 15).

    ``n = rbar / ||rbar||`` with ``rbar = xbar_self - xbar_nbr``, so the two agents of a
    pair use opposite normals. Where the two linearization points coincide
    (``||rbar|| < 1e-9``) there is no direction; the rule is then
    ``n = +e_0`` for the agent with the smaller id and ``n = -e_0`` for the other
    (``e_0`` = first coordinate axis). It is deterministic and antisymmetric, so both
    agents separate along the same axis in opposite directions. Without ids every
    coincident point gets ``+e_0`` (not antisymmetric: pass ids in a multi-agent loop).

    Args:
        xbar_self: the agents' linearization points, shape (B, T+1, D).
        xbar_nbr: their neighbours' linearization points, shape (B, M, T+1, D).
        self_ids: agent ids, shape (B,) (integers).
        nbr_ids: neighbour ids, shape (B, M) (integers).

    Returns:
        Normals, shape (B, M, T+1, D).
    """
    if xbar_nbr.dim() != 4 or xbar_self.dim() != 3 or xbar_nbr.shape[0] != xbar_self.shape[0] \
            or xbar_nbr.shape[2:] != xbar_self.shape[1:]:
        raise GpmpcError(
            f"collision_normals: xbar_self (B, T+1, D) and xbar_nbr (B, M, T+1, D) do not match: "
            f"{tuple(xbar_self.shape)} vs {tuple(xbar_nbr.shape)}"
        )
    rbar = xbar_self.unsqueeze(1) - xbar_nbr
    dist = torch.linalg.vector_norm(rbar, dim=-1, keepdim=True)
    coincident = dist < COINCIDENT_TOL
    safe_dist = torch.where(coincident, torch.ones_like(dist), dist)
    normals = rbar / safe_dist
    sign = _tie_break_sign(xbar_nbr.shape[:2], self_ids, nbr_ids, xbar_nbr)
    fallback = torch.zeros_like(rbar)
    fallback[..., 0] = sign[:, :, None]
    return torch.where(coincident, fallback, normals)


def _tie_break_sign(shape, self_ids, nbr_ids, like: Tensor) -> Tensor:
    """+1 where the agent's id is below its neighbour's, else -1; shape (B, M)."""
    if self_ids is None or nbr_ids is None:
        return like.new_ones(shape)
    self_ids = torch.as_tensor(self_ids).reshape(-1, 1)
    nbr_ids = torch.as_tensor(nbr_ids)
    return torch.where(self_ids < nbr_ids, like.new_ones(shape), -like.new_ones(shape))


def lqr_gain(A: Tensor, B: Tensor, state_weight: float = 1.0, input_weight: float = 1e-3) -> Tensor:
    """Infinite-horizon discrete LQR gain K (``u = K x``) of the model ``x' = A x + B u``.

    The ancillary feedback of ``uncertainty = feedback``; with ``Q = state_weight I`` and
    ``R = input_weight I`` (the MPC's own weights: tracking 1, effort alpha).

    Args:
        A: (n, n) state matrix. B: (n, m) input matrix.

    Returns:
        K, shape (m, n), float64 (not differentiable: the nominal model is fixed).
    """
    import numpy as np
    import scipy.linalg

    a, b = A.detach().cpu().double().numpy(), B.detach().cpu().double().numpy()
    q, r = state_weight * np.eye(a.shape[0]), input_weight * np.eye(b.shape[1])
    p = scipy.linalg.solve_discrete_are(a, b, q, r)
    return torch.as_tensor(-np.linalg.solve(r + b.T @ p @ b, b.T @ p @ a), dtype=torch.float64)


def projected_variances(normals: Tensor, sigma: Tensor) -> Tensor:
    """An agent's variance along each collision normal, ``s = n^T Sigma_k n`` (clamped at 0).

    This is all a neighbour needs of the agent's uncertainty for a sound pair margin:
    ``sum`` and ``joint`` exchange these numbers per edge, never a covariance matrix.

    Args:
        normals: unit normals, shape (B, M, S, D).
        sigma: the agent's own state covariances, shape (B, S, D, D).

    Returns:
        Projected variances, shape (B, M, S).
    """
    return torch.einsum("bmtd,btde,bmte->bmt", normals, sigma, normals).clamp_min(0.0)


def safe_sqrt(var: Tensor) -> Tensor:
    """``sqrt(var)`` with value and gradient 0 below 1e-30 (finite gradients everywhere)."""
    positive = var > _VAR_FLOOR
    return torch.where(positive, torch.sqrt(torch.where(positive, var, torch.ones_like(var))), torch.zeros_like(var))


def pair_margins(mode: str, var_own: Tensor, var_nbr: Tensor, eps_own: Tensor, eps_nbr: Tensor) -> Tensor:
    """The tightening of an agent's collision row for each pair, by formulation.

    With independent Gaussian deviations of the two agents, ``n^T (x_k - x_j)`` deviates
    from its plan by a ``N(0, s_k + s_j)`` variable (``s = n^T Sigma n``), so:

    * ``own`` (the paper's eq. 24): ``m_k = Phi^-1(1 - eps_k) sqrt(s_k)``. Not sound: at
      consensus the pair is ``r_safe + max(m_k, m_j)`` apart while both agents deviate.
    * ``sum``: ``m_k + m_j``. Sound by the union bound: P(violation) <= eps_k + eps_j.
    * ``joint``: ``Phi^-1(1 - eps_k - eps_j) sqrt(s_k + s_j)``: exact for independent
      Gaussians, the tightest sound choice; it depends on the pair's total risk only.

    Args:
        mode: ``own``, ``sum`` or ``joint``.
        var_own: the agent's projected variances ``s_k``, shape (B, M, S).
        var_nbr: its neighbours' projected variances ``s_j`` on the same edges, shape (B, M, S).
        eps_own: the agent's risk per slot ``eps_k``, shape (B, M).
        eps_nbr: the neighbour's risk per slot ``eps_j``, shape (B, M).

    Returns:
        Margins to add to ``r_safe``, shape (B, M, S).
    """
    q_own = chance_quantile(eps_own)[..., None]
    if mode == "own":
        return q_own * safe_sqrt(var_own)
    if mode == "sum":
        return q_own * safe_sqrt(var_own) + chance_quantile(eps_nbr)[..., None] * safe_sqrt(var_nbr)
    if mode == "joint":
        return chance_quantile(eps_own + eps_nbr)[..., None] * safe_sqrt(var_own + var_nbr)
    raise GpmpcError(f"pair_margin: unknown formulation {mode!r}; choose from own, sum, joint")
