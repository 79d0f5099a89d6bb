"""Warm-started exact solves of the local problem: a primal-dual active-set (semismooth Newton)
method from the previous solution, compiled by numba.

Inside one control step ADMM solves every agent's local problem again at each iteration with the
same matrices; only the linear terms (and rho, when the penalty adapts) change, and so the set of
active rows changes little. Given a guess of which inequalities are active (from the previous
solve's primal-dual point), the solution is one linear solve: the equality-constrained problem
``[[W, -E^T], [E, Dd]] [du; z] = [-r; -g]`` (W = H plus the norm rows' curvature, E the active
rows' gradients, ``Dd = |n|^2 / rho`` for a collision row whose copy is eliminated). Each round
solves it, re-classifies every inequality (an inactive row that is violated becomes active, an
active multiplier that turns negative becomes inactive, a soft row's multiplier above its
penalty saturates: its slack opens), and stops when no class changes and the nonlinear (norm)
rows hold; a stable class with norm rows needs one or two more Newton rounds. The point is then
written in the interior-point kernel's layout (:mod:`~torch_gpmpc.control.solvers.ipm_kernel`)
and accepted only if that kernel's own KKT error (:func:`~.ipm_residuals.kkt_error`) is below the
target and every slack and multiplier has its sign: an accepted point is the optimum to the same
test the interior point applies, reached with exact complementarity (no barrier). Problems that
do not get there within ``max_rounds`` rounds (a guess too far off, a degenerate active set), or
whose Newton step leaves the inputs' bound by far (:data:`DIVERGED_STEP`), are reported
unconverged and the caller solves them cold.

This is the classic warm start of active-set QP solvers (qpOASES' homotopy from the previous
active set, OSQP's polish step, which solves the same reduced KKT system for its guessed active
set); an interior point cannot reuse its previous point this way (its iterate must stay interior).

Classes per inequality: 0 inactive (multiplier 0), 1 active (holds with equality), 2 saturated
(a soft row whose multiplier sits at its price: collision and state rows at the slack penalty P,
state-norm rows at ``P / v_max``; their slack is what the row lacks).
"""

from __future__ import annotations

import numba
import numpy as np

from torch_gpmpc.control.solvers.ipm_linalg import absmax, absmax2, backward_solve, cholesky, fill, forward_solve
from torch_gpmpc.control.solvers.ipm_residuals import (
    add_state_norm_curvature, kkt_error, offsets, residuals, row_widths, state_values, weights,
)

_jit = numba.njit(cache=True, error_model="numpy", nogil=True)

INACTIVE, ACTIVE, SATURATED = 0, 1, 2

#: Re-classification allowance, relative to the problem's scales: an inactive row becomes active
#: only when violated by more than this, an active multiplier leaves only when below -this (so
#: round-off on a degenerate row cannot make the classes cycle).
HYSTERESIS = 1e-13

#: A round whose Newton step moves some input by more than this many times the input bound (the
#: norm bound, else the largest box bound) has diverged: the guessed classes are far from the
#: optimum's (a plan saturated at its bound meeting new neighbour rows), and the rounds left would
#: not reach it. The problem is then solved cold at once. Measured on the crowds' problems: the
#: largest step of any solve that converged was 20 times the bound (100 agents, 30 steps) and 9
#: (1000 agents, 20 steps); the failing solves of one 1000-agent iteration stop after 4.1 rounds
#: instead of 7.6, and the crowds' plans are the same bits.
DIVERGED_STEP = 100.0


@_jit
def _constraint_count(R: int, Tq: int, nb: int, Ts: int) -> int:
    """Inequalities in the active-set numbering: linear rows, input-norm rows, box upper, box
    lower, state-norm rows (the slacks s and sigma are not separate: a saturated row's slack)."""
    return R + Tq + 2 * nb + Ts


@_jit
def _zmax(i: int, R: int, Tq: int, nb: int, penalty: float, v_max: float) -> float:
    """The largest multiplier of inequality ``i`` (its price when its slack opens; inf: hard)."""
    if i < R:
        return penalty
    if i < R + Tq + 2 * nb:
        return np.inf
    return penalty / v_max


