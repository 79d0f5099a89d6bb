"""Tests of torch_gpmpc.control.risk against closed forms and hand-unrolled computations."""

from __future__ import annotations

import math

import numpy as np

import pytest
import torch

from torch_gpmpc.errors import GpmpcError
from torch_gpmpc.control.risk import (
    chance_quantile,
    collision_normals,
    pair_margins,
    pair_risks,
    projected_variances,
    state_covariances,
)


NDTRI_095 = 1.6448536269514722


def own_margin(n, sigma, eps):
    """The production path's ``own`` margin ``Phi^-1(1 - eps_k) sqrt(n^T Sigma_k n)`` (eq. 24)."""
    var = projected_variances(n, sigma)
    eps = torch.as_tensor(eps, dtype=torch.float64).expand(var.shape[:2])
    return pair_margins("own", var, var, eps, 0.1 - eps)


def test_pair_risks_split_sums_to_total():
    low, high = pair_risks(torch.tensor(0.1, dtype=torch.float64), torch.tensor(0.3, dtype=torch.float64))
    assert low.item() == pytest.approx(0.03)
    assert high.item() == pytest.approx(0.07)
    assert (low + high).item() == pytest.approx(0.1)


def test_chance_quantile_closed_form():
    assert chance_quantile(0.05).item() == pytest.approx(NDTRI_095, abs=1e-12)
    assert chance_quantile(torch.tensor([0.5], dtype=torch.float64)).item() == pytest.approx(0.0, abs=1e-12)


def test_margin_equals_quantile_times_sigma_tilde():
    """bound = r_safe + 1.645 sigma~ for eps_k = 0.05 (paper eqs. 22, 24)."""
    torch.manual_seed(0)
    r_safe = 0.5
    rbar = torch.tensor([3.0, -4.0], dtype=torch.float64)
    n = (rbar / rbar.norm()).reshape(1, 1, 1, 2)
    a = torch.randn(2, 2, dtype=torch.float64)
    sigma = (a @ a.T + 0.1 * torch.eye(2, dtype=torch.float64)).reshape(1, 1, 2, 2)
    eps_low, _ = pair_risks(0.1, 0.5)
    margin = own_margin(n, sigma, eps_low.reshape(1, 1))
    sigma_tilde = math.sqrt(float(rbar @ sigma[0, 0] @ rbar) / float(rbar @ rbar))
    assert (r_safe + margin).item() == pytest.approx(r_safe + NDTRI_095 * sigma_tilde, rel=1e-12)


def test_margin_zero_variance_has_finite_gradient():
    n = torch.tensor([1.0, 0.0], dtype=torch.float64).reshape(1, 1, 1, 2)
    sigma = torch.zeros(1, 1, 2, 2, requires_grad=True, dtype=torch.float64)
    eps = torch.tensor([[0.05]], requires_grad=True, dtype=torch.float64)
    margin = own_margin(n, sigma, eps)
    margin.sum().backward()
    assert margin.item() == 0.0
    assert torch.isfinite(sigma.grad).all() and torch.isfinite(eps.grad).all()


def test_margin_gradient_wrt_split_matches_closed_form():
    split = torch.tensor(0.3, requires_grad=True, dtype=torch.float64)
    eps_low, _ = pair_risks(0.1, split)
    n = torch.tensor([0.6, 0.8], dtype=torch.float64).reshape(1, 1, 1, 2)
    sigma = torch.diag(torch.tensor([0.04, 0.09], dtype=torch.float64)).reshape(1, 1, 2, 2)
    margin = own_margin(n, sigma, eps_low.reshape(1, 1))
    margin.sum().backward()
    s_tilde = math.sqrt(0.36 * 0.04 + 0.64 * 0.09)
    q = torch.special.ndtri(torch.tensor(1 - 0.03, dtype=torch.float64)).item()
    dq_deps = -1.0 / (math.exp(-q * q / 2) / math.sqrt(2 * math.pi))
    assert split.grad.item() == pytest.approx(dq_deps * 0.1 * s_tilde, rel=1e-9)


def test_pointwise_covariance_is_diagonal_of_variance():
    var = torch.rand(2, 4, 3, dtype=torch.float64)
    sigma = state_covariances("pointwise", var, torch.zeros(2, 3, 3, 3, dtype=torch.float64))
    assert torch.equal(sigma, torch.diag_embed(var))


