"""Both local solvers on general linear models (double integrators, a model file with a box input
bound and a state bound) against a direct cvxpy solve written independently (with the state bound
hard: the soft bound must give the same plan when the hard one is feasible), and the fast
solver's gradients against finite differences."""

from __future__ import annotations

import cvxpy as cp
import numpy as np
import pytest
import torch

from torch_gpmpc.config.model_spec import double_integrator, parse_model
from torch_gpmpc.control.problem import LocalProblemData
from torch_gpmpc.control.solvers import make_local_solver
from torch_gpmpc.dynamics.systems import NominalModel

#: the reference solves of this module run Clarabel at 1e-11 tolerances: cvxpy and diffcp say
#: "inaccurate" where it stops a little short, which the comparisons' own tolerances cover
pytestmark = [pytest.mark.filterwarnings("ignore:Solution may be inaccurate:UserWarning"),
              pytest.mark.filterwarnings("ignore:Solved/Inaccurate:UserWarning")]


T, ALPHA, PENALTY, RHO = 8, 1e-3, 1e4, 20.0
F64 = torch.float64


def box_model():
    """A 2D double integrator from a model file with a box input bound and a speed limit."""
    spec = double_integrator(2, 0.1, 1.0)
    return parse_model({"name": "box", "dt": 0.1, "A": [list(r) for r in spec.A], "B": [list(r) for r in spec.B],
                        "position": [0, 1], "residual": [2, 3], "gp_inputs": ["x0", "x1", "u0", "u1"],
                        "input_bound": {"box": [1.5, 0.8]}, "state_bound": {"indices": [2, 3], "norm": 0.9}})


def instance(nominal: NominalModel, num_nbr: int, seed: int, time_varying_b: bool) -> LocalProblemData:
    """A crossing-like local problem: the agent heads for the origin, neighbours' copies sit near
    its path (collision rows on the positions active), perturbed linearized dynamics."""
    g = torch.Generator().manual_seed(seed)
    D, Du, pos = nominal.dim, nominal.input_dim, nominal.position
    A, B = nominal.A(), nominal.B()
    dyn_A = A + 0.01 * torch.randn(1, T, D, D, generator=g, dtype=F64)
    dyn_B = (B + 0.01 * torch.randn(1, T, D, Du, generator=g, dtype=F64)) if time_varying_b else None
    dyn_c = 0.005 * torch.randn(1, T, D, generator=g, dtype=F64)
    start = torch.zeros(len(pos), dtype=F64)
    start[0] = -1.0
    x0 = nominal.states_at(start)[None]
    path = torch.linspace(0, 1, T + 1, dtype=F64)[:, None] * (-start) + start  # towards the origin
    xref = nominal.reference_states(path)[None]
    normals = torch.zeros(1, num_nbr, T, D, dtype=F64)
    z_nbr = torch.zeros(1, num_nbr, T + 1, D, dtype=F64)
    for j in range(num_nbr):
        angle = 0.7 + 2.0 * j + 0.3 * torch.rand((), generator=g, dtype=F64)
        offset = torch.zeros(len(pos), dtype=F64)
        offset[0], offset[1] = torch.cos(angle), torch.sin(angle)
        nbr_path = path + 0.3 * offset
        z_nbr[0, j] = nominal.states_at(nbr_path)
        normals[0, j][..., pos] = -offset  # a row that pushes the agent away from the neighbour
    bounds = torch.full((1, num_nbr, T), 0.4, dtype=F64)  # above the 0.3 offset: rows bind
    z_own = xref[:, None].expand(1, num_nbr, T + 1, D).clone()
    zeros = torch.zeros_like(z_own)
    return LocalProblemData(x0=x0, xref=xref, dyn_A=dyn_A, dyn_c=dyn_c, normals=normals, bounds=bounds,
                            active=torch.ones(1, num_nbr, dtype=torch.bool), rho=torch.tensor(RHO, dtype=F64),
                            z_own=z_own, z_nbr=z_nbr, lam_own=zeros.clone(), lam_nbr=zeros.clone(), dyn_B=dyn_B)


