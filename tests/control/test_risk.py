"""Tests of torch_gpmpc.control.risk against closed forms and hand-unrolled computations."""

from __future__ import annotations

import math

import pytest
import torch

from torch_gpmpc.errors import GpmpcError
from torch_gpmpc.control.risk import (
    chance_margins,
    chance_quantile,
    collision_normals,
    pair_risks,
    state_covariances,
)


NDTRI_095 = 1.6448536269514722


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
    margin = chance_margins(n, sigma, eps_low.reshape(1, 1))
    sigma_tilde = math.sqrt(float(rbar @ sigma[0, 0] @ rbar) / float(rbar @ rbar))
    assert (r_safe + margin).item() == pytest.approx(r_safe + NDTRI_095 * sigma_tilde, rel=1e-12)


def test_margin_zero_variance_has_finite_gradient():
    n = torch.tensor([1.0, 0.0], dtype=torch.float64).reshape(1, 1, 1, 2)
    sigma = torch.zeros(1, 1, 2, 2, requires_grad=True, dtype=torch.float64)
    eps = torch.tensor([[0.05]], requires_grad=True, dtype=torch.float64)
    margin = chance_margins(n, sigma, eps)
    margin.sum().backward()
    assert margin.item() == 0.0
    assert torch.isfinite(sigma.grad).all() and torch.isfinite(eps.grad).all()


def test_margin_gradient_wrt_split_matches_closed_form():
    split = torch.tensor(0.3, requires_grad=True, dtype=torch.float64)
    eps_low, _ = pair_risks(0.1, split)
    n = torch.tensor([0.6, 0.8], dtype=torch.float64).reshape(1, 1, 1, 2)
    sigma = torch.diag(torch.tensor([0.04, 0.09], dtype=torch.float64)).reshape(1, 1, 2, 2)
    margin = chance_margins(n, sigma, eps_low.reshape(1, 1))
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
