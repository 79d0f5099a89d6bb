"""The interior-point kernel of :class:`~torch_gpmpc.control.solvers.interior_point.InteriorPointMPC`, compiled by numba.

One local problem (paper eq. 27 with the constraints of :mod:`torch_gpmpc.control.constraints`)
after condensing the dynamics, in the variables ``u = vec(U)`` (n = T Du), the copies ``y``
(R = M T rows of D), the row slacks ``s`` (R) and the state-norm slacks ``sigma`` (Ts)::

    minimize    1/2 u^T H u + g0^T u + sum_k (rho_k / 2 ||y_k||^2 - wy_k . y_k) + P (sum(s) + sum(sigma))
    subject to  g_c = A u - N.y + s - bt >= 0                      (R linear rows)
                s >= 0                                             (R)
                g_q = (u_max^2 - ||U_t||^2) / 2 >= 0               (Tq = T or 0: input norm)
                box_i - u_i >= 0,  box_i + u_i >= 0                (nb = n or 0: input box)
                g_v = (v^2 + 2 v sigma_t - ||P x_t||^2) / 2 >= 0   (Ts = T or 0: state norm, x = G u + h)
                sigma >= 0                                         (Ts)

with ``H = 2 c_x G^T G + 2 alpha I + 2 beta D^T D + H_cost`` (D: first differences of the U_t, the
input-rate weight; ``H_cost``: a user cost's Hessian beyond the default one), ``g0 = G^T (2 c_x h - l_x) + g_u``
(``g_u = -2 beta U_{-1}`` on U_0, plus a user cost's linear part), ``A_k = G_t^T n_k`` and
``bt_k = bound_k - n_k . h_t`` for row ``k = j T + t`` (built by
:func:`~torch_gpmpc.control.solvers.ipm_residuals.setup`). The first Rc rows are collision rows
(slot flag ``couple = 1``: ``N = n``); the rest are soft state rows (``N = 0``, ``y = 0``).

Inequalities ``g >= 0`` get slacks ``w`` and multipliers ``z`` (length m), ordered
``[linear rows | s | input norm | box upper | box lower | state norm | sigma]``. Method:
primal-dual Mehrotra predictor-corrector from an infeasible start, one step length, fraction
to the boundary 0.99, inputs projected onto the norm ball and the box after each step
(globalization).

Linear algebra per Newton step: per linear row, ``y_k`` and ``s_k`` are eliminated in closed
form with weight ``deff_k = 1 / (w_c/z_c + |N_k|^2/rho_k + s/z_s)``; a collision row's weight is
at most ``rho_k / |n_k|^2`` and it goes into ``S0 = H + blockdiag(z_q I) + diag(box terms) +
sum_t z_v G_t^T P^T P G_t + A^T diag(deff) A`` (n x n, positive definite). A state row's weight
grows like 1/mu as it becomes active, so a heavy one (``deff |A_k|^2 > AUGMENT_WEIGHT max H_ii``)
stays in augmented form with the quadratic rows: ``[[S0, E^T], [E, -W]]``, ``E`` rows ``-U_t``
(input norm), ``-G_t^T P^T P x_t`` (state norm) and ``A_k`` (heavy rows), solved through the
Schur complement ``W + E S0^-1 E^T`` (positive definite): two Cholesky factorizations per
iteration and no 1/mu-sized entry in either (the box rows are diagonal, which Cholesky takes
at any size).

Why numba: the closed loop solves batches of 3 problems of ~80 unknowns. Written as
batched NumPy/torch operations, one interior-point iteration costs about 0.85 ms at batch
3, almost all of it the dispatch overhead of ~180 small-array calls; compiled loops take
about 25 us per problem and iteration.
The Cholesky and triangular solves are written out because LAPACK's per-call overhead
dominates at n = 26. Everything is float64, serial and IEEE (no fastmath), so results
are reproducible; compiled code is cached on disk (``cache=True``).
"""

from __future__ import annotations

import sys

import numba
import numpy as np

