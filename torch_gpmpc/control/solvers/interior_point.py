"""A fast batched, differentiable interior-point solver for the agent-local MPC problem.

:class:`InteriorPointMPC` solves exactly the problem of :class:`torch_gpmpc.control.solvers.conic.CvxpyLayerMPC`
(same :class:`~torch_gpmpc.control.solvers.conic.LocalProblemData` in, same
:class:`~torch_gpmpc.control.solvers.conic.LocalSolution` out) with a primal-dual interior-point method
and differentiates it implicitly through its KKT conditions (a ``torch.autograd.Function``).
Data flow: :func:`~torch_gpmpc.control.solvers.canonical.canonicalize` (torch, differentiable:
condensed dynamics, so only the inputs, the neighbour copies and the collision slacks remain) -> the
compiled kernels (NumPy arrays, CPU): with a guess (a previous solution's ``solver_point``) the warm
active-set solves of :mod:`torch_gpmpc.control.solvers.ipm_active`, then the interior point of
:mod:`torch_gpmpc.control.solvers.ipm_kernel` for every problem not solved warm (both called on the
NumPy batch by :mod:`~torch_gpmpc.control.solvers.ipm_batch`) -> outputs and gradients back in torch.
"""

from __future__ import annotations

import logging

import numpy as np
import torch
from torch import Tensor, nn

from torch_gpmpc.control.constraints import LocalConstraints
from torch_gpmpc.control.numpy_views import as_array
from torch_gpmpc.control.solvers import ipm_threads
from torch_gpmpc.control.solvers.ipm_batch import (
    KernelLimits, StructureCache, batched_mv, kernel_arrays, point_outputs, row_multipliers, solve_points,
)
from torch_gpmpc.control.solvers.repeated import KernelSettings, RepeatedSolve
from torch_gpmpc.control.solvers.canonical import (  # noqa: F401 (condense_dynamics: re-exported)
    CanonicalData, CondensedCache, CostTermsCache, canonicalize, condense_dynamics, finite_problems, state_row_blocks,
    with_state_rows,
)
from torch_gpmpc.errors import GpmpcError
from torch_gpmpc.control.problem import (
    LocalProblemData, LocalSolution, check_layer_sizes, planned_cost, solve_verdicts,
)
from torch_gpmpc.dynamics.systems import NominalModel

logger = logging.getLogger(__name__)


