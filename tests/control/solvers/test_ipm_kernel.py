"""The compiled interior-point kernel's building blocks against NumPy's dense answers."""

from __future__ import annotations

import numpy as np
import pytest

from torch_gpmpc.control.solvers import ipm_kernel as ipm


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


def _setup(canonical, alpha: float):
    G, h, _, _, _, _, normals, _ = canonical
    M, T, D = normals.shape
    n, K = h.shape[0], M * T
    H, g0, A = np.empty((n, n)), np.empty(n), np.empty((K, n))
    bt, rho, N, wy = np.empty(K), np.empty(K), np.empty((K, D)), np.empty((K, D))
    ipm._setup(*canonical, alpha, H, g0, A, bt, rho, N, wy)
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


@pytest.mark.parametrize("seed", range(5))
def test_schur_cholesky_solve_matches_dense_augmented_solve(seed):
    """_factor + _solve against np.linalg.solve of [[S0, E^T], [E, -W]] assembled densely."""
    canonical, u, w, z = _random_problem(seed)
    normals = canonical[6]
    M, T, D = normals.shape
    n, K = T * D, M * T
    H, g0, A, bt, rho, N, wy = _setup(canonical, alpha=0.1)
    deff, S, V, Sch = np.empty(K), np.empty((n, n)), np.empty((T, n)), np.empty((T, T))
    assert ipm._factor(H, A, N, rho, D, u, w, z, deff, S, V, Sch)
    wc, s, wq = w[:K], w[K:2 * K], w[2 * K:]
    zc, zs, zq = z[:K], z[K:2 * K], z[2 * K:]
    expected_deff = 1.0 / (wc / zc + (N * N).sum(1) / rho + s / zs)
    np.testing.assert_allclose(deff, expected_deff, rtol=1e-13)
    S0 = H + np.diag(np.repeat(zq, D)) + A.T @ np.diag(deff) @ A
    E = np.zeros((T, n))
    for t in range(T):
        E[t, t * D:(t + 1) * D] = -u[t * D:(t + 1) * D]
    kkt = np.block([[S0, E.T], [E, -np.diag(wq / zq)]])
    rng = np.random.default_rng(100 + seed)
    rhs1, rhs2 = rng.standard_normal(n), rng.standard_normal(T)
    x1, x2 = np.empty(n), np.empty(T)
    ipm._solve(S, V, Sch, rhs1, rhs2, x1, x2)
    np.testing.assert_allclose(np.concatenate([x1, x2]), np.linalg.solve(kkt, np.concatenate([rhs1, rhs2])),
                               rtol=1e-9, atol=1e-11)


def test_cholesky_rejects_indefinite_and_nan():
    assert not ipm._cholesky(np.array([[1.0, 2.0], [2.0, 1.0]]), 2)
    assert not ipm._cholesky(np.array([[np.nan, 0.0], [0.0, 1.0]]), 2)
    S = np.array([[4.0, 0.0], [2.0, 5.0]])
    assert ipm._cholesky(S, 2)
    np.testing.assert_allclose(np.tril(S) @ np.tril(S).T, [[4.0, 2.0], [2.0, 5.0]])


def test_absmax_propagates_nan():
    assert ipm._absmax(np.array([1.0, -3.0, 2.0])) == 3.0
    assert np.isnan(ipm._absmax(np.array([1.0, np.nan, 2.0])))
    assert np.isnan(ipm._absmax2(np.array([[1.0], [np.nan]])))
    assert ipm._absmax(np.zeros(0)) == 0.0


def test_kkt_error_hand_computed_and_nan_anywhere_is_inf():
    r_u, r_y, r_s = np.array([0.5, -2.0]), np.array([[0.1, 0.2]]), np.array([3.0])
    r_pc, r_pq, w, z = np.array([0.0]), np.array([-4.0]), np.array([1.0, 2.0]), np.array([0.5, 0.25])
    # max(2/2, 0.2/1, 3/(1+2), 0/4, 4/4, w.z = 1.0) = 1.0; then make the u residual dominate
    assert ipm._kkt_error(r_u, r_y, r_s, r_pc, r_pq, w, z, 2.0, 1.0, 4.0, 2.0) == 1.0
    assert ipm._kkt_error(r_u, r_y, r_s, r_pc, r_pq, w, z, 0.5, 1.0, 4.0, 2.0) == 4.0
    for bad in (r_y, r_s, r_pc, r_pq):  # a NaN in any residual, not only the first one checked
        saved = bad.flat[0]
        bad.flat[0] = np.nan
        assert ipm._kkt_error(r_u, r_y, r_s, r_pc, r_pq, w, z, 2.0, 1.0, 4.0, 2.0) == np.inf
        bad.flat[0] = saved
