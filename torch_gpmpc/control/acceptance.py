"""The acceptance rule's residuals for a batch of returned plans, compiled by numba.

:func:`~torch_gpmpc.control.problem.acceptance_failures` states the rule; this module evaluates it
in one compiled pass per batch. Every solve of the closed loop is checked, and written as NumPy
array expressions the check took about 40 small-array calls (0.17 ms at batch 3, more than a
warm solve of the three problems); the loops here take a few microseconds. Serial float64, no
fastmath (reproducible); compiled code is cached on disk (``cache=True``; this module calls into no
other numba module, so numba's own check of its source keeps the cache fresh).
"""

from __future__ import annotations

import numba
import numpy as np

_jit = numba.njit(cache=True, error_model="numpy", nogil=True)


@_jit
def _all_finite(a) -> bool:
    for v in a.ravel():
        if not np.isfinite(v):
            return False
    return True


@_jit
def _dynamics_residual(X, U, A, Bd, c) -> float:
    """``max |X_{t+1} - (A_t X_t + B_t U_t + c_t)|`` of one plan: X (T+1, D), U (T, Du),
    A (T, D, D), Bd (T, D, Du), c (T, D)."""
    T, D, Du = A.shape[0], A.shape[1], U.shape[1]
    worst = 0.0
    for t in range(T):
        for d in range(D):
            v = c[t, d]
            for e in range(D):
                v += A[t, d, e] * X[t, e]
            for j in range(Du):
                v += Bd[t, d, j] * U[t, j]
            worst = max(worst, abs(X[t + 1, d] - v))
    return worst


@_jit
def _input_excess(U, box, u_norm) -> float:
    """How far one plan's inputs U (T, Du) leave the box (Du,) (empty: none) and the norm ball
    ``u_norm`` (``inf``: none)."""
    worst = 0.0
    for t in range(U.shape[0]):
        norm2 = 0.0
        for j in range(U.shape[1]):
            norm2 += U[t, j] * U[t, j]
            if box.shape[0]:
                worst = max(worst, abs(U[t, j]) - box[j])
        if u_norm < np.inf:
            worst = max(worst, np.sqrt(norm2) - u_norm)
    return worst


@_jit
def _collision_excess(X, Y, S, normals, bounds, active) -> float:
    """Largest violation of the softened collision rows ``n . (X_tau - Y_j,tau) + s_j,tau >=
    bound_j,tau`` (tau = 1..T) of one plan's active slots: X (T+1, D), Y (M, T+1, D), S (M, T),
    normals (M, T, D), bounds (M, T), active (M,)."""
    M, T, D = normals.shape
    worst = 0.0
    for j in range(M):
        if not active[j]:
            continue
        for t in range(T):
            gap = 0.0
            for d in range(D):
                gap += normals[j, t, d] * (X[t + 1, d] - Y[j, t + 1, d])
            worst = max(worst, bounds[j, t] - gap - S[j, t])
    return worst


@_jit
def failure_codes(X, U, Y, S, x0, A, Bd, c, normals, bounds, active, box, u_norm, input_scale, tol,
                  kinds, codes) -> None:
    """The acceptance rule per problem, written into ``codes (B,)`` int64: ``kinds[0]`` accepted,
    ``kinds[1]`` non-finite, ``kinds[2]`` inaccurate (the codes of
    :mod:`~torch_gpmpc.control.problem`).

    Args:
        X (B, T+1, D), U (B, T, Du), Y (B, M, T+1, D), S (B, M, T): the returned plans.
        x0 (B, D), A (B, T, D, D), Bd (B, T, D, Du), c (B, T, D): initial states and dynamics.
        normals (B, M, T, D), bounds (B, M, T), active (B, M) bool: the collision rows.
        box (Du,) or (0,), u_norm (``inf``: none), input_scale: the input bounds and their scale.
        tol: the relative feasibility tolerance. kinds (3,) int64: the codes.
    """
    for b in range(X.shape[0]):
        if not (_all_finite(X[b]) and _all_finite(U[b]) and _all_finite(S[b]) and _all_finite(Y[b])):
            codes[b] = kinds[1]
            continue
        scale = 1.0
        for v in X[b].ravel():
            scale = max(scale, 1.0 + abs(v))
        init = 0.0
        for d in range(X.shape[2]):
            init = max(init, abs(X[b, 0, d] - x0[b, d]))
        slack = 0.0
        for v in S[b].ravel():
            slack = max(slack, -v)
        rows = 0.0
        if Y.shape[1] > 0 and S.shape[1] * S.shape[2] > 0:
            rows = _collision_excess(X[b], Y[b], S[b], normals[b], bounds[b], active[b])
        feasible = (_dynamics_residual(X[b], U[b], A[b], Bd[b], c[b]) <= tol * scale and init <= tol * scale
                    and _input_excess(U[b], box, u_norm) <= tol * (1.0 + input_scale)
                    and slack <= tol * scale and rows <= tol * scale)
        codes[b] = kinds[0] if feasible else kinds[2]


def warm_up() -> None:
    """Compile (or load from numba's cache) :func:`failure_codes` for the arrays the solvers pass."""
    B, M, T, D, Du = 1, 1, 1, 1, 1
    X, U, Y, S = np.zeros((B, T + 1, D)), np.zeros((B, T, Du)), np.zeros((B, M, T + 1, D)), np.zeros((B, M, T))
    failure_codes(X, U, Y, S, np.zeros((B, D)), np.zeros((B, T, D, D)), np.zeros((B, T, D, Du)), np.zeros((B, T, D)),
                  np.zeros((B, M, T, D)), np.zeros((B, M, T)), np.ones((B, M), dtype=np.bool_), np.ones(Du), 1.0, 1.0,
                  1e-5, np.arange(3, dtype=np.int64), np.empty(B, dtype=np.int64))
