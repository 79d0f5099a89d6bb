"""The input-rate term ``beta sum_t ||U_t - U_{t-1}||^2`` (``U_{-1} = u_prev``) in both solvers,
against a direct cvxpy solve of the problem written out, central finite differences, and the
problem without it."""

from __future__ import annotations

import dataclasses

import cvxpy as cp
import numpy as np
import pytest
import torch

from tests.control.solvers.test_interior_point import (
    ALPHA, B_GAIN, D, NOMINAL, T, U_MAX, _weights, make_data,
)
from torch_gpmpc.control.solvers import make_local_solver
from torch_gpmpc.errors import GpmpcError

BETA = 0.5


def with_u_prev(data, seed: int):
    g = torch.Generator().manual_seed(seed)
    return dataclasses.replace(data, u_prev=torch.randn(data.x0.shape[0], D, generator=g, dtype=torch.float64))


def direct_solve(data, beta: float, penalty: float, ours) -> list[tuple[np.ndarray, float, float, str]]:
    """Each problem written naturally in cvxpy (Clarabel, tight tolerances): its U, its optimal
    value, the value of that objective at ``ours`` (a LocalSolution) and the solver status."""
    batch, M = data.active.shape
    rho = data.rho.expand(batch, M) if data.rho.dim() == 0 else data.rho
    out = []
    for b in range(batch):
        X, U = cp.Variable((T + 1, D)), cp.Variable((T, D))
        Y = [cp.Variable((T + 1, D)) for _ in range(M)]
        S = cp.Variable((M, T), nonneg=True) if M else None
        cons = [X[0] == data.x0[b].numpy(), cp.norm(U, 2, axis=1) <= U_MAX]
        cons += [X[t + 1] == data.dyn_A[b, t].numpy() @ X[t] + B_GAIN * U[t] + data.dyn_c[b, t].numpy()
                 for t in range(T)]
        prev = data.u_prev[b].numpy()
        changes = cp.sum_squares(U[0] - prev) + sum(cp.sum_squares(U[t] - U[t - 1]) for t in range(1, T))
        obj = cp.sum_squares(X - data.xref[b].numpy()) + ALPHA * cp.sum_squares(U) + beta * changes
        for j in range(M):
            r = float(rho[b, j])
            obj += cp.sum(cp.multiply(data.lam_own[b, j].numpy(), X)) \
                + cp.sum(cp.multiply(data.lam_nbr[b, j].numpy(), Y[j])) \
                + r / 2 * (cp.sum_squares(X - data.z_own[b, j].numpy()) + cp.sum_squares(Y[j] - data.z_nbr[b, j].numpy()))
            cons += [data.normals[b, j, t - 1].numpy() @ (X[t] - Y[j][t]) + S[j, t - 1] >= float(data.bounds[b, j, t - 1])
                     for t in range(1, T + 1)]
        if M:
            obj += penalty * cp.sum(S)
        problem = cp.Problem(cp.Minimize(obj), cons)
        problem.solve(solver=cp.CLARABEL, tol_gap_abs=1e-12, tol_gap_rel=1e-12, tol_feas=1e-12, tol_ktratio=1e-10)
        assert problem.status in ("optimal", "optimal_inaccurate")
        U_ref, f_ref = U.value.copy(), problem.value
        X.value, U.value = ours.X[b].detach().numpy(), ours.U[b].detach().numpy()
        for j in range(M):
            Y[j].value = ours.Y[b, j].detach().numpy()
        if M:
            S.value = np.maximum(ours.slack[b].detach().numpy(), 0.0)
        out.append((U_ref, f_ref, float(problem.objective.value), problem.status))
    return out


@pytest.mark.parametrize("solver", ["fast", "clarabel"])
@pytest.mark.parametrize("M, kwargs, penalty", [(0, dict(push=1.6), 1e4), (1, dict(push=0.6), 1e4),
                                                (2, dict(push=0.8, bound_extra=1.5), 2.0)])