# ------------------------------------------------------------------------ differentiation
def _stationarity_vjp(arrays: list[np.ndarray], u: np.ndarray, y: np.ndarray, zc: np.ndarray, a_u: np.ndarray,
                      a_y: np.ndarray, xi: np.ndarray, norm_idx: np.ndarray, zv: np.ndarray,
                      xi_v: np.ndarray) -> list[np.ndarray]:
    """Gradients, with respect to the ten canonical arrays, of the pairing
    ``a^T grad_v L(v, z; theta) + xi^T g(v; theta)`` summed over the batch, negated: the
    implicit-function-theorem vector-Jacobian product (in closed form, NumPy).

    Only the terms of the pairing that depend on the problem data theta matter. With
    ``x = G u + h``, ``dx = G a_u`` (per step ``x_t``, ``dx_t``; rows ``k = j T + t``)::

        (2 c_x x - l_x) . dx + g_u . a_u + a_u^T H_cost u + sum_k (rho_j y_k - w_k) . a_y_k
        - sum_k zc_k n_k . (dx_t - a_y_k) + sum_k xi_k (n_k . (x_t - y_k) - b_k)
        + sum_t zv_t (P x_t) . (P dx_t) - 1/2 sum_t xi_v_t ||P x_t||^2

    (the last line: the state-norm rows ``(v^2 + 2 v sigma - ||P x_t||^2) / 2 >= 0``, P selecting
    ``norm_idx``; the input bounds hold no data).

    Args:
        arrays: G (B, nx, n), h (B, nx), c_x (B,), l_x (B, nx), rho_y (B, M), w_y (B, M, T, D),
            normals (B, M, T, D), bounds (B, M, T), g_u (B, n), H_cost (B, n, n) (nx = T D, M slots).
        u, a_u (B, n); y, a_y (B, R, D); zc, xi (B, R) (R = M T); zv, xi_v (B, Ts), Ts = T or 0.

    Returns:
        The ten gradients, shaped like ``arrays``.
    """
    G, h, c_x, _, _, _, normals, _, _, _ = arrays
    B, M, T, D = normals.shape
    x = (G @ u[..., None])[..., 0] + h
    dx = (G @ a_u[..., None])[..., 0]
    X, dX = x.reshape(B, T, D), dx.reshape(B, T, D)
    Y, AY = y.reshape(B, M, T, D), a_y.reshape(B, M, T, D)
    ZC, XI = zc.reshape(B, M, T, 1), xi.reshape(B, M, T, 1)
    c2 = 2.0 * c_x[:, None, None]
    g_x = c2 * dX + (XI * normals).sum(1)  # d/dx
    g_dx = c2 * X - arrays[3].reshape(B, T, D) - (ZC * normals).sum(1)  # d/d(dx)
    if zv.shape[1]:
        xs, dxs = X[:, :, norm_idx], dX[:, :, norm_idx]
        g_x[:, :, norm_idx] += zv[:, :, None] * dxs - xi_v[:, :, None] * xs
        g_dx[:, :, norm_idx] += zv[:, :, None] * xs
    g_x, g_dx = g_x.reshape(B, -1), g_dx.reshape(B, -1)
    grads = [g_x[:, :, None] * u[:, None, :] + g_dx[:, :, None] * a_u[:, None, :], g_x, 2.0 * (x * dx).sum(1), -dx,
             (Y * AY).sum((2, 3)), -AY, -ZC * (dX[:, None] - AY) + XI * (X[:, None] - Y), -XI[..., 0], a_u,
             a_u[:, :, None] * u[:, None, :]]
    return [-g for g in grads]


class _LocalQpFunction(torch.autograd.Function):
    """Batched interior-point solve with implicit differentiation of its KKT conditions.

    Inputs are the :class:`CanonicalData` tensors (G, h, c_x, l_x, rho_y, w_y, normals,
    bounds, g_u, H_cost; M' = M + L slots) and a settings tuple ``((alpha, beta), limits, penalty, tol,
    max_iter, stats, guess, arrays)`` (``arrays``: those tensors as :func:`kernel_arrays`, made once
    by the caller, then their :class:`StructureCache` pair ``GtG, A``; ``guess``: a previous solve's
    points, which start the warm active-set solves, or ``None``: every problem cold; never pass one
    when gradients are wanted: a warm point has exact complementarity, which the adjoint cannot
    take; ``stats["point"]`` receives this solve's points); outputs ``(u (B, n), y (B, M', T, D),
    s (B, M', T), converged (B,))``.
    """

    @staticmethod
    def forward(ctx, G, h, c_x, l_x, rho_y, w_y, normals, bounds, g_u, H_cost, settings):  # noqa: D102
        weights, limits = settings[0], settings[1]
        point, at, converged = solve_points(settings, keep_at=True)
        ctx.at = at
        ctx.weights, ctx.limits = weights, limits
        ctx.save_for_backward(G, h, c_x, l_x, rho_y, w_y, normals, bounds, g_u, H_cost)
        outputs = point_outputs(point, converged, normals.shape, h)
        ctx.mark_non_differentiable(outputs[3])
        return outputs

    @staticmethod
    def backward(ctx, g_u, g_y, g_s, _g_conv):  # noqa: D102
        at = ctx.at  # the polished point (forward)
        weights, limits = ctx.weights, ctx.limits
        inputs = ctx.saved_tensors  # (autograd checks these were not modified in place)
        arrays = kernel_arrays(inputs)
        B, R, D = at.y.shape
        n = at.u.shape[1]
        T = inputs[6].shape[2]
        _, ov, Ts = limits.sizes(R, n, T)
        ref = inputs[1]

        def arr(g: Tensor | None, *shape: int) -> np.ndarray:
            if g is None:
                return np.zeros(shape)
            return as_array(g).reshape(shape)

        def ten(a: np.ndarray) -> Tensor:
            return torch.from_numpy(np.ascontiguousarray(a)).to(dtype=ref.dtype, device=ref.device)

        a_u, a_y, xi, xi_v = np.empty((B, n)), np.empty((B, R, D)), np.empty((B, R)), np.empty((B, Ts))
        failed = np.empty(B, dtype=np.bool_)
        ipm_threads.adjoint_batch(*arrays, limits.couple, *weights, *limits.args(), at.u, at.w, at.z,
                                  arr(g_u, B, n), arr(g_y, B, R, D), arr(g_s, B, R), a_u, a_y, xi, xi_v, failed)
        a_u, a_y, xi, xi_v = (np.nan_to_num(a) for a in (a_u, a_y, xi, xi_v))
        grads = _stationarity_vjp(arrays, at.u, at.y, at.z[:, :R], a_u, a_y, xi, limits.norm_idx,
                                  at.z[:, ov:ov + Ts], xi_v)
        out = [ten(g) if n else None for g, n in zip(grads, ctx.needs_input_grad[:10])]
        return (*out, None)


