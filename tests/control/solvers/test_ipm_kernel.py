"""The compiled interior-point kernel's building blocks against NumPy's dense answers."""

from __future__ import annotations

import numpy as np
import pytest

from torch_gpmpc.control.solvers import ipm_kernel as ipm
from torch_gpmpc.control.solvers import ipm_linalg, ipm_residuals


def _random_problem(seed: int, T: int = 5, D: int = 2, M: int = 2):
    """Random canonical data of one problem (batch axis dropped) and a strictly interior point."""
    rng = np.random.default_rng(seed)
    n, K = T * D, M * T
    G = np.tril(rng.standard_normal((n, n))) + 2.0 * np.eye(n)
    h, l_x = rng.standard_normal(n), rng.standard_normal(n)
    rho_y = 1.0 + rng.random(M)
    w_y, normals = rng.standard_normal((M, T, D)), rng.standard_normal((M, T, D))
    bounds = rng.standard_normal((M, T))
    u = 0.5 * rng.standard_normal(n)
    w, z = 0.1 + rng.random(2 * K + T), 0.1 + rng.random(2 * K + T)
    return (G, h, 1.7, l_x, rho_y, w_y, normals, bounds), u, w, z


def _setup(canonical, alpha: float, beta: float = 0.0, g_u=None, H_cost=None):
    G, h, _, _, _, _, normals, _ = canonical
    M, T, D = normals.shape
    n, K = h.shape[0], M * T
    H, g0, A = np.empty((n, n)), np.empty(n), np.empty((K, n))
    bt, rho, N, wy = np.empty(K), np.empty(K), np.empty((K, D)), np.empty((K, D))
    g_u = np.zeros(n) if g_u is None else g_u
    H_cost = np.zeros((n, n)) if H_cost is None else H_cost
    ipm_residuals.setup(*canonical, g_u, H_cost, np.ones(M), alpha, beta, H, g0, A, bt, rho, N, wy)
    return H, g0, A, bt, rho, N, wy


def test_setup_matches_the_condensed_problem_written_out():
    canonical, *_ = _random_problem(0)
    G, h, c_x, l_x, rho_y, w_y, normals, bounds = canonical
    M, T, D = normals.shape
    H, g0, A, bt, rho, N, wy = _setup(canonical, alpha=0.3)
    np.testing.assert_allclose(H, 2 * c_x * G.T @ G + 0.6 * np.eye(T * D), atol=1e-12)
    np.testing.assert_allclose(g0, G.T @ (2 * c_x * h - l_x), atol=1e-12)
    Gt = G.reshape(T, D, T * D)
    for j in range(M):
        for t in range(T):
            k = j * T + t
            np.testing.assert_allclose(A[k], normals[j, t] @ Gt[t], atol=1e-12)
            assert bt[k] == pytest.approx(bounds[j, t] - normals[j, t] @ h[t * D:(t + 1) * D])
            assert rho[k] == rho_y[j] and (N[k] == normals[j, t]).all() and (wy[k] == w_y[j, t]).all()


def test_setup_adds_the_input_rate_weight_as_first_differences():
    """beta sum_t ||U_t - U_{t-1}||^2 (U_{-1} in g_u): H gains 2 beta D^T D with D the
    first-difference map of the T blocks of Du inputs, g0 gains g_u."""
    canonical, *_ = _random_problem(1)
    G, h, c_x, l_x, _, _, normals, _ = canonical
    M, T, D = normals.shape
    n = T * D
    g_u = np.random.default_rng(3).standard_normal(n)
    H, g0, *_ = _setup(canonical, alpha=0.3, beta=0.7, g_u=g_u)
    Dm = np.eye(n) - np.eye(n, k=-D)  # rows: U_0 - U_{-1} (its U_{-1} part is g_u), U_t - U_{t-1}
    np.testing.assert_allclose(H, 2 * c_x * G.T @ G + 0.6 * np.eye(n) + 1.4 * Dm.T @ Dm, atol=1e-12)
    np.testing.assert_allclose(g0, G.T @ (2 * c_x * h - l_x) + g_u, atol=1e-12)


