"""A fast batched, differentiable interior-point solver for the agent-local MPC problem.

:class:`FastLocalMPC` solves exactly the problem of :class:`torch_gpmpc.mpc.LocalMPC`
(same :class:`~torch_gpmpc.mpc.LocalProblemData` in, same
:class:`~torch_gpmpc.mpc.LocalSolution` out) with a batched primal-dual interior-point method,
and differentiates it implicitly through its KKT conditions (a ``torch.autograd.Function``).
It exploits the structure of the problem (condensed dynamics, diagonal neighbour copies,
one scalar collision row per neighbour and step), so each Newton step costs one dense LU
factorization of size T*D + T per agent. The data preparation and the gradients are
torch; the iteration itself runs in NumPy on zero-copy views (CPU), where per-operation
overhead on these tiny arrays is several times lower.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor, nn

from .errors import GpmpcError
from .local_problem import (
    FAIL_INACCURATE, FAIL_NONFINITE, SLACK_ACTIVE_TOL, LocalProblemData, LocalSolution, acceptance_failures,
)
from .systems import NominalModel

logger = logging.getLogger(__name__)

#: Fraction of the step to the boundary of the positive orthant taken by the corrector.
STEP_FRACTION = 0.99

#: The backward pass differentiates at a point polished to ``POLISH_FACTOR * tol``
#: (at most ``POLISH_ITERATIONS`` extra iterations).
POLISH_FACTOR = 1e-2
POLISH_ITERATIONS = 6

#: After each step every U_t is projected onto the ball of this multiple of u_max
#: (globalization of the input bounds, see :func:`_project_inputs`).
TRUST_RADIUS = 1.0


# --------------------------------------------------------------------------- problem data
def condense_dynamics(x0: Tensor, dyn_A: Tensor, dyn_c: Tensor, b: float) -> tuple[Tensor, Tensor]:
    """Eliminate the dynamics: ``X_{1..T} = G U + h`` (differentiable).

    With ``X_0 = x0`` and ``X_{t+1} = A_t X_t + b U_t + c_t``, block row ``t`` of ``G``
    is ``b A_{t-1} ... A_{k+1}`` in block column ``k < t`` and ``b I`` for ``k = t - 1``.

    Args:
        x0: initial states, shape (B, D).
        dyn_A: state matrices, shape (B, T, D, D).
        dyn_c: offsets, shape (B, T, D).
        b: the input gain (``B = b I``).

    Returns:
        ``(G, h)`` with G of shape (B, T*D, T*D) and h of shape (B, T*D), states and
        inputs flattened time-major (index ``t * D + d``).
    """
    batch, horizon, dim = dyn_c.shape
    n = horizon * dim
    eye_b = b * torch.eye(dim, dtype=dyn_c.dtype, device=dyn_c.device).expand(batch, dim, dim)
    # Augmented block row [G_t | h_t] of shape (B, D, n + 1), propagated step by step.
    row = torch.cat([x0.new_zeros(batch, dim, n), x0[:, :, None]], dim=2)
    rows = []
    for t in range(horizon):
        row = torch.bmm(dyn_A[:, t], row)
        inject = torch.cat([x0.new_zeros(batch, dim, t * dim), eye_b,
                            x0.new_zeros(batch, dim, n - (t + 1) * dim), dyn_c[:, t, :, None]], dim=2)
        row = row + inject
        rows.append(row)
    stacked = torch.cat(rows, dim=1)  # (B, n, n + 1)
    return stacked[:, :, :n], stacked[:, :, n]


@dataclass
class CanonicalData:
    """The local problem in the solver's variables (all differentiable functions of the data).

    Objective (up to constants) over ``u = vec(U)``, ``Y_{j,1..T}`` and ``s``::

        c_X ||G u + h||^2 - l_X . (G u + h) + alpha ||u||^2
        + sum_j (rho_y_j / 2 ||Y_j||^2 - w_y_j . Y_j) + slack_penalty * sum(s)

    Attributes:
        G: condensed input-to-state map, shape (B, T*D, T*D).
        h: condensed free response, shape (B, T*D).
        c_x: quadratic weight of the states, ``1 + sum_{active j} rho_j / 2``, shape (B,).
        l_x: linear weight of X_{1..T}, ``2 Xref + sum_{active j} (rho_j z_own_j - lam_own_j)``,
            shape (B, T*D).
        rho_y: weight of the neighbour copies (1 on inactive slots), shape (B, M).
        w_y: linear weight of Y_{j,1..T}, ``rho_j z_nbr_j - lam_nbr_j`` (0 inactive),
            shape (B, M, T, D).
        y0: the closed-form copies at step 0, ``w_y / rho_y`` at tau = 0, shape (B, M, D).
        normals: collision normals (0 inactive), shape (B, M, T, D).
        bounds: collision bounds (-1 inactive), shape (B, M, T).
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