def test_propagated_covariance_hand_unrolled_two_steps():
    torch.manual_seed(1)
    var = torch.rand(1, 3, 2, dtype=torch.float64)
    dyn_A = torch.eye(2, dtype=torch.float64) + 0.1 * torch.randn(1, 2, 2, 2, dtype=torch.float64)
    sigma = state_covariances("propagated", var, dyn_A)
    s0 = torch.zeros(2, 2, dtype=torch.float64)
    s1 = dyn_A[0, 0] @ s0 @ dyn_A[0, 0].T + torch.diag(var[0, 0])
    s2 = dyn_A[0, 1] @ s1 @ dyn_A[0, 1].T + torch.diag(var[0, 1])
    torch.testing.assert_close(sigma[0, 0], s0)
    torch.testing.assert_close(sigma[0, 1], s1)
    torch.testing.assert_close(sigma[0, 2], s2, rtol=1e-14, atol=1e-14)


def test_state_covariances_rejects_unknown_mode_and_bad_shapes():
    with pytest.raises(GpmpcError, match="uncertainty"):
        state_covariances("full", torch.rand(1, 3, 2, dtype=torch.float64), torch.zeros(1, 2, 2, 2, dtype=torch.float64))
    with pytest.raises(GpmpcError, match="dyn_A"):
        state_covariances("propagated", torch.rand(1, 3, 2, dtype=torch.float64), torch.zeros(1, 3, 2, 2, dtype=torch.float64))


def test_normals_are_unit_and_antisymmetric():
    torch.manual_seed(2)
    xa, xb = torch.randn(1, 5, 2, dtype=torch.float64), torch.randn(1, 5, 2, dtype=torch.float64)
    xb[0, 2] = xa[0, 2]  # coincident at step 2
    n_ab = collision_normals(xa, xb[:, None], torch.tensor([0]), torch.tensor([[1]]))
    n_ba = collision_normals(xb, xa[:, None], torch.tensor([1]), torch.tensor([[0]]))
    torch.testing.assert_close(n_ab, -n_ba)
    torch.testing.assert_close(n_ab.norm(dim=-1), torch.ones(1, 1, 5, dtype=torch.float64))
    assert n_ab[0, 0, 2].tolist() == [1.0, 0.0]  # lower id: +e_0
    assert n_ba[0, 0, 2].tolist() == [-1.0, 0.0]


def test_coincident_normals_in_a_batch_agree_per_pair():
    """Three agents all at the origin: every pair separates along e_0 in opposite directions."""
    x = torch.zeros(3, 2, 2, dtype=torch.float64)
    ids = torch.arange(3)
    nbr_ids = torch.tensor([[1, 2], [0, 2], [0, 1]])
    normals = collision_normals(x, x[nbr_ids], ids, nbr_ids)
    for k in range(3):
        for m, j in enumerate(nbr_ids[k].tolist()):
            back = nbr_ids[j].tolist().index(k)
            torch.testing.assert_close(normals[k, m], -normals[j, back])


def test_normals_shape_mismatch_raises():
    with pytest.raises(GpmpcError):
        collision_normals(torch.zeros(2, 4, 2, dtype=torch.float64), torch.zeros(2, 1, 3, 2, dtype=torch.float64))


# ---------------------------------------------------------------- pair margins (sound formulations)
def test_pair_margins_closed_forms():
    """own: q(eps_k) sqrt(s_k); sum: q(eps_k) sqrt(s_k) + q(eps_j) sqrt(s_j); joint:
    q(eps_k + eps_j) sqrt(s_k + s_j), with q = Phi^-1(1 - .) from scipy (independent)."""
    from scipy.stats import norm

    from torch_gpmpc.control.risk import pair_margins

    s_k = torch.tensor([[[0.01, 0.04]]], dtype=torch.float64)
    s_j = torch.tensor([[[0.09, 0.0]]], dtype=torch.float64)
    e_k = torch.tensor([[0.03]], dtype=torch.float64)
    e_j = torch.tensor([[0.07]], dtype=torch.float64)
    own = pair_margins("own", s_k, s_j, e_k, e_j)
    total = pair_margins("sum", s_k, s_j, e_k, e_j)
    joint = pair_margins("joint", s_k, s_j, e_k, e_j)
    qk, qj, q = norm.ppf(1 - 0.03), norm.ppf(1 - 0.07), norm.ppf(1 - 0.10)
    np.testing.assert_allclose(own.numpy().ravel(), [qk * 0.1, qk * 0.2], rtol=1e-12)
    np.testing.assert_allclose(total.numpy().ravel(), [qk * 0.1 + qj * 0.3, qk * 0.2], rtol=1e-12)
    np.testing.assert_allclose(joint.numpy().ravel(), [q * np.sqrt(0.10), q * 0.2], rtol=1e-12)
    # joint is the tightest sound margin: never above sum
    assert bool((joint <= total + 1e-15).all())


