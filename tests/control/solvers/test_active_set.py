"""The warm active-set solves of the fast solver (:mod:`torch_gpmpc.control.solvers.ipm_active`):
from the previous solve's point they return the optimum of the next problem, checked against a
direct cvxpy solve, against the cold interior point, and on the problem sequences of closed loops."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from torch_gpmpc.bench.warm import QUADROTOR, measure
from torch_gpmpc.config.schema import Config
from torch_gpmpc.control.problem import LocalProblemData
from tests.control.solvers.test_constraint_families import FAMILIES, direct_solve, family_problem, solver_for

#: the reference solves of this module run Clarabel at 1e-11 tolerances: cvxpy and diffcp say
#: "inaccurate" where it stops a little short, which the comparisons' own tolerances cover
pytestmark = [pytest.mark.filterwarnings("ignore:Solution may be inaccurate:UserWarning"),
              pytest.mark.filterwarnings("ignore:Solved/Inaccurate:UserWarning")]


F64 = torch.float64


def next_iteration(data: LocalProblemData, seed: int, size: float = 0.02) -> LocalProblemData:
    """``data`` as ADMM's next iteration would pose it: the consensus values moved a little (the
    duals stay 0, as :func:`direct_solve` has no dual terms)."""
    g = torch.Generator().manual_seed(seed)

    def nudge(t):
        return t + size * torch.randn(t.shape, generator=g, dtype=F64)

    return dataclasses.replace(data, z_own=nudge(data.z_own), z_nbr=nudge(data.z_nbr))


@pytest.mark.parametrize("family", FAMILIES)
@pytest.mark.parametrize("model", ["single-integrator-2d", "double-integrator-3d", "model-file-skewed-B-2d"])
def test_a_warm_solve_matches_a_direct_cvxpy_solve(model, family):
    nominal, c, data, _ = family_problem(model, family)
    layer, cold = solver_for(nominal, c), solver_for(nominal, c).with_warm_start(False)
    first = layer(data)  # a cold solve; its point is the next call's guess
    after = next_iteration(data, seed=1)
    sol = layer(after, guess=first.solver_point)
    assert layer.last_warm_rows == 1, "the warm path did not solve the next iteration's problem"
    X_ref, U_ref = direct_solve(after, nominal, c)
    assert bool(sol.ok.all())
    assert np.abs(sol.X[0].numpy() - X_ref).max() < 1e-6
    # the inputs to 1e-4 only: Clarabel calls one reference (3D state box) inaccurate, 1.2e-5 off
    # the cold interior point, which the warm solve matches to 1e-14
    assert np.abs(sol.U[0].numpy() - U_ref).max() < 1e-4
    again = cold(after)
    assert (sol.X - again.X).abs().max() < 1e-7 and (sol.U - again.U).abs().max() < 1e-6
    assert (sol.Y - again.Y).abs().max() < 1e-7
    assert (sol.slack - again.slack).abs().max() < 1e-7 and (sol.state_slack - again.state_slack).abs().max() < 1e-7


def test_a_guess_from_another_problem_still_gives_that_problems_optimum():
    """A wrong active set costs rounds or a cold solve, never accuracy."""
    nominal, c, data, _ = family_problem("double-integrator-3d", "all")
    other = family_problem("double-integrator-3d", "state-box")[2]
    layer, cold = solver_for(nominal, c), solver_for(nominal, c).with_warm_start(False)
    guess = layer(other).solver_point
    for target in (data, next_iteration(data, seed=2, size=0.5), other):
        sol, ref = layer(target, guess=guess), cold(target)
        guess = sol.solver_point
        assert bool(sol.ok.all()) and (sol.X - ref.X).abs().max() < 1e-7 and (sol.U - ref.U).abs().max() < 1e-6


@pytest.mark.parametrize("family", ["input-norm-and-box", "input-box"])
def test_a_diverging_warm_solve_stops_at_once_and_is_solved_cold(family, monkeypatch):
    """A guess whose first Newton step moves an input by more than ``DIVERGED_STEP`` times the input
    bound is given up after that round (not after ``ACTIVE_SET_ROUNDS``) and solved cold; a guess
    off by less keeps its rounds and solves warm."""
    from torch_gpmpc.control.solvers import ipm_active, ipm_threads

    nominal, c, data, _ = family_problem("double-integrator-3d", family)
    layer, cold = solver_for(nominal, c), solver_for(nominal, c).with_warm_start(False)
    good = layer(data).solver_point
    rounds = []
    active_set_batch = ipm_threads.active_set_batch

    def recorded(*args):
        active_set_batch(*args)
        rounds.append((bool(args[-3][0]), int(args[-2][0])))

    monkeypatch.setattr(ipm_threads, "active_set_batch", recorded)
    bound = float(c.input_norm) if c.input_norm is not None else float(max(c.input_box))
    ref = cold(data)
    assert ipm_active.DIVERGED_STEP < 1000  # the first guess is off by more than the stop allows
    for offset, warm in ((1000 * bound, False), (0.1 * bound, True)):
        guess = good.copy()
        guess.u += offset  # inputs far off the optimum, the classes still the optimum's
        sol = layer(data, guess=guess)
        assert layer.last_warm_rows == int(warm)
        assert rounds[-1][0] if warm else rounds[-1] == (False, 1)
        assert bool(sol.ok.all()) and (sol.X - ref.X).abs().max() < 1e-7 and (sol.U - ref.U).abs().max() < 1e-6


def test_gradients_are_taken_on_the_cold_path_and_are_unchanged():
    nominal, c, data, _ = family_problem("double-integrator-3d", "all")
    layer, cold = solver_for(nominal, c), solver_for(nominal, c).with_warm_start(False)
    guess = layer(data).solver_point
    grads = []
    for solver in (layer, cold):
        rho = torch.tensor(float(data.rho), dtype=F64, requires_grad=True)
        sol = solver(dataclasses.replace(data, rho=rho), guess=guess)
        (sol.X.sum() + sol.Y.sum()).backward()
        grads.append(rho.grad)
    assert layer.last_warm_rows == 0
    assert torch.equal(grads[0], grads[1])


@pytest.mark.parametrize("name, cfg", [
    ("paper", Config(admm_coupling="copies", max_steps=8)),
    ("quadrotor demo (input norm, speed limit)", Config(admm_coupling="copies", model=QUADROTOR, scenario="circle",
                                                        num_agents=4, noise_std=0.03, max_steps=5)),
])
def test_recorded_closed_loop_problems_solve_warm_to_the_cold_plans(name, cfg):
    """The local problems of a closed loop, replayed in ADMM's order (bench.warm): the same plans to
    1e-6 and the same accepted problems; the whole run warm takes the same ADMM iterations."""
    row = measure(name, cfg)
    assert row["max_abs_plan_diff"] < 1e-6 and row["same_acceptance"]
    assert row["warm_fraction"] > 0.9
    assert row["admm_iterations_warm"] == row["admm_iterations_cold"]