def canonicalize(data: LocalProblemData, b: float) -> CanonicalData:
    """Map :class:`LocalProblemData` to :class:`CanonicalData` (differentiable).

    Inactive slots get ``rho = 1``, ``w = 0`` (so ``Y_j = 0``), normal 0 and bound -1,
    and contribute nothing to the state cost (as in :class:`~torch_gpmpc.mpc.LocalMPC`).
    """
    batch, M = data.active.shape
    active = data.active.to(torch.bool)
    rho = data.rho.expand(batch, M) if data.rho.dim() == 0 else data.rho
    act4 = active[:, :, None, None]
    rho4 = rho[:, :, None, None]
    zero4 = data.z_own.new_zeros(())
    w_own = torch.where(act4, rho4 * data.z_own - data.lam_own, zero4)
    w_nbr = torch.where(act4, rho4 * data.z_nbr - data.lam_nbr, zero4)
    rho_y = torch.where(active, rho, torch.ones_like(rho))
    c_x = 1.0 + 0.5 * torch.where(active, rho, torch.zeros_like(rho)).sum(dim=1)
    l_x = (2.0 * data.xref[:, 1:] + w_own[:, :, 1:].sum(dim=1)).flatten(1)
    normals = torch.where(act4, data.normals, zero4)
    bounds = torch.where(active[:, :, None], data.bounds, -torch.ones_like(data.bounds))
    G, h = condense_dynamics(data.x0, data.dyn_A, data.dyn_c, b)
    y0 = w_nbr[:, :, 0] / rho_y[:, :, None]
    return CanonicalData(G=G, h=h, c_x=c_x, l_x=l_x, rho_y=rho_y, w_y=w_nbr[:, :, 1:], y0=y0,
                         normals=normals, bounds=bounds)


# ------------------------------------------------------------------------ interior point
# The iteration runs in NumPy (float64, zero-copy views of the CPU tensors): the arrays
# are tiny, so the cost is per-operation overhead, which is several times lower in NumPy
# than in torch. Autograd never enters the iteration (see _LocalQpFunction).
def _mv(mat: Tensor, vec: Tensor) -> Tensor:
    """Batched matrix-vector product, (B, p, q) x (B, q) -> (B, p)."""
    return torch.bmm(mat, vec.unsqueeze(-1)).squeeze(-1)


def _npmv(mat: np.ndarray, vec: np.ndarray) -> np.ndarray:
    """Batched matrix-vector product in NumPy, (B, p, q) x (B, q) -> (B, p)."""
    return np.matmul(mat, vec[:, :, None])[:, :, 0]


