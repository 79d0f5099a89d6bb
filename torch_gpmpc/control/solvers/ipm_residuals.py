"""The interior-point kernel's problem evaluation, compiled by numba: the problem arrays of one
local problem from its canonical data, the inequality layout, the starting point, and the
residuals and KKT error (the formulation: :mod:`torch_gpmpc.control.solvers.ipm_kernel`)."""

from __future__ import annotations

import numba
import numpy as np

from torch_gpmpc.control.solvers.ipm_linalg import absmax, absmax2, fill

# error_model="numpy": float division by zero gives inf/nan (checked), never an exception.
_jit = numba.njit(cache=True, error_model="numpy", nogil=True)


@_jit
def offsets(R: int, n: int, T: int, has_norm: bool, has_box: bool, has_state_norm: bool):
    """Sizes and offsets of the inequality families in ``w, z`` (module docstring):
    ``(oq, ob, ov, osg, Tq, nb, Ts, m)``."""
    Tq = T if has_norm else 0
    nb = n if has_box else 0
    Ts = T if has_state_norm else 0
    oq = 2 * R
    ob = oq + Tq
    ov = ob + 2 * nb
    osg = ov + Ts
    return oq, ob, ov, osg, Tq, nb, Ts, osg + Ts


@_jit
def coupled_rows(couple, T: int) -> int:
    """Rc = T times the number of neighbour slots (``couple`` 1; they come first)."""
    c = 0
    for j in range(couple.shape[0]):
        if couple[j] != 0.0:
            c += 1
    return c * T


@_jit
def structure(G, normals, GtG, A) -> None:
    """The parts of a problem that only the dynamics and the row normals fix (within a control step
    ADMM poses the same ones at every iteration): ``GtG = G^T G`` (n, n) and the rows' gradients
    ``A_k = G_t^T n_k`` (R, n), from G (nx, n) and normals (M, T, D) (row ``k = j T + t``)."""
    nx, n = G.shape
    M, T, D = normals.shape
    # G is causal (an input moves only later states), so its columns start with zeros: lead[i] is
    # column i's first nonzero row. Sums start there; the skipped terms are exact zeros, so GtG and
    # A are bit for bit the full sums, in a third of the work.
    lead = np.empty(n, dtype=np.int64)
    for i in range(n):
        r = 0
        while r < nx and G[r, i] == 0.0:
            r += 1
        lead[i] = r
    for i in range(n):
        for j in range(i + 1):
            v = 0.0
            for r in range(max(lead[i], lead[j]), nx):
                v += G[r, i] * G[r, j]
            GtG[i, j] = v
            GtG[j, i] = v
    for j in range(M):
        for t in range(T):
            k = j * T + t
            for i in range(n):
                v = 0.0
                if (t + 1) * D > lead[i]:
                    for d in range(D):
                        v += normals[j, t, d] * G[t * D + d, i]
                A[k, i] = v


@_jit
def row_widths(A, width) -> None:
    """``width[k]``: one past the last nonzero entry of row ``k`` of ``A (R, n)`` (0 for a zero row).
    The condensed dynamics are causal (an input moves only later states), so a row at horizon step
    t has its zeros at the end, after (t + 1) Du entries: sums over a row stop at its width, and
    the skipped terms are exact zeros, so they are the full sums bit for bit."""
    R, n = A.shape
    for k in range(R):
        j = n
        while j > 0 and A[k, j - 1] == 0.0:
            j -= 1
        width[k] = j


@_jit
def weights(GtG, G, h, c_x, l_x, rho_y, w_y, normals, bounds, g_u, H_cost, couple, alpha, beta, H, g0, bt, rho, N,
            wy) -> None:
    """The rest of :func:`setup`, given ``GtG`` (n, n) from :func:`structure`: H, g0, bt, rho, N, wy.
    ``H_cost`` (n, n) is the user cost's Hessian beyond ``2 G^T G + 2 alpha I`` (0 for the default cost)."""
    nx, n = G.shape
    M, T, D = normals.shape
    c2 = 2.0 * c_x
    for i in range(n):
        for j in range(i + 1):
            H[i, j] = c2 * GtG[i, j] + H_cost[i, j]
            H[j, i] = c2 * GtG[i, j] + H_cost[j, i]
        H[i, i] += 2.0 * alpha
    if beta != 0.0:
        Du = n // normals.shape[1]
        for i in range(n):
            H[i, i] += 2.0 * beta * (2.0 if i < n - Du else 1.0)
            if i + Du < n:
                H[i, i + Du] -= 2.0 * beta
                H[i + Du, i] -= 2.0 * beta
    for i in range(n):
        v = g_u[i]
        for r in range(nx):
            v += G[r, i] * (c2 * h[r] - l_x[r])
        g0[i] = v
    for j in range(M):
        for t in range(T):
            k = j * T + t
            rho[k] = rho_y[j]
            b = bounds[j, t]
            for d in range(D):
                N[k, d] = couple[j] * normals[j, t, d]
                wy[k, d] = w_y[j, t, d]
                b -= normals[j, t, d] * h[t * D + d]
            bt[k] = b