@_jit
def _value(i, u, A, width, N, bt, rho, wy, zc, R, Tq, nb, Du, box, u_max2, v_max, xs):
    """``(g0, d)``: inequality ``i``'s value at ``u`` without its multiplier's part, and the weight
    ``d`` of its own multiplier (``g = g0 + d z``: a collision row's copy ``y = (wy - z n) / rho``
    is eliminated; ``d = 0`` elsewhere). ``xs`` holds the bounded state entries at ``u``;
    ``width (R,)`` the rows' :func:`~.ipm_residuals.row_widths`."""
    if i < R:
        v = -bt[i]
        for j in range(width[i]):
            v += A[i, j] * u[j]
        nn = 0.0
        for d in range(N.shape[1]):
            v -= N[i, d] * wy[i, d] / rho[i]
            nn += N[i, d] * N[i, d]
        return v, nn / rho[i]
    i -= R
    if i < Tq:
        v = u_max2
        for d in range(Du):
            v -= u[i * Du + d] * u[i * Du + d]
        return 0.5 * v, 0.0
    i -= Tq
    if i < nb:
        return box[i % Du] - u[i], 0.0
    i -= nb
    if i < nb:
        return box[i % Du] + u[i], 0.0
    i -= nb
    v = v_max * v_max
    for a in range(xs.shape[1]):
        v -= xs[i, a] * xs[i, a]
    return 0.5 * v, 0.0


@_jit
def _gradient(i, u, A, G, sbi, D, R, Tq, nb, Du, xs, row) -> int:
    """Write inequality ``i``'s gradient in u into ``row (n,)``; returns its first nonzero index."""
    n = u.shape[0]
    if i < R:
        for j in range(n):
            row[j] = A[i, j]
        return 0
    fill(row, 0.0)
    i -= R
    if i < Tq:
        for d in range(Du):
            row[i * Du + d] = -u[i * Du + d]
        return i * Du
    i -= Tq
    if i < nb:
        row[i] = -1.0
        return i
    i -= nb
    if i < nb:
        row[i] = 1.0
        return i
    i -= nb
    for a in range(sbi.shape[0]):
        r = i * D + sbi[a]
        c = xs[i, a]
        for j in range(n):
            row[j] -= c * G[r, j]
    return 0


@_jit
def _input_bound(u_max2: float, box, Tq: int, nb: int) -> float:
    """The size of the inputs' bound: the norm bound, else the largest box bound, else inf."""
    if Tq:
        return np.sqrt(u_max2)
    return absmax(box) if nb else np.inf


@_jit
def _initial_classes(w, z, R, Tq, nb, Ts, off, cls, zc) -> None:
    """Classes and multipliers from a primal-dual point in the kernel's layout (the guess): a row
    is active where its multiplier exceeds its slack, saturated where also its slack variable
    (s or sigma) exceeds that slack's multiplier."""
    oq, ob, ov, osg = off[0], off[1], off[2], off[3]
    for k in range(R):
        zc[k] = z[k]
        cls[k] = INACTIVE
        if z[k] > w[k]:
            cls[k] = SATURATED if w[R + k] > z[R + k] else ACTIVE
    for t in range(Tq):
        i = R + t
        zc[i] = z[oq + t]
        cls[i] = ACTIVE if z[oq + t] > w[oq + t] else INACTIVE
    for j in range(2 * nb):
        i = R + Tq + j
        zc[i] = z[ob + j]
        cls[i] = ACTIVE if z[ob + j] > w[ob + j] else INACTIVE
    for t in range(Ts):
        i = R + Tq + 2 * nb + t
        zc[i] = z[ov + t]
        cls[i] = INACTIVE
        if z[ov + t] > w[ov + t]:
            cls[i] = SATURATED if w[osg + t] > z[osg + t] else ACTIVE


