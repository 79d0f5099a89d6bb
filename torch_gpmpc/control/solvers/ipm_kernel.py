"""The interior-point kernel of :class:`~torch_gpmpc.control.solvers.interior_point.InteriorPointMPC`, compiled by numba.

One local problem (paper eq. 27) after condensing the dynamics, in the variables
``u = vec(U)`` (n = T Du), the neighbour copies ``y`` (R = M T rows of D; R counts collision rows) and the
collision slacks ``s`` (R)::

    minimize    1/2 u^T H u + g0^T u + sum_k (rho_k / 2 ||y_k||^2 - wy_k . y_k) + P sum(s)
    subject to  g_c = A u - N.y + s - bt >= 0        (R collision rows)
                s >= 0                               (R)
                g_q = (u_max^2 - ||U_t||^2) / 2 >= 0 (T input bounds)

with ``H = 2 c_x G^T G + 2 alpha I``, ``g0 = G^T (2 c_x h - l_x)``, ``A_k = G_t^T n_k`` and
``bt_k = bound_k - n_k . h_t`` for row ``k = j T + t`` (built by :func:`_setup`).

Inequalities ``g >= 0`` get slacks ``w`` and multipliers ``z`` (both of length
``m = 2 R + T``), ordered ``[collision rows | s | input bounds]``. Method: primal-dual
Mehrotra predictor-corrector from an infeasible start, one step length, fraction to the
boundary 0.99, inputs projected onto ``||U_t|| <= u_max`` after each step (globalization).

Linear algebra per Newton step: per collision row, ``y_k`` and ``s_k`` are eliminated in
closed form, leaving ``S0 = H + blockdiag(z_q I) + A^T diag(deff) A`` (n x n, positive
definite, bounded entries) with ``deff_k = 1 / (w_c/z_c + |n_k|^2/rho_k + s/z_s)``. The
input bounds stay in augmented form ``[[S0, E^T], [E, -diag(w_q/z_q)]]`` (``E`` row t
is ``-U_t`` in block t), solved through the Schur complement
``diag(w_q/z_q) + E S0^-1 E^T`` (T x T, positive definite): two Cholesky factorizations,
no 1/mu-sized entry (eliminating ``dz_q`` instead would add ``(z_q/w_q) U_t U_t^T`` to S0).

Why numba: the closed loop solves batches of 3 problems of ~80 unknowns. Written as
batched NumPy/torch operations, one interior-point iteration costs about 0.85 ms at batch
3, almost all of it the dispatch overhead of ~180 small-array calls; compiled loops take
about 25 us per problem and iteration.
The Cholesky and triangular solves are written out because LAPACK's per-call overhead
dominates at n = 26. Everything is float64, serial and IEEE (no fastmath), so results
are reproducible; compiled code is cached on disk (``cache=True``).
"""

from __future__ import annotations

import numba
import numpy as np

#: Fraction of the step to the boundary of the positive orthant.
STEP_FRACTION = 0.99

#: After each step every U_t is projected onto the ball of this multiple of u_max.
TRUST_RADIUS = 1.0

# error_model="numpy": float division by zero gives inf/nan (checked), never an exception.
_jit = numba.njit(cache=True, error_model="numpy", nogil=True)


# ------------------------------------------------------------------------ small dense algebra
# (explicit loops, not array expressions: numba compiles them several times faster)
@_jit
def _absmax(x: np.ndarray) -> float:
    """``max |x|`` of a 1-D array (0 if empty, NaN if any entry is NaN)."""
    v = 0.0
    for i in range(x.shape[0]):
        a = abs(x[i])
        if a > v:
            v = a
        elif a != a:
            return np.nan
    return v


@_jit
def _absmax2(x: np.ndarray) -> float:
    """``max |x|`` of a 2-D array (0 if empty, NaN if any entry is NaN)."""
    v = 0.0
    for i in range(x.shape[0]):
        a = _absmax(x[i])
        if a != a:
            return a
        v = max(v, a)
    return v


@_jit
def _fill(x: np.ndarray, value: float) -> None:
    """``x[:] = value`` for a 1-D array."""
    for i in range(x.shape[0]):
        x[i] = value


@_jit
def _copy(src: np.ndarray, dst: np.ndarray) -> None:
    """``dst[:] = src`` for 1-D arrays."""
    for i in range(src.shape[0]):
        dst[i] = src[i]