def test_projected_variance_is_the_quadratic_form():
    from torch_gpmpc.control.risk import projected_variances

    n = torch.tensor([0.6, 0.8], dtype=torch.float64).reshape(1, 1, 1, 2)
    sigma = torch.tensor([[0.04, 0.01], [0.01, 0.09]], dtype=torch.float64).reshape(1, 1, 2, 2)
    expected = 0.36 * 0.04 + 2 * 0.48 * 0.01 + 0.64 * 0.09
    assert projected_variances(n, sigma).item() == pytest.approx(expected, rel=1e-14)


@pytest.mark.parametrize("mode", ["sum", "joint"])
def test_monte_carlo_single_pair_violation_rate_is_at_most_eps(mode):
    """Two agents with fixed plans exactly at the required separation along n; each deviates
    by independent Gaussian noise of its own covariance. The empirical rate of the linearized
    distance falling below r_safe is <= eps (binomial 3-sigma allowance); the paper's ``own``
    margin exceeds eps with the same noise."""
    from torch_gpmpc.control.risk import pair_margins, projected_variances

    gen = torch.Generator().manual_seed(0)
    n = torch.tensor([1.0, 0.0], dtype=torch.float64)
    cov_k = torch.tensor([[0.02, 0.005], [0.005, 0.01]], dtype=torch.float64)
    cov_j = torch.tensor([[0.03, -0.004], [-0.004, 0.02]], dtype=torch.float64)
    eps, split, r_safe, N = 0.1, 0.5, 0.5, 200_000
    s = [projected_variances(n.reshape(1, 1, 1, 2), c.reshape(1, 1, 2, 2)) for c in (cov_k, cov_j)]
    e = torch.tensor([[eps * split]], dtype=torch.float64)

    def rate(formulation: str) -> float:
        margin = float(pair_margins(formulation, s[0], s[1], e, eps - e))
        sep = r_safe + margin
        w_k = torch.randn(N, 2, generator=gen, dtype=torch.float64) @ torch.linalg.cholesky(cov_k).T
        w_j = torch.randn(N, 2, generator=gen, dtype=torch.float64) @ torch.linalg.cholesky(cov_j).T
        d = sep + (w_k - w_j) @ n
        return float((d < r_safe).double().mean())

    allowance = 3 * np.sqrt(eps * (1 - eps) / N)
    assert rate(mode) <= eps + allowance
    assert rate("own") > eps + allowance


def test_feedback_covariance_matches_the_scalar_lqr_closed_form():
    """Single integrator x' = x + b u per axis, Q = 1, R = r: the DARE's scalar solution
    p = (b^2 + sqrt(b^4 + 4 b^2 r)) / (2 b^2), gain k = -b p / (b^2 p + r), closed loop
    a = 1 + b k; with noise v per step Sigma_tau = v sum_{i<tau} a^(2i) (bounded), while
    open-loop propagation gives tau v (growing)."""
    from torch_gpmpc.control.risk import lqr_gain

    b, r, v, T = 0.1, 1e-3, 0.0121, 13
    A, B = torch.eye(2, dtype=torch.float64), b * torch.eye(2, dtype=torch.float64)
    K = lqr_gain(A, B, 1.0, r)
    p = (b * b + math.sqrt(b ** 4 + 4 * b * b * r)) / (2 * b * b)
    k = -b * p / (b * b * p + r)
    torch.testing.assert_close(K, k * torch.eye(2, dtype=torch.float64), rtol=1e-9, atol=0)
    a = 1 + b * k
    var = torch.full((1, T + 1, 2), v, dtype=torch.float64)
    dyn_A = torch.eye(2, dtype=torch.float64).expand(1, T, 2, 2)
    fb = state_covariances("feedback", var, dyn_A, feedback=B @ K)
    ol = state_covariances("propagated", var, dyn_A)
    for tau in range(T + 1):
        expected = v * sum(a ** (2 * i) for i in range(tau))
        assert fb[0, tau, 0, 0].item() == pytest.approx(expected, rel=1e-9, abs=1e-15)
        assert ol[0, tau, 0, 0].item() == pytest.approx(tau * v, rel=1e-12)
    assert fb[0, -1, 0, 0] < 2 * v < ol[0, -1, 0, 0]
    with pytest.raises(GpmpcError, match="feedback"):
        state_covariances("feedback", var, dyn_A)
