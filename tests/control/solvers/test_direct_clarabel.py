"""Clarabel handed the condensed problem directly (no cvxpy, no gradients): the same plans, copies,
slacks and collision multipliers as the fast solver and the cvxpylayers path on crossing instances
with active and inactive slots, in ~1 ms a problem with nothing to build. The families of state
constraints, the input-rate term and a stated cost are compared with direct cvxpy solves in
test_constraint_families, test_input_rate and test_cost."""

from __future__ import annotations

import pytest
import torch

from torch_gpmpc import CvxpyLayerMPC, GpmpcError, InteriorPointMPC, NominalModel
from torch_gpmpc.control.examples import crossing_instance
from torch_gpmpc.control.problem import FAIL_NONE, FAIL_NONFINITE, LocalProblemData
from torch_gpmpc.control.solvers.direct_clarabel import DirectClarabelMPC


def _args(M: int) -> tuple:
    return 13, 2, M, NominalModel(2), 2.0, 1e-3


@pytest.mark.parametrize("M", [0, 1, 3])
def test_plans_copies_slacks_and_multipliers_equal_the_fast_solvers(M):
    data = crossing_instance(batch=4, num_neighbors=M, method="nominal", seed=M).problem_data()
    direct = DirectClarabelMPC(*_args(M))(data)
    fast = InteriorPointMPC(*_args(M))(data)
    assert bool(direct.ok.all()) and bool(fast.ok.all())
    # Clarabel stops at its own tolerances: plans within 1e-6 (the cvxpy comparisons' bound), inputs 1e-5
    for name, atol in (("X", 1e-6), ("U", 1e-5), ("Y", 1e-6), ("slack", 1e-6), ("cost", 1e-7), ("multipliers", 1e-5)):
        torch.testing.assert_close(getattr(direct, name), getattr(fast, name), rtol=0, atol=atol, msg=name)


def test_plans_equal_the_cvxpylayers_path():
    data = crossing_instance(batch=3, num_neighbors=2, method="nominal", seed=5).problem_data()
    direct = DirectClarabelMPC(*_args(2))(data)
    reference = CvxpyLayerMPC(*_args(2), solver="clarabel")(data)
    torch.testing.assert_close(direct.X, reference.X.detach(), rtol=0, atol=1e-6)


def test_inactive_slots_leave_the_plan_as_without_them():
    data = crossing_instance(batch=2, num_neighbors=2, method="nominal", seed=1).problem_data()
    active = data.active.clone()
    active[:, 1] = False
    masked = LocalProblemData(**{**data.__dict__, "active": active})
    direct = DirectClarabelMPC(*_args(2))(masked)
    fast = InteriorPointMPC(*_args(2))(masked)
    assert bool(direct.ok.all())
    torch.testing.assert_close(direct.X, fast.X, rtol=0, atol=1e-6)


def test_a_gradient_request_is_refused_by_name():
    data = crossing_instance(batch=1, num_neighbors=1, method="nominal").problem_data()
    x0 = data.x0.clone().requires_grad_(True)
    with pytest.raises(GpmpcError, match="no gradients"):
        DirectClarabelMPC(*_args(1))(LocalProblemData(**{**data.__dict__, "x0": x0}))
    with torch.no_grad():  # without autograd the same data is solved
        assert bool(DirectClarabelMPC(*_args(1))(LocalProblemData(**{**data.__dict__, "x0": x0})).ok.all())


@pytest.mark.parametrize("field", ["x0", "bounds", "z_nbr", "xref"])
def test_non_finite_data_fails_that_problem_only_as_non_finite(field):
    data = crossing_instance(batch=3, num_neighbors=1, method="nominal").problem_data()
    value = getattr(data, field).clone()
    value[1].view(-1)[-1] = float("nan")  # the last entry: xref[0] is not in the problem
    sol = DirectClarabelMPC(*_args(1))(LocalProblemData(**{**data.__dict__, field: value}))
    assert sol.ok.tolist() == [True, False, True]
    assert sol.failure.tolist() == [FAIL_NONE, FAIL_NONFINITE, FAIL_NONE]  # as the fast solver says
    assert bool(torch.isfinite(sol.X).all()) and bool(torch.isfinite(sol.Y).all())


def test_make_local_solver_builds_it_and_names_every_backend_on_a_wrong_one():
    from torch_gpmpc import make_local_solver

    assert isinstance(make_local_solver(13, 2, 1, NominalModel(2), 2.0, 1e-3, solver="direct"), DirectClarabelMPC)
    with pytest.raises(GpmpcError, match="fast, clarabel, reference, direct"):
        make_local_solver(13, 2, 1, NominalModel(2), 2.0, 1e-3, solver="Direct")