def test_setup_adds_a_stated_costs_hessian():
    """A stated cost's Hessian beyond the default (H_cost) is added to H as it is."""
    canonical, *_ = _random_problem(2)
    G, h, c_x, l_x, _, _, normals, _ = canonical
    M, T, D = normals.shape
    n = T * D
    root = np.random.default_rng(4).standard_normal((n, n))
    H_cost = root @ root.T
    H, g0, *_ = _setup(canonical, alpha=0.3, H_cost=H_cost)
    np.testing.assert_allclose(H, 2 * c_x * G.T @ G + 0.6 * np.eye(n) + H_cost, atol=1e-12)


@pytest.mark.parametrize("heavy_row", [False, True])
@pytest.mark.parametrize("seed", range(5))
def test_schur_cholesky_solve_matches_dense_augmented_solve(seed, heavy_row):
    """factor + solve against np.linalg.solve of [[S0, E^T], [E, -W]] assembled densely. With
    ``heavy_row`` the last slot is a state row (no copy) whose first row is nearly active
    (weight ~1e8): it must join the augmented rows (E row A_k, W entry 1 / deff_k)."""
    canonical, u, w, z = _random_problem(seed, M=3)
    normals = canonical[6]
    M, T, D = normals.shape
    n, K = T * D, M * T
    couple = np.array([1.0, 1.0, 0.0 if heavy_row else 1.0])
    H, g0, A = np.empty((n, n)), np.empty(n), np.empty((K, n))
    bt, rho, N, wy = np.empty(K), np.empty(K), np.empty((K, D)), np.empty((K, D))
    ipm_residuals.setup(*canonical, np.zeros(n), np.zeros((n, n)), couple, 0.1, 0.0, H, g0, A, bt, rho, N, wy)
    Rc = ipm_residuals.coupled_rows(couple, T)
    heavy = 2 * T
    if heavy_row:
        w[heavy], w[K + heavy] = 1e-9, 1e-9  # w_c / z_c and s / z_s tiny: deff ~ 1e8
    off = ipm_residuals.offsets(K, n, T, True, False, False)
    deff, aug = np.empty(K), np.empty(K, dtype=np.int64)
    S, E, V, Sch = np.empty((n, n)), np.empty((T + K, n)), np.empty((T + K, n)), np.empty((T + K, T + K))
    first, xs = np.zeros(T + K, dtype=np.int64), np.empty((0, 0))
    width = np.empty(K, dtype=np.int64)
    ipm_residuals.row_widths(A, width)
    Ta = ipm._factor(H, A, width, N, rho, canonical[0], np.zeros(0, dtype=np.int64), D, D, 1.0, off, Rc, u, w, z, xs,
                     deff, aug, S, E, first, V, Sch)
    assert Ta == T + int(heavy_row) and (aug[:Rc] == -1).all()
    wc, s, wq = w[:K], w[K:2 * K], w[2 * K:]
    zc, zs, zq = z[:K], z[K:2 * K], z[2 * K:]
    expected_deff = 1.0 / (wc / zc + (N * N).sum(1) / rho + s / zs)
    np.testing.assert_allclose(deff, expected_deff, rtol=1e-13)
    eliminated = aug < 0
    S0 = H + np.diag(np.repeat(zq, D)) + A[eliminated].T @ np.diag(deff[eliminated]) @ A[eliminated]
    E_dense = np.zeros((Ta, n))
    W = np.zeros(Ta)
    for t in range(T):
        E_dense[t, t * D:(t + 1) * D] = -u[t * D:(t + 1) * D]
        W[t] = wq[t] / zq[t]
    for k in np.flatnonzero(~eliminated):
        E_dense[aug[k]], W[aug[k]] = A[k], 1.0 / deff[k]
    kkt = np.block([[S0, E_dense.T], [E_dense, -np.diag(W)]])
    rng = np.random.default_rng(100 + seed)
    rhs1, rhs2 = rng.standard_normal(n), rng.standard_normal(Ta)
    x1, x2 = np.empty(n), np.empty(Ta)
    ipm._solve(S, V, Sch, Ta, rhs1, rhs2, x1, x2)
    np.testing.assert_allclose(np.concatenate([x1, x2]), np.linalg.solve(kkt, np.concatenate([rhs1, rhs2])),
                               rtol=1e-8, atol=1e-10)


