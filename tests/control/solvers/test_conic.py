"""Tests of torch_gpmpc.control.solvers.conic.CvxpyLayerMPC against independent cvxpy solves and finite differences."""

from __future__ import annotations

import logging
from dataclasses import replace

import cvxpy as cp
import numpy as np
import pytest
import torch

from torch_gpmpc.errors import GpmpcError
from torch_gpmpc.control import examples
from torch_gpmpc.control.problem import LocalProblemData
from torch_gpmpc.control.solvers import make_local_solver
from torch_gpmpc.control.solvers.conic import CvxpyLayerMPC
from torch_gpmpc.dynamics.systems import NominalModel, VortexWind


T, D = 13, 2
U_MAX, ALPHA, PENALTY, R_SAFE = 2.0, 1e-3, 1e4, 0.5
NOMINAL = NominalModel()
METHODS = ("nominal", "nominal-chance", "nonlinear", "nonlinear-chance", "gp", "gp-chance")
#: Tight interior-point tolerances for finite-difference checks.


class FakeGP:
    """Stand-in for ResidualGP: mean = a scaled vortex wind, quadratic variance."""

    def __init__(self, scale: float = 0.08):
        self.wind = VortexWind(scale=scale)
        self.noise = torch.full((D,), 0.01, dtype=torch.float64)

    def linearize(self, x):
        var = 0.01 + 0.002 * (x ** 2).sum(-1, keepdim=True) * torch.tensor([1.0, 1.5], dtype=torch.float64)
        return self.wind(x), self.wind.jacobian(x), var


def crossing_instance(batch, num_nbr, method="gp-chance", mode="pointwise", seed=0, active=None):
    """Agents on a circle of radius 0.9 heading through the centre, neighbours crossing them
    (the shared factory, with :class:`FakeGP` residuals)."""
    return examples.crossing_instance(batch, num_nbr, method=method, mode=mode, seed=seed, active=active,
                                      gps=[FakeGP() for _ in range(batch)])


def problem_data(inst, rho=20.0, split=0.5, eps=0.1, x0=None, z_own=None, z_nbr=None):
    """LocalProblemData through the differentiable chain pair_risks -> ndtri -> margins."""
    return inst.problem_data(rho=rho, split=split, eps=eps, r_safe=R_SAFE, x0=x0, z_own=z_own, z_nbr=z_nbr)


def reference_solve(data: LocalProblemData, b: int):
    """Agent b's problem in the natural (non-DPP) form with numeric values, plain Clarabel."""
    n = lambda t: t[b].detach().numpy()  # noqa: E731
    rho = data.rho.expand(data.active.shape)[b].detach().numpy() if data.rho.dim() == 0 else n(data.rho)
    X, U = cp.Variable((T + 1, D)), cp.Variable((T, D))
    B = NOMINAL.B().numpy()
    cost = cp.sum_squares(X - n(data.xref)) + ALPHA * cp.sum_squares(U)
    cons = [X[0] == n(data.x0)]
    A, c = n(data.dyn_A), n(data.dyn_c)
    for tau in range(T):
        cons += [X[tau + 1] == A[tau] @ X[tau] + B @ U[tau] + c[tau], cp.norm(U[tau]) <= U_MAX]
    Ys, slacks = {}, {}
    for j in np.flatnonzero(n(data.active)):
        Y, s = cp.Variable((T + 1, D)), cp.Variable(T, nonneg=True)
        Ys[j], slacks[j] = Y, s
        cost += (cp.sum(cp.multiply(n(data.lam_own)[j], X)) + cp.sum(cp.multiply(n(data.lam_nbr)[j], Y))
                 + rho[j] / 2 * (cp.sum_squares(X - n(data.z_own)[j]) + cp.sum_squares(Y - n(data.z_nbr)[j]))
                 + PENALTY * cp.sum(s))
        for tau in range(1, T + 1):
            cons.append(n(data.normals)[j, tau - 1] @ (X[tau] - Y[tau]) + s[tau - 1] >= n(data.bounds)[j, tau - 1])
    cp.Problem(cp.Minimize(cost), cons).solve(solver=cp.CLARABEL, tol_gap_abs=1e-10, tol_gap_rel=1e-10,
                                              tol_feas=1e-10)
    return X.value, U.value, {j: Y.value for j, Y in Ys.items()}, {j: s.value for j, s in slacks.items()}


