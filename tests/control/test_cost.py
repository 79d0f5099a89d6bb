"""A stated QuadraticCost through the local solvers, against independent answers: a direct cvxpy
solve of the problem written out (compiled and reference paths), central differences of the plans
with respect to Q, R, P and u_ref, and the LQR terminal weight against the Riccati equation."""

import cvxpy as cp
import numpy as np
import pytest
import torch

from torch_gpmpc import GpmpcError, ModelSpec, NominalModel, QuadraticCost, make_local_solver
from torch_gpmpc.control.cost import lqr_terminal_weight
from torch_gpmpc.control.problem import LocalProblemData

T, PENALTY = 8, 1e4


def _psd(rng, n, floor):
    root = rng.standard_normal((n, n))
    return torch.tensor(root @ root.T / n + floor * np.eye(n))


def _instance(seed: int, rho: float = 5.0):
    """One double-integrator agent (n = 4, m = 2) with one active neighbour slot whose collision row
    binds, a stated cost and random consensus terms."""
    rng = np.random.default_rng(seed)
    model = NominalModel(ModelSpec.double_integrator(2, dt=0.2, u_max=2.0))
    n, m = 4, 2
    A, B = model.A(), model.B()
    x0 = torch.tensor([0.0, 0.0, 0.5, 0.0]) + 0.1 * torch.tensor(rng.standard_normal(n))
    xref = torch.zeros(T + 1, n)
    xref[:, 0] = torch.linspace(0.0, 3.0, T + 1)
    normal = torch.zeros(T, n)
    normal[:, 1] = 1.0  # keep y >= copy's y + 0.3: pushes the plan off the reference
    z = 0.2 * torch.tensor(rng.standard_normal((2, T + 1, n)))
    lam = 0.5 * torch.tensor(rng.standard_normal((2, T + 1, n)))
    data = LocalProblemData(
        x0=x0[None], xref=xref[None], dyn_A=A.expand(1, T, n, n).clone(), dyn_c=torch.zeros(1, T, n),
        normals=normal[None, None], bounds=torch.full((1, 1, T), 0.3), active=torch.ones(1, 1, dtype=torch.bool),
        rho=torch.tensor(rho, dtype=torch.float64), z_own=z[0][None, None], z_nbr=z[1][None, None],
        lam_own=lam[0][None, None], lam_nbr=lam[1][None, None],
        cost_Q=_psd(rng, n, 0.1)[None], cost_R=_psd(rng, m, 0.05)[None], cost_P=_psd(rng, n, 0.5)[None],
        u_ref=0.3 * torch.tensor(rng.standard_normal(m))[None])
    return model, data


def _direct_cvxpy(model, data, rho: float):
    """The local problem written out in cvxpy, solved by Clarabel: ``(X, U)``."""
    n, m = 4, 2
    A, B = model.A().numpy(), model.B().numpy()
    Q, R, P = (data.cost_Q[0].numpy(), data.cost_R[0].numpy(), data.cost_P[0].numpy())
    u_ref, r = data.u_ref[0].numpy(), data.xref[0].numpy()
    X, U, Y, s = cp.Variable((T + 1, n)), cp.Variable((T, m)), cp.Variable((T + 1, n)), cp.Variable(T, nonneg=True)
    cost = sum(cp.quad_form(X[t] - r[t], Q) + cp.quad_form(U[t] - u_ref, R) for t in range(T))
    cost += cp.quad_form(X[T] - r[T], P)
    z_own, z_nbr = data.z_own[0, 0].numpy(), data.z_nbr[0, 0].numpy()
    cost += cp.sum(cp.multiply(data.lam_own[0, 0].numpy(), X)) + cp.sum(cp.multiply(data.lam_nbr[0, 0].numpy(), Y))
    cost += rho / 2 * (cp.sum_squares(X - z_own) + cp.sum_squares(Y - z_nbr)) + PENALTY * cp.sum(s)
    nrm, bnd = data.normals[0, 0].numpy(), data.bounds[0, 0].numpy()
    cons = [X[0] == data.x0[0].numpy()]
    cons += [X[t + 1] == A @ X[t] + B @ U[t] for t in range(T)]
    cons += [cp.norm(U[t]) <= 2.0 for t in range(T)]
    cons += [nrm[t] @ (X[t + 1] - Y[t + 1]) + s[t] >= bnd[t] for t in range(T)]
    cp.Problem(cp.Minimize(cost), cons).solve(solver=cp.CLARABEL, tol_gap_abs=1e-12, tol_gap_rel=1e-12,
                                              tol_feas=1e-12)
    return X.value, U.value


@pytest.mark.parametrize("solver", ["fast", "clarabel", "direct"])
@pytest.mark.parametrize("seed", [0, 1])
def test_stated_cost_equals_a_direct_cvxpy_solve(solver, seed):
    model, data = _instance(seed)
    layer = make_local_solver(T, 4, 1, model, None, 1e-3, PENALTY, solver=solver)
    sol = layer(data)
    X, U = _direct_cvxpy(model, data, 5.0)
    assert bool(sol.ok.all())
    np.testing.assert_allclose(sol.U[0].detach().numpy(), U, atol=1e-6)
    np.testing.assert_allclose(sol.X[0].detach().numpy(), X, atol=1e-6)


def test_the_cost_changes_the_plan():
    """The stated cost is used (else this test could not fail): its plan differs from the default's."""
    model, data = _instance(0)
    layer = make_local_solver(T, 4, 1, model, None, 1e-3, PENALTY)
    default = layer(LocalProblemData(**{**data.__dict__, "cost_Q": None, "cost_R": None, "cost_P": None,
                                        "u_ref": None}))
    assert float((layer(data).U - default.U).abs().max()) > 1e-2


