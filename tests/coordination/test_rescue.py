"""The fast solver's rescue: problems the compiled interior point leaves inaccurate (no
convergence within its iteration cap) are solved again, cold, by the compiled solver at a relaxed
tolerance, and what that leaves by Clarabel (handed the problem directly; through cvxpylayers when
a gradient is wanted), row by row; the other rows keep the fast answers bit for bit."""

from __future__ import annotations

import torch

from torch_gpmpc import ControllerSettings, LocalStep, ModelSpec
from torch_gpmpc.control.examples import crossing_instance
from torch_gpmpc.control.problem import FAIL_INACCURATE
from torch_gpmpc.control.solvers.direct_clarabel import DirectClarabelMPC
from torch_gpmpc.coordination.rescue import RESCUE_MAX_ITER, RESCUE_TOL


def _step_and_data(solver: str = "fast"):
    step = LocalStep(ControllerSettings(method="nominal", horizon=13, solver=solver), ModelSpec.single_integrator(2))
    data = crossing_instance(batch=4, num_neighbors=2, method="nominal").problem_data()
    return step, data


def test_inaccurate_rows_are_solved_again_at_the_relaxed_tolerance_and_the_rest_kept():
    step, data = _step_and_data()
    layer = step.solver(2)
    fast = layer(data)
    assert bool(fast.ok.all())
    layer.max_iter = 3  # no row converges in 3 Newton steps: every row is inaccurate
    capped = layer(data)
    assert bool((capped.failure == FAIL_INACCURATE).all())
    sol = step.solve(layer, data)
    relaxed = LocalStep(step.settings, step.nominal).solver(2)
    relaxed.tol, relaxed.max_iter, relaxed.warm_start = RESCUE_TOL, RESCUE_MAX_ITER, False
    assert bool(sol.ok.all()) and step.rescued_solves == 4
    torch.testing.assert_close(sol.X, relaxed(data).X, rtol=0, atol=0)  # the compiled solver's own answers
    torch.testing.assert_close(sol.X, fast.X, rtol=0, atol=1e-7)   # the plans of a solve at 1e-10
    layer.max_iter = 100
    again = step.solve(layer, data)
    torch.testing.assert_close(again.X, fast.X, rtol=0, atol=0)  # nothing to rescue: the fast answers
    assert step.rescued_solves == 4


def test_what_the_relaxed_solve_leaves_goes_to_clarabel_directly():
    step, data = _step_and_data()
    layer = step.solver(2)
    fast = layer(data)
    layer.max_iter = 3
    step.rescue.solver("fast", 2).max_iter = 3  # the relaxed solve fails too
    sol = step.solve(layer, data)
    direct = DirectClarabelMPC(13, 2, 2, step.nominal, None, step.settings.alpha, step.settings.slack_penalty,
                               constraints=step.constraints)(data)
    assert bool(sol.ok.all()) and step.rescued_solves == 4
    torch.testing.assert_close(sol.X, direct.X, rtol=0, atol=0)  # Clarabel's own answers
    torch.testing.assert_close(sol.X, fast.X, rtol=0, atol=1e-6)   # and the same plans as a converged fast solve
    assert ("clarabel", 2) not in step.rescue._solvers  # no cvxpylayers layer was built


def test_with_a_gradient_wanted_the_last_rung_is_the_differentiable_reference_path():
    step, data = _step_and_data()
    layer = step.solver(2)
    layer.max_iter = 3
    step.rescue.solver("fast", 2).max_iter = 3
    x0 = data.x0.clone().requires_grad_(True)
    sol = step.solve(layer, type(data)(**{**data.__dict__, "x0": x0}))
    reference = LocalStep(step.settings.replace(solver="clarabel"), step.nominal).solver(2)(data)
    assert bool(sol.ok.all()) and step.rescued_solves == 4
    torch.testing.assert_close(sol.X.detach(), reference.X.detach(), rtol=0, atol=0)
    sol.X[:, 1].sum().backward()
    assert x0.grad is not None and bool(torch.isfinite(x0.grad).all()) and float(x0.grad.abs().sum()) > 0


def test_a_rescued_row_keeps_its_gradient():
    step, data = _step_and_data()
    layer = step.solver(2)
    layer.max_iter = 3
    x0 = data.x0.clone().requires_grad_(True)
    sol = step.solve(layer, type(data)(**{**data.__dict__, "x0": x0}))
    sol.X[:, 1].sum().backward()
    assert x0.grad is not None and bool(torch.isfinite(x0.grad).all()) and float(x0.grad.abs().sum()) > 0


def test_other_solvers_are_left_alone():
    step, data = _step_and_data("clarabel")
    sol = step.solve(step.solver(2), data)
    assert bool(sol.ok.all()) and step.rescued_solves == 0