from torch_gpmpc.control import acceptance
from torch_gpmpc.control.solvers import ipm_active
from torch_gpmpc.control.solvers.ipm_cache import ensure_fresh, newest_source_time
from torch_gpmpc.control.solvers.ipm_linalg import (
    absmax, absmax2, backward_solve, cholesky, copy_into, fill, forward_solve,
)
from torch_gpmpc.control.solvers.ipm_residuals import (
    add_state_norm_curvature, coupled_rows, initial_point, kkt_error, offsets, residuals, row_widths, setup,
    state_values, structure, weights,
)

#: Fraction of the step to the boundary of the positive orthant, and how it tends to 1 as the
#: duality measure mu falls: ``max(STEP_FRACTION, 1 - END_GAME mu)`` (from mu < 1e-4 on). A fixed
#: 0.99 cuts the last complementarity products by only 100x per step, so every solve spent its
#: last 3-5 Newton steps (and the polish) on that; letting the fraction tend to 1 gives the
#: method's fast local convergence back (the constraint-family problems: 16 % fewer Newton steps
#: in the main solves, and the polish usually needs none).
STEP_FRACTION, END_GAME = 0.99, 100.0

#: After each step every U_t is projected onto the ball of this multiple of u_max.
TRUST_RADIUS = 1.0

#: A state row whose Newton weight ``deff |A_k|^2`` exceeds this multiple of H's largest
#: diagonal entry (a nearly active row, weight ~1/mu) joins the augmented rows instead of S0.
AUGMENT_WEIGHT = 1e4

# error_model="numpy": float division by zero gives inf/nan (checked), never an exception.
_jit = numba.njit(cache=True, error_model="numpy", nogil=True)


