"""The compiled acceptance rule (control.acceptance via problem.acceptance_failures) against the rule
written out in NumPy, on solved plans of every constraint family and on plans perturbed across the
tolerance (dynamics, start, inputs, slacks, collision rows, non-finite values, inactive slots)."""

import numpy as np
import pytest
import torch

from torch_gpmpc.bench.local import ALPHA, HORIZON, NEIGHBORS, _HALFSPACES, family_problem
from torch_gpmpc.control.problem import (
    FAIL_INACCURATE, FAIL_NONE, FAIL_NONFINITE, FEASIBILITY_TOL, LocalProblemData, acceptance_failures,
)
from torch_gpmpc.control.solvers.interior_point import InteriorPointMPC


def numpy_rule(data: LocalProblemData, X, U, Y, S, B_nom, constraints) -> np.ndarray:
    """The acceptance rule as array expressions (the reference)."""
    X, U, Y, S = (t.detach().numpy() for t in (X, U, Y, S))
    batch = X.shape[0]
    finite = np.array([all(np.isfinite(a[b]).all() for a in (X, U, Y, S)) for b in range(batch)])
    X, U, Y, S = (np.nan_to_num(a) for a in (X, U, Y, S))
    scale = 1.0 + np.abs(X.reshape(batch, -1)).max(1)
    Bd = B_nom.numpy() if data.dyn_B is None else data.dyn_B.numpy()
    drive = (np.broadcast_to(Bd, (batch, *U.shape[1:2], *Bd.shape[-2:])) @ U[..., None])[..., 0]
    pred = (data.dyn_A.numpy() @ X[:, :-1, :, None])[..., 0] + drive + data.dyn_c.numpy()
    dyn = np.abs(X[:, 1:] - pred).reshape(batch, -1).max(1)
    init = np.abs(X[:, 0] - data.x0.numpy()).max(1)
    u_res = np.zeros(batch)
    if constraints.input_box is not None:
        u_res = np.maximum(u_res, (np.abs(U) - np.asarray(constraints.input_box)).reshape(batch, -1).max(1))
    if constraints.input_norm is not None:
        u_res = np.maximum(u_res, (np.linalg.norm(U, axis=-1) - constraints.input_norm).max(1))
    s_res = (-S).reshape(batch, -1).max(1, initial=0.0)
    gap = (data.normals.numpy() * (X[:, None, 1:] - Y[:, :, 1:])).sum(-1)
    viol = np.where(data.active.numpy()[:, :, None], data.bounds.numpy() - gap - S, 0.0)
    c_res = viol.reshape(batch, -1).max(1, initial=0.0)
    tol = FEASIBILITY_TOL
    ok = (dyn <= tol * scale) & (init <= tol * scale) & (u_res <= tol * (1 + constraints.input_scale)) \
        & (s_res <= tol * scale) & (c_res <= tol * scale)
    return np.where(finite, np.where(ok, FAIL_NONE, FAIL_INACCURATE), FAIL_NONFINITE)


def _perturbations(sol, scale: float):
    """Named copies of (X, U, Y, S) with one part moved by ``scale``."""
    X, U, Y, S = (t.detach().clone() for t in (sol.X, sol.U, sol.Y, sol.slack))
    yield "solved", (X, U, Y, S)
    for name, (i, idx) in {"dynamics": (0, (0, 5, 1)), "start": (0, (1, 0, 0)), "input": (1, (2, 3, 0)),
                           "copy": (2, (0, 1, 4, 0)), "slack": (3, (1, 0, 2))}.items():
        parts = [X.clone(), U.clone(), Y.clone(), S.clone()]
        parts[i][idx] += scale if name != "slack" else -scale
        yield name, tuple(parts)
    parts = [X.clone(), U.clone(), Y.clone(), S.clone()]
    parts[1][1] *= 1.0 + scale  # every input of problem 1 scaled out past its bound
    yield "inputs scaled", tuple(parts)
    parts = [X.clone(), U.clone(), Y.clone(), S.clone()]
    parts[0][2, 3, 0] = float("nan")
    yield "non-finite", tuple(parts)


@pytest.mark.parametrize("family", ["input-norm", "input-box", "input-norm-and-box", "all"])
@pytest.mark.parametrize("scale", [1e-7, 1e-4, 1e-2])
def test_compiled_rule_matches_numpy(family, scale):
    nominal, constraints, _ = family_problem(family, 1)
    data = family_problem(family, 4, seed=1)[2]
    data.active[3, 1] = False  # an inactive slot: its rows do not count
    layer = InteriorPointMPC(HORIZON, 6, NEIGHBORS, nominal, None, ALPHA, constraints=constraints,
                             num_halfspaces=_HALFSPACES)
    with torch.no_grad():
        sol = layer(data)
    B_nom = nominal.B(torch.float64)
    seen = set()
    for name, (X, U, Y, S) in _perturbations(sol, scale):
        got = acceptance_failures(data, X, U, Y, S, B_nom, constraints).numpy()
        want = numpy_rule(data, X, U, Y, S, B_nom, constraints)
        assert got.tolist() == want.tolist(), name
        seen.update(got.tolist())
    assert FAIL_NONE in seen and FAIL_NONFINITE in seen
    if scale >= 1e-4:
        assert FAIL_INACCURATE in seen


def test_per_step_input_matrices():
    """``dyn_B`` given per problem and step (GPs that read the input) is the one checked."""
    nominal, constraints, _ = family_problem("input-norm", 1)
    data = family_problem("input-norm", 3, seed=2)[2]
    layer = InteriorPointMPC(HORIZON, 6, NEIGHBORS, nominal, None, ALPHA, constraints=constraints,
                             num_halfspaces=_HALFSPACES)
    B_nom = nominal.B(torch.float64)
    dyn_B = B_nom.expand(3, HORIZON, *B_nom.shape).clone()
    dyn_B[1] *= 1.5
    data = LocalProblemData(**{**vars(data), "dyn_B": dyn_B})
    with torch.no_grad():
        sol = layer(data)
    got = acceptance_failures(data, sol.X, sol.U, sol.Y, sol.slack, B_nom, constraints).numpy()
    assert got.tolist() == [FAIL_NONE] * 3
    nominal_only = LocalProblemData(**{**vars(data), "dyn_B": None})
    got = acceptance_failures(nominal_only, sol.X, sol.U, sol.Y, sol.slack, B_nom, constraints).numpy()
    want = numpy_rule(nominal_only, sol.X, sol.U, sol.Y, sol.slack, B_nom, constraints)
    assert got.tolist() == want.tolist() and got[1] == FAIL_INACCURATE
