"""The agent-local MPC problem (paper eq. 27) as one differentiable, batched layer.

The cvxpy problem is written once, in DPP form, and wrapped in a
:class:`cvxpylayers.torch.CvxpyLayer`; all agents of one ADMM iteration are solved by
one batched call. Everything that depends on rho, the risk levels or the consensus
variables is computed in torch and passed in as parameters, so gradients reach them.
"""

from __future__ import annotations

import logging
from typing import Any

import cvxpy as cp
import numpy as np
import torch
from cvxpylayers.torch import CvxpyLayer
from torch import Tensor, nn

from torch_gpmpc.control.constraints import LocalConstraints
from torch_gpmpc.errors import GpmpcError
from torch_gpmpc.dynamics.systems import NominalModel

from torch_gpmpc.control.problem import (
    ConsensusTerms, FAIL_EXCEPTION, FAIL_NONE, SLACK_ACTIVE_TOL, LocalProblemData, LocalSolution, acceptance_failures,
    check_layer_sizes, planned_cost,
)
from torch_gpmpc.control.cost import horizon_weights

logger = logging.getLogger(__name__)

#: Solver arguments per ``solver`` name (merged with per-call overrides); passed to
#: diffcp's batch solve and from there to the solver's settings.
SOLVER_ARGS: dict[str, dict[str, Any]] = {
    # diffcp with Clarabel (interior point). cvxpylayers hands diffcp the conic form
    # (squares as second-order cones), where Clarabel's defaults leave input errors
    # ~3e-4 (inputs carry 10x the state error since B = 0.1 I) and occasional stalls at
    # ~1e-5. Tolerances 1e-12 with a shorter step (0.9 of the way to the cone boundary)
    # gave plans within 1e-6 of a direct QP solve on 144 crossing instances, and ran
    # faster than the defaults with 1e-12 (fewer stalled iterations).
    "clarabel": {"solve_method": "Clarabel", "n_jobs_forward": 1,
                 "tol_gap_abs": 1e-12, "tol_gap_rel": 1e-12, "tol_feas": 1e-12,
                 "max_step_fraction": 0.9},
    # cvxpylayers' default: diffcp + SCS, with tight tolerances.
    "reference": {"eps_abs": 1e-9, "eps_rel": 1e-9, "max_iters": 100_000, "n_jobs_forward": 1},
}

#: diffcp arguments that only exist when gradients are computed (the solve-only path
#: would hand them to the solver's settings and fail). diffcp's default derivative mode
#: ``lsqr`` is an iterative solve whose gradients were off by 20-100% on the paper-size
#: problem; ``dense`` factorizes the (~600 x 600) derivative system exactly.
BACKWARD_ARGS: dict[str, Any] = {"n_jobs_backward": 1, "mode": "dense"}
_BACKWARD_ONLY_KEYS = frozenset({"n_jobs_backward", "mode", "derivative_kwargs"})