@_jit
def _write_point(gv, dv, N, rho, wy, zc, cls, R, Tq, nb, Ts, v_max, penalty, off, y, w, z) -> None:
    """The kernel-layout point ``(y, w, z)`` of ``(u, zc)`` with exact complementarity: an
    inactive row's slack is its value and its multiplier 0; an active row's slack is 0 (its value,
    0 up to round-off, shows in the primal residual rather than, times a large multiplier, in the
    complementarity); a saturated row's slack variable takes what the row lacks and its
    multiplier the whole price. ``gv, dv (mc,)``: every inequality's :func:`_value` at u (the
    re-classification's, at the same point)."""
    oq, ov, osg = off[0], off[2], off[3]
    for k in range(R):
        g = gv[k] + dv[k] * zc[k]
        for dd in range(N.shape[1]):
            y[k, dd] = (wy[k, dd] - zc[k] * N[k, dd]) / rho[k]
        z[k] = zc[k]
        z[R + k] = penalty - zc[k]
        if cls[k] == SATURATED:
            w[k], w[R + k] = 0.0, max(-g, 0.0)
        else:
            w[k], w[R + k] = (max(g, 0.0) if cls[k] == INACTIVE else 0.0), 0.0
    for j in range(Tq + 2 * nb):
        g = gv[R + j]
        w[oq + j] = max(g, 0.0) if cls[R + j] == INACTIVE else 0.0
        z[oq + j] = max(zc[R + j], 0.0)
    for t in range(Ts):
        i = R + Tq + 2 * nb + t
        g = gv[i]
        z[ov + t] = zc[i]
        z[osg + t] = penalty - v_max * zc[i]
        if cls[i] == SATURATED:  # sigma opens: g + 2 v sigma / 2 = 0
            w[ov + t], w[osg + t] = 0.0, max(-g / v_max, 0.0)
        else:
            w[ov + t], w[osg + t] = (max(g, 0.0) if cls[i] == INACTIVE else 0.0), 0.0