# ------------------------------------------------------------------------------ the layer
class InteriorPointMPC(nn.Module):
    r"""Agent-local MPC problem (paper eqs. 26-27) by a batched differentiable interior-point method.

    Solves, for each of B agents with horizon T, dimension D and M neighbour slots, the
    same problem as :class:`torch_gpmpc.control.solvers.conic.CvxpyLayerMPC`::

        minimize    ||X - Xref||_F^2 + alpha ||U||_F^2 + beta sum_t ||U_t - U_{t-1}||^2
                    + slack_penalty * sum(s)
                    + sum_{active j} [ lam_own_j . X + lam_nbr_j . Y_j
                                       + rho_j / 2 (||X - z_own_j||^2 + ||Y_j - z_nbr_j||^2) ]
                    + sum_{inactive j} 1/2 ||Y_j||^2
                    + slack_penalty * (sum(s_state) + sum(sigma))
        over        X (T+1, D), U (T, Du), Y_j (T+1, D), s (M, T), s_state (L, T), sigma (T)
        subject to  X_0 = x0,  X_{t+1} = dyn_A_t X_t + dyn_B_t U_t + dyn_c_t   t = 0..T-1
                    ||U_t||_2 <= u_max  and/or  |U_t,i| <= box_i               t = 0..T-1
                    n_{j,t}^T (X_t - Y_{j,t}) + s_{j,t} >= bound_{j,t},  s >= 0   t = 1..T
                    n_{l,t}^T X_t + s_state_{l,t} >= b_{l,t},  s_state >= 0       t = 1..T
                    ||X_t[idx]||^2 <= v^2 + 2 v sigma_t,  sigma >= 0             t = 1..T

    (inactive slots have no collision row; the state rows are the model's state box and rows,
    the workspace and the data's half-spaces, see :mod:`torch_gpmpc.control.constraints`). Method:

    * **Condensing.** ``X_{1..T} = G u + h`` with ``u = vec(U)`` (:func:`condense_dynamics`);
      ``Y_{j,0} = (rho z_nbr - lam_nbr)_{j,0} / rho_j`` in closed form. Variables left:
      ``u`` (T Du), ``Y_{j,1..T}`` (M T D), ``s`` (M T).
    * **Interior point.** Primal-dual, infeasible start, Mehrotra predictor-corrector,
      one step length, fraction to the boundary 0.99. The input bounds are the smooth
      convex constraints ``(u_max^2 - ||U_t||^2) / 2 >= 0`` with their own slacks (not
      second-order cones: an NT-scaled cone loses precision at tight tolerances because
      its distance to the boundary is a difference of O(1) numbers; a scalar slack
      does not). Globalization: after each step every ``U_t`` is projected onto the
      ball of radius ``u_max`` (the iterate may be moved since all residuals are
      recomputed; near the solution the projection is inactive).
    * **Linear algebra** (:mod:`torch_gpmpc.control.solvers.ipm_kernel`, compiled per problem). Per collision
      row, ``Y_{j,t}`` and ``s_{j,t}`` are eliminated in closed form (diagonal Hessian
      ``rho_j``), leaving ``S0 = H + blockdiag(z_q I) + A^T diag(deff) A`` (T Du x T Du) with
      bounded weights; the input-bound multipliers stay in the system (augmented,
      quasi-definite, size T Du + T) and are solved through their T x T Schur complement,
      so no 1/mu-sized term is ever factored. Two Cholesky factorizations per iteration
      serve the predictor and the corrector.
    * **Stopping.** Relative dual residuals, relative primal residuals and the absolute
      complementarity ``sum(w z)`` all below ``tol``, per problem.
    * **Gradients.** Implicit differentiation of the KKT conditions at the returned
      primal-dual point: one adjoint solve with the same reduced matrix, then the
      data-dependent part of the KKT residual is differentiated by autograd, so every
      tensor field of :class:`~torch_gpmpc.control.solvers.conic.LocalProblemData` gets its gradient.
      The backward first continues the iteration to ``tol / 100`` from the returned
      point (usually 1-2 iterations): gradients are more sensitive to the barrier
      perturbation than solutions (nearly degenerate rows).

    Never raises on numerical trouble: problems that do not converge within
    ``max_iter`` (or have non-finite data) get ``ok = False`` and finite outputs.

    The state rows are slots without a neighbour copy (eliminated like the collision rows),
    the input box is a pair of rows per input (diagonal in the reduced matrix), and the state
    norm bound is a smooth convex row like the input norm bound (augmented, with its slack
    eliminated), so every family keeps the same two factorizations per iteration.

    Args:
        horizon: T.
        dim: D, the state dimension.
        num_neighbors: M (0 allowed).
        nominal: the nominal model: its B (D, Du) is used where the data has no ``dyn_B``.
        u_max: input norm bound (``None``: the model's; ignored if the model has only a box).
        alpha: control-effort weight.
        slack_penalty: exact-penalty weight of the collision and state slacks.
        tol: stopping tolerance on the KKT error.
        max_iter: iteration limit.
        constraints: the input bounds and soft state constraints (``None``: the model's,
            :meth:`LocalConstraints.of`); pass one to add a workspace.
        num_halfspaces: L, the per-problem half-space rows the data carries (0: none).
        input_rate_weight: beta, the weight of the input changes (``U_{-1}`` is ``data.u_prev``,
            the input applied last; 0: not in the problem).
        warm_start: when a call gets a ``guess`` (a previous solution's ``solver_point``, e.g. ADMM's
            last iteration) and no gradient is wanted, solve each problem first by the exact
            active-set method of :mod:`~torch_gpmpc.control.solvers.ipm_active` from it, and cold
            only what that does not solve; ``False``: every problem cold (the earlier path).

    Examples:
        >>> from torch_gpmpc import InteriorPointMPC, NominalModel
        >>> from torch_gpmpc.control.examples import crossing_instance
        >>> layer = InteriorPointMPC(13, 2, 2, NominalModel(2), 2.0, 1e-3)
        >>> sol = layer(crossing_instance(batch=3, num_neighbors=2, method="nominal").problem_data())
        >>> tuple(sol.X.shape), bool(sol.ok.all())
        ((3, 14, 2), True)
    """

    #: :meth:`forward` takes a ``guess`` (``coordination.agent_step.call_layer`` passes ADMM's)
    accepts_guess = True

    def __init__(self, horizon: int, dim: int, num_neighbors: int, nominal: NominalModel, u_max: float | None,
                 alpha: float, slack_penalty: float = 1e4, tol: float = 1e-10, max_iter: int = 100,
                 constraints: LocalConstraints | None = None, num_halfspaces: int = 0,
                 input_rate_weight: float = 0.0, warm_start: bool = True) -> None:
        super().__init__()
        check_layer_sizes("InteriorPointMPC", horizon, dim, num_neighbors, num_halfspaces, nominal.dim, alpha,
                          slack_penalty, input_rate_weight)
        if tol <= 0 or max_iter < 1:
            raise GpmpcError(f"InteriorPointMPC: tol must be > 0 and max_iter >= 1; got {tol}, {max_iter}")
        self.constraints = constraints or LocalConstraints.of(nominal.spec, u_max)
        self.horizon, self.dim, self.num_neighbors = horizon, dim, num_neighbors
        self.num_halfspaces = int(num_halfspaces)
        self.nominal, self.input_dim = nominal, nominal.input_dim
        self.u_max = self.constraints.input_norm
        self.alpha, self.slack_penalty = float(alpha), float(slack_penalty)
        self.input_rate_weight = float(input_rate_weight)
        self.tol, self.max_iter = float(tol), int(max_iter)
        self._limits = KernelLimits.of(self.constraints, num_neighbors, num_halfspaces + self.constraints.num_rows)
        #: Iterations used by the last call (for benchmarks and logging).
        self.last_iterations = 0
        #: Problems of the last call solved warm (by the active-set method).
        self.last_warm_rows = 0
        self.warm_start = bool(warm_start)
        self._condensed = CondensedCache()
        self._cost_terms = CostTermsCache()
        self._structure = StructureCache()
        self._B: Tensor | None = None

    def with_warm_start(self, warm_start: bool) -> "InteriorPointMPC":
        """A new layer for the same problem (sizes, model, weights, constraints, tolerances) with
        the given ``warm_start`` and no previous point."""
        return InteriorPointMPC(self.horizon, self.dim, self.num_neighbors, self.nominal, self.u_max, self.alpha,
                                self.slack_penalty, self.tol, self.max_iter, self.constraints, self.num_halfspaces,
                                self.input_rate_weight, warm_start)

    def forward(self, data: LocalProblemData, guess=None) -> LocalSolution:
        """Solve the B local problems.

        Args:
            data: inputs with shapes as in :class:`~torch_gpmpc.control.solvers.conic.LocalProblemData`
                (float64 recommended; computations run in the dtype of ``x0``).
            guess: a previous solution's ``solver_point`` (same batch and sizes), the warm start
                (``warm_start``); ``None``: solve cold. The layer keeps no state between calls.

        Returns:
            The :class:`~torch_gpmpc.control.solvers.conic.LocalSolution`; differentiable with respect to
            every floating-point field of ``data``.

        Raises:
            GpmpcError: if a field has the wrong shape.
        """
        batch = data.validate(self.horizon, self.dim, self.num_neighbors, self.input_dim, self.num_halfspaces)
        T, D, M = self.horizon, self.dim, self.num_neighbors
        beta = self.input_rate_weight
        canon = with_state_rows(canonicalize(data, self._input_matrix(data), self._condensed, beta, self.alpha,
                                             self._cost_terms),
                                state_row_blocks(data, self.constraints, self.num_halfspaces, T, D))
        inputs = canon.kernel_inputs()
        arrays = kernel_arrays(inputs)
        valid = finite_problems(arrays, canon.y0)
        if not valid.all():
            canon = _benign_rows(canon, torch.from_numpy(valid).to(data.x0.device))
            inputs = canon.kernel_inputs()
            arrays = kernel_arrays(inputs)
        arrays = arrays + list(self._structure(arrays[0], arrays[6]))
        stats: dict = {}
        wants_grad = torch.is_grad_enabled() and any(t.requires_grad for t in inputs)
        guess = guess if self.warm_start and not wants_grad else None
        settings = ((self.alpha, beta), self._limits, self.slack_penalty, self.tol, self.max_iter, stats, guess,
                    arrays)
        if wants_grad:
            u, y1, slack, converged = _LocalQpFunction.apply(*inputs, settings)
        else:  # nothing to differentiate: no autograd node, no point kept for a backward
            point, _, done = solve_points(settings, keep_at=False)
            u, y1, slack, converged = point_outputs(point, done, canon.normals.shape, canon.h)
        y1, slack = y1[:, :M], slack[:, :M]  # the state rows' copies are 0; their slacks show in state_slack
        self.last_iterations, self.last_warm_rows = stats["iterations"], stats["warm_rows"]
        x0, xref = data.x0, data.xref
        if not valid.all():
            keep = torch.from_numpy(valid).to(x0.device)
            x0 = torch.where(keep[:, None], x0, torch.zeros_like(x0))
            xref = torch.where(keep[:, None, None], xref, torch.zeros_like(xref))
        X = torch.cat([x0[:, None], (batched_mv(canon.G, u) + canon.h).view(batch, T, D)], dim=1)
        U = u.view(batch, T, self.input_dim)
        Y = torch.cat([canon.y0[:, :, None], y1], dim=2)
        failure, ok, slack_active = solve_verdicts(data, X, U, Y, slack, self._B, self.constraints,
                                                   converged.cpu().numpy(), valid)
        if not bool(ok.all()):  # ADMM counts and warns (once per kind); keep the details here
            logger.debug("InteriorPointMPC: %d of %d local problems rejected (tol %g, %d iterations)",
                         int((~ok).sum()), ok.shape[0], self.tol, self.max_iter)
        cost = planned_cost(data, X, U, xref, self.alpha, beta)
        state_slack = self.constraints.state_violation(X, data.halfspace_normals, data.halfspace_bounds)
        return LocalSolution(X=X, U=U, Y=Y, slack=slack, slack_active=slack_active, ok=ok, cost=cost,
                             failure=failure, state_slack=state_slack, solver_point=stats["point"],
                             multipliers=row_multipliers(stats["point"], M, T))

    def repeated(self, data: LocalProblemData) -> RepeatedSolve | None:
        """``data``'s problems kept for solves with new consensus terms only (ADMM's later iterations
        of a control step; :mod:`~torch_gpmpc.control.solvers.repeated`), or ``None`` where they cannot
        be: the fixed part is not finite. The caller writes every consensus term before each solve
        (the copies' penalties ``rho``/``rho_nbr`` are terms, not part of the kept problems).

        Args:
            data: the problems as last solved by this layer (shapes as in :meth:`forward`).
        """
        data.validate(self.horizon, self.dim, self.num_neighbors, self.input_dim, self.num_halfspaces)
        B = self._input_matrix(data)
        canon = with_state_rows(canonicalize(data, B, self._condensed, self.input_rate_weight, self.alpha,
                                             self._cost_terms),
                                state_row_blocks(data, self.constraints, self.num_halfspaces, self.horizon,
                                                 self.dim))
        G, normals = kernel_arrays((canon.G, canon.normals))
        kernel = KernelSettings((self.alpha, self.input_rate_weight), self._limits, self.slack_penalty, self.tol,
                                self.max_iter)
        solve = RepeatedSolve(data, canon, self._structure(G, normals), B, self.constraints, kernel)
        return solve if solve.fixed_part_finite else None

    def _input_matrix(self, data: LocalProblemData) -> Tensor:
        """The nominal B (D, Du) in the data's dtype and device: one object (the caches key on it)."""
        if self._B is None or self._B.dtype != data.x0.dtype or self._B.device != data.x0.device:
            self._B = self.nominal.B(data.x0.dtype, data.x0.device)
        return self._B


def _benign_rows(canon: CanonicalData, valid: Tensor) -> CanonicalData:
    """``canon`` with the problems where ``valid (B,)`` is False replaced by a benign one:
    ``G = 0, h = 0, c_x = 1, l_x = 0, rho_y = 1, w_y = 0``, no collision rows."""

    def keep(t: Tensor, fill: float) -> Tensor:
        mask = valid.view(-1, *([1] * (t.dim() - 1)))
        return torch.where(mask, t, torch.full_like(t, fill))

    return CanonicalData(G=keep(canon.G, 0.0), h=keep(canon.h, 0.0), c_x=keep(canon.c_x, 1.0),
                         l_x=keep(canon.l_x, 0.0), rho_y=keep(canon.rho_y, 1.0), w_y=keep(canon.w_y, 0.0),
                         y0=keep(canon.y0, 0.0), normals=keep(canon.normals, 0.0),
                         bounds=keep(canon.bounds, -1.0), g_u=keep(canon.g_u, 0.0),
                         H_cost=keep(canon.H_cost, 0.0))