@_jit
def setup(G, h, c_x, l_x, rho_y, w_y, normals, bounds, g_u, H_cost, couple, alpha, beta, H, g0, A, bt, rho, N,
          wy) -> None:
    """Fill the problem arrays of one problem from its canonical data (see module docstring).

    Shapes: G (nx, n), h (nx,), l_x (nx,), rho_y (M,), w_y (M, T, D), normals (M, T, D),
    bounds (M, T), g_u (n,), H_cost (n, n), couple (M,) with nx = T D states and n = T Du inputs; outputs
    H (n, n), g0 (n,), A (R, n), bt (R,), rho (R,), N (R, D) (the copy's coefficient,
    ``couple_j n_k``), wy (R, D). ``beta`` weighs the input changes ``sum_t ||U_t - U_{t-1}||^2``
    (its ``U_{-1}`` part is in ``g_u``): ``H += 2 beta D^T D`` with D the first difference.
    :func:`structure` then :func:`weights`.
    """
    n = G.shape[1]
    GtG = np.empty((n, n))
    structure(G, normals, GtG, A)
    weights(GtG, G, h, c_x, l_x, rho_y, w_y, normals, bounds, g_u, H_cost, couple, alpha, beta, H, g0, bt, rho, N, wy)


@_jit
def state_values(G, h, sbi, D, u, xs) -> None:
    """``xs[t, a] = (G u + h)[t D + sbi[a]]``: the bounded state entries per step, (Ts, p)."""
    n = u.shape[0]
    for t in range(xs.shape[0]):
        for a in range(xs.shape[1]):
            r = t * D + sbi[a]
            v = h[r]
            for i in range(n):
                v += G[r, i] * u[i]
            xs[t, a] = v


@_jit
def add_state_norm_curvature(S, G, sbi, D, t, zt) -> None:
    """``S += zt G_t^T P^T P G_t`` on the lower triangle: the Hessian of state-norm row ``t``
    (``P`` selects the indices ``sbi``) times its multiplier ``zt``; S (n, n)."""
    n = S.shape[0]
    for a in range(sbi.shape[0]):
        r = t * D + sbi[a]
        for i in range(n):
            gi = zt * G[r, i]
            if gi != 0.0:
                for j in range(i + 1):
                    S[i, j] += gi * G[r, j]


@_jit
def initial_point(N, bt, rho, wy, G, h, sbi, D, box, u_max2, v_max, penalty, off, u, y, w, z, xs) -> None:
    """Infeasible start: ``u = 0``, unconstrained copies, ``z_c + z_s = P`` (dual feasible
    in s) and ``s z_s = 1``, so every complementarity product starts near 1; likewise the
    state-norm slacks (``v z_v + z_sigma = P``)."""
    R, D_ = N.shape
    oq, ob, ov, osg, Tq, nb, Ts, m = off
    zc0 = min(1.0, 0.5 * penalty)
    zs0 = penalty - zc0
    fill(u, 0.0)
    for k in range(R):
        s = 1.0 / zs0
        gc = s - bt[k]
        for d in range(D_):
            y[k, d] = wy[k, d] / rho[k]
            gc -= N[k, d] * y[k, d]
        w[k] = max(gc, 1.0)
        w[R + k] = s
        z[k] = zc0
        z[R + k] = zs0
    for t in range(Tq):
        w[oq + t] = 0.5 * u_max2
        z[oq + t] = 1.0
    Du = box.shape[0]
    for i in range(nb):
        w[ob + i] = box[i % Du]
        w[ob + nb + i] = box[i % Du]
        z[ob + i] = 1.0
        z[ob + nb + i] = 1.0
    if Ts:
        state_values(G, h, sbi, D, u, xs)
        zv0 = min(1.0, 0.5 * penalty / v_max)
        zsg0 = penalty - v_max * zv0
        for t in range(Ts):
            sg = 1.0 / zsg0
            g = v_max * v_max + 2.0 * v_max * sg
            for a in range(xs.shape[1]):
                g -= xs[t, a] * xs[t, a]
            w[ov + t] = max(0.5 * g, 1.0)
            z[ov + t] = zv0
            w[osg + t] = sg
            z[osg + t] = zsg0


