"""The agent-local problem handed to Clarabel directly: the fast solver's condensed problem
(:mod:`~torch_gpmpc.control.solvers.canonical`) written as Clarabel's conic QP, one problem at a time.

Why not the cvxpylayers path: building a :class:`~torch_gpmpc.control.solvers.conic.CvxpyLayerMPC`
compiles the problem with cvxpy, about 0.7 s for 18 neighbour slots (plus a second's import on first
use), and it is built per slot count. As the last rung of the fast solver's rescue that build landed
inside a control step. Here nothing is compiled: each call assembles the sparse matrices (NumPy) and
calls the solver. The price: no gradients (the differentiable rescue stays on cvxpylayers).

The problem (in :class:`~.canonical.CanonicalData`'s variables, ``x = [u, Y, s, sigma]``)::

    minimize    1/2 x^T P x + q^T x
    subject to  n_jt^T (G_t u + h_t) - c_j n_jt^T Y_jt + s_jt >= bound_jt,  s >= 0      (rows, t = 1..T)
                ||U_t|| <= u_max  and/or  |U_t,i| <= box_i                                (inputs)
                ||X_t[idx]||^2 <= v^2 + 2 v sigma_t,  sigma >= 0                         (state norm, soft)

with ``c_j`` 1 for a neighbour slot and 0 for a state row (whose copy is not a variable), the input
bounds as second-order cones and the soft norm bound as the cone
``((v^2 + 2 v sigma + 1) / 2, X_t[idx], (v^2 + 2 v sigma - 1) / 2)``.
"""

from __future__ import annotations

import clarabel
import numpy as np
import scipy.sparse as sp
import torch
from torch import Tensor, nn

from torch_gpmpc.control.constraints import LocalConstraints
from torch_gpmpc.control.numpy_views import as_array
from torch_gpmpc.control.problem import (
    LocalProblemData, LocalSolution, check_layer_sizes, planned_cost, solve_verdicts, wants_grad,
)
from torch_gpmpc.control.solvers.canonical import (
    KERNEL_FIELDS, CanonicalData, canonicalize, finite_problems, state_row_blocks, with_state_rows,
)
from torch_gpmpc.dynamics.systems import NominalModel
from torch_gpmpc.errors import GpmpcError

#: Clarabel's settings: at its defaults, and at tolerances 1e-10, inputs were off by 4e-5 on a crossing
#: instance; tolerances 1e-12 with a shorter step (0.9 of the way to the cone boundary, as the
#: cvxpylayers path's) agreed with the cvxpylayers path and the fast solver to 1e-6 in the plans and
#: 1e-5 in the inputs (tests/control/solvers/test_direct_clarabel.py)
SETTINGS = {"tol_gap_abs": 1e-12, "tol_gap_rel": 1e-12, "tol_feas": 1e-12, "tol_ktratio": 1e-10,
            "max_step_fraction": 0.9, "verbose": False}
#: the statuses whose point is taken (then judged by the acceptance rule like every solver's)
_USABLE = {"Solved", "AlmostSolved"}