@_jit
def _cholesky(S: np.ndarray, size: int) -> bool:
    """In place: the lower triangle of ``S[:size, :size]`` becomes L with S = L L^T.

    Only the lower triangle of S is read. Returns False if S is not (numerically)
    positive definite (a pivot <= 0 or NaN).
    """
    for j in range(size):
        d = S[j, j]
        for k in range(j):
            d -= S[j, k] * S[j, k]
        if not d > 0.0:
            return False
        d = np.sqrt(d)
        S[j, j] = d
        inv = 1.0 / d
        for i in range(j + 1, size):
            v = S[i, j]
            for k in range(j):
                v -= S[i, k] * S[j, k]
            S[i, j] = v * inv
    return True


@_jit
def _forward(L: np.ndarray, x: np.ndarray, size: int, first: int) -> None:
    """In place ``x <- L^-1 x`` for lower-triangular L, where ``x[:first] == 0``."""
    for i in range(first, size):
        v = x[i]
        for k in range(first, i):
            v -= L[i, k] * x[k]
        x[i] = v / L[i, i]


@_jit
def _backward(L: np.ndarray, x: np.ndarray, size: int) -> None:
    """In place ``x <- L^-T x`` for lower-triangular L."""
    for i in range(size - 1, -1, -1):
        v = x[i]
        for k in range(i + 1, size):
            v -= L[k, i] * x[k]
        x[i] = v / L[i, i]


# ------------------------------------------------------------------------ one problem
@_jit
def _setup(G, h, c_x, l_x, rho_y, w_y, normals, bounds, alpha, H, g0, A, bt, rho, N, wy) -> None:
    """Fill the problem arrays of one problem from its canonical data (see module docstring).

    Shapes: G (nx, n), h (nx,), l_x (nx,), rho_y (M,), w_y (M, T, D), normals (M, T, D),
    bounds (M, T) with nx = T D states and n = T Du inputs; outputs H (n, n), g0 (n,), A (R, n),
    bt (R,), rho (R,), N (R, D), wy (R, D).
    """
    nx, n = G.shape
    M, T, D = normals.shape
    c2 = 2.0 * c_x
    for i in range(n):
        for j in range(i + 1):
            v = 0.0
            for r in range(nx):
                v += G[r, i] * G[r, j]
            H[i, j] = c2 * v
            H[j, i] = c2 * v
        H[i, i] += 2.0 * alpha
    for i in range(n):
        v = 0.0
        for r in range(nx):
            v += G[r, i] * (c2 * h[r] - l_x[r])
        g0[i] = v
    for j in range(M):
        for t in range(T):
            k = j * T + t
            rho[k] = rho_y[j]
            b = bounds[j, t]
            for d in range(D):
                N[k, d] = normals[j, t, d]
                wy[k, d] = w_y[j, t, d]
                b -= normals[j, t, d] * h[t * D + d]
            bt[k] = b
            for i in range(n):
                v = 0.0
                for d in range(D):
                    v += normals[j, t, d] * G[t * D + d, i]
                A[k, i] = v


@_jit
def _initial_point(N, bt, rho, wy, u_max2, penalty, u, y, w, z) -> None:
    """Infeasible start: ``u = 0``, unconstrained copies, ``z_c + z_s = P`` (dual feasible
    in s) and ``s z_s = 1``, so every complementarity product starts near 1."""
    R, D = N.shape
    T = w.shape[0] - 2 * R
    zc0 = min(1.0, 0.5 * penalty)
    zs0 = penalty - zc0
    _fill(u, 0.0)
    for k in range(R):
        s = 1.0 / zs0
        gc = s - bt[k]
        for d in range(D):
            y[k, d] = wy[k, d] / rho[k]
            gc -= N[k, d] * y[k, d]
        w[k] = max(gc, 1.0)
        w[R + k] = s
        z[k] = zc0
        z[R + k] = zs0
    for t in range(T):
        w[2 * R + t] = 0.5 * u_max2
        z[2 * R + t] = 1.0