class _Kkt:
    """Per-call constants and the structured Newton solve of the interior-point method.

    Inequalities ``g(v) >= 0`` with slacks ``w`` and multipliers ``z`` (both (B, m),
    ``m = 2K + T``, ``K = M T``), stored in the order
    ``[collision rows (K) | slacks s >= 0 (K) | input bounds (T)]``; for ``s >= 0`` the
    slack *is* ``s``. Input bounds are the smooth convex constraints
    ``g_q = (u_max^2 - ||U_t||^2) / 2 >= 0``. All arrays are NumPy float64.

    Args:
        G, h, c_x, l_x, rho_y, w_y, normals, bounds: the :class:`CanonicalData` arrays.
        alpha, u_max, slack_penalty: problem constants.
    """

    def __init__(self, G: np.ndarray, h: np.ndarray, c_x: np.ndarray, l_x: np.ndarray, rho_y: np.ndarray,
                 w_y: np.ndarray, normals: np.ndarray, bounds: np.ndarray, alpha: float, u_max: float,
                 slack_penalty: float) -> None:
        batch, n = h.shape
        M, T, D = normals.shape[1:]
        K = M * T
        self.batch, self.n, self.T, self.D, self.K, self.m = batch, n, T, D, K, 2 * K + T
        self.u_max2, self.penalty = u_max * u_max, slack_penalty
        self.radius = TRUST_RADIUS * u_max
        self.N = normals.reshape(batch, K, D)
        # Collision rows in u: a_k = G_t^T n_k, shape (B, K, n); g_c = A u - N.y + s - bt.
        self.A = (normals[..., None] * G.reshape(batch, 1, T, D, n)).sum(3).reshape(batch, K, n)
        self.At = self.A.transpose(0, 2, 1)
        self.bt = (bounds - (normals * h.reshape(batch, 1, T, D)).sum(-1)).reshape(batch, K)
        self.rho = np.repeat(rho_y, T, axis=1)
        self.nn_rho = (self.N * self.N).sum(-1) / self.rho
        self.wy = w_y.reshape(batch, K, D)
        c2 = 2.0 * c_x[:, None, None]
        self.H = c2 * np.matmul(G.transpose(0, 2, 1), G) + 2.0 * alpha * np.eye(n)
        self.g0 = np.matmul((c2[:, :, 0] * h - l_x)[:, None, :], G)[:, 0]
        self.scale_u = 1.0 + np.abs(self.g0).max(1)
        self.scale_y = 1.0 + np.abs(self.wy).reshape(batch, -1).max(1, initial=0.0)
        self.scale_p = 1.0 + np.maximum(np.abs(self.bt).max(1, initial=0.0), self.u_max2)
        self.diag_n = np.arange(n)
        self.diag_t = np.arange(T)
        self.col_t = n + np.repeat(self.diag_t, D)  # column of the input bound of u entry i

    # ---- residuals
    def residuals(self, u: np.ndarray, y: np.ndarray, w: np.ndarray, z: np.ndarray) -> tuple[np.ndarray, ...]:
        """Dual and primal residuals at ``(u, y, w, z)``.

        Returns:
            ``(r_u (B, n), r_y (B, K, D), r_s (B, K), r_pc (B, K), r_pq (B, T))``.
        """
        K, B, T, D = self.K, self.batch, self.T, self.D
        U = u.reshape(B, T, D)
        zc, zs, zq = z[:, :K], z[:, K:2 * K], z[:, 2 * K:]
        wc, s, wq = w[:, :K], w[:, K:2 * K], w[:, 2 * K:]
        r_u = _npmv(self.H, u) + self.g0 - _npmv(self.At, zc) + (zq[:, :, None] * U).reshape(B, -1)
        r_y = self.rho[:, :, None] * y - self.wy + zc[:, :, None] * self.N
        r_s = self.penalty - zc - zs
        r_pc = _npmv(self.A, u) - (self.N * y).sum(-1) + s - self.bt - wc
        r_pq = 0.5 * (self.u_max2 - (U * U).sum(-1)) - wq
        return r_u, r_y, r_s, r_pc, r_pq

    def kkt_error(self, res: tuple[np.ndarray, ...], w: np.ndarray, z: np.ndarray) -> np.ndarray:
        """KKT error per problem, (B,): the largest of the relative dual residuals, the
        relative primal residuals and the absolute complementarity ``sum(w z)`` (absolute
        because nearly degenerate collision rows need it: their copies Y follow z)."""
        r_u, r_y, r_s, r_pc, r_pq = res
        B = self.batch
        err = np.abs(r_u).max(1) / self.scale_u
        if self.K:
            err = np.maximum(err, np.abs(r_y).reshape(B, -1).max(1) / self.scale_y)
            err = np.maximum(err, np.abs(r_s).max(1) / (1.0 + self.penalty))
            err = np.maximum(err, np.abs(r_pc).max(1) / self.scale_p)
        err = np.maximum(err, np.abs(r_pq).max(1) / self.scale_p)
        return np.maximum(err, (w * z).sum(1))

    # ---- Newton system
    def factor(self, u: np.ndarray, w: np.ndarray, z: np.ndarray) -> "_Factor":
        """Factor the reduced Newton system at the iterate ``(u, w, z)``.

        Per collision row, ``Y`` and ``s`` are eliminated in closed form: the row adds
        ``deff_k a_k a_k^T`` to the u-block with the bounded weight
        ``deff_k = 1 / (w_c/z_c + |n_k|^2/rho_k + s/z_s)``. The input bounds stay in
        augmented form: with ``E`` the (T, n) Jacobian of ``g_q`` (row t is ``-U_t`` in
        block t) and ``S0 = H + blockdiag(z_q I) + A^T diag(deff) A``, the step solves::

            [ S0   E^T            ] [du]   [ r0     ]
            [ E   -diag(w_q/z_q)  ] [y ] = [ -rho_q ],      dz_q = -y,

        a quasi-definite matrix without 1/mu-sized entries (w_q/z_q only grows on
        inactive bounds, on the diagonal). Eliminating ``dz_q`` instead would add
        ``(z_q/w_q) U_t U_t^T`` to S0 and ruin the factorization near the solution.

        The matrix is factored by LU with partial pivoting (it is symmetric but
        indefinite).

        Returns:
            The factorization, with ``deff`` (B, K) and ``failed`` (B,) (singular matrix).
        """
        K, B, T, D, n = self.K, self.batch, self.T, self.D, self.n
        zc, zs, zq = z[:, :K], z[:, K:2 * K], z[:, 2 * K:]
        wc, s, wq = w[:, :K], w[:, K:2 * K], w[:, 2 * K:]
        deff = 1.0 / (wc / zc + self.nn_rho + s / zs)
        kmat = np.empty((B, n + T, n + T))
        torch.bmm(torch.from_numpy(self.At * deff[:, None, :]), torch.from_numpy(self.A),
                  out=torch.from_numpy(kmat)[:, :n, :n])
        kmat[:, :n, :n] += self.H
        kmat[:, self.diag_n, self.diag_n] += np.repeat(zq, D, axis=1)
        kmat[:, :n, n:] = 0.0
        kmat[:, n:, :] = 0.0
        kmat[:, self.diag_n, self.col_t] = -u
        kmat[:, self.col_t, self.diag_n] = -u
        kmat[:, n + self.diag_t, n + self.diag_t] = -wq / zq
        lu, pivots, info = torch.linalg.lu_factor_ex(torch.from_numpy(kmat))
        return _Factor(lu=lu, pivots=pivots, deff=deff, failed=info.numpy() != 0)

    @staticmethod
    def solve(fac: "_Factor", rhs: np.ndarray) -> np.ndarray:
        """Solve with the factored Newton matrix, (B, n+T) -> (B, n+T); failed rows give 0."""
        sol = torch.linalg.lu_solve(fac.lu, fac.pivots, torch.from_numpy(rhs)[:, :, None]).numpy()[:, :, 0]
        if fac.failed.any():
            sol[fac.failed] = 0.0
        return sol

    def direction(self, fac: "_Factor", u: np.ndarray, w: np.ndarray, z: np.ndarray,
                  res: tuple[np.ndarray, ...], rc: np.ndarray) -> tuple[np.ndarray, ...]:
        """Newton direction for the complementarity residual ``rc`` (``z dw + w dz = -rc``).

        Args:
            fac: from :meth:`factor`.
            u, w, z: the iterate.
            res: from :meth:`residuals`.
            rc: complementarity residual ``w z - sigma mu (+ corrector)``, shape (B, m).

        Returns:
            ``(du (B, n), dy (B, K, D), dw (B, m), dz (B, m))``.
        """
        K, B, T, D, n = self.K, self.batch, self.T, self.D, self.n
        deff = fac.deff
        r_u, r_y, r_s, r_pc, r_pq = res
        zc, zs, zq = z[:, :K], z[:, K:2 * K], z[:, 2 * K:]
        wc, s = w[:, :K], w[:, K:2 * K]
        rcc, rcs, rcq = rc[:, :K], rc[:, K:2 * K], rc[:, 2 * K:]
        rho_c = r_pc + rcc / zc
        s_zs = s / zs
        rt_s = -r_s - rcs / s
        gam = (self.N * r_y).sum(-1) / self.rho + rt_s * s_zs
        rhs = np.concatenate([-r_u - _npmv(self.At, deff * (gam + rho_c)), -r_pq - rcq / zq], 1)
        sol = self.solve(fac, rhs)
        du = sol[:, :n]
        xi = deff * (gam + rho_c + _npmv(self.A, du))
        dy = (self.N * xi[:, :, None] - r_y) / self.rho[:, :, None]
        ds = s_zs * (rt_s - xi)
        dwq = r_pq - (u.reshape(B, T, D) * du.reshape(B, T, D)).sum(-1)
        dw = np.concatenate([(wc * xi - rcc) / zc, ds, dwq], 1)
        dz = np.concatenate([-xi, r_s + xi, -sol[:, n:]], 1)
        return du, dy, dw, dz

    def adjoint(self, fac: "_Factor", w: np.ndarray, z: np.ndarray,
                g_u: np.ndarray, g_y: np.ndarray, g_s: np.ndarray) -> tuple[np.ndarray, ...]:
        """Solve the (symmetric) reduced KKT system for a right-hand side ``(g_u, g_y, g_s)``.

        Returns:
            ``(a_u (B, n), a_y (B, K, D), xi (B, K))`` where ``xi`` is the scaled
            multiplier ``(z_c / w_c) (grad g_c . a)`` of the collision rows.
        """
        K, n, deff = self.K, self.n, fac.deff
        s_zs = w[:, K:2 * K] / z[:, K:2 * K]
        gam = -(self.N * g_y).sum(-1) / self.rho + g_s * s_zs
        rhs = np.concatenate([g_u - _npmv(self.At, deff * gam), np.zeros((self.batch, self.T))], 1)
        a_u = self.solve(fac, rhs)[:, :n]
        xi = deff * (gam + _npmv(self.A, a_u))
        a_y = (g_y + self.N * xi[:, :, None]) / self.rho[:, :, None]
        return a_u, a_y, xi