@pytest.mark.parametrize("field", ["cost_Q", "cost_R", "cost_P", "u_ref"])
def test_gradients_match_central_differences(field):
    model, data = _instance(2)
    layer = make_local_solver(T, 4, 1, model, None, 1e-3, PENALTY, warm_start=False)
    weights = torch.tensor(np.random.default_rng(7).standard_normal((T, 2)))

    def loss(value):
        sol = layer(LocalProblemData(**{**data.__dict__, field: value}))
        return (sol.U[0] * weights).sum() + (sol.X[0, -1] ** 2).sum()

    base = getattr(data, field).clone().requires_grad_(True)
    (grad,) = torch.autograd.grad(loss(base), base)
    h = 1e-5
    numeric = torch.zeros(grad.numel(), dtype=grad.dtype)
    flat = base.detach().reshape(-1)
    for i in range(flat.numel()):
        step = torch.zeros_like(flat)
        step[i] = h
        if field in ("cost_Q", "cost_R", "cost_P"):  # keep the weight symmetric: perturb (i,j) and (j,i)
            shaped = step.view_as(base)
            step = (0.5 * (shaped + shaped.mT)).reshape(-1)
        with torch.no_grad():
            up = loss((flat + step).view_as(base))
            down = loss((flat - step).view_as(base))
        numeric[i] = (up - down) / (2 * h)
    if field in ("cost_Q", "cost_R", "cost_P"):  # compare along symmetric perturbations
        grad = 0.5 * (grad + grad.mT)
    assert float(grad.abs().max()) > 1e-3  # a gradient that is there
    np.testing.assert_allclose(grad.reshape(-1).numpy(), numeric.numpy(), atol=1e-5, rtol=1e-5)


def test_lqr_terminal_weight_solves_the_riccati_equation():
    model = NominalModel(ModelSpec.double_integrator(3, dt=0.1, u_max=2.0))
    A, B = model.A(), model.B()
    Q, R = torch.diag(torch.tensor([1.0, 2.0, 3.0, 0.1, 0.1, 0.1])), 0.01 * torch.eye(3)
    P = lqr_terminal_weight(A, B, Q, R)
    K = torch.linalg.solve(R + B.T @ P @ B, B.T @ P @ A)
    np.testing.assert_allclose((Q + A.T @ P @ A - A.T @ P @ B @ K).numpy(), P.numpy(), rtol=1e-9, atol=1e-9)
    # the scalar single integrator: p^2 - p - 0.1 = 0 (closed form)
    p = lqr_terminal_weight(torch.eye(1), 0.1 * torch.eye(1), torch.eye(1), 1e-3 * torch.eye(1))
    assert float(p) == pytest.approx((1 + np.sqrt(1.4)) / 2, rel=1e-8)


@pytest.mark.parametrize("kwargs, field", [
    (dict(Q=torch.ones(3), R=1.0), "Q"),
    (dict(Q=torch.tensor([[1.0, 2.0], [0.0, 1.0]]).repeat(2, 2), R=1.0), "Q"),
    (dict(Q=-torch.eye(4), R=1.0), "Q"),
    (dict(Q=1.0, R=0.0), "R"),
    (dict(Q=1.0, R=1.0, P=torch.eye(3)), "P"),
    (dict(Q=1.0, R=1.0, u_ref=torch.zeros(3)), "u_ref"),
    (dict(Q="abc", R=1.0), "Q"),
    (dict(Q=float("nan"), R=1.0), "Q"),
])
def test_bad_weights_name_their_field(kwargs, field):
    model = NominalModel(ModelSpec.double_integrator(2, dt=0.1, u_max=2.0))
    with pytest.raises(GpmpcError, match=f"QuadraticCost.{field}"):
        QuadraticCost(**kwargs).resolve(model)


def test_the_default_lqr_terminal_weight_passes_gradients_to_q_and_r():
    """With P left to the LQR cost-to-go, the plans' gradient with respect to Q and R includes P's
    dependence on them (the Riccati equation's implicit derivative): central differences agree."""
    model, data = _instance(3)
    layer = make_local_solver(T, 4, 1, model, None, 1e-3, PENALTY, warm_start=False)

    def loss(Q, R):
        Qw, Rw, Pw, _ = QuadraticCost(Q=Q, R=R).resolve(model)
        sol = layer(LocalProblemData(**{**data.__dict__, "cost_Q": Qw[None], "cost_R": Rw[None],
                                        "cost_P": Pw[None], "u_ref": None}))
        return (sol.X[0, 1:, :2] ** 2).sum() + (sol.U[0] ** 2).sum()

    q = torch.tensor([1.0, 2.0, 0.3, 0.2], dtype=torch.float64, requires_grad=True)
    r = torch.tensor([0.05, 0.08], dtype=torch.float64, requires_grad=True)
    gq, gr = torch.autograd.grad(loss(q, r), (q, r))
    h = 1e-5
    for value, grad, which in ((q, gq, 0), (r, gr, 1)):
        for i in range(value.numel()):
            step = torch.zeros_like(value)
            step[i] = h
            with torch.no_grad():
                args_up = (q + step, r) if which == 0 else (q, r + step)
                args_down = (q - step, r) if which == 0 else (q, r - step)
                numeric = (loss(*args_up) - loss(*args_down)) / (2 * h)
            assert float(grad[i]) == pytest.approx(float(numeric), rel=1e-5, abs=1e-6)