@_jit
def _residuals(H, g0, A, N, bt, rho, wy, u_max2, penalty, Du, u, y, w, z, r_u, r_y, r_s, r_pc, r_pq) -> None:
    """Dual residuals ``r_u (n,), r_y (R, D), r_s (R,)`` and primal residuals
    ``r_pc (R,), r_pq (T,)`` at ``(u, y, w, z)``, written in place (``Du``: input dimension)."""
    n = u.shape[0]
    R, D = N.shape
    T = r_pq.shape[0]
    for i in range(n):
        v = g0[i] + z[2 * R + i // Du] * u[i]
        for j in range(n):
            v += H[i, j] * u[j]
        r_u[i] = v
    for k in range(R):
        zc = z[k]
        for i in range(n):
            r_u[i] -= A[k, i] * zc
        v = w[R + k] - bt[k] - w[k]
        for i in range(n):
            v += A[k, i] * u[i]
        for d in range(D):
            r_y[k, d] = rho[k] * y[k, d] - wy[k, d] + zc * N[k, d]
            v -= N[k, d] * y[k, d]
        r_pc[k] = v
        r_s[k] = penalty - zc - z[R + k]
    for t in range(T):
        v = u_max2
        for d in range(Du):
            v -= u[t * Du + d] * u[t * Du + d]
        r_pq[t] = 0.5 * v - w[2 * R + t]


@_jit
def _kkt_error(r_u, r_y, r_s, r_pc, r_pq, w, z, scale_u, scale_y, scale_p, penalty) -> float:
    """Largest of the relative dual residuals, the relative primal residuals and the
    absolute complementarity ``sum(w z)`` (absolute because nearly degenerate collision
    rows need it: their copies y follow z)."""
    e_u = _absmax(r_u) / scale_u
    e_y = _absmax2(r_y) / scale_y
    e_s = _absmax(r_s) / (1.0 + penalty)
    e_c = _absmax(r_pc) / scale_p
    e_q = _absmax(r_pq) / scale_p
    gap = 0.0
    for i in range(w.shape[0]):
        gap += w[i] * z[i]
    # checked on the sum: max() drops a NaN that is not its first argument
    if not np.isfinite(e_u + e_y + e_s + e_c + e_q + gap):
        return np.inf
    return max(e_u, e_y, e_s, e_c, e_q, gap)


@_jit
def _factor(H, A, N, rho, Du, u, w, z, deff, S, V, Sch) -> bool:
    """Factor the reduced Newton matrix at ``(u, w, z)`` (see the module docstring).

    Writes ``deff (R,)``, the Cholesky factor of S0 into ``S (n, n)``, ``V = L^-1 E^T``
    stored by rows into ``V (T, n)`` and the Cholesky factor of the Schur complement into
    ``Sch (T, T)``. Returns False if a factorization breaks down.
    """
    n = u.shape[0]
    R, D = N.shape
    T = V.shape[0]
    for i in range(n):
        for j in range(i + 1):
            S[i, j] = H[i, j]
        S[i, i] += z[2 * R + i // Du]
    for k in range(R):
        nn = 0.0
        for d in range(D):
            nn += N[k, d] * N[k, d]
        dk = 1.0 / (w[k] / z[k] + nn / rho[k] + w[R + k] / z[R + k])
        deff[k] = dk
        for i in range(n):
            a = dk * A[k, i]
            if a != 0.0:
                for j in range(i + 1):
                    S[i, j] += a * A[k, j]
    if not _cholesky(S, n):
        return False
    for t in range(T):
        _fill(V[t], 0.0)
        for d in range(Du):
            V[t, t * Du + d] = -u[t * Du + d]
        _forward(S, V[t], n, t * Du)
    for t1 in range(T):
        for t2 in range(t1 + 1):
            v = 0.0
            for i in range(n):
                v += V[t1, i] * V[t2, i]
            Sch[t1, t2] = v
        Sch[t1, t1] += w[2 * R + t1] / z[2 * R + t1]
    return _cholesky(Sch, T)


@_jit
def _solve(S, V, Sch, rhs1, rhs2, x1, x2) -> None:
    """Solve ``[[S0, E^T], [E, -W]] [x1; x2] = [rhs1; rhs2]`` with the factors of :func:`_factor`.

    Shapes: rhs1, x1 (n,); rhs2, x2 (T,).
    """
    n = x1.shape[0]
    T = x2.shape[0]
    _copy(rhs1, x1)
    _forward(S, x1, n, 0)  # a = L^-1 rhs1
    for t in range(T):
        v = -rhs2[t]
        for i in range(n):
            v += V[t, i] * x1[i]
        x2[t] = v
    _forward(Sch, x2, T, 0)
    _backward(Sch, x2, T)  # x2 = Sch^-1 (E S0^-1 rhs1 - rhs2)
    for t in range(T):
        for i in range(n):
            x1[i] -= V[t, i] * x2[t]
    _backward(S, x1, n)  # x1 = S0^-1 (rhs1 - E^T x2)


@_jit
def _direction(A, N, rho, Du, u, w, z, deff, S, V, Sch, r_u, r_y, r_s, r_pc, r_pq, rc,
               du, dy, dw, dz, rhs1, rhs2, gam, dq) -> None:
    """Newton direction for the complementarity residual ``rc`` (``z dw + w dz = -rc``), shape (m,).

    Writes ``du (n,), dy (R, D), dw (m,), dz (m,)``; ``rhs1 (n,), rhs2 (T,), gam (R,),
    dq (T,)`` are work space.
    """
    n = u.shape[0]
    R, D = N.shape
    T = rhs2.shape[0]
    for i in range(n):
        rhs1[i] = -r_u[i]
    for k in range(R):
        v = 0.0
        for d in range(D):
            v += N[k, d] * r_y[k, d]
        s_zs = w[R + k] / z[R + k]
        rt_s = -r_s[k] - rc[R + k] / w[R + k]
        gam[k] = v / rho[k] + rt_s * s_zs + r_pc[k] + rc[k] / z[k]  # gam + rho_c
        c = deff[k] * gam[k]
        for i in range(n):
            rhs1[i] -= A[k, i] * c
    for t in range(T):
        rhs2[t] = -r_pq[t] - rc[2 * R + t] / z[2 * R + t]
    _solve(S, V, Sch, rhs1, rhs2, du, dq)
    for k in range(R):
        v = gam[k]
        for i in range(n):
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
    for t in range(T):
        v = r_pq[t]
        for d in range(Du):
            v -= u[t * Du + d] * du[t * Du + d]
        dw[2 * R + t] = v
        dz[2 * R + t] = -dq[t]


@_jit
def _max_step(w, z, dw, dz) -> float:
    """Largest step in [0, 1] keeping ``w + a dw >= 0`` and ``z + a dz >= 0``."""
    ratio = 0.0
    for i in range(w.shape[0]):
        ratio = min(ratio, dw[i] / w[i], dz[i] / z[i])
    return 1.0 / max(-ratio, 1.0)


@_jit
def _iterate(H, g0, A, N, bt, rho, wy, u_max2, penalty, Du, tol, max_iter, u, y, w, z):
    """Run the method on one problem from ``(u, y, w, z)`` (updated in place).

    Returns:
        ``(converged, iterations, kkt_error)``. A problem whose Newton system breaks down
        or whose step is not finite stops there, unconverged.
    """
    n = u.shape[0]
    R, D = N.shape
    m = w.shape[0]
    T = m - 2 * R
    radius2 = TRUST_RADIUS * TRUST_RADIUS * u_max2
    scale_u = 1.0 + _absmax(g0)
    scale_y = 1.0 + _absmax2(wy)
    scale_p = 1.0 + max(_absmax(bt), u_max2)
    r_u, rhs1, du = np.empty(n), np.empty(n), np.empty(n)
    r_y, dy = np.empty((R, D)), np.empty((R, D))
    r_s, r_pc, deff, gam = np.empty(R), np.empty(R), np.empty(R), np.empty(R)
    r_pq, rhs2, dq = np.empty(T), np.empty(T), np.empty(T)
    wz, rc, dw, dz = np.empty(m), np.empty(m), np.empty(m), np.empty(m)
    S, V, Sch = np.empty((n, n)), np.empty((T, n)), np.empty((T, T))
    err = np.inf
    for it in range(max_iter + 1):
        _residuals(H, g0, A, N, bt, rho, wy, u_max2, penalty, Du, u, y, w, z, r_u, r_y, r_s, r_pc, r_pq)
        err = _kkt_error(r_u, r_y, r_s, r_pc, r_pq, w, z, scale_u, scale_y, scale_p, penalty)
        if err <= tol:
            return True, it, err
        if it == max_iter or not _factor(H, A, N, rho, Du, u, w, z, deff, S, V, Sch):
            return False, it, err
        mu = 0.0
        for i in range(m):
            wz[i] = w[i] * z[i]
            mu += wz[i]
        mu /= m
        # predictor (affine scaling)
        _direction(A, N, rho, Du, u, w, z, deff, S, V, Sch, r_u, r_y, r_s, r_pc, r_pq, wz,
                   du, dy, dw, dz, rhs1, rhs2, gam, dq)
        a_aff = _max_step(w, z, dw, dz)
        mu_aff = 0.0
        for i in range(m):
            mu_aff += (w[i] + a_aff * dw[i]) * (z[i] + a_aff * dz[i])
        sigma = min(mu_aff / m / mu, 1.0) ** 3
        # corrector
        for i in range(m):
            rc[i] = wz[i] + dw[i] * dz[i] - sigma * mu
        _direction(A, N, rho, Du, u, w, z, deff, S, V, Sch, r_u, r_y, r_s, r_pc, r_pq, rc,
                   du, dy, dw, dz, rhs1, rhs2, gam, dq)
        step = min(STEP_FRACTION * _max_step(w, z, dw, dz), 1.0)
        total = step + _absmax(du) + _absmax2(dy) + _absmax(dw) + _absmax(dz)
        if not total < np.inf:  # inf or NaN
            return False, it, err
        for t in range(T):  # update U_t, then project it onto the trust ball
            norm2 = 0.0
            for d in range(Du):
                i = t * Du + d
                u[i] += step * du[i]
                norm2 += u[i] * u[i]
            if norm2 > radius2:
                shrink = np.sqrt(radius2 / norm2)
                for d in range(Du):
                    u[t * Du + d] *= shrink
        for k in range(R):
            for d in range(D):
                y[k, d] += step * dy[k, d]
        for i in range(m):
            w[i] += step * dw[i]
            z[i] += step * dz[i]
    return False, max_iter, err


# ------------------------------------------------------------------------ batched entry points
@_jit
def solve_batch(G, h, c_x, l_x, rho_y, w_y, normals, bounds, alpha, u_max, penalty, tol, max_iter,
                u, y, w, z, warm, converged, iterations, kkt_error) -> None:
    """Solve B problems one after another.

    Args:
        G (B, nx, n), h (B, nx), c_x (B,), l_x (B, nx), rho_y (B, M), w_y (B, M, T, D),
        normals (B, M, T, D), bounds (B, M, T): the canonical data (float64, C-contiguous).
        alpha, u_max, penalty, tol: floats; max_iter: int.
        u (B, n), y (B, R, D), w (B, m), z (B, m): the primal-dual iterate, written in
            place; read as the starting point when ``warm`` (needs ``w, z > 0``).
        warm: start from the given iterate instead of the default initial point.
        converged (B,) bool, iterations (B,) int64, kkt_error (B,) float: written.

    Outputs are written into arrays the caller owns and nothing is returned: returning
    new arrays would make the compiled code call back into Python, where a pending
    KeyboardInterrupt surfaces as a SystemError.
    """
    B, n = h.shape[0], G.shape[2]
    M, T, D = normals.shape[1], normals.shape[2], normals.shape[3]
    R, Du = M * T, n // T
    u_max2 = u_max * u_max
    H, g0, A = np.empty((n, n)), np.empty(n), np.empty((R, n))
    bt, rho, N, wy = np.empty(R), np.empty(R), np.empty((R, D)), np.empty((R, D))
    for b in range(B):
        _setup(G[b], h[b], c_x[b], l_x[b], rho_y[b], w_y[b], normals[b], bounds[b], alpha, H, g0, A, bt, rho, N, wy)
        if not warm:
            _initial_point(N, bt, rho, wy, u_max2, penalty, u[b], y[b], w[b], z[b])
        converged[b], iterations[b], kkt_error[b] = _iterate(H, g0, A, N, bt, rho, wy, u_max2, penalty, Du, tol,
                                                             max_iter, u[b], y[b], w[b], z[b])


@_jit
def adjoint_batch(G, h, c_x, l_x, rho_y, w_y, normals, bounds, alpha, u, w, z, g_u, g_y, g_s, a_u, a_y, xi,
                  failed) -> None:
    """Solve the reduced KKT system at each primal-dual point for the right-hand side
    ``(g_u, g_y, g_s)`` (the implicit-function adjoint; the system is symmetric).

    Shapes: canonical data as in :func:`solve_batch`; ``u, g_u, a_u`` (B, n);
    ``g_y, a_y`` (B, R, D); ``w, z`` (B, m); ``g_s, xi`` (B, R). Writes ``a_u, a_y`` and
    ``xi``, the scaled multiplier ``(z_c / w_c) (grad g_c . a)`` of the collision rows,
    and ``failed (B,)`` bool: problems whose matrix cannot be factored (they get zeros).
    """
    B, n = h.shape[0], G.shape[2]
    M, T, D = normals.shape[1], normals.shape[2], normals.shape[3]
    R, Du = M * T, n // T
    H, g0, A = np.empty((n, n)), np.empty(n), np.empty((R, n))
    bt, rho, N, wy = np.empty(R), np.empty(R), np.empty((R, D)), np.empty((R, D))
    S, V, Sch = np.empty((n, n)), np.empty((T, n)), np.empty((T, T))
    deff, rhs1, rhs2, dq = np.empty(R), np.empty(n), np.zeros(T), np.empty(T)
    for b in range(B):
        failed[b] = False
        _setup(G[b], h[b], c_x[b], l_x[b], rho_y[b], w_y[b], normals[b], bounds[b], alpha, H, g0, A, bt, rho, N, wy)
        _fill(a_u[b], 0.0)
        _fill(xi[b], 0.0)
        for k in range(R):
            _fill(a_y[b, k], 0.0)
        if not _factor(H, A, N, rho, Du, u[b], w[b], z[b], deff, S, V, Sch):
            failed[b] = True
            continue
        _copy(g_u[b], rhs1)
        for k in range(R):
            v = 0.0
            for d in range(D):
                v -= N[k, d] * g_y[b, k, d]
            v = v / rho[k] + g_s[b, k] * w[b, R + k] / z[b, R + k]  # gam
            xi[b, k] = v
            for i in range(n):
                rhs1[i] -= A[k, i] * deff[k] * v
        _solve(S, V, Sch, rhs1, rhs2, a_u[b], dq)
        for k in range(R):
            v = xi[b, k]
            for i in range(n):
                v += A[k, i] * a_u[b, i]
            xi[b, k] = deff[k] * v
            for d in range(D):
                a_y[b, k, d] = (g_y[b, k, d] + N[k, d] * xi[b, k]) / rho[k]


def warm_up() -> None:
    """Compile (or load from the on-disk cache) both entry points on a tiny problem.

    Call before starting several processes that use the kernel, so they load the cache
    instead of each compiling it (about 10 s of one core, once per installation).
    """
    B, M, T, D = 1, 1, 1, 1
    R, n, m = M * T, T * D, 2 * M * T + T
    canonical = (np.eye(n)[None], np.zeros((B, n)), np.ones(B), np.zeros((B, n)), np.ones((B, M)),
                 np.zeros((B, M, T, D)), np.ones((B, M, T, D)), -np.ones((B, M, T)))
    u, y, w, z = np.empty((B, n)), np.empty((B, R, D)), np.empty((B, m)), np.empty((B, m))
    flags, counts, errors = np.empty(B, dtype=np.bool_), np.empty(B, dtype=np.int64), np.empty(B)
    solve_batch(*canonical, 1e-3, 1.0, 1e4, 1e-8, 30, u, y, w, z, False, flags, counts, errors)
    adjoint_batch(*canonical, 1e-3, u, w, z, np.ones((B, n)), np.ones((B, R, D)), np.ones((B, R)),
                  np.empty((B, n)), np.empty((B, R, D)), np.empty((B, R)), flags)


def is_cached() -> bool:
    """Whether numba's on-disk cache next to this module holds every compiled function, newer
    than this source (if not, the first solve compiles them: about 20-30 s, once)."""
    from pathlib import Path

    source = Path(__file__)
    index = list((source.parent / "__pycache__").glob(f"{source.stem}.*.nbi"))
    cached = {p.name.split(".")[1].rsplit("-", 1)[0] for p in index}
    compiled = {name for name, obj in globals().items() if hasattr(obj, "py_func")}
    return bool(index) and compiled <= cached and min(p.stat().st_mtime for p in index) >= source.stat().st_mtime
