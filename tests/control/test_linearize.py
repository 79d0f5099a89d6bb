"""Tests of torch_gpmpc.control.linearize: Table 1 methods, finite differences, errors."""

from __future__ import annotations

import pytest
import torch

from torch_gpmpc.errors import GpmpcError
from torch_gpmpc.control.linearize import linearize_plan
from torch_gpmpc.dynamics.systems import NominalModel, VortexWind


METHODS = ("nominal", "nominal-chance", "nonlinear", "nonlinear-chance", "gp", "gp-chance")


class FakeGP:
    """Stand-in for ResidualGP: mean = a scaled vortex wind, quadratic variance."""

    def __init__(self, dim: int = 2, scale: float = 0.08):
        self.wind = VortexWind(scale=scale)
        self.dim = dim
        self.noise = torch.full((dim,), 0.01, dtype=torch.float64)

    def linearize(self, x):
        var = 0.01 + 0.002 * (x ** 2).sum(-1, keepdim=True) * torch.arange(1, self.dim + 1)
        return self.wind(x), self.wind.jacobian(x), var


@pytest.fixture
def plan():
    torch.manual_seed(0)
    return 2.0 * torch.randn(3, 6, 2, dtype=torch.float64)


@pytest.mark.parametrize("method", METHODS)
def test_plan_follows_linearized_dynamics_at_linearization_points(method, plan):
    """x_{tau+1} = dyn_A x_tau + B u + dyn_c reproduces f + mu at x = xbar (eq. 14)."""
    nominal, wind, gps = NominalModel(), VortexWind(), [FakeGP() for _ in range(3)]
    lin = linearize_plan(method, plan, nominal, wind, gps)
    assert lin.dyn_A.shape == (3, 5, 2, 2) and lin.dyn_c.shape == (3, 5, 2) and lin.var.shape == (3, 6, 2)
    affine = (lin.dyn_A @ plan[:, :-1, :, None]).squeeze(-1) + lin.dyn_c
    residual = {"nominal": torch.zeros_like(plan), "nonlinear": wind(plan), "gp": gps[0].wind(plan)}
    expected = plan[:, :-1] @ nominal.A().T + residual[method.removesuffix("-chance")][:, :-1]
    torch.testing.assert_close(affine, expected)
    if method.endswith("-chance"):
        torch.testing.assert_close(lin.var, torch.stack([g.linearize(p)[2] for g, p in zip(gps, plan)]))
    else:
        assert torch.count_nonzero(lin.var) == 0


def test_nonlinear_jacobian_matches_finite_differences(plan):
    wind = VortexWind()
    lin = linearize_plan("nonlinear", plan, NominalModel(), wind)
    h = 1e-6
    for e in range(2):
        step = torch.zeros(2, dtype=torch.float64)
        step[e] = h
        fd = (wind(plan[:, :-1] + step) - wind(plan[:, :-1] - step)) / (2 * h)
        torch.testing.assert_close(lin.dyn_A[..., e] - torch.eye(2, dtype=torch.float64)[:, e], fd, atol=1e-9, rtol=1e-7)


def test_affine_model_is_first_order_taylor(plan):
    """Near xbar the affine model matches the true f + g to second order."""
    wind = VortexWind()
    lin = linearize_plan("nonlinear", plan, NominalModel(), wind)
    delta = 1e-3 * torch.randn(3, 5, 2, dtype=torch.float64)
    x = plan[:, :-1] + delta
    affine = (lin.dyn_A @ x[..., None]).squeeze(-1) + lin.dyn_c
    assert (affine - (x + wind(x))).abs().max() < 1e-6


def test_include_noise_adds_observation_noise(plan):
    gps = [FakeGP() for _ in range(3)]
    a = linearize_plan("gp-chance", plan, NominalModel(), gps=gps)
    b = linearize_plan("gp-chance", plan, NominalModel(), gps=gps, include_noise=True)
    torch.testing.assert_close(b.var - a.var, torch.full_like(a.var, 0.01))


@pytest.mark.parametrize("method", ["nominal-chance", "gp", "gp-chance", "nonlinear-chance"])
def test_missing_gp_raises(method, plan):
    with pytest.raises(GpmpcError, match="GP"):
        linearize_plan(method, plan, NominalModel(), VortexWind(), gps=None)


def test_missing_wind_raises(plan):
    with pytest.raises(GpmpcError, match="wind"):
        linearize_plan("nonlinear", plan, NominalModel(), wind=None)


def test_wrong_gp_count_or_dimension_raises(plan):
    with pytest.raises(GpmpcError, match="3 agents"):
        linearize_plan("gp", plan, NominalModel(), gps=[FakeGP()])
    with pytest.raises(GpmpcError, match="shape"):
        linearize_plan("gp", torch.zeros(1, 4, 3, dtype=torch.float64), NominalModel(dim=3), gps=[FakeGP(dim=2)])


def test_unknown_method_and_bad_shapes_raise(plan):
    with pytest.raises(GpmpcError, match="method"):
        linearize_plan("linear", plan, NominalModel())
    with pytest.raises(GpmpcError, match="dim"):
        linearize_plan("nominal", plan, NominalModel(dim=3))