@dataclass
class _Factor:
    """LU factorization of the reduced Newton matrix (see :meth:`_Kkt.factor`)."""

    lu: Tensor
    pivots: Tensor
    deff: np.ndarray
    failed: np.ndarray


def _max_step(w: np.ndarray, z: np.ndarray, dw: np.ndarray, dz: np.ndarray) -> np.ndarray:
    """Largest step in [0, 1] keeping ``w + a dw >= 0`` and ``z + a dz >= 0``, shape (B, 1)."""
    ratio = np.minimum((dw / w).min(1), (dz / z).min(1))
    return (1.0 / np.maximum(-ratio, 1.0))[:, None]


def _project_inputs(u: np.ndarray, T: int, D: int, radius: float) -> np.ndarray:
    """Scale every ``U_t`` with ``||U_t|| > radius`` back onto that sphere, shape (B, T*D).

    Globalization of the input bounds: a pure Newton step on ``||U_t||^2 <= u_max^2``
    can overshoot by orders of magnitude in the first iterations. The method starts
    infeasible and recomputes all residuals from the iterate, so moving the iterate is
    allowed; near the solution ``||U_t|| <= u_max`` and the projection is inactive.
    """
    U = u.reshape(u.shape[0], T, D)
    norm = np.sqrt((U * U).sum(-1, keepdims=True))
    return (U * (radius / np.maximum(norm, radius))).reshape(u.shape)