@_jit
def _solve_one(H, g0, A, width, N, bt, rho, wy, G, h, sbi, D, Du, box, u_max2, v_max, penalty, off, tol, max_rounds,
               u, y, w, z, cls, zc, S, E, V, Sch, first, act, r, x, rhs2, zn, gv, dv, xs, r_u, r_y, r_s, r_p):
    """One problem from the guess ``(u, w, z)`` (kernel layout; overwritten with the solution).

    Returns:
        ``(converged, rounds, kkt_error)``.
    """
    n = u.shape[0]
    R = N.shape[0]
    oq, ob, ov, osg, Tq, nb, Ts, m = off
    mc = _constraint_count(R, Tq, nb, Ts)
    scale_u = 1.0 + absmax(g0)
    scale_y = 1.0 + absmax2(wy)
    scale_p = 1.0 + max(absmax(bt), 0.0 if Tq == 0 else u_max2, absmax(box), 0.0 if Ts == 0 else v_max * v_max)
    eps_g = HYSTERESIS * scale_p
    eps_z = HYSTERESIS * (1.0 + penalty)
    max_step = DIVERGED_STEP * _input_bound(u_max2, box, Tq, nb)
    _initial_classes(w, z, R, Tq, nb, Ts, off, cls, zc)
    err = np.inf
    factored_h = False  # S holds the Cholesky factor of H itself (no norm row curved it)
    for rnd in range(max_rounds):
        if Ts:
            state_values(G, h, sbi, D, u, xs)
        # W = H + the norm rows' curvature at their current multipliers; a round where no norm row
        # adds curvature reuses the factor of H from an earlier round (the same matrix, same bits)
        curved = False
        for t in range(Tq):
            curved = curved or (cls[R + t] != INACTIVE and not zc[R + t] <= 0.0)  # NaN: curved
        for t in range(Ts):
            i = R + Tq + 2 * nb + t
            curved = curved or (cls[i] != INACTIVE and not zc[i] <= 0.0)
        if curved or not factored_h:
            for i in range(n):
                for j in range(i + 1):
                    S[i, j] = H[i, j]
            for t in range(Tq):
                zt = max(zc[R + t], 0.0) if cls[R + t] != INACTIVE else 0.0
                for d in range(Du):
                    S[t * Du + d, t * Du + d] += zt
            for t in range(Ts):
                i = R + Tq + 2 * nb + t
                if cls[i] != INACTIVE:
                    add_state_norm_curvature(S, G, sbi, D, t, max(zc[i], 0.0))
            if not cholesky(S, n):
                return False, rnd, err
            factored_h = not curved
        # r = H u + g0 - sum_saturated zmax grad g (the stationarity without the active multipliers)
        for i in range(n):
            v = g0[i]
            for j in range(n):
                v += H[i, j] * u[j]
            r[i] = v
        na = 0
        for i in range(mc):
            if cls[i] == SATURATED:
                _gradient(i, u, A, G, sbi, D, R, Tq, nb, Du, xs, x)
                zm = _zmax(i, R, Tq, nb, penalty, v_max)
                for j in range(n):
                    r[j] -= zm * x[j]
            elif cls[i] == ACTIVE:
                act[na] = i
                first[na] = _gradient(i, u, A, G, sbi, D, R, Tq, nb, Du, xs, E[na])
                na += 1
        for q in range(na):
            for j in range(n):
                V[q, j] = E[q, j]
            forward_solve(S, V[q], n, first[q])
        for j in range(n):
            x[j] = r[j]
        forward_solve(S, x, n, 0)  # x = L^-1 r
        for q1 in range(na):
            g0q, dq = _value(act[q1], u, A, width, N, bt, rho, wy, zc, R, Tq, nb, Du, box, u_max2, v_max, xs)
            v = -g0q
            for j in range(n):
                v += V[q1, j] * x[j]
            rhs2[q1] = v
            for q2 in range(q1 + 1):
                v = 0.0
                for j in range(n):
                    v += V[q1, j] * V[q2, j]
                Sch[q1, q2] = v
            Sch[q1, q1] += dq
        if not cholesky(Sch, na):
            return False, rnd, err
        forward_solve(Sch, rhs2, na, 0)
        backward_solve(Sch, rhs2, na)  # the active multipliers
        for j in range(n):
            x[j] = -x[j]
        for q in range(na):
            for j in range(n):
                x[j] += V[q, j] * rhs2[q]
        backward_solve(S, x, n)  # du = W^-1 (-r + E^T z_act)
        step = 0.0
        for j in range(n):
            u[j] += x[j]
            step = max(step, abs(x[j]))
        if not step < np.inf or step > max_step:  # NaN, or diverged
            return False, rnd + 1, err
        for i in range(mc):
            zn[i] = 0.0 if cls[i] == INACTIVE else _zmax(i, R, Tq, nb, penalty, v_max)
        for q in range(na):
            zn[act[q]] = rhs2[q]
        # re-classify at the new point
        if Ts:
            state_values(G, h, sbi, D, u, xs)
        changed = False
        for i in range(mc):
            g0i, di = _value(i, u, A, width, N, bt, rho, wy, zn, R, Tq, nb, Du, box, u_max2, v_max, xs)
            gv[i], dv[i] = g0i, di
            g = g0i + di * zn[i]
            zm = _zmax(i, R, Tq, nb, penalty, v_max)
            c = cls[i]
            if c == INACTIVE and g < -eps_g:
                cls[i] = ACTIVE
                zn[i] = 0.0
            elif c == ACTIVE and zn[i] < -eps_z:
                cls[i] = INACTIVE
                zn[i] = 0.0
            elif c == ACTIVE and zn[i] > zm + eps_z:
                cls[i] = SATURATED
                zn[i] = zm
            elif c == SATURATED and g > eps_g:
                cls[i] = ACTIVE
            changed = changed or cls[i] != c
            zc[i] = zn[i]
        if changed:
            continue
        # the classes hold: accept by the interior point's own test (an active norm row that the
        # Newton rounds have not yet met shows in the primal residual; then one more round)
        _write_point(gv, dv, N, rho, wy, zc, cls, R, Tq, nb, Ts, v_max, penalty, off, y, w, z)
        residuals(H, g0, A, width, N, bt, rho, wy, G, h, sbi, D, Du, box, u_max2, v_max, penalty, off,
                  u, y, w, z, xs, r_u, r_y, r_s, r_p)
        err = kkt_error(r_u, r_y, r_s, r_p, w, z, scale_u, scale_y, scale_p, penalty)
        signs = True
        for i in range(m):
            signs = signs and z[i] >= -eps_z
        if err <= tol and signs:
            return True, rnd + 1, err
    return False, max_rounds, err