class DirectClarabelMPC(nn.Module):
    """The local problem of :class:`~torch_gpmpc.control.solvers.interior_point.InteriorPointMPC`
    (same data in, same solution out) solved by Clarabel, without gradients.

    The constructor's arguments (``horizon``: T, ``dim``: D, ``num_neighbors``: M, ``nominal``, ``u_max``,
    ``alpha``, ``slack_penalty``, ``constraints``, ``num_halfspaces``: L, ``input_rate_weight``: beta) are
    those of :class:`~torch_gpmpc.control.solvers.interior_point.InteriorPointMPC`.

    Examples:
        >>> from torch_gpmpc import NominalModel
        >>> from torch_gpmpc.control.examples import crossing_instance
        >>> layer = DirectClarabelMPC(13, 2, 2, NominalModel(2), 2.0, 1e-3)
        >>> sol = layer(crossing_instance(batch=3, num_neighbors=2, method="nominal").problem_data())
        >>> tuple(sol.X.shape), bool(sol.ok.all())
        ((3, 14, 2), True)
    """

    def __init__(self, horizon: int, dim: int, num_neighbors: int, nominal: NominalModel, u_max: float | None,
                 alpha: float, slack_penalty: float = 1e4, constraints: LocalConstraints | None = None,
                 num_halfspaces: int = 0, input_rate_weight: float = 0.0) -> None:
        super().__init__()
        check_layer_sizes("DirectClarabelMPC", horizon, dim, num_neighbors, num_halfspaces, nominal.dim, alpha,
                          slack_penalty, input_rate_weight)
        self.constraints = constraints or LocalConstraints.of(nominal.spec, u_max)
        self.horizon, self.dim, self.num_neighbors = horizon, dim, num_neighbors
        self.num_halfspaces = int(num_halfspaces)
        self.nominal, self.input_dim = nominal, nominal.input_dim
        self.alpha, self.slack_penalty = float(alpha), float(slack_penalty)
        self.input_rate_weight = float(input_rate_weight)

    def forward(self, data: LocalProblemData) -> LocalSolution:
        """Solve the B local problems (shapes as in
        :meth:`~torch_gpmpc.control.solvers.interior_point.InteriorPointMPC.forward`); a problem Clarabel
        does not solve, or whose answer fails the acceptance rule, gets ``ok = False``.

        Raises:
            GpmpcError: if a field has the wrong shape, or a gradient is wanted.
        """
        batch = data.validate(self.horizon, self.dim, self.num_neighbors, self.input_dim, self.num_halfspaces)
        if wants_grad(data):
            raise GpmpcError("DirectClarabelMPC gives no gradients; for gradients use solver='fast' or 'clarabel'")
        T, D, M = self.horizon, self.dim, self.num_neighbors
        B = self.nominal.B(data.x0.dtype, data.x0.device)
        with torch.no_grad():
            canon = with_state_rows(canonicalize(data, B, beta=self.input_rate_weight, alpha=self.alpha),
                                    state_row_blocks(data, self.constraints, self.num_halfspaces, T, D))
        inputs = [as_array(t) for t in canon.kernel_inputs()]
        valid = finite_problems(inputs, canon.y0)
        arrays = dict(zip(KERNEL_FIELDS, inputs))
        n = T * self.input_dim
        u = np.zeros((batch, n))
        y = np.zeros((batch, M, T, D))
        slack = np.zeros((batch, M, T))
        multipliers = np.full((batch, M, T), np.nan)
        converged = np.zeros(batch, dtype=bool)
        for b in np.flatnonzero(valid):
            one = {name: a[b] for name, a in arrays.items()}
            solution = self._solve_one(one)
            if solution is None:
                continue
            x, z = solution
            u[b] = x[:n]
            y[b] = x[n:n + M * T * D].reshape(M, T, D)
            slack[b] = x[n + M * T * D:n + M * T * D + M * T].reshape(M, T)
            multipliers[b] = z[:M * T].reshape(M, T)
            converged[b] = True
        return self._solution(data, canon, B, u, y, slack, multipliers, converged, valid)

    def _solve_one(self, one: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray] | None:
        """Clarabel's primal point x and the rows' duals z of one problem (arrays of
        :class:`~.canonical.CanonicalData` without the batch axis), or ``None`` if it is not solved."""
        P, q, A, b, cones = self._conic_problem(one)
        solver = clarabel.DefaultSolver(P, q, A, b, cones, _settings())
        result = solver.solve()
        if str(result.status) not in _USABLE:
            return None
        return np.asarray(result.x), np.asarray(result.z)

    def _conic_problem(self, one: dict[str, np.ndarray]) -> tuple:
        """``(P, q, A, b, cones)`` of one problem: ``min 1/2 x'Px + q'x  s.t.  A x + s = b, s in cones``
        (P upper triangular CSC, as Clarabel reads it)."""
        T, D, M, Du = self.horizon, self.dim, self.num_neighbors, self.input_dim
        n = T * Du
        G, h = one["G"], one["h"]
        normals, bounds = one["normals"], one["bounds"]  # (M + L, T, D), (M + L, T)
        S = normals.shape[0]
        c = self.constraints
        soft_norm = c.norm_bound is not None
        ny, ns, nsig = M * T * D, S * T, T if soft_norm else 0
        nx = n + ny + ns + nsig
        # objective: c_x ||G u + h||^2 - l_x . (G u + h) + alpha ||u||^2 + beta ||D u||^2 + g_u . u
        # + 1/2 u' H_cost u + sum_j (rho_j / 2 ||Y_j||^2 - w_j . Y_j) + slack_penalty (sum s + sum sigma)
        first_diff = np.eye(n) - np.eye(n, k=-Du)
        P_u = (2.0 * one["c_x"] * G.T @ G + 2.0 * self.alpha * np.eye(n)
               + 2.0 * self.input_rate_weight * first_diff.T @ first_diff + one["H_cost"])
        q_u = 2.0 * one["c_x"] * G.T @ h - G.T @ one["l_x"] + one["g_u"]
        upper = np.triu_indices(n)
        P = _csc(np.concatenate([P_u[upper], np.repeat(one["rho_y"][:M], T * D)]),
                 np.concatenate([upper[0], n + np.arange(ny)]), np.concatenate([upper[1], n + np.arange(ny)]), nx, nx)
        q = np.concatenate([q_u, -one["w_y"][:M].ravel(), np.full(ns + nsig, self.slack_penalty)])

        # A as (value, row, column) triplets, one block of rows after another (one sparse build: scipy's
        # per-call cost made block-by-block assembly the larger part of a small problem's solve)
        Gt = G.reshape(T, D, n)
        A = _Triplets()
        # collision and state rows (nonnegative): -(n' G_t) u + c_j n' Y_jt - s_jt <= n' h_t - bound
        A.dense(-np.einsum("jtd,tdn->jtn", normals, Gt).reshape(ns, n), row=0, col=0)
        A.add(normals[:M].ravel(), np.repeat(np.arange(M * T), D), n + np.arange(ny))
        A.add(-np.ones(ns), np.arange(ns), n + ny + np.arange(ns))
        rhs = [np.einsum("jtd,td->jt", normals, h.reshape(T, D)).ravel() - bounds.ravel()]
        # s >= 0 and sigma >= 0
        A.add(-np.ones(ns + nsig), ns + np.arange(ns + nsig), n + ny + np.arange(ns + nsig))
        rhs.append(np.zeros(ns + nsig))
        cones = [clarabel.NonnegativeConeT(2 * ns + nsig)]
        row = 2 * ns + nsig
        if c.input_box is not None:  # U_t,i <= box_i and -U_t,i <= box_i
            box = np.tile(np.asarray(c.input_box, dtype=np.float64), T)
            A.add(np.concatenate([np.ones(n), -np.ones(n)]), row + np.arange(2 * n), np.tile(np.arange(n), 2))
            rhs.append(np.concatenate([box, box]))
            cones.append(clarabel.NonnegativeConeT(2 * n))
            row += 2 * n
        if c.input_norm is not None:  # (u_max, U_t) in the second-order cone, t = 0..T-1
            per_step = np.arange(T * (Du + 1)).reshape(T, Du + 1)[:, 1:].ravel()  # the U_t rows of each cone
            A.add(-np.ones(n), row + per_step, np.arange(n))
            rhs.append(np.tile(np.concatenate([[c.input_norm], np.zeros(Du)]), T))
            cones.extend(clarabel.SecondOrderConeT(Du + 1) for _ in range(T))
            row += T * (Du + 1)
        if soft_norm:  # ((v^2 + 1)/2 + v sigma_t, X_t[idx], (v^2 - 1)/2 + v sigma_t) in the cone
            v, idx = float(c.norm_bound), list(c.norm_indices)
            for t in range(T):
                sigma = n + ny + ns + t
                A.add(np.array([-v, -v]), np.array([row, row + len(idx) + 1]), np.array([sigma, sigma]))
                A.dense(-Gt[t, idx], row=row + 1, col=0)
                rhs.append(np.concatenate([[(v * v + 1.0) / 2.0], h.reshape(T, D)[t, idx], [(v * v - 1.0) / 2.0]]))
                cones.append(clarabel.SecondOrderConeT(len(idx) + 2))
                row += len(idx) + 2
        return P, q, A.csc(row, nx), np.concatenate(rhs), cones

    def _solution(self, data: LocalProblemData, canon: CanonicalData, B: Tensor, u: np.ndarray, y: np.ndarray,
                  slack: np.ndarray, multipliers: np.ndarray, converged: np.ndarray, valid: np.ndarray
                  ) -> LocalSolution:
        """The :class:`LocalSolution` of the solved points: unsolved problems fail (inaccurate), problems
        with non-finite data fail as such with zero plans and copies (as the fast solver's: finite)."""
        batch, T, D = u.shape[0], self.horizon, self.dim
        like = data.x0
        u_t = torch.from_numpy(u).to(like)
        X = torch.cat([data.x0[:, None], (canon.G @ u_t[..., None])[..., 0].add(canon.h).view(batch, T, D)], dim=1)
        U = u_t.view(batch, T, self.input_dim)
        Y = torch.cat([canon.y0[:, :, None], torch.from_numpy(y).to(like)], dim=2)
        keep = torch.from_numpy(valid).to(like.device)
        X, Y = torch.where(keep[:, None, None], X, 0.0), torch.where(keep[:, None, None, None], Y, 0.0)
        slack_t = torch.from_numpy(slack).to(like)
        failure, ok, slack_active = solve_verdicts(data, X, U, Y, slack_t, B, self.constraints, converged, valid)
        return LocalSolution(
            X=X, U=U, Y=Y, slack=slack_t, slack_active=slack_active, ok=ok,
            cost=planned_cost(data, X, U, data.xref, self.alpha, self.input_rate_weight), failure=failure,
            state_slack=self.constraints.state_violation(X, data.halfspace_normals, data.halfspace_bounds),
            multipliers=torch.from_numpy(multipliers).to(like))