@dataclass
class IpmResult:
    """Primal-dual solution of the batched interior-point method (NumPy arrays).

    Attributes:
        u: inputs, shape (B, T*D).
        y: neighbour copies at tau = 1..T, shape (B, K, D) with K = M*T.
        w: slacks ``[g_c | s | g_q]``, shape (B, 2K + T).
        z: multipliers in the same order, shape (B, 2K + T).
        converged: KKT error below tolerance, shape (B,).
        iterations: number of iterations run.
        kkt_error: final KKT error, shape (B,).
    """

    u: np.ndarray
    y: np.ndarray
    w: np.ndarray
    z: np.ndarray
    converged: np.ndarray
    iterations: int
    kkt_error: np.ndarray


def _initial_point(kkt: _Kkt) -> tuple[np.ndarray, ...]:
    """Infeasible start: ``u = 0``, unconstrained copies, ``z_c + z_s = P`` (dual feasible in
    s) and ``s z_s = 1``, so that every complementarity product starts near 1."""
    B, K, T = kkt.batch, kkt.K, kkt.T
    zc0 = min(1.0, 0.5 * kkt.penalty)
    zs0 = kkt.penalty - zc0
    y = kkt.wy / kkt.rho[:, :, None]
    s = np.full((B, K), 1.0 / zs0)
    gc = -(kkt.N * y).sum(-1) + s - kkt.bt
    w = np.concatenate([np.maximum(gc, 1.0), s, np.full((B, T), 0.5 * kkt.u_max2)], 1)
    z = np.concatenate([np.full((B, K), zc0), np.full((B, K), zs0), np.ones((B, T))], 1)
    return np.zeros((B, kkt.n)), y, w, z


def interior_point(kkt: _Kkt, tol: float, max_iter: int,
                   start: tuple[np.ndarray, ...] | None = None) -> IpmResult:
    """Mehrotra predictor-corrector interior-point method on the batched problem.

    Problems that converge are frozen (zero step) while the others continue; problems
    whose Newton system cannot be inverted are frozen as failed.

    Args:
        kkt: the problem.
        tol: stopping tolerance on :meth:`_Kkt.kkt_error`.
        max_iter: iteration limit.
        start: optional ``(u, y, w, z)`` to continue from (``w, z > 0``).
    """
    B = kkt.batch
    u, y, w, z = _initial_point(kkt) if start is None else start
    done = np.zeros(B, dtype=bool)
    failed = np.zeros(B, dtype=bool)
    err = np.full(B, np.inf)
    it = 0
    with np.errstate(all="ignore"):
        for it in range(max_iter + 1):
            res = kkt.residuals(u, y, w, z)
            err = kkt.kkt_error(res, w, z)
            done |= err <= tol
            if (done | failed).all() or it == max_iter:
                break
            fac = kkt.factor(u, w, z)
            failed |= fac.failed & ~done
            wz = w * z
            mu = wz.mean(1, keepdims=True)
            # predictor (affine scaling)
            du, dy, dw, dz = kkt.direction(fac, u, w, z, res, wz)
            a_aff = _max_step(w, z, dw, dz)
            mu_aff = ((w + a_aff * dw) * (z + a_aff * dz)).mean(1, keepdims=True)
            sigma = np.minimum(mu_aff / mu, 1.0) ** 3
            # corrector
            du, dy, dw, dz = kkt.direction(fac, u, w, z, res, wz + dw * dz - sigma * mu)
            step = np.minimum(STEP_FRACTION * _max_step(w, z, dw, dz), 1.0)
            finite = np.isfinite(step[:, 0] + du.sum(1) + dw.sum(1) + dz.sum(1) + dy.reshape(B, -1).sum(1))
            step[done | failed | ~finite] = 0.0
            if not finite.all():
                du, dy, dw, dz = (np.nan_to_num(d, nan=0.0, posinf=0.0, neginf=0.0) for d in (du, dy, dw, dz))
            u = _project_inputs(u + step * du, kkt.T, kkt.D, kkt.radius)
            y = y + step[:, :, None] * dy
            w = w + step * dw
            z = z + step * dz
    return IpmResult(u=u, y=y, w=w, z=z, converged=done & ~failed, iterations=it, kkt_error=err)


# ------------------------------------------------------------------------ differentiation
def _stationarity_pairing(G: Tensor, h: Tensor, c_x: Tensor, l_x: Tensor, rho_y: Tensor, w_y: Tensor,
                          normals: Tensor, bounds: Tensor, u: Tensor, y: Tensor, zc: Tensor,
                          a_u: Tensor, a_y: Tensor, xi: Tensor) -> Tensor:
    """``a^T grad_v L(v, z; theta) + xi^T g_c(v; theta)`` summed over the batch (a scalar).

    Only the terms that depend on the problem data theta are kept; its gradient with
    respect to theta, negated, is the implicit-function-theorem vector-Jacobian product.

    Shapes: G (B, n, n), h (B, n), c_x (B,), l_x (B, n), rho_y (B, M), w_y (B, M, T, D),
    normals (B, M, T, D), bounds (B, M, T); u, a_u (B, n); y, a_y (B, K, D); zc, xi (B, K).
    """
    B, M, T, D = normals.shape
    x1 = _mv(G, u) + h
    dx1 = _mv(G, a_u)
    obj = ((2.0 * c_x[:, None] * x1 - l_x) * dx1).sum()
    rho = rho_y[:, :, None].expand(B, M, T).reshape(B, -1, 1)
    obj = obj + ((rho * y - w_y.reshape(B, -1, D)) * a_y).sum()
    N = normals.reshape(B, -1, D)
    x_rows = x1.view(B, 1, T, D).expand(B, M, T, D).reshape(B, -1, D)
    dx_rows = dx1.view(B, 1, T, D).expand(B, M, T, D).reshape(B, -1, D)
    obj = obj - (zc * (N * (dx_rows - a_y)).sum(-1)).sum()
    return obj + (xi * ((N * (x_rows - y)).sum(-1) - bounds.reshape(B, -1))).sum()