@_jit
def residuals(H, g0, A, width, N, bt, rho, wy, G, h, sbi, D, Du, box, u_max2, v_max, penalty, off,
               u, y, w, z, xs, r_u, r_y, r_s, r_p) -> None:
    """Residuals at ``(u, y, w, z)``, written in place: dual ``r_u (n,)``, ``r_y (R, D)``,
    ``r_s (R + Ts,)`` (collision slacks, then state-norm slacks) and primal ``r_p (m,)``
    (0 at the slack entries, which are their own variables); ``xs (Ts, p)`` the bounded
    state entries; ``width (R,)``: the rows' :func:`row_widths`."""
    n = u.shape[0]
    R, D_ = N.shape
    oq, ob, ov, osg, Tq, nb, Ts, m = off
    for i in range(n):
        v = g0[i]
        for j in range(n):
            v += H[i, j] * u[j]
        if Tq:
            v += z[oq + i // Du] * u[i]
        if nb:
            v += z[ob + i] - z[ob + nb + i]
        r_u[i] = v
    if Ts:
        state_values(G, h, sbi, D, u, xs)
        for t in range(Ts):
            zt = z[ov + t]
            for a in range(xs.shape[1]):
                c = zt * xs[t, a]
                r = t * D + sbi[a]
                for i in range(n):
                    r_u[i] += c * G[r, i]
    for k in range(R):
        zc = z[k]
        if zc != 0.0:  # an inactive row of a warm point adds exact zeros
            for i in range(width[k]):
                r_u[i] -= A[k, i] * zc
        v = w[R + k] - bt[k] - w[k]
        for i in range(width[k]):
            v += A[k, i] * u[i]
        for d in range(D_):
            r_y[k, d] = rho[k] * y[k, d] - wy[k, d] + zc * N[k, d]
            v -= N[k, d] * y[k, d]
        r_p[k] = v
        r_p[R + k] = 0.0
        r_s[k] = penalty - zc - z[R + k]
    for t in range(Tq):
        v = u_max2
        for d in range(Du):
            v -= u[t * Du + d] * u[t * Du + d]
        r_p[oq + t] = 0.5 * v - w[oq + t]
    for i in range(nb):
        b = box[i % Du]
        r_p[ob + i] = b - u[i] - w[ob + i]
        r_p[ob + nb + i] = b + u[i] - w[ob + nb + i]
    for t in range(Ts):
        g = v_max * v_max + 2.0 * v_max * w[osg + t]
        for a in range(xs.shape[1]):
            g -= xs[t, a] * xs[t, a]
        r_p[ov + t] = 0.5 * g - w[ov + t]
        r_p[osg + t] = 0.0
        r_s[R + t] = penalty - v_max * z[ov + t] - z[osg + t]


@_jit
def kkt_error(r_u, r_y, r_s, r_p, w, z, scale_u, scale_y, scale_p, penalty) -> float:
    """Largest of the relative dual residuals, the relative primal residuals and the
    absolute complementarity ``sum(w z)`` (absolute because nearly degenerate collision
    rows need it: their copies y follow z)."""
    e_u = absmax(r_u) / scale_u
    e_y = absmax2(r_y) / scale_y
    e_s = absmax(r_s) / (1.0 + penalty)
    e_p = absmax(r_p) / scale_p
    gap = 0.0
    for i in range(w.shape[0]):
        gap += w[i] * z[i]
    # checked on the sum: max() drops a NaN that is not its first argument
    if not np.isfinite(e_u + e_y + e_s + e_p + gap):
        return np.inf
    return max(e_u, e_y, e_s, e_p, gap)