class _Triplets:
    """A sparse matrix collected as (value, row, column) triplets, built once (:meth:`csc`)."""

    def __init__(self) -> None:
        self.values: list[np.ndarray] = []
        self.rows: list[np.ndarray] = []
        self.cols: list[np.ndarray] = []

    def add(self, values: np.ndarray, rows: np.ndarray, cols: np.ndarray) -> None:
        """Entries ``values`` at ``(rows, cols)`` (equal lengths)."""
        self.values.append(values)
        self.rows.append(rows)
        self.cols.append(cols)

    def dense(self, block: np.ndarray, row: int, col: int) -> None:
        """A dense ``block`` (r, c) with its top-left entry at ``(row, col)``."""
        r, c = np.indices(block.shape)
        self.add(block.ravel(), row + r.ravel(), col + c.ravel())

    def csc(self, num_rows: int, num_cols: int) -> sp.csc_matrix:
        """The (num_rows, num_cols) matrix."""
        return _csc(np.concatenate(self.values), np.concatenate(self.rows), np.concatenate(self.cols),
                    num_rows, num_cols)


def _csc(values: np.ndarray, rows: np.ndarray, cols: np.ndarray, num_rows: int, num_cols: int) -> sp.csc_matrix:
    """The CSC matrix of the triplets (duplicates summed, zeros dropped: Clarabel factors what is stored)."""
    matrix = sp.csc_matrix((values, (rows, cols)), shape=(num_rows, num_cols))
    matrix.eliminate_zeros()
    return matrix


def _settings() -> "clarabel.DefaultSettings":
    """Clarabel's settings with :data:`SETTINGS`."""
    settings = clarabel.DefaultSettings()
    for name, value in SETTINGS.items():
        setattr(settings, name, value)
    return settings