class CvxpyLayerMPC(nn.Module):
    r"""Agent-local augmented-Lagrangian MPC problem (paper eqs. 26-27), batched over agents.

    For one agent with horizon T, state dimension D, input dimension Du and M neighbour slots::

        minimize    ||X - Xref||_F^2 + alpha ||U||_F^2 + beta sum_tau ||U_tau - U_{tau-1}||^2
                    + slack_penalty * sum(s)
                    + sum_j [ lam_own_j . X + lam_nbr_j . Y_j
                              + rho_j / 2 (||X - z_own_j||_F^2 + ||Y_j - z_nbr_j||_F^2) ]
        over        X (T+1, D), U (T, Du), Y_j (T+1, D) for j < M, s (M, T)
        subject to  X_0 = x0
                    X_{tau+1} = dyn_A_tau X_tau + dyn_B_tau U_tau + dyn_c_tau   tau = 0..T-1
                    ||U_tau||_2 <= u_max  and/or  |U_tau,i| <= b_i (the model's)  tau = 0..T-1
                    n_{j,tau}^T (X_tau - Y_{j,tau}) + s_{j,tau} >= bound_{j,tau}   tau = 1..T
                    s >= 0
                    + the soft state constraints (state box and rows, workspace, the data's
                      half-spaces, state norm bound: state_constraints)

    Agent k's copy of edge (k, j) is ``y_kj,k = [X; Y_j]`` with consensus value
    ``z_kj = [z_own_j; z_nbr_j]`` and multiplier ``[lam_own_j; lam_nbr_j]``;
    ``bound = r_safe + Phi^{-1}(1 - eps_k) sigma_k`` (paper eq. 24) and ``n`` the unit
    normal of the linearized distance (eq. 15, ``n^T rbar = ||rbar||`` so the constant
    terms cancel). The slack with a large exact penalty keeps the problem feasible.

    DPP form (how it is stated to cvxpy): with ``w = rho z - lam`` (computed in torch),
    up to constants the objective is
    ``c_X ||X||^2 - (2 Xref + sum_j w_own_j) . X + sum_j (rho_j/2 ||Y_j||^2 - w_nbr_j . Y_j)
    + alpha ||U||^2 + slack_penalty sum(s)`` with ``c_X = 1 + sum_j rho_j / 2``. Completing
    the squares (variables scaled by square roots of the weights)::

        ||sqrt(c_X) X - (Xref + sum_j w_own_j / 2) / sqrt(c_X)||^2
        + sum_j ||sqrt(rho_j/2) Y_j - w_nbr_j / (2 sqrt(rho_j/2))||^2 + ...

    with the scales and shifts computed in torch and passed as parameters: a parameter
    times a variable inside ``sum_squares`` is DPP, and unlike the expanded form the
    optimal value involves no cancellation between large terms, so the interior-point
    solve of the conic form is accurate to ~1e-8 instead of ~1e-5. Inactive slots get
    ``rho_j = 1``, ``w = 0`` (so ``Y_j = 0``), normal 0 and bound -1, keeping one problem
    for all agents.

    Args:
        horizon: T.
        dim: D, the state dimension.
        num_neighbors: M, the number of neighbour slots (0 allowed).
        nominal: the nominal model: its B where the data has no ``dyn_B``, its input bound
            (norm or box) and its optional state bound.
        u_max: input norm bound (``None``: the model's; ignored if the model has only a box).
        alpha: control-effort weight.
        slack_penalty: exact-penalty weight of the collision and state slacks.
        solver: ``clarabel`` (diffcp with Clarabel) or ``reference`` (cvxpylayers'
            default diffcp + SCS with tolerances 1e-9).
        constraints: input bounds and soft state constraints (``None``: the model's).
        num_halfspaces: L, the per-problem half-space rows the data carries.
        input_rate_weight: beta (``U_{-1}`` is ``data.u_prev``; 0: no such term).

    Examples:
        >>> from torch_gpmpc import CvxpyLayerMPC, NominalModel
        >>> from torch_gpmpc.control.examples import crossing_instance
        >>> layer = CvxpyLayerMPC(13, 2, 1, NominalModel(2), 2.0, 1e-3, solver="clarabel")
        >>> sol = layer(crossing_instance(batch=1, num_neighbors=1, method="nominal").problem_data())
        >>> tuple(sol.X.shape), bool(sol.ok.all())
        ((1, 14, 2), True)
    """

    def __init__(
        self,
        horizon: int,
        dim: int,
        num_neighbors: int,
        nominal: NominalModel,
        u_max: float | None,
        alpha: float,
        slack_penalty: float = 1e4,
        solver: str = "clarabel",
        constraints: LocalConstraints | None = None,
        num_halfspaces: int = 0,
        input_rate_weight: float = 0.0,
    ) -> None:
        super().__init__()
        if solver not in SOLVER_ARGS:
            raise GpmpcError(f"solver: {solver!r} is not a cvxpylayers path; choose from {', '.join(SOLVER_ARGS)}")
        check_layer_sizes("CvxpyLayerMPC", horizon, dim, num_neighbors, num_halfspaces, nominal.dim, alpha,
                          slack_penalty, input_rate_weight)
        self.constraints = constraints or LocalConstraints.of(nominal.spec, u_max)
        self.horizon, self.dim, self.num_neighbors = horizon, dim, num_neighbors
        self.num_halfspaces = int(num_halfspaces)
        self.nominal, self.u_max, self.alpha = nominal, self.constraints.input_norm, float(alpha)
        self.slack_penalty, self.solver = float(slack_penalty), solver
        self.input_rate_weight = float(input_rate_weight)
        self.problem, parameters, variables = self._build_problem()
        #: cvxpy parameters in the order of :meth:`layer_parameters` (for plain cvxpy solves).
        self.cvxpy_parameters = parameters
        self._variable_shapes = [tuple(v.shape) for v in variables]
        self.layer = CvxpyLayer(self.problem, parameters=parameters, variables=variables)
        self._stated_cost_layer: CvxpyLayer | None = None  # built when data first states a cost

    def _layer_for(self, data: LocalProblemData) -> CvxpyLayer:
        """The layer of the default cost, or (built once, on first use) that of a stated cost."""
        if not data.has_cost:
            return self.layer
        if self._stated_cost_layer is None:
            problem, parameters, variables = self._build_problem(stated_cost=True)
            self._stated_cost_layer = CvxpyLayer(problem, parameters=parameters, variables=variables)
        return self._stated_cost_layer

    # ------------------------------------------------------------------ build
    def _build_problem(self, stated_cost: bool = False) -> tuple[cp.Problem, list[cp.Parameter], list[cp.Variable]]:
        """The DPP problem, its parameters (layer order) and returned variables; ``stated_cost``: the
        tracking cost is the data's :class:`~torch_gpmpc.control.cost.QuadraticCost` (see
        :meth:`layer_parameters`), else ``||X - Xref||^2 + alpha ||U||^2``."""
        T, D, M = self.horizon, self.dim, self.num_neighbors
        Du = self.nominal.input_dim
        X, U = cp.Variable((T + 1, D), name="X"), cp.Variable((T, Du), name="U")
        x0 = cp.Parameter(D, name="x0")
        scale_x = cp.Parameter(nonneg=True, name="scale_X")
        shift_x = cp.Parameter((T + 1, D), name="shift_X")
        a_cols = [cp.Parameter((T, D), name=f"A_col{e}") for e in range(D)]
        b_cols = [cp.Parameter((T, D), name=f"B_col{j}") for j in range(Du)]
        dyn_c = cp.Parameter((T, D), name="dyn_c")
        ones_row = np.ones((1, D))
        drift = sum(cp.multiply(a_cols[e], cp.reshape(X[:-1, e], (T, 1), order="F") @ ones_row)
                    for e in range(D))
        drive = sum(cp.multiply(b_cols[j], cp.reshape(U[:, j], (T, 1), order="F") @ ones_row)
                    for j in range(Du))
        if stated_cost:
            # ||F_t X_t - f_t||^2 per step (F_t^T F_t = W_t, the state weight with the own copies' rho)
            # and ||U_t L - f_u,t||^2 (L L^T = R): parameters times variables, so DPP
            f_cols = [cp.Parameter((T, D), name=f"F_col{e}") for e in range(D)]
            f_x = cp.Parameter((T, D), name="f_X")
            weighted = sum(cp.multiply(f_cols[e], cp.reshape(X[1:, e], (T, 1), order="F") @ ones_row)
                           for e in range(D))
            r_root = cp.Parameter((Du, Du), name="R_root")
            f_u = cp.Parameter((T, Du), name="f_U")
            objective = cp.sum_squares(weighted - f_x) + cp.sum_squares(U @ r_root - f_u)
            cost_parameters = [*f_cols, f_x, r_root, f_u]
        else:
            objective = cp.sum_squares(scale_x * X - shift_x) + self.alpha * cp.sum_squares(U)
            cost_parameters = [scale_x, shift_x]
        constraints = [X[0] == x0, X[1:] == drift + drive + dyn_c]
        parameters = [x0, *cost_parameters, *a_cols, *b_cols, dyn_c]
        if self.input_rate_weight:
            u_prev = cp.Parameter(Du, name="u_prev")
            objective += self.input_rate_weight * input_changes(U, u_prev)
            parameters.append(u_prev)
        L = self.num_halfspaces
        half_normals = [cp.Parameter((T, D), name=f"halfspace{j}") for j in range(L)]
        half_bounds = cp.Parameter((L, T), name="halfspace_bounds") if L else None
        cons, penalty = state_constraints(X, U, self.constraints, self.slack_penalty,
                                          list(zip(half_normals, [half_bounds[j] for j in range(L)])))
        constraints += cons
        objective += penalty
        parameters += [*half_normals, *([half_bounds] if L else [])]
        variables = [X, U]
        if M > 0:
            Ys = [cp.Variable((T + 1, D), name=f"Y{j}") for j in range(M)]
            S = cp.Variable((M, T), nonneg=True, name="slack")
            scale_y = cp.Parameter(M, nonneg=True, name="scale_Y")
            shift_y = [cp.Parameter((T + 1, D), name=f"shift_Y{j}") for j in range(M)]
            normals = [cp.Parameter((T, D), name=f"normal{j}") for j in range(M)]
            bounds = cp.Parameter((M, T), name="bounds")
            for j in range(M):
                objective += cp.sum_squares(scale_y[j] * Ys[j] - shift_y[j])
                gap = cp.sum(cp.multiply(normals[j], X[1:] - Ys[j][1:]), axis=1)
                constraints.append(gap + S[j] >= bounds[j])
            objective += self.slack_penalty * cp.sum(S)
            parameters += [scale_y, *shift_y, *normals, bounds]
            variables += [*Ys, S]
        problem = cp.Problem(cp.Minimize(objective), constraints)
        if not problem.is_dpp():  # pragma: no cover - guarded by tests
            raise RuntimeError("CvxpyLayerMPC problem is not DPP")
        return problem, parameters, variables

    # ---------------------------------------------------------------- forward
    def layer_parameters(self, data: LocalProblemData) -> list[Tensor]:
        """Torch values of the layer's parameters (batched over B), in layer order.

        Args:
            data: the problem inputs (validated by the caller).

        Returns:
            Tensors ``[x0, scale_X, shift_X, A_col_0..A_col_{D-1}, B_col_0..B_col_{Du-1}, dyn_c]`` (with a
            stated cost ``F_col_0..F_col_{D-1}, f_X, R_root, f_U`` in place of ``scale_X, shift_X``:
            :func:`stated_cost_parameters`), if beta > 0
            ``[u_prev]`` (0 when the data has none), if L > 0
            ``[halfspace_0.., halfspace_bounds]`` and, if M > 0, ``[scale_Y, shift_Y_0.., normal_0.., bounds]``
            (see the class docstring).
        """
        M = self.num_neighbors
        terms = ConsensusTerms.of(data)
        cost_params = stated_cost_parameters(data, terms) if data.has_cost else self._default_cost_parameters(data, terms)
        dyn_B = data.dyn_B if data.dyn_B is not None else \
            self.nominal.B(data.x0.dtype, data.x0.device).expand(data.x0.shape[0], self.horizon, -1, -1)
        params = [data.x0, *cost_params, *[data.dyn_A[..., e] for e in range(self.dim)],
                  *[dyn_B[..., j] for j in range(self.nominal.input_dim)], data.dyn_c]
        if self.input_rate_weight:
            params.append(data.x0.new_zeros(data.x0.shape[0], self.nominal.input_dim) if data.u_prev is None
                          else data.u_prev)
        if self.num_halfspaces:
            params += [*[data.halfspace_normals[:, j] for j in range(self.num_halfspaces)], data.halfspace_bounds]
        if M > 0:
            scale_y = torch.sqrt(0.5 * terms.rho_y)
            shift_y = terms.w_nbr / (2.0 * scale_y[:, :, None, None])
            params += [scale_y, *[shift_y[:, j] for j in range(M)],
                       *[terms.normals[:, j] for j in range(M)], terms.bounds]
        return params

    @staticmethod
    def _default_cost_parameters(data: LocalProblemData, terms: ConsensusTerms) -> list[Tensor]:
        """``[scale_X (B,), shift_X (B, T+1, D)]`` of ``||X - Xref||^2`` with the own copies' terms."""
        scale_x = torch.sqrt(terms.c_x)
        return [scale_x, (data.xref + 0.5 * terms.w_own.sum(dim=1)) / scale_x[:, None, None]]

    def forward(self, data: LocalProblemData, solver_args: dict[str, Any] | None = None,
                guess: Any = None) -> LocalSolution:
        """Solve the B local problems with one batched layer call.

        A solver exception does not propagate: the batch is retried agent by agent and
        the failing agents are returned with ``ok = False`` (NaN rows) and ``failure``
        set (logged at DEBUG level; :class:`~torch_gpmpc.coordination.admm.ADMM` warns once per kind).

        Args:
            data: inputs with shapes as in :class:`LocalProblemData`.
            solver_args: overrides of the solver arguments (e.g. tolerances).
            guess: ignored (this path keeps no warm start; the fast solver's takes one).

        Returns:
            The :class:`LocalSolution`.
        """
        batch = data.validate(self.horizon, self.dim, self.num_neighbors, self.nominal.input_dim,
                              self.num_halfspaces)
        params = self.layer_parameters(data)
        needs_grad = torch.is_grad_enabled() and any(p.requires_grad for p in params)
        args = {**SOLVER_ARGS[self.solver], **(BACKWARD_ARGS if needs_grad else {}), **(solver_args or {})}
        if not needs_grad:
            args = {k: v for k, v in args.items() if k not in _BACKWARD_ONLY_KEYS}
        detail = None
        try:
            outputs = self._layer_for(data)(*params, solver_args=args)
            failed = torch.zeros(batch, dtype=torch.bool)
        except Exception as exc:  # noqa: BLE001 - any solver failure is reported, not raised
            logger.debug("CvxpyLayerMPC: batched solve of %d problems failed (%s); retrying one by one",
                         batch, exc)
            outputs, failed, detail = self._solve_one_by_one(self._layer_for(data), params, args)
        return self._solution(data, outputs, failed, detail)

    def _solve_one_by_one(self, layer: CvxpyLayer, params: list[Tensor], args: dict[str, Any]
                          ) -> tuple[list[Tensor], Tensor, str | None]:
        """Solve each problem alone; failures become NaN rows.

        Returns:
            ``(outputs, failed (B,), first exception message or None)``.
        """
        batch = params[0].shape[0]
        rows, failed, detail = [], torch.zeros(batch, dtype=torch.bool), None
        for b in range(batch):
            try:
                rows.append(layer(*[p[b:b + 1] for p in params], solver_args=args))
            except Exception as exc:  # noqa: BLE001
                logger.debug("CvxpyLayerMPC: problem %d of %d failed: %s", b, batch, exc)
                detail = detail or f"{type(exc).__name__}: {exc}"
                failed[b] = True
                rows.append(None)
        template = next((r for r in rows if r is not None), None)
        if template is None:
            template = [torch.full((1, *v), float("nan"), dtype=params[0].dtype)
                        for v in self._variable_shapes]
        outputs = []
        for i, ref in enumerate(template):
            nan_row = torch.full_like(ref.detach(), float("nan"))
            outputs.append(torch.cat([r[i] if r is not None else nan_row for r in rows]))
        return outputs, failed, detail

    def _solution(self, data: LocalProblemData, outputs: list[Tensor], failed: Tensor,
                  detail: str | None = None) -> LocalSolution:
        """Assemble a :class:`LocalSolution` and check each returned solution."""
        T, D, M = self.horizon, self.dim, self.num_neighbors
        batch = data.x0.shape[0]
        X, U = outputs[0], outputs[1]
        if M > 0:
            Y = torch.stack(list(outputs[2:2 + M]), dim=1)
            slack = outputs[2 + M]
            slack_used = torch.where(data.active.to(torch.bool)[:, :, None], slack, torch.zeros_like(slack))
            slack_active = (slack_used > SLACK_ACTIVE_TOL).flatten(1).any(dim=1)
        else:
            Y = X.new_zeros(batch, 0, T + 1, D)
            slack = X.new_zeros(batch, 0, T)
            slack_active = torch.zeros(batch, dtype=torch.bool)
        failure = self._check(data, X.detach(), U.detach(), Y.detach(), slack.detach())
        failure = torch.where(failed, torch.full_like(failure, FAIL_EXCEPTION), failure)
        ok = failure == FAIL_NONE
        if not bool(ok.all()):
            logger.debug("CvxpyLayerMPC: %d of %d local problems returned no valid solution (kinds %s)",
                         int((~ok).sum()), batch, failure.tolist())
        cost = planned_cost(data, X, U, data.xref, self.alpha, self.input_rate_weight)
        state_slack = self.constraints.state_violation(X, data.halfspace_normals, data.halfspace_bounds)
        return LocalSolution(X=X, U=U, Y=Y, slack=slack, slack_active=slack_active & ok, ok=ok, cost=cost,
                             failure=failure, failure_detail=detail, state_slack=state_slack)

    def _check(self, data: LocalProblemData, X: Tensor, U: Tensor, Y: Tensor, slack: Tensor) -> Tensor:
        """Failure code per problem, (B,): see :func:`acceptance_failures`."""
        return acceptance_failures(data, X, U, Y, slack, self.nominal.B(X.dtype, X.device), self.constraints)