@pytest.fixture(scope="module")
def layers():
    return {m: make_local_solver(T, D, m, NOMINAL, U_MAX, ALPHA, PENALTY, "clarabel") for m in (0, 1, 3)}


def assert_feasible(data, sol, tol=1e-6):
    X, U = sol.X.detach(), sol.U.detach()
    pred = (data.dyn_A @ X[:, :-1, :, None]).squeeze(-1) + U @ NOMINAL.B().T + data.dyn_c
    assert (X[:, 1:] - pred).abs().max() < tol
    assert (X[:, 0] - data.x0).abs().max() < tol
    assert U.norm(dim=-1).max() <= U_MAX + tol
    if sol.Y.shape[1]:
        gap = (data.normals * (X[:, None, 1:] - sol.Y.detach()[:, :, 1:])).sum(-1) + sol.slack.detach()
        assert (gap - data.bounds).min() >= -tol
        assert sol.slack.min() >= -tol


@pytest.mark.parametrize("num_nbr", [0, 1, 3])
@pytest.mark.parametrize("mode", ["pointwise", "propagated"])
@pytest.mark.parametrize("method", METHODS)
def test_matches_independent_cvxpy(layers, method, mode, num_nbr):
    active = torch.ones(3, num_nbr, dtype=torch.bool)
    if num_nbr == 3:
        active[1, 2] = False  # padding slot
    inst = crossing_instance(3, num_nbr, method, mode, seed=METHODS.index(method) + 7 * num_nbr, active=active)
    data = problem_data(inst)
    sol = layers[num_nbr](data)
    assert sol.ok.all()
    assert_feasible(data, sol)
    for b in range(3):
        X, U, Ys, slacks = reference_solve(data, b)
        np.testing.assert_allclose(sol.X[b].detach().numpy(), X, atol=1e-5)
        np.testing.assert_allclose(sol.U[b].detach().numpy(), U, atol=1e-5)
        for j in range(num_nbr):
            if active[b, j]:
                np.testing.assert_allclose(sol.Y[b, j].detach().numpy(), Ys[j], atol=1e-5)
                np.testing.assert_allclose(sol.slack[b, j].detach().numpy(), slacks[j], atol=1e-5)
            else:  # padding slot: Y -> 0, no slack
                assert sol.Y[b, j].abs().max() < 1e-6 and sol.slack[b, j].abs().max() < 1e-6
    cost = ((sol.X - data.xref) ** 2).sum((1, 2)) + ALPHA * (sol.U ** 2).sum((1, 2))
    torch.testing.assert_close(sol.cost, cost)


def test_collision_rows_are_active_in_crossing_instance(layers):
    data = problem_data(crossing_instance(1, 1))
    sol = layers[1](data)
    gap = (data.normals * (sol.X[:, None, 1:] - sol.Y[:, :, 1:])).sum(-1) - data.bounds
    assert gap.min().abs() < 1e-6  # some row is tight
    assert not sol.slack_active.any()


def test_gradients_match_finite_differences(layers):
    """d/d(rho, risk split, x0, z) of a fixed random functional of the plan."""
    inst = crossing_instance(1, 1, seed=3)
    weights = torch.randn(T + 1, D, generator=torch.Generator().manual_seed(5), dtype=torch.float64)
    layer = layers[1]

    def objective(rho, split, x0, z_own, z_nbr):
        sol = layer(problem_data(inst, rho=rho, split=split, x0=x0, z_own=z_own, z_nbr=z_nbr))
        assert sol.ok.all()
        return (sol.X[0] * weights).sum() + sol.cost.sum()

    base = dict(rho=torch.tensor(20.0, dtype=torch.float64), split=torch.tensor(0.4, dtype=torch.float64), x0=inst.x0.clone(),
                z_own=inst.z_own.clone(), z_nbr=inst.z_nbr.clone())
    leaves = {k: v.clone().requires_grad_(True) for k, v in base.items()}
    objective(**leaves).backward()
    g = torch.Generator().manual_seed(11)
    # steps well above the solution accuracy (~1e-9) but small for the curvature
    h = {"rho": 1e-2, "split": 1e-3, "x0": 1e-3, "z_own": 1e-3, "z_nbr": 1e-3}
    for name, value in base.items():
        direction = torch.randn(value.shape, generator=g, dtype=torch.float64)
        with torch.no_grad():
            up = objective(**{**base, name: value + h[name] * direction})
            down = objective(**{**base, name: value - h[name] * direction})
        fd = (up - down).item() / (2 * h[name])
        analytic = (leaves[name].grad * direction).sum().item()
        assert abs(fd) > 1e-3, name  # the instance is sensitive to every input
        assert analytic == pytest.approx(fd, rel=1e-3), name
    assert abs(leaves["split"].grad.item()) > 1e-3  # the collision row is active


