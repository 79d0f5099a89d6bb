"""The input-rate term ``beta sum_t ||U_t - U_{t-1}||^2`` (``U_{-1} = u_prev``) in both solvers,
against a direct cvxpy solve of the problem written out (the reference of test_interior_point with
the term), central finite differences, and the problem without it."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from tests.control.solvers.test_interior_point import (
    ALPHA, D, NOMINAL, T, U_MAX, _weights, cvxpy_reference, make_data, objective,
)
from torch_gpmpc.control.solvers import make_local_solver
from torch_gpmpc.errors import GpmpcError

#: the reference solves of this module run Clarabel at 1e-11 tolerances: cvxpy and diffcp say
#: "inaccurate" where it stops a little short, which the comparisons' own tolerances cover
pytestmark = [pytest.mark.filterwarnings("ignore:Solution may be inaccurate:UserWarning"),
              pytest.mark.filterwarnings("ignore:Solved/Inaccurate:UserWarning")]


BETA = 0.5


def with_u_prev(data, seed: int):
    g = torch.Generator().manual_seed(seed)
    return dataclasses.replace(data, u_prev=torch.randn(data.x0.shape[0], D, generator=g, dtype=torch.float64))


@pytest.mark.parametrize("solver", ["fast", "clarabel", "direct"])
@pytest.mark.parametrize("M, kwargs, penalty", [(0, dict(push=1.6), 1e4), (1, dict(push=0.6), 1e4),
                                                (2, dict(push=0.8, bound_extra=1.5), 2.0)])
def test_plans_match_a_direct_cvxpy_solve(solver, M, kwargs, penalty):
    data = with_u_prev(make_data(3, M, seed=7, active_frac=1.0, **kwargs), seed=1)
    layer = make_local_solver(T, D, M, NOMINAL, U_MAX, ALPHA, penalty, solver=solver, input_rate_weight=BETA)
    sol = layer(data)
    assert bool(sol.ok.all())
    tol = 1e-4 if solver == "clarabel" else 1e-6  # cvxpylayers' clarabel path stops earlier
    matched = 0
    for b, ref in enumerate(cvxpy_reference(data, penalty, beta=BETA)):
        # equal within tol, unless Clarabel says it stopped short and our point is better
        if np.abs(sol.U[b].numpy() - ref["U"]).max() <= tol:
            matched += 1
        else:
            f_ours = objective(data, b, sol.X[b], sol.U[b], sol.Y[b], sol.slack[b], penalty, beta=BETA)
            assert ref["status"] == "optimal_inaccurate" and f_ours < ref["objective"], (b, ref["status"])
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