def stated_cost_parameters(data: LocalProblemData, terms: ConsensusTerms) -> list[Tensor]:
    """The stated-cost layer's cost parameters ``[F_col_0..F_col_{D-1} (B, T, D), f_X (B, T, D),
    R_root (B, Du, Du), f_U (B, T, Du)]``.

    Per step t = 1..T the state terms are ``X_t^T W_t X_t - X_t . (2 Q_t r_t + w_t)`` with
    ``Q_t = Q`` (``P`` at T), ``W_t = Q_t + sum_j rho_j / 2 I`` and ``w_t`` the own copies'
    ``sum_j w_own_j``; with ``W_t = L L^T`` (Cholesky, a 1e-12 relative jitter for a singular Q without
    neighbours), ``F_t = L^T`` and ``f_t = L^{-1} (Q_t r_t + w_t / 2)`` give ``||F_t X_t - f_t||^2`` up
    to a constant.
    The inputs: ``R = L_R L_R^T``, ``R_root = L_R``, ``f_U = u_ref^T L_R`` on every step.
    """
    B, T, D = data.xref.shape[0], data.xref.shape[1] - 1, data.xref.shape[2]
    Q, R, P = data.cost_Q.to(data.xref), data.cost_R.to(data.xref), data.cost_P.to(data.xref)
    eye = torch.eye(D, dtype=Q.dtype, device=Q.device)
    stage = horizon_weights(Q, P, T)  # Q_t, (B, T, D, D)
    W = stage + (terms.c_x - 1.0)[:, None, None, None] * eye
    jitter = 1e-12 * (1.0 + W.detach().abs().amax(dim=(-2, -1), keepdim=True))
    L = torch.linalg.cholesky(W + jitter * eye)  # (B, T, D, D)
    w_own = terms.w_own.sum(dim=1)[:, 1:]  # (B, T, D)
    linear = (stage @ data.xref[:, 1:, :, None])[..., 0] + 0.5 * w_own  # Q_t r_t + w_t / 2
    f_x = torch.linalg.solve_triangular(L, linear[..., None], upper=False)[..., 0]
    F = L.mT  # F_t = L^T; column e of F_t for every t
    L_R = torch.linalg.cholesky(R)
    u_ref = torch.zeros(B, R.shape[-1], dtype=R.dtype, device=R.device) if data.u_ref is None else data.u_ref.to(R)
    f_u = (u_ref[:, None, :] @ L_R)[:, 0]  # (B, Du)
    return [*[F[..., :, e] for e in range(D)], f_x, L_R, f_u[:, None, :].expand(B, T, -1)]