def test_infeasible_copies_use_slack_and_batched_equals_one_by_one(layers):
    """Neighbour copies pinned onto the agent's own plan by a huge rho: slack, no exception."""
    inst = crossing_instance(3, 1, seed=4)
    pinned = replace(inst, z_nbr=inst.xbar[:, None].clone(), z_own=inst.xbar[:, None].clone())
    data = problem_data(pinned, rho=1e7)
    data.rho = torch.tensor([[1e7], [20.0], [1e7]], dtype=torch.float64)
    sol = layers[1](data)
    assert sol.ok.all()
    assert sol.slack_active.tolist() == [True, False, True]
    assert_feasible(data, sol, tol=1e-5)
    for b in range(3):
        single = layers[1](LocalProblemData(**{k: (v if v is None or (k == "rho" and v.dim() == 0) else v[b:b + 1])
                                               for k, v in vars(data).items()}))
        for field in ("X", "U", "Y", "slack"):
            torch.testing.assert_close(getattr(single, field)[0], getattr(sol, field)[b], atol=1e-6, rtol=0)


def test_solver_exception_is_isolated(layers, caplog, monkeypatch):
    """A solver error in one agent's problem: the others are solved, ok=False for it, no raise."""
    layer = layers[1]
    data = problem_data(crossing_instance(3, 1, seed=6))
    real_forward = layer.layer.forward

    def flaky(*params, solver_args=None):
        if params[0].shape[0] > 1 or torch.allclose(params[0], data.x0[1:2]):
            raise RuntimeError("synthetic solver failure")
        return real_forward(*params, solver_args=solver_args)

    monkeypatch.setattr(layer.layer, "forward", flaky)
    with caplog.at_level(logging.DEBUG, logger="torch_gpmpc.control.solvers.conic"):  # ADMM warns once per kind
        sol = layer(data)
    assert sol.ok.tolist() == [True, False, True]
    assert torch.isnan(sol.X[1]).all() and torch.isfinite(sol.X[[0, 2]]).all()
    assert "synthetic solver failure" in caplog.text


def test_reference_solver_agrees_with_clarabel(layers):
    data = problem_data(crossing_instance(1, 1, seed=8))
    ref = CvxpyLayerMPC(T, D, 1, NOMINAL, U_MAX, ALPHA, PENALTY, solver="reference")(data)
    sol = layers[1](data)
    assert ref.ok.all()
    torch.testing.assert_close(ref.X, sol.X, atol=1e-5, rtol=0)
    torch.testing.assert_close(ref.Y, sol.Y, atol=1e-5, rtol=0)


def test_cache_and_input_errors(layers):
    # every call builds a module owned by its caller (no shared, mutable solver)
    assert make_local_solver(T, D, 1, NOMINAL, U_MAX, ALPHA, PENALTY, "clarabel") is not layers[1]
    data = problem_data(crossing_instance(2, 1))
    with pytest.raises(GpmpcError, match="normals"):
        layers[3](data)
    with pytest.raises(GpmpcError, match="solver"):
        CvxpyLayerMPC(T, D, 1, NOMINAL, U_MAX, ALPHA, solver="scs")
    assert CvxpyLayerMPC(T, D, 0, NOMINAL, U_MAX, ALPHA).problem.is_dpp()