class _LocalQpFunction(torch.autograd.Function):
    """Batched interior-point solve with implicit differentiation of its KKT conditions.

    Inputs are the :class:`CanonicalData` tensors (G, h, c_x, l_x, rho_y, w_y, normals,
    bounds) and a settings tuple; outputs ``(u (B, n), y (B, M, T, D), s (B, M, T),
    converged (B,))``.
    """

    @staticmethod
    def forward(ctx, G, h, c_x, l_x, rho_y, w_y, normals, bounds, settings):  # noqa: D102
        alpha, u_max, penalty, tol, max_iter, stats = settings
        arrays = [t.detach().cpu().numpy().astype(np.float64, copy=False) for t in
                  (G, h, c_x, l_x, rho_y, w_y, normals, bounds)]
        kkt = _Kkt(*arrays, alpha, u_max, penalty)
        result = interior_point(kkt, tol, max_iter)
        stats["iterations"] = result.iterations
        ctx.kkt, ctx.result, ctx.tol = kkt, result, tol
        ctx.save_for_backward(G, h, c_x, l_x, rho_y, w_y, normals, bounds)
        B, M, T, D = normals.shape

        def out(a: np.ndarray, *shape: int) -> Tensor:
            return torch.from_numpy(np.ascontiguousarray(a)).to(dtype=h.dtype, device=h.device).reshape(*shape)

        converged = torch.from_numpy(result.converged).to(h.device)
        ctx.mark_non_differentiable(converged)
        return (out(result.u, B, T * D), out(result.y, B, M, T, D), out(result.w[:, kkt.K:2 * kkt.K], B, M, T),
                converged)

    @staticmethod
    def backward(ctx, g_u, g_y, g_s, _g_conv):  # noqa: D102
        kkt, res = ctx.kkt, ctx.result
        inputs = ctx.saved_tensors
        B, K, D = res.y.shape
        ref = inputs[1]

        def arr(g: Tensor | None, *shape: int) -> np.ndarray:
            if g is None:
                return np.zeros(shape)
            return g.detach().cpu().numpy().astype(np.float64, copy=False).reshape(shape)

        def ten(a: np.ndarray) -> Tensor:
            return torch.from_numpy(np.ascontiguousarray(a)).to(dtype=ref.dtype, device=ref.device)

        # Gradients are more sensitive than solutions to the barrier perturbation (a
        # nearly degenerate row counts as half active): continue from the returned point
        # to a tighter tolerance before differentiating (usually one or two iterations).
        polished = interior_point(kkt, POLISH_FACTOR * ctx.tol, POLISH_ITERATIONS,
                                  start=(res.u, res.y, res.w, res.z))
        keep = ~res.converged | polished.converged | (polished.kkt_error <= res.kkt_error)
        res = IpmResult(u=np.where(keep[:, None], polished.u, res.u),
                        y=np.where(keep[:, None, None], polished.y, res.y),
                        w=np.where(keep[:, None], polished.w, res.w), z=np.where(keep[:, None], polished.z, res.z),
                        converged=res.converged, iterations=res.iterations, kkt_error=polished.kkt_error)
        with np.errstate(all="ignore"):
            fac = kkt.factor(res.u, res.w, res.z)
            a_u, a_y, xi = kkt.adjoint(fac, res.w, res.z, arr(g_u, B, kkt.n), arr(g_y, B, K, D),
                                       arr(g_s, B, K))
        a_u, a_y, xi = (ten(np.nan_to_num(a)) for a in (a_u, a_y, xi))
        needs = ctx.needs_input_grad[:8]
        with torch.enable_grad():
            leaves = [t.detach().requires_grad_(n) for t, n in zip(inputs, needs)]
            pairing = _stationarity_pairing(*leaves, ten(res.u), ten(res.y), ten(res.z[:, :K]), a_u, a_y, xi)
            wanted = [leaf for leaf, n in zip(leaves, needs) if n]
            grads = iter(torch.autograd.grad(pairing, wanted, allow_unused=True)) if wanted else iter(())
        out = []
        for leaf, n in zip(leaves, needs):
            grad = next(grads) if n else None
            out.append(None if grad is None else -grad)
        return (*out, None)