def input_changes(U: cp.Expression, u_prev: Any) -> cp.Expression:
    """``sum_t ||U_t - U_{t-1}||^2`` of a plan's inputs U (T, Du) with ``U_{-1} = u_prev`` (Du,)
    (a parameter or an array): the input-rate term without its weight."""
    changes = cp.sum_squares(U[0] - u_prev)
    return changes + cp.sum_squares(U[1:] - U[:-1]) if U.shape[0] > 1 else changes


def state_constraints(X: cp.Expression, U: cp.Expression, constraints: LocalConstraints, slack_penalty: float,
                      halfspaces: list[tuple[Any, Any]] = ()) -> tuple[list, cp.Expression]:
    """The input bounds and soft state constraints of one plan in cvxpy (as
    :mod:`torch_gpmpc.control.constraints` states them), and the penalty of their slacks.

    Args:
        X: the plan (T+1, D). U: the inputs (T, Du).
        constraints: the bounds and constant rows.
        slack_penalty: the exact-penalty weight.
        halfspaces: per-problem rows ``(normals (T, D), bounds (T,))`` (parameters or arrays).

    Returns:
        ``(constraints, penalty)``; the penalty is ``slack_penalty`` times the slacks' sum.
    """
    T, D = X.shape[0] - 1, X.shape[1]
    cons: list = []
    penalty = cp.Constant(0.0)
    if constraints.input_box is not None:
        cons.append(cp.abs(U) <= np.ones((T, 1)) @ np.asarray(constraints.input_box)[None, :])
    if constraints.input_norm is not None:
        cons.append(cp.norm(U, 2, axis=1) <= constraints.input_norm)
    rows = []
    if constraints.num_rows:
        normals = np.asarray(constraints.row_normals).reshape(-1, D)
        rows.append((X[1:] @ normals.T, np.ones((T, 1)) @ np.asarray(constraints.row_bounds)[None, :]))
    for normal, bound in halfspaces:
        rows.append((cp.reshape(cp.sum(cp.multiply(normal, X[1:]), axis=1), (T, 1), order="F"),
                     cp.reshape(bound, (T, 1), order="F")))
    for lhs, rhs in rows:
        s = cp.Variable(lhs.shape, nonneg=True)
        cons.append(lhs + s >= rhs)
        penalty = penalty + slack_penalty * cp.sum(s)
    if constraints.norm_bound is not None:
        v = constraints.norm_bound
        sigma = cp.Variable(T, nonneg=True)
        cons.append(cp.sum(cp.square(X[1:, list(constraints.norm_indices)]), axis=1) <= v * v + 2 * v * sigma)
        penalty = penalty + slack_penalty * cp.sum(sigma)
    return cons, penalty