def test_row_widths_end_at_the_last_nonzero_and_match_the_causal_dynamics():
    A = np.array([[1.0, 0.0, 2.0, 0.0], [0.0, 0.0, 0.0, 0.0], [0.0, -3.0, 0.0, 0.0], [1.0, 1.0, 1.0, 1.0]])
    width = np.empty(4, dtype=np.int64)
    ipm_residuals.row_widths(A, width)
    assert width.tolist() == [3, 0, 2, 4]
    # the condensed dynamics are causal: a row at horizon step t reads the inputs of steps 0..t
    T, D = 6, 2
    G = np.kron(np.tril(np.ones((T, T))), np.ones((D, D)))  # block lower triangular, Du = D
    normals = np.random.default_rng(0).standard_normal((3, T, D))
    GtG, rows = np.empty((T * D, T * D)), np.empty((3 * T, T * D))
    ipm_residuals.structure(G, normals, GtG, rows)
    width = np.empty(3 * T, dtype=np.int64)
    ipm_residuals.row_widths(rows, width)
    assert width.tolist() == [(k % T + 1) * D for k in range(3 * T)]


def test_cholesky_rejects_indefinite_and_nan():
    assert not ipm_linalg.cholesky(np.array([[1.0, 2.0], [2.0, 1.0]]), 2)
    assert not ipm_linalg.cholesky(np.array([[np.nan, 0.0], [0.0, 1.0]]), 2)
    S = np.array([[4.0, 0.0], [2.0, 5.0]])
    assert ipm_linalg.cholesky(S, 2)
    np.testing.assert_allclose(np.tril(S) @ np.tril(S).T, [[4.0, 2.0], [2.0, 5.0]])


def test_absmax_propagates_nan():
    assert ipm_linalg.absmax(np.array([1.0, -3.0, 2.0])) == 3.0
    assert np.isnan(ipm_linalg.absmax(np.array([1.0, np.nan, 2.0])))
    assert np.isnan(ipm_linalg.absmax2(np.array([[1.0], [np.nan]])))
    assert ipm_linalg.absmax(np.zeros(0)) == 0.0


def test_kkt_error_hand_computed_and_nan_anywhere_is_inf():
    r_u, r_y, r_s = np.array([0.5, -2.0]), np.array([[0.1, 0.2]]), np.array([3.0])
    r_p, w, z = np.array([0.0, -4.0]), np.array([1.0, 2.0]), np.array([0.5, 0.25])
    # max(2/2, 0.2/1, 3/(1+2), 4/4, w.z = 1.0) = 1.0; then make the u residual dominate
    assert ipm_residuals.kkt_error(r_u, r_y, r_s, r_p, w, z, 2.0, 1.0, 4.0, 2.0) == 1.0
    assert ipm_residuals.kkt_error(r_u, r_y, r_s, r_p, w, z, 0.5, 1.0, 4.0, 2.0) == 4.0
    for bad in (r_y, r_s, r_p):  # a NaN in any residual, not only the first one checked
        saved = bad.flat[-1]
        bad.flat[-1] = np.nan
        assert ipm_residuals.kkt_error(r_u, r_y, r_s, r_p, w, z, 2.0, 1.0, 4.0, 2.0) == np.inf
        bad.flat[-1] = saved