# ------------------------------------------------------------------------------ the layer
class FastLocalMPC(nn.Module):
    r"""Agent-local MPC problem (paper eqs. 26-27) by a batched differentiable interior-point method.

    Solves, for each of B agents with horizon T, dimension D and M neighbour slots, the
    same problem as :class:`torch_gpmpc.mpc.LocalMPC`::

        minimize    ||X - Xref||_F^2 + alpha ||U||_F^2 + slack_penalty * sum(s)
                    + sum_{active j} [ lam_own_j . X + lam_nbr_j . Y_j
                                       + rho_j / 2 (||X - z_own_j||^2 + ||Y_j - z_nbr_j||^2) ]
                    + sum_{inactive j} 1/2 ||Y_j||^2
        over        X (T+1, D), U (T, D), Y_j (T+1, D), s (M, T)
        subject to  X_0 = x0,  X_{t+1} = dyn_A_t X_t + b U_t + dyn_c_t       t = 0..T-1
                    ||U_t||_2 <= u_max                                      t = 0..T-1
                    n_{j,t}^T (X_t - Y_{j,t}) + s_{j,t} >= bound_{j,t},  s >= 0   t = 1..T

    (inactive slots have no collision row). Method:

    * **Condensing.** ``X_{1..T} = G u + h`` with ``u = vec(U)`` (:func:`condense_dynamics`);
      ``Y_{j,0} = (rho z_nbr - lam_nbr)_{j,0} / rho_j`` in closed form. Variables left:
      ``u`` (T D), ``Y_{j,1..T}`` (M T D), ``s`` (M T).
    * **Interior point.** Primal-dual, infeasible start, Mehrotra predictor-corrector,
      one step length, fraction to the boundary 0.99. The input bounds are the smooth
      convex constraints ``(u_max^2 - ||U_t||^2) / 2 >= 0`` with their own slacks (not
      second-order cones: an NT-scaled cone loses precision at tight tolerances because
      its distance to the boundary is a difference of O(1) numbers; a scalar slack
      does not). Globalization: after each step every ``U_t`` is projected onto the
      ball of radius ``u_max`` (the iterate may be moved since all residuals are
      recomputed; near the solution the projection is inactive).
    * **Linear algebra.** Per collision row, ``Y_{j,t}`` and ``s_{j,t}`` are eliminated in
      closed form (diagonal Hessian ``rho_j``), leaving ``S0 = H + blockdiag(z_q I) +
      A^T diag(deff) A`` (T D x T D) with bounded weights; the input-bound multipliers
      stay in the system (augmented, quasi-definite, size T D + T), so no 1/mu-sized
      term is ever factored (see :meth:`_Kkt.factor`). One LU per iteration serves the
      predictor and the corrector.
    * **Stopping.** Relative dual residuals, relative primal residuals and the absolute
      complementarity ``sum(w z)`` all below ``tol``. Converged problems are frozen
      while the rest of the batch continues.
    * **Gradients.** Implicit differentiation of the KKT conditions at the returned
      primal-dual point: one adjoint solve with the same reduced matrix, then the
      data-dependent part of the KKT residual is differentiated by autograd, so every
      tensor field of :class:`~torch_gpmpc.mpc.LocalProblemData` gets its gradient.
      The backward first continues the iteration to ``tol / 100`` from the returned
      point (usually 1-2 iterations): gradients are more sensitive to the barrier
      perturbation than solutions (nearly degenerate rows).

    Never raises on numerical trouble: problems that do not converge within
    ``max_iter`` (or have non-finite data) get ``ok = False`` and finite outputs.

    Args:
        horizon: T.
        dim: D (inputs have dimension D too).
        num_neighbors: M (0 allowed).
        nominal: the nominal model; its ``B() = b I`` is used.
        u_max: input norm bound.
        alpha: control-effort weight.
        slack_penalty: exact-penalty weight of the collision slacks.
        tol: stopping tolerance on the KKT error.
        max_iter: iteration limit.
    """

    def __init__(self, horizon: int, dim: int, num_neighbors: int, nominal: NominalModel, u_max: float,
                 alpha: float, slack_penalty: float = 1e4, tol: float = 1e-10, max_iter: int = 50) -> None:
        super().__init__()
        if horizon < 1 or dim < 1 or num_neighbors < 0:
            raise GpmpcError(f"FastLocalMPC needs horizon >= 1, dim >= 1, num_neighbors >= 0; got "
                             f"{horizon}, {dim}, {num_neighbors}")
        if nominal.dim != dim:
            raise GpmpcError(f"nominal model has dim {nominal.dim}, FastLocalMPC dim is {dim}")
        if u_max <= 0 or alpha <= 0 or slack_penalty <= 0 or tol <= 0 or max_iter < 1:
            raise GpmpcError(f"u_max, alpha, slack_penalty, tol must be > 0 and max_iter >= 1; got "
                             f"{u_max}, {alpha}, {slack_penalty}, {tol}, {max_iter}")
        b_mat = nominal.B()
        b = float(b_mat[0, 0])
        if not torch.equal(b_mat, b * torch.eye(dim, dtype=b_mat.dtype)):
            raise GpmpcError("FastLocalMPC needs an input matrix B = b I")
        self.horizon, self.dim, self.num_neighbors = horizon, dim, num_neighbors
        self.nominal, self.b = nominal, b
        self.u_max, self.alpha, self.slack_penalty = float(u_max), float(alpha), float(slack_penalty)
        self.tol, self.max_iter = float(tol), int(max_iter)
        #: Iterations used by the last call (for benchmarks and logging).
        self.last_iterations = 0

    def forward(self, data: LocalProblemData) -> LocalSolution:
        """Solve the B local problems.

        Args:
            data: inputs with shapes as in :class:`~torch_gpmpc.mpc.LocalProblemData`
                (float64 recommended; computations run in the dtype of ``x0``).

        Returns:
            The :class:`~torch_gpmpc.mpc.LocalSolution`; differentiable with respect to
            every floating-point field of ``data``.

        Raises:
            GpmpcError: if a field has the wrong shape.
        """
        batch = data.validate(self.horizon, self.dim, self.num_neighbors)
        T, D, M = self.horizon, self.dim, self.num_neighbors
        canon = canonicalize(data, self.b)
        canon, valid = _sanitize(canon)
        stats: dict = {}
        settings = (self.alpha, self.u_max, self.slack_penalty, self.tol, self.max_iter, stats)
        u, y1, slack, converged = _LocalQpFunction.apply(canon.G, canon.h, canon.c_x, canon.l_x, canon.rho_y,
                                                         canon.w_y, canon.normals, canon.bounds, settings)
        self.last_iterations = stats["iterations"]
        x0 = torch.where(valid[:, None], data.x0, torch.zeros_like(data.x0))
        X = torch.cat([x0[:, None], (_mv(canon.G, u) + canon.h).view(batch, T, D)], dim=1)
        U = u.view(batch, T, D)
        Y = torch.cat([canon.y0[:, :, None], y1], dim=2)
        # the same acceptance rule as the cvxpylayers path; unconverged or invalid rows fail too
        failure = acceptance_failures(data, X.detach(), U.detach(), Y.detach(), slack.detach(),
                                      self.nominal, self.u_max)
        failure = torch.where(~valid, torch.full_like(failure, FAIL_NONFINITE), failure)  # bad input data
        failure = torch.where(~converged & (failure == 0), torch.full_like(failure, FAIL_INACCURATE), failure)
        ok = failure == 0
        if M > 0:
            used = torch.where(data.active.to(torch.bool)[:, :, None], slack, torch.zeros_like(slack))
            slack_active = (used > SLACK_ACTIVE_TOL).flatten(1).any(dim=1) & ok
        else:
            slack_active = torch.zeros(batch, dtype=torch.bool)
        if not bool(ok.all()):  # ADMM counts and warns (once per kind); keep the details here
            logger.debug("FastLocalMPC: %d of %d local problems rejected (tol %g, %d iterations)",
                         int((~ok).sum()), batch, self.tol, self.max_iter)
        xref = torch.where(valid[:, None, None], data.xref, torch.zeros_like(data.xref))
        cost = ((X - xref) ** 2).sum(dim=(1, 2)) + self.alpha * (U ** 2).sum(dim=(1, 2))
        return LocalSolution(X=X, U=U, Y=Y, slack=slack, slack_active=slack_active, ok=ok, cost=cost,
                             failure=failure)