# ------------------------------------------------------------------------ one problem
@_jit
def _factor(H, A, width, N, rho, G, sbi, D, Du, v_max, off, Rc, u, w, z, xs, deff, aug, S, E, first, V,
            Sch) -> int:
    """Factor the reduced Newton matrix at ``(u, w, z)`` (see the module docstring).

    ``width (R,)``: the rows' :func:`~.ipm_residuals.row_widths` (their trailing zeros are skipped).
    Writes ``deff (R,)``, ``aug (R,)`` (the augmented position of a state row whose weight
    ``deff |A_k|^2`` exceeds ``AUGMENT_WEIGHT`` times the scale of H, else -1), the Cholesky
    factor of S0 into ``S (n, n)``, the rows of the augmented constraints' gradients into
    ``E (Ta, n)`` (``first (Ta,)``: their first nonzero column; order: input norm rows, state
    norm rows, heavy state rows), ``V = L^-1 E^T`` stored by rows into ``V (Ta, n)`` and the
    Cholesky factor of the Schur complement into ``Sch (Ta, Ta)``.

    Returns:
        Ta, the number of augmented rows, or -1 if a factorization breaks down.
    """
    n = u.shape[0]
    R, D_ = N.shape
    oq, ob, ov, osg, Tq, nb, Ts, m = off
    Ta = Tq + Ts
    hscale = 1.0
    for i in range(n):
        hscale = max(hscale, H[i, i])
    for i in range(n):
        for j in range(i + 1):
            S[i, j] = H[i, j]
        if Tq:
            S[i, i] += z[oq + i // Du]
        if nb:
            S[i, i] += z[ob + i] / w[ob + i] + z[ob + nb + i] / w[ob + nb + i]
    for t in range(Ts):  # Hessian of the state-norm rows: z_v G_t^T P^T P G_t
        add_state_norm_curvature(S, G, sbi, D, t, z[ov + t])
    for k in range(R):
        nn = 0.0
        for d in range(D_):
            nn += N[k, d] * N[k, d]
        dk = 1.0 / (w[k] / z[k] + nn / rho[k] + w[R + k] / z[R + k])
        deff[k] = dk
        aug[k] = -1
        if k >= Rc:  # a state row: its deff is not bounded by rho; augment it when it is heavy
            a2 = 0.0
            for i in range(width[k]):
                a2 += A[k, i] * A[k, i]
            if dk * a2 > AUGMENT_WEIGHT * hscale:
                aug[k] = Ta
                Ta += 1
                continue
        for i in range(width[k]):
            a = dk * A[k, i]
            if a != 0.0:
                for j in range(i + 1):
                    S[i, j] += a * A[k, j]
    if not cholesky(S, n):
        return -1
    for t in range(Tq):
        fill(E[t], 0.0)
        for d in range(Du):
            E[t, t * Du + d] = -u[t * Du + d]
        first[t] = t * Du
    for t in range(Ts):
        row = E[Tq + t]
        fill(row, 0.0)
        for a in range(sbi.shape[0]):
            r = t * D + sbi[a]
            c = xs[t, a]
            for i in range(n):
                row[i] -= c * G[r, i]
        first[Tq + t] = 0
    for k in range(Rc, R):
        if aug[k] >= 0:
            copy_into(A[k], E[aug[k]])
            first[aug[k]] = 0
    for q in range(Ta):
        copy_into(E[q], V[q])
        forward_solve(S, V[q], n, first[q])
    for q1 in range(Ta):
        for q2 in range(q1 + 1):
            v = 0.0
            for i in range(n):
                v += V[q1, i] * V[q2, i]
            Sch[q1, q2] = v
    for t in range(Tq):
        Sch[t, t] += w[oq + t] / z[oq + t]
    for t in range(Ts):
        Sch[Tq + t, Tq + t] += w[ov + t] / z[ov + t] + v_max * v_max * w[osg + t] / z[osg + t]
    for k in range(Rc, R):
        if aug[k] >= 0:
            Sch[aug[k], aug[k]] += 1.0 / deff[k]
    return Ta if cholesky(Sch, Ta) else -1


@_jit
def _solve(S, V, Sch, Ta, rhs1, rhs2, x1, x2) -> None:
    """Solve ``[[S0, E^T], [E, -W]] [x1; x2] = [rhs1; rhs2]`` with the factors of :func:`_factor`.

    Shapes: rhs1, x1 (n,); rhs2, x2 (at least Ta,).
    """
    n = x1.shape[0]
    copy_into(rhs1, x1)
    forward_solve(S, x1, n, 0)  # a = L^-1 rhs1
    for q in range(Ta):
        v = -rhs2[q]
        for i in range(n):
            v += V[q, i] * x1[i]
        x2[q] = v
    forward_solve(Sch, x2, Ta, 0)
    backward_solve(Sch, x2, Ta)  # x2 = Sch^-1 (E S0^-1 rhs1 - rhs2)
    for q in range(Ta):
        for i in range(n):
            x1[i] -= V[q, i] * x2[q]
    backward_solve(S, x1, n)  # x1 = S0^-1 (rhs1 - E^T x2)


@_jit
def _direction(A, width, N, rho, Du, v_max, off, w, z, deff, aug, Ta, S, E, V, Sch, r_u, r_y, r_s, r_p, rc,
               du, dy, dw, dz, rhs1, rhs2, gam, dq) -> None:
    """Newton direction for the complementarity residual ``rc`` (``z dw + w dz = -rc``), shape (m,).

    Writes ``du (n,), dy (R, D), dw (m,), dz (m,)``; ``rhs1 (n,), rhs2 (Ta,), gam (R,),
    dq (Ta,)`` are work space.
    """
    n = du.shape[0]
    R, D = N.shape
    oq, ob, ov, osg, Tq, nb, Ts, m = off
    for i in range(n):
        rhs1[i] = -r_u[i]
    for k in range(R):
        v = 0.0
        for d in range(D):
            v += N[k, d] * r_y[k, d]
        s_zs = w[R + k] / z[R + k]
        rt_s = -r_s[k] - rc[R + k] / w[R + k]
        gam[k] = v / rho[k] + rt_s * s_zs + r_p[k] + rc[k] / z[k]  # gam + rho_c
        if aug[k] >= 0:  # augmented row: A_k du - xi_k / deff_k = -gam_k
            rhs2[aug[k]] = -gam[k]
            continue
        c = deff[k] * gam[k]
        for i in range(width[k]):
            rhs1[i] -= A[k, i] * c
    for i in range(nb):  # box rows: dz_+ - dz_- = p - q + (z_+/w_+ + z_-/w_-) du_i
        p = (-rc[ob + i] - z[ob + i] * r_p[ob + i]) / w[ob + i]
        q = (-rc[ob + nb + i] - z[ob + nb + i] * r_p[ob + nb + i]) / w[ob + nb + i]
        rhs1[i] -= p - q
    for t in range(Tq):
        rhs2[t] = -r_p[oq + t] - rc[oq + t] / z[oq + t]
    for t in range(Ts):
        sg, zsg = w[osg + t], z[osg + t]
        rhs2[Tq + t] = -r_p[ov + t] + v_max * (rc[osg + t] + sg * r_s[R + t]) / zsg - rc[ov + t] / z[ov + t]
    _solve(S, V, Sch, Ta, rhs1, rhs2, du, dq)
    for k in range(R):
        if aug[k] >= 0:
            xi = dq[aug[k]]
        else:
            v = gam[k]
            for i in range(width[k]):
                v += A[k, i] * du[i]
            xi = deff[k] * v
        for d in range(D):
            dy[k, d] = (N[k, d] * xi - r_y[k, d]) / rho[k]
        s_zs = w[R + k] / z[R + k]
        rt_s = -r_s[k] - rc[R + k] / w[R + k]
        dw[k] = (w[k] * xi - rc[k]) / z[k]
        dw[R + k] = s_zs * (rt_s - xi)
        dz[k] = -xi
        dz[R + k] = r_s[k] + xi
    for t in range(Tq):
        v = r_p[oq + t]
        for i in range(n):
            v += E[t, i] * du[i]
        dw[oq + t] = v
        dz[oq + t] = -dq[t]
    for i in range(nb):
        j = ob + nb + i
        dw[ob + i] = r_p[ob + i] - du[i]
        dz[ob + i] = (-rc[ob + i] - z[ob + i] * dw[ob + i]) / w[ob + i]
        dw[j] = r_p[j] + du[i]
        dz[j] = (-rc[j] - z[j] * dw[j]) / w[j]
    for t in range(Ts):
        dzv = -dq[Tq + t]
        sg, zsg = w[osg + t], z[osg + t]
        dz[ov + t] = dzv
        dw[ov + t] = (-rc[ov + t] - w[ov + t] * dzv) / z[ov + t]
        dw[osg + t] = (-rc[osg + t] - sg * r_s[R + t] + sg * v_max * dzv) / zsg
        dz[osg + t] = r_s[R + t] - v_max * dzv


@_jit
def _max_step(w, z, dw, dz) -> float:
    """Largest step in [0, 1] keeping ``w + a dw >= 0`` and ``z + a dz >= 0``."""
    ratio = 0.0
    for i in range(w.shape[0]):
        ratio = min(ratio, dw[i] / w[i], dz[i] / z[i])
    return 1.0 / max(-ratio, 1.0)


@_jit
def _project_inputs(u, Du, u_max2, box) -> None:
    """Globalization: each ``U_t`` onto the ball of radius ``TRUST_RADIUS u_max`` (if a norm
    bound, ``u_max2 < inf``), then onto the box (if one)."""
    T = u.shape[0] // Du
    radius2 = TRUST_RADIUS * TRUST_RADIUS * u_max2
    for t in range(T):
        norm2 = 0.0
        for d in range(Du):
            norm2 += u[t * Du + d] * u[t * Du + d]
        if norm2 > radius2:
            shrink = np.sqrt(radius2 / norm2)
            for d in range(Du):
                u[t * Du + d] *= shrink
    if box.shape[0]:
        for i in range(u.shape[0]):
            b = box[i % Du]
            u[i] = min(max(u[i], -b), b)


@_jit
def _iterate(H, g0, A, width, N, bt, rho, wy, G, h, sbi, D, Du, box, u_max2, v_max, penalty, off, Rc, tol,
             max_iter, u, y, w, z):
    """Run the method on one problem from ``(u, y, w, z)`` (updated in place).

    Returns:
        ``(converged, iterations, kkt_error)``. A problem whose Newton system breaks down
        or whose step is not finite stops there, unconverged.
    """
    n = u.shape[0]
    R, D_ = N.shape
    oq, ob, ov, osg, Tq, nb, Ts, m = off
    Ta = Tq + Ts + R - Rc
    p = sbi.shape[0]
    scale_u = 1.0 + absmax(g0)
    scale_y = 1.0 + absmax2(wy)
    scale_p = 1.0 + max(absmax(bt), 0.0 if Tq == 0 else u_max2, absmax(box), 0.0 if Ts == 0 else v_max * v_max)
    r_u, rhs1, du = np.empty(n), np.empty(n), np.empty(n)
    r_y, dy = np.empty((R, D_)), np.empty((R, D_))
    r_s = np.empty(R + Ts)
    deff, gam, aug = np.empty(R), np.empty(R), np.empty(R, dtype=np.int64)
    rhs2, dq = np.empty(Ta), np.empty(Ta)
    r_p, wz, rc, dw, dz = np.empty(m), np.empty(m), np.empty(m), np.empty(m), np.empty(m)
    S, E, V, Sch = np.empty((n, n)), np.empty((Ta, n)), np.empty((Ta, n)), np.empty((Ta, Ta))
    first = np.zeros(Ta, dtype=np.int64)
    xs = np.empty((Ts, p))
    err = np.inf
    for it in range(max_iter + 1):
        residuals(H, g0, A, width, N, bt, rho, wy, G, h, sbi, D, Du, box, u_max2, v_max, penalty, off,
                   u, y, w, z, xs, r_u, r_y, r_s, r_p)
        err = kkt_error(r_u, r_y, r_s, r_p, w, z, scale_u, scale_y, scale_p, penalty)
        if err <= tol:
            return True, it, err
        if it == max_iter:
            return False, it, err
        Ta_now = _factor(H, A, width, N, rho, G, sbi, D, Du, v_max, off, Rc, u, w, z, xs, deff, aug, S, E, first, V,
                         Sch)
        if Ta_now < 0:
            return False, it, err
        mu = 0.0
        for i in range(m):
            wz[i] = w[i] * z[i]
            mu += wz[i]
        mu /= m
        # predictor (affine scaling)
        _direction(A, width, N, rho, Du, v_max, off, w, z, deff, aug, Ta_now, S, E, V, Sch, r_u, r_y, r_s, r_p, wz,
                   du, dy, dw, dz, rhs1, rhs2, gam, dq)
        a_aff = _max_step(w, z, dw, dz)
        mu_aff = 0.0
        for i in range(m):
            mu_aff += (w[i] + a_aff * dw[i]) * (z[i] + a_aff * dz[i])
        sigma = min(mu_aff / m / mu, 1.0) ** 3
        # corrector
        for i in range(m):
            rc[i] = wz[i] + dw[i] * dz[i] - sigma * mu
        _direction(A, width, N, rho, Du, v_max, off, w, z, deff, aug, Ta_now, S, E, V, Sch, r_u, r_y, r_s, r_p, rc,
                   du, dy, dw, dz, rhs1, rhs2, gam, dq)
        step = max(STEP_FRACTION, 1.0 - END_GAME * mu) * _max_step(w, z, dw, dz)
        total = step + absmax(du) + absmax2(dy) + absmax(dw) + absmax(dz)
        if not total < np.inf:  # inf or NaN
            return False, it, err
        for i in range(n):
            u[i] += step * du[i]
        _project_inputs(u, Du, u_max2, box)
        for k in range(R):
            for d in range(D_):
                y[k, d] += step * dy[k, d]
        for i in range(m):
            w[i] += step * dw[i]
            z[i] += step * dz[i]
    return False, max_iter, err


# ------------------------------------------------------------------------ batched entry points
@_jit
def structure_batch(G, normals, GtG, A) -> None:
    """:func:`~.ipm_residuals.structure` of B problems: G (B, nx, n), normals (B, M, T, D) ->
    ``GtG (B, n, n)``, ``A (B, R, n)`` (written). A caller that poses the same dynamics and rows
    again (ADMM within a control step) keeps them and passes them to the solves."""
    for b in range(G.shape[0]):
        structure(G[b], normals[b], GtG[b], A[b])


@_jit
def solve_polish_batch(G, h, c_x, l_x, rho_y, w_y, normals, bounds, g_u, H_cost, GtG, A, couple, alpha, beta, u_max, box,
                       sbi, v_max, penalty, tol, max_iter, u, y, w, z, warm, converged, iterations, kkt_error,
                       polish_tol, polish_iter, pu, py, pw, pz, p_conv, p_iter, p_err) -> None:
    """Solve B problems one after another, then continue each from its point to ``polish_tol`` (the
    polish: at most ``polish_iter`` more iterations, on a copy; a problem already there is copied
    with 0 iterations), building each problem once.

    Args:
        G (B, nx, n), h (B, nx), c_x (B,), l_x (B, nx), rho_y (B, M), w_y (B, M, T, D),
        normals (B, M, T, D), bounds (B, M, T), g_u (B, n), H_cost (B, n, n): the canonical data
            (float64, C-contiguous);
        GtG (B, n, n), A (B, R, n): their :func:`structure_batch`;
        couple (M,): 1 for a neighbour slot (the row has a copy), 0 for a state row; the
            neighbour slots come first.
        alpha, beta: floats (effort and input-rate weights). u_max: input norm bound (``inf``:
            none). box (Du,) or (0,): input box.
        sbi (p,) int64 or (0,): state indices of the soft norm bound ``v_max``.
        penalty, tol: floats; max_iter: int.
        u (B, n), y (B, R, D), w (B, m), z (B, m): the primal-dual iterate, written in
            place; read as the starting point when ``warm`` (needs ``w, z > 0``).
        warm: start from the given iterate instead of the default initial point.
        converged (B,) bool, iterations (B,) int64, kkt_error (B,) float: written.
        polish_tol: float; polish_iter: int; pu, py, pw, pz: the polished iterate (shapes of
            u, y, w, z); p_conv, p_iter, p_err: its outputs (as converged, iterations, kkt_error).

    Outputs are written into arrays the caller owns and nothing is returned: returning
    new arrays would make the compiled code call back into Python, where a pending
    KeyboardInterrupt surfaces as a SystemError.
    """
    B, n = h.shape[0], G.shape[2]
    M, T, D = normals.shape[1], normals.shape[2], normals.shape[3]
    R, Du = M * T, n // T
    off = offsets(R, n, T, u_max < np.inf, box.shape[0] > 0, sbi.shape[0] > 0)
    Rc = coupled_rows(couple, T)
    u_max2 = u_max * u_max
    H, g0 = np.empty((n, n)), np.empty(n)
    bt, rho, N, wy = np.empty(R), np.empty(R), np.empty((R, D)), np.empty((R, D))
    width = np.empty(R, dtype=np.int64)
    xs = np.empty((off[6], sbi.shape[0]))
    for b in range(B):
        weights(GtG[b], G[b], h[b], c_x[b], l_x[b], rho_y[b], w_y[b], normals[b], bounds[b], g_u[b], H_cost[b], couple,
                alpha,
                beta, H, g0, bt, rho, N, wy)
        Ab = A[b]
        row_widths(Ab, width)
        if not warm:
            initial_point(N, bt, rho, wy, G[b], h[b], sbi, D, box, u_max2, v_max, penalty, off,
                           u[b], y[b], w[b], z[b], xs)
        converged[b], iterations[b], kkt_error[b] = _iterate(H, g0, Ab, width, N, bt, rho, wy, G[b], h[b], sbi, D, Du,
                                                             box, u_max2, v_max, penalty, off, Rc, tol, max_iter,
                                                             u[b], y[b], w[b], z[b])
        pu[b, :], py[b, :, :], pw[b, :], pz[b, :] = u[b], y[b], w[b], z[b]
        if kkt_error[b] <= polish_tol:
            p_conv[b], p_iter[b], p_err[b] = True, 0, kkt_error[b]
        else:
            p_conv[b], p_iter[b], p_err[b] = _iterate(H, g0, Ab, width, N, bt, rho, wy, G[b], h[b], sbi, D, Du, box,
                                                      u_max2, v_max, penalty, off, Rc, polish_tol, polish_iter,
                                                      pu[b], py[b], pw[b], pz[b])


@_jit
def adjoint_batch(G, h, c_x, l_x, rho_y, w_y, normals, bounds, g_u_data, H_cost, couple, alpha, beta, u_max, box, sbi,
                  v_max, u, w, z, g_u, g_y, g_s, a_u, a_y, xi, xi_v, failed) -> None:
    """Solve the reduced KKT system at each primal-dual point for the right-hand side
    ``(g_u, g_y, g_s)`` (the implicit-function adjoint; the system is symmetric).

    Shapes: canonical data and constraints as in :func:`solve_polish_batch`; ``u, g_u, a_u`` (B, n);
    ``g_y, a_y`` (B, R, D); ``w, z`` (B, m); ``g_s, xi`` (B, R); ``xi_v`` (B, Ts). Writes
    ``a_u, a_y``, ``xi``, the scaled multiplier ``(z_c / w_c) (grad g_c . a)`` of the linear
    rows, ``xi_v``, the adjoint multiplier of the state-norm rows, and ``failed (B,)`` bool:
    problems whose matrix cannot be factored (they get zeros).
    """
    B, n = h.shape[0], G.shape[2]
    M, T, D = normals.shape[1], normals.shape[2], normals.shape[3]
    R, Du = M * T, n // T
    off = offsets(R, n, T, u_max < np.inf, box.shape[0] > 0, sbi.shape[0] > 0)
    Rc = coupled_rows(couple, T)
    Tq, Ts = off[4], off[6]
    Ta = Tq + Ts + R - Rc
    H, g0, A = np.empty((n, n)), np.empty(n), np.empty((R, n))
    bt, rho, N, wy = np.empty(R), np.empty(R), np.empty((R, D)), np.empty((R, D))
    S, E, V, Sch = np.empty((n, n)), np.empty((Ta, n)), np.empty((Ta, n)), np.empty((Ta, Ta))
    first = np.zeros(Ta, dtype=np.int64)
    xs = np.empty((Ts, sbi.shape[0]))
    deff, rhs1, rhs2, dq = np.empty(R), np.empty(n), np.empty(Ta), np.empty(Ta)
    aug, width = np.empty(R, dtype=np.int64), np.empty(R, dtype=np.int64)
    for b in range(B):
        failed[b] = False
        setup(G[b], h[b], c_x[b], l_x[b], rho_y[b], w_y[b], normals[b], bounds[b], g_u_data[b], H_cost[b], couple,
              alpha, beta,
               H, g0, A, bt, rho, N, wy)
        row_widths(A, width)
        fill(a_u[b], 0.0)
        fill(rhs2, 0.0)
        fill(xi[b], 0.0)
        fill(xi_v[b], 0.0)
        for k in range(R):
            fill(a_y[b, k], 0.0)
        state_values(G[b], h[b], sbi, D, u[b], xs)
        Ta_now = _factor(H, A, width, N, rho, G[b], sbi, D, Du, v_max, off, Rc, u[b], w[b], z[b], xs, deff, aug, S, E,
                         first, V, Sch)
        if Ta_now < 0:
            failed[b] = True
            continue
        copy_into(g_u[b], rhs1)
        for k in range(R):
            v = 0.0
            for d in range(D):
                v -= N[k, d] * g_y[b, k, d]
            v = v / rho[k] + g_s[b, k] * w[b, R + k] / z[b, R + k]  # gam
            xi[b, k] = v
            if aug[k] >= 0:
                rhs2[aug[k]] = -v
                continue
            for i in range(width[k]):
                rhs1[i] -= A[k, i] * deff[k] * v
        _solve(S, V, Sch, Ta_now, rhs1, rhs2, a_u[b], dq)
        for t in range(Ts):
            xi_v[b, t] = dq[Tq + t]
        for k in range(R):
            if aug[k] >= 0:
                xi[b, k] = dq[aug[k]]
            else:
                v = xi[b, k]
                for i in range(width[k]):
                    v += A[k, i] * a_u[b, i]
                xi[b, k] = deff[k] * v
            for d in range(D):
                a_y[b, k, d] = (g_y[b, k, d] + N[k, d] * xi[b, k]) / rho[k]


def warm_up() -> None:
    """Compile (or load from the on-disk cache) the entry points (the structure, the solve with its
    polish, the warm active-set solve of :mod:`~.ipm_active` and the adjoint) on a tiny problem,
    and the acceptance check (:mod:`~torch_gpmpc.control.acceptance`).

    Call before starting several processes that use the kernel, so they load the cache
    instead of each compiling it (about 10 s of one core, once per installation, and again after
    a kernel source changes: :func:`~.ipm_cache.ensure_fresh`).
    """
    ensure_fresh()
    B, M, T, D = 1, 1, 1, 1
    R, n, m = M * T, T * D, 2 * M * T + 4 * T
    canonical = (np.eye(n)[None], np.zeros((B, n)), np.ones(B), np.zeros((B, n)), np.ones((B, M)),
                 np.zeros((B, M, T, D)), np.ones((B, M, T, D)), -np.ones((B, M, T)), np.zeros((B, n)),
                 np.zeros((B, n, n)), np.ones(M))
    limits = (1.0, np.ones(D), np.zeros(1, dtype=np.int64), 1.0)
    u, y, w, z = np.empty((B, n)), np.empty((B, R, D)), np.empty((B, m)), np.empty((B, m))
    flags, counts, errors = np.empty(B, dtype=np.bool_), np.empty(B, dtype=np.int64), np.empty(B)
    built = (np.empty((B, n, n)), np.empty((B, R, n)))
    structure_batch(canonical[0], canonical[6], *built)
    solve_polish_batch(*canonical[:10], *built, canonical[10], 1e-3, 0.0, *limits, 1e4, 1e-8, 30, u, y, w, z, False,
                       flags, counts, errors, 1e-10, 6, u.copy(), y.copy(), w.copy(), z.copy(), flags.copy(),
                       counts.copy(), errors.copy())
    ipm_active.solve_batch(*canonical[:10], *built, canonical[10], 1e-3, 0.0, *limits, 1e4, 1e-8, 3, u, y, w, z, False,
                           flags, counts, errors)
    adjoint_batch(*canonical, 1e-3, 0.0, *limits, u, w, z, np.ones((B, n)), np.ones((B, R, D)), np.ones((B, R)),
                  np.empty((B, n)), np.empty((B, R, D)), np.empty((B, R)), np.empty((B, T)), flags)
    acceptance.warm_up()  # the check of every solve


def is_cached() -> bool:
    """Whether numba's on-disk cache next to this module holds every compiled function, newer
    than every kernel source (:mod:`~.ipm_cache`; if not, the first solve compiles them: about
    20-30 s, once)."""
    from pathlib import Path

    source = Path(__file__)
    # numba names an index file <module>.<function>-<first line>.<python>.nbi
    wanted = {f"{Path(module.__file__).stem}.{name}-{obj.py_func.__code__.co_firstlineno}"
              for module in (sys.modules[__name__], ipm_active) for name, obj in vars(module).items()
              if hasattr(obj, "py_func") and obj.py_func.__module__ == module.__name__}
    index = {p.name.rsplit(".", 2)[0]: p for p in (source.parent / "__pycache__").glob("ipm_*.nbi")}
    newest = newest_source_time(source.parent)
    return wanted <= set(index) and all(index[key].stat().st_mtime >= newest for key in wanted)