def test_plans_match_a_direct_cvxpy_solve(solver, M, kwargs, penalty):
    data = with_u_prev(make_data(3, M, seed=7, active_frac=1.0, **kwargs), seed=1)
    layer = make_local_solver(T, D, M, NOMINAL, U_MAX, ALPHA, penalty, solver=solver, input_rate_weight=BETA)
    sol = layer(data)
    assert bool(sol.ok.all())
    tol = 1e-6 if solver == "fast" else 1e-4  # cvxpylayers' clarabel path stops earlier
    matched = 0
    for b, (U_ref, f_ref, f_ours, status) in enumerate(direct_solve(data, BETA, penalty, sol)):
        # equal within tol, unless Clarabel says it stopped short and our point is better
        if np.abs(sol.U[b].numpy() - U_ref).max() <= tol:
            matched += 1
        else:
            assert status == "optimal_inaccurate" and f_ours < f_ref, (b, status, f_ours, f_ref)
    assert matched >= 2
    # the term changes the plan, and the reported cost contains it
    plain = make_local_solver(T, D, M, NOMINAL, U_MAX, ALPHA, penalty, solver=solver)(data)
    assert float((plain.U - sol.U).abs().max()) > 1e-2
    changes = torch.diff(sol.U, dim=1, prepend=data.u_prev[:, None]).pow(2).sum(dim=(1, 2))
    tracking = (sol.X - data.xref).pow(2).sum(dim=(1, 2)) + ALPHA * sol.U.pow(2).sum(dim=(1, 2))
    torch.testing.assert_close(sol.cost, tracking + BETA * changes, rtol=1e-12, atol=1e-12)


def test_zero_weight_or_no_previous_input_is_the_plain_problem():
    data = make_data(2, 1, seed=3, push=0.6)
    plain = make_local_solver(T, D, 1, NOMINAL, U_MAX, ALPHA)(data)
    same = make_local_solver(T, D, 1, NOMINAL, U_MAX, ALPHA, input_rate_weight=0.0)(with_u_prev(data, 2))
    assert torch.equal(plain.U, same.U)
    zero_prev = dataclasses.replace(data, u_prev=torch.zeros(2, D, dtype=torch.float64))
    rated = make_local_solver(T, D, 1, NOMINAL, U_MAX, ALPHA, input_rate_weight=BETA)
    torch.testing.assert_close(rated(data).U, rated(zero_prev).U, rtol=0, atol=0)


@pytest.mark.parametrize("field", ["u_prev", "rho", "z_own", "xref"])
def test_gradients_match_central_differences(field):
    M = 1
    data = with_u_prev(make_data(2, M, seed=11, push=0.6), seed=4)
    layer = make_local_solver(T, D, M, NOMINAL, U_MAX, ALPHA, input_rate_weight=BETA)
    layer.tol, layer.max_iter = 1e-13, 80
    weights = _weights(2, M, seed=1)

    def loss(d):
        sol = layer(d)
        return sum((w * t).sum() for w, t in zip(weights, (sol.X, sol.U, sol.Y, sol.slack)))

    base = getattr(data, field)
    leaf = base.clone().requires_grad_(True)
    loss(dataclasses.replace(data, **{field: leaf})).backward()
    direction = torch.randn(base.shape, generator=torch.Generator().manual_seed(2), dtype=torch.float64)
    eps = 1e-6 * (1.0 + float(base.abs().max()))
    with torch.no_grad():
        fd = float(loss(dataclasses.replace(data, **{field: base + eps * direction}))
                   - loss(dataclasses.replace(data, **{field: base - eps * direction}))) / (2 * eps)
    analytic = float((leaf.grad * direction).sum())
    assert abs(analytic - fd) <= 1e-4 * max(abs(fd), 1e-3 * float(leaf.grad.norm() * direction.norm()), 1e-8)


def test_bad_weight_and_shape_are_named():
    with pytest.raises(GpmpcError, match="input_rate_weight"):
        make_local_solver(T, D, 1, NOMINAL, U_MAX, ALPHA, input_rate_weight=-1.0)
    data = dataclasses.replace(make_data(2, 1, seed=3), u_prev=torch.zeros(2, D + 1, dtype=torch.float64))
    with pytest.raises(GpmpcError, match="u_prev"):
        make_local_solver(T, D, 1, NOMINAL, U_MAX, ALPHA, input_rate_weight=BETA)(data)