@_jit
def solve_batch(G, h, c_x, l_x, rho_y, w_y, normals, bounds, g_u, H_cost, GtG, A_all, couple, alpha, beta, u_max, box, sbi,
                v_max, penalty, tol, max_rounds, u, y, w, z, unused, converged, iterations, kkt_error) -> None:
    """Solve B problems from the guesses ``(u, w, z)`` (kernel layout, e.g. the previous solve's
    points; ``y`` is output only), one after another.

    The arguments are those of :func:`~torch_gpmpc.control.solvers.ipm_kernel.solve_polish_batch`
    up to ``kkt_error`` (same positions, so :mod:`~.ipm_threads` splits both alike; ``GtG, A_all``:
    the problems' :func:`~torch_gpmpc.control.solvers.ipm_kernel.structure_batch`), with
    ``max_rounds`` in place of ``max_iter`` and ``unused`` in place of ``warm``. Rows with
    ``converged = False`` hold no solution (solve them cold); the others hold the optimum with
    ``kkt_error <= tol`` and exact complementarity (``w z = 0``). ``iterations`` counts the rounds
    (one linear solve each).
    """
    B, n = h.shape[0], G.shape[2]
    M, T, D = normals.shape[1], normals.shape[2], normals.shape[3]
    R, Du = M * T, n // T
    off = offsets(R, n, T, u_max < np.inf, box.shape[0] > 0, sbi.shape[0] > 0)
    Tq, nb, Ts, m = off[4], off[5], off[6], off[7]
    mc = _constraint_count(R, Tq, nb, Ts)
    u_max2 = u_max * u_max
    H, g0 = np.empty((n, n)), np.empty(n)
    bt, rho, N, wy = np.empty(R), np.empty(R), np.empty((R, D)), np.empty((R, D))
    width = np.empty(R, dtype=np.int64)
    S, E, V, Sch = np.empty((n, n)), np.empty((mc, n)), np.empty((mc, n)), np.empty((mc, mc))
    first, act, cls = np.zeros(mc, dtype=np.int64), np.zeros(mc, dtype=np.int64), np.zeros(mc, dtype=np.int64)
    zc, zn, rhs2, gv, dv = np.empty(mc), np.empty(mc), np.empty(mc), np.empty(mc), np.empty(mc)
    r, x = np.empty(n), np.empty(n)
    xs = np.empty((Ts, sbi.shape[0]))
    r_u, r_y, r_s, r_p = np.empty(n), np.empty((R, D)), np.empty(R + Ts), np.empty(m)
    for b in range(B):
        weights(GtG[b], G[b], h[b], c_x[b], l_x[b], rho_y[b], w_y[b], normals[b], bounds[b], g_u[b], H_cost[b], couple,
                alpha,
                beta, H, g0, bt, rho, N, wy)
        A = A_all[b]
        row_widths(A, width)
        converged[b], iterations[b], kkt_error[b] = _solve_one(
            H, g0, A, width, N, bt, rho, wy, G[b], h[b], sbi, D, Du, box, u_max2, v_max, penalty, off, tol, max_rounds,
            u[b], y[b], w[b], z[b], cls, zc, S, E, V, Sch, first, act, r, x, rhs2, zn, gv, dv, xs, r_u, r_y, r_s,
            r_p)