def _sanitize(canon: CanonicalData) -> tuple[CanonicalData, Tensor]:
    """Replace problems with non-finite data or ``rho <= 0`` by a benign one.

    Returns:
        ``(canon, valid (B,))``; rows with ``valid = False`` are the problem with
        ``G = 0, h = 0, c_x = 1, l_x = 0, rho_y = 1, w_y = 0``, no collision rows.
    """
    parts = [canon.G.flatten(1), canon.h, canon.c_x[:, None], canon.l_x, canon.rho_y, canon.w_y.flatten(1),
             canon.y0.flatten(1), canon.normals.flatten(1), canon.bounds.flatten(1)]
    total = torch.cat([p.detach() for p in parts], dim=1).sum(1)
    valid = torch.isfinite(total)
    if canon.rho_y.numel():
        valid = valid & (canon.rho_y.detach() > 0).all(1)
    if bool(valid.all()):
        return canon, valid

    def keep(t: Tensor, fill: float) -> Tensor:
        mask = valid.view(-1, *([1] * (t.dim() - 1)))
        return torch.where(mask, t, torch.full_like(t, fill))

    return CanonicalData(G=keep(canon.G, 0.0), h=keep(canon.h, 0.0), c_x=keep(canon.c_x, 1.0),
                         l_x=keep(canon.l_x, 0.0), rho_y=keep(canon.rho_y, 1.0), w_y=keep(canon.w_y, 0.0),
                         y0=keep(canon.y0, 0.0), normals=keep(canon.normals, 0.0),
                         bounds=keep(canon.bounds, -1.0)), valid