def direct_solve(data: LocalProblemData, nominal: NominalModel):
    """The local problem in its natural form with plain Clarabel (no DPP, no condensing)."""
    n = lambda t: t[0].detach().numpy()  # noqa: E731
    spec, D, Du = nominal.spec, nominal.dim, nominal.input_dim
    X, U = cp.Variable((T + 1, D)), cp.Variable((T, Du))
    Bs = n(data.dyn_B) if data.dyn_B is not None else np.repeat(nominal.B().numpy()[None], T, 0)
    cost = cp.sum_squares(X - n(data.xref)) + ALPHA * cp.sum_squares(U)
    cons = [X[0] == n(data.x0)]
    for tau in range(T):
        cons.append(X[tau + 1] == n(data.dyn_A)[tau] @ X[tau] + Bs[tau] @ U[tau] + n(data.dyn_c)[tau])
        cons.append(cp.abs(U[tau]) <= np.array(spec.input_box) if spec.input_box is not None
                    else cp.norm(U[tau]) <= spec.input_norm)
        if spec.state_bound_norm is not None:
            cons.append(cp.norm(X[tau + 1, list(spec.state_bound_indices)]) <= spec.state_bound_norm)
    for j in range(data.active.shape[1]):
        Y, s = cp.Variable((T + 1, D)), cp.Variable(T, nonneg=True)
        cost += RHO / 2 * (cp.sum_squares(X - n(data.z_own)[j]) + cp.sum_squares(Y - n(data.z_nbr)[j])) \
            + PENALTY * cp.sum(s)
        for tau in range(1, T + 1):
            cons.append(n(data.normals)[j, tau - 1] @ (X[tau] - Y[tau]) + s[tau - 1] >= n(data.bounds)[j, tau - 1])
    cp.Problem(cp.Minimize(cost), cons).solve(solver=cp.CLARABEL, tol_gap_abs=1e-10, tol_gap_rel=1e-10,
                                              tol_feas=1e-10)
    return X.value, U.value


CASES = {
    "double-integrator-2d": (NominalModel(double_integrator(2, 0.1, 2.0)), ("fast", "clarabel", "direct")),
    "double-integrator-3d": (NominalModel(double_integrator(3, 0.1, 2.0)), ("fast", "clarabel", "direct")),
    "model-file-box-and-speed-limit": (NominalModel(box_model()), ("fast", "clarabel", "direct")),
}


@pytest.mark.parametrize("time_varying_b", [False, True])
@pytest.mark.parametrize("case", list(CASES))
def test_general_models_match_a_direct_cvxpy_solve(case, time_varying_b):
    nominal, solvers = CASES[case]
    data = instance(nominal, num_nbr=2, seed=3, time_varying_b=time_varying_b)
    X_ref, U_ref = direct_solve(data, nominal)
    for solver in solvers:
        layer = make_local_solver(T, nominal.dim, 2, nominal, None, ALPHA, PENALTY, solver)
        sol = layer(data)
        assert bool(sol.ok.all()), solver
        assert sol.X.shape == (1, T + 1, nominal.dim) and sol.U.shape == (1, T, nominal.input_dim)
        assert np.abs(sol.X[0].detach().numpy() - X_ref).max() < 1e-5, solver
        assert np.abs(sol.U[0].detach().numpy() - U_ref).max() < 1e-4, solver
    if case.startswith("model-file"):  # the bounds bind: otherwise the test would not test them
        assert np.abs(U_ref).max(axis=0)[0] == pytest.approx(1.5, abs=1e-5) or \
            np.linalg.norm(X_ref[1:, 2:], axis=1).max() == pytest.approx(0.9, abs=1e-5)


def test_fast_solver_gradients_match_finite_differences_for_a_double_integrator():
    """d/d(x0, dyn_B, z_nbr) of a fixed functional of the plan of a 2D double integrator."""
    nominal = NominalModel(double_integrator(2, 0.1, 2.0))
    base = instance(nominal, num_nbr=1, seed=5, time_varying_b=True)
    layer = make_local_solver(T, 4, 1, nominal, None, ALPHA, PENALTY, "fast")
    weights = torch.randn(T + 1, 4, generator=torch.Generator().manual_seed(7), dtype=F64)

    def objective(x0, dyn_B, z_nbr):
        sol = layer(LocalProblemData(**{**base.__dict__, "x0": x0, "dyn_B": dyn_B, "z_nbr": z_nbr}))
        assert bool(sol.ok.all())
        return (sol.X[0] * weights).sum() + sol.cost.sum()

    values = {"x0": base.x0, "dyn_B": base.dyn_B, "z_nbr": base.z_nbr}
    leaves = {k: v.clone().requires_grad_(True) for k, v in values.items()}
    objective(**leaves).backward()
    g = torch.Generator().manual_seed(11)
    for name, value in values.items():
        direction = torch.randn(value.shape, generator=g, dtype=F64)
        h = 1e-4
        with torch.no_grad():
            up = objective(**{**values, name: value + h * direction})
            down = objective(**{**values, name: value - h * direction})
        fd = (up - down).item() / (2 * h)
        assert abs(fd) > 1e-4, name
        assert (leaves[name].grad * direction).sum().item() == pytest.approx(fd, rel=1e-4, abs=1e-7), name
