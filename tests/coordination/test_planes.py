"""Plane coupling (``admm_coupling = planes``): the same team problem as the copies, solved by
consensus on one separating-plane offset per edge and horizon step."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from torch_gpmpc.coordination.agent_step import LocalStep
from torch_gpmpc.config.schema import Config
from torch_gpmpc.config.settings import ControllerSettings
from torch_gpmpc.control.examples import crossing_instance
from torch_gpmpc.coordination.admm import ADMM
from torch_gpmpc.coordination.agent_step import message_size
from torch_gpmpc.coordination.centralized import solve_centralized
from torch_gpmpc.coordination.graph import communication_graph, graph_from_edges
from torch_gpmpc.coordination.planes import (
    PLANE_MAX_MOVE, PLANE_PIN, SAFE, SAFE_NOW, UNSAFE, SafeIterates, end_multipliers, midpoint_planes, plane_geometry,
    plane_problem, plane_residuals, plane_update, unsafe_ends,
)
from torch_gpmpc.coordination.state import adapt_state, initial_state
from torch_gpmpc.dynamics.systems import NominalModel
from torch_gpmpc.errors import GpmpcError
from torch_gpmpc.sim.closed_loop import simulate
from torch_gpmpc.sim.metrics import compute_metrics

TIGHT = dict(admm_tol=1e-7, admm_dual_tol=1e-7, admm_rel_tol=0.0, admm_max_iter=3000)


def _crossing(num_agents: int = 4, jitter: float = 0.0):
    """``num_agents`` on a circle of radius 1, each heading for its antipode (all pairs coupled);
    ``jitter``: the starts moved by up to that much (seeded), which breaks the symmetry."""
    angles = 2 * torch.pi * torch.arange(num_agents, dtype=torch.float64) / num_agents
    x0 = torch.stack([angles.cos(), angles.sin()], dim=1)
    x0 = x0 + jitter * torch.rand(x0.shape, generator=torch.Generator().manual_seed(num_agents), dtype=torch.float64)
    xref = x0[:, None] + torch.linspace(0, 1, 9, dtype=torch.float64)[None, :, None] * (-2 * x0)[:, None]
    return x0, xref, communication_graph(x0, None)


@pytest.mark.parametrize("method", ["nominal", "nominal-chance"])
def test_planes_reach_the_centralized_optimum_and_the_copies_plans(method):
    """Run to a tight tolerance from a cold start on an asymmetric crossing, the plane steps give the
    plans of an independent centralized cvxpy solve of the same step problem (to the pin's give,
    ``mu / PLANE_PIN``), and the copies' plans."""
    from tests.helpers import ConstantVarianceGP

    cfg = Config(admm_coupling="copies", horizon=8, rho=5.0, noise_std=0.0, **TIGHT)
    gps = [ConstantVarianceGP(0.01)] * 4 if method.endswith("chance") else None
    x0, xref, graph = _crossing(jitter=0.3)
    planes = ADMM(LocalStep(cfg.replace(admm_coupling="planes", admm_tol=1e-6, admm_max_iter=1000), NominalModel(2),
                            method, None, gps)).solve_step(x0, xref, graph)
    copies = ADMM(LocalStep(cfg, NominalModel(2), method, None, gps)).solve_step(x0, xref, graph)
    assert copies.converged
    # the chance margins' optimum sits where a half starts to bind (a kink of the team cost in the
    # offset): the gradient steps settle there more slowly
    atol = 2e-4 if method == "nominal" else 2e-3
    central = solve_centralized(planes.problem, graph, NominalModel(2), cfg.u_max, cfg.alpha, cfg.slack_penalty)
    np.testing.assert_allclose(planes.plans.numpy(), central.plans.numpy(), atol=atol)
    np.testing.assert_allclose(planes.plans.numpy(), copies.plans.numpy(), atol=atol)
    assert planes.slack_max < 1e-6
    # a pair row is active: the coupling is really tested
    data, (k, m) = planes.problem, torch.nonzero(graph.active, as_tuple=True)
    gap = (data.normals[k, m] * (central.plans[k, 1:] - central.plans[graph.slot_nbr[k, m], 1:])).sum(-1) - data.bounds[k, m]
    assert float(gap.min()) < 1e-5


@pytest.mark.parametrize("iterations", [1, 2, 3, 5, 10, 30])
def test_every_iterate_keeps_every_pair_and_the_cost_falls_towards_the_optimum(iterations):
    """Stopped at any iteration, the plans keep every pair's row at every horizon step (each end
    keeps its half of one shared plane: no fallback acts), and their team cost approaches the
    centralized optimum's as the budget grows (6 agents crossing, asymmetric)."""
    cfg = Config(horizon=8, noise_std=0.0, admm_coupling="planes", admm_max_iter=iterations)
    x0, xref, graph = _crossing(6, jitter=0.3)
    res = ADMM(LocalStep(cfg, NominalModel(2), "nominal")).solve_step(x0, xref, graph)
    assert not res.fallback and not res.unsafe_plan
    data, (k, m) = res.problem, torch.nonzero(graph.active, as_tuple=True)
    sep = torch.linalg.vector_norm(res.plans[k, 1:] - res.plans[graph.slot_nbr[k, m], 1:], dim=-1)
    assert float((sep - data.bounds[k, m]).min()) > -1e-3  # the pin's give under large multipliers
    central = solve_centralized(res.problem, graph, NominalModel(2), cfg.u_max, cfg.alpha, cfg.slack_penalty)
    cost = float(res.solution.cost.sum())
    optimum = float(((central.plans - xref) ** 2).sum() + cfg.alpha * (central.inputs ** 2).sum())
    assert cost >= optimum - 1e-6
    gaps = test_every_iterate_keeps_every_pair_and_the_cost_falls_towards_the_optimum.gaps
    gaps[iterations] = cost - optimum
    if iterations == 30:
        assert gaps[30] < gaps[1] / 3 and gaps[30] <= gaps[10] + 1e-9


test_every_iterate_keeps_every_pair_and_the_cost_falls_towards_the_optimum.gaps = {}


def test_a_converged_step_keeps_every_row_less_the_tolerance():
    """The planes' primal test bounds each end's offset within admm_tol / 2 of the consensus, so
    the two halves of a pair overlap by at most admm_tol: every row holds to admm_tol."""
    cfg = Config(horizon=8, noise_std=0.0, admm_coupling="planes")
    x0, xref, graph = _crossing(6)
    res = ADMM(LocalStep(cfg, NominalModel(2), "nominal")).solve_step(x0, xref, graph)
    assert res.converged
    data, (k, m) = res.problem, torch.nonzero(graph.active, as_tuple=True)
    gap = (data.normals[k, m] * (res.plans[k, 1:] - res.plans[graph.slot_nbr[k, m], 1:])).sum(-1) - data.bounds[k, m]
    assert float(gap.min()) > -cfg.admm_tol
    assert float(gap.min()) < 1e-3  # and some row is tight


def test_plane_problem_pins_both_halves_to_one_plane_and_the_copies_read_the_solvers_multipliers():
    """The local problems of the planes: slot rows ``+-n`` with bound d/2, both ends' copies pinned
    to the same offset ``c n``; each plan keeps its half (to the pin's give), and the multipliers read
    off the pinned copies (``PLANE_PIN`` times how far the copy gave) equal the solver's own row
    multipliers (an independent reading of the same KKT point)."""
    data = crossing_instance(batch=2, num_neighbors=1, method="nominal").problem_data()
    graph = graph_from_edges(2, [(0, 1)])
    # make the two slots one edge's ends: agent 1's normal is agent 0's negated
    data = dataclasses.replace(data, normals=torch.stack([data.normals[0], -data.normals[0]]),
                               bounds=torch.stack([data.bounds[0], data.bounds[0] + 0.1]))
    geometry = plane_geometry(data, graph)
    assert torch.equal(geometry.distance, data.bounds[1])  # the larger end's bound
    planes = torch.full((1, data.bounds.shape[-1]), 0.1, dtype=torch.float64)
    problem = plane_problem(data, geometry, planes)
    assert torch.equal(problem.normals[1], -problem.normals[0]) and torch.equal(problem.bounds[0], geometry.distance / 2)
    assert float(problem.rho) == 0.0 and torch.equal(problem.rho_nbr, torch.full((2, 1), PLANE_PIN, dtype=torch.float64))
    for k in range(2):
        np.testing.assert_allclose((geometry.normals[0] * problem.z_nbr[k, 0, 1:]).sum(-1), planes[0])
    from torch_gpmpc import make_local_solver

    sol = make_local_solver(13, 2, 1, NominalModel(2), 2.0, 1e-3)(problem)
    assert bool(sol.ok.all()) and sol.multipliers is not None
    half = geometry.distance[0] / 2
    lo = (geometry.normals[0] * sol.X[0, 1:]).sum(-1)
    hi = (geometry.normals[0] * sol.X[1, 1:]).sum(-1)
    # each half holds, softened by its slack where the problem cannot keep it, less the pin's give
    # (at most the slack price over the pin)
    give = 1e4 / PLANE_PIN + 1e-6
    assert float((lo - planes[0] - half + sol.slack[0, 0]).min()) > -give
    assert float((planes[0] - half - hi + sol.slack[1, 0]).min()) > -give
    from_solver = end_multipliers(sol.multipliers, sol.Y, sol.ok, geometry, planes)
    from_copies = end_multipliers(None, sol.Y, sol.ok, geometry, planes)
    assert float(from_solver.max()) > 0.1  # a half binds
    np.testing.assert_allclose(from_solver.numpy(), from_copies.numpy(), rtol=1e-4, atol=1e-4)


def test_plane_update_steps_against_the_multiplier_difference_and_backs_off_when_it_overshoots():
    """Closed form: ``c - (mu_lo - mu_hi) / (2 rho)``, capped at PLANE_MAX_MOVE of the distance; a
    gradient that changed sign doubles that coordinate's rho, one that kept it eases it back towards
    the starting rho; the residual is the move at the starting rho."""
    mu = torch.tensor([[[3.0, 0.0, 100.0], [1.0, 2.0, 0.0]]], dtype=torch.float64)
    planes, rho0 = torch.zeros(1, 3, dtype=torch.float64), torch.tensor(2.0, dtype=torch.float64)
    distance = torch.tensor([[5.0, 5.0, 0.5]], dtype=torch.float64)
    first = plane_update(mu, planes, rho0.expand(1, 3).clone(), None, distance, rho0)
    assert torch.allclose(first.gradient, torch.tensor([[2.0, -2.0, 100.0]], dtype=torch.float64))
    assert torch.allclose(first.planes, torch.tensor([[-0.5, 0.5, -PLANE_MAX_MOVE * 0.5]], dtype=torch.float64))
    assert torch.allclose(first.move, torch.tensor([25.0], dtype=torch.float64))
    flipped = torch.tensor([[[0.0, 0.0, 100.0], [1.0, 1.0, 0.0]]], dtype=torch.float64)  # -1, -1, 100
    rho = torch.tensor([[2.0, 8.0, 8.0]], dtype=torch.float64)
    second = plane_update(flipped, first.planes, rho, first.gradient, distance, rho0)
    assert torch.allclose(second.rho, torch.tensor([[4.0, 8.0 / 1.25, 8.0 / 1.25]], dtype=torch.float64))


def test_unsafe_ends_grade_how_near_a_plan_leaves_its_half_and_the_step_applies_the_safest_latest():
    """An end whose plan crosses its half by more than tol / 2 at tau = 1 makes its edge UNSAFE, only
    at tau = 2 SAFE_NOW, only later SAFE (the later steps are planned again); a step applies the
    latest SAFE iterate, else the latest SAFE_NOW, else none."""
    T = 3
    geometry = plane_geometry(dataclasses.replace(
        crossing_instance(batch=2, num_neighbors=1, method="nominal", horizon=T).problem_data(),
        normals=torch.tensor([[1.0, 0.0], [-1.0, 0.0]], dtype=torch.float64)[:, None, None].expand(2, 1, T, 2).clone(),
        bounds=torch.full((2, 1, T), 0.5, dtype=torch.float64)), graph_from_edges(2, [(0, 1)]))
    planes = torch.zeros(1, T, dtype=torch.float64)
    plans = torch.zeros(2, T + 1, 2, dtype=torch.float64)
    plans[0, 1:, 0], plans[1, 1:, 0] = 0.25, -0.25  # both halves just kept

    def level():
        return float(unsafe_ends(plans, geometry, planes, 1e-3)[0])

    assert level() == SAFE
    plans[1, 3, 0] = 0.0  # hi crosses at tau = 3: left to the next steps
    assert level() == SAFE
    plans[1, 2, 0] = -0.2496  # within tol / 2 at tau = 2
    assert level() == SAFE
    plans[1, 2, 0] = -0.2  # 5 cm across at tau = 2
    assert level() == SAFE_NOW
    plans[0, 1, 0] = 0.2
    assert level() == UNSAFE
    res = plane_residuals(torch.tensor([1e-4], dtype=torch.float64), torch.tensor([UNSAFE]), ControllerSettings())
    assert float(res.primal_ratio) == 0.2 and float(res.dual_ratio) == 1.0  # an unsafe iterate never stops a step
    kept = SafeIterates()
    one, two, three = (torch.full((1,), float(i)) for i in range(3))
    kept.record(SAFE_NOW, one, one)
    assert kept.best()[0] is one
    kept.record(SAFE, two, two)
    kept.record(SAFE_NOW, three, three)
    kept.record(UNSAFE, three, three)
    assert kept.best()[0] is two


def test_midpoint_planes_split_the_linearization_plans():
    x0, _, graph = _crossing(2)
    state = initial_state(x0, 4, graph)
    data = crossing_instance(batch=2, num_neighbors=1, method="nominal", horizon=4).problem_data()
    n = (x0[0] - x0[1]) / (x0[0] - x0[1]).norm()
    data = dataclasses.replace(data, normals=torch.stack([n, -n])[:, None, None].expand(2, 1, 4, 2).clone())
    planes = midpoint_planes(plane_geometry(data, graph), state.plans, graph, [0, 1])
    np.testing.assert_allclose(planes, torch.full((1, 4), float(n @ (x0[0] + x0[1]) / 2)), atol=1e-15)


def test_shifted_states_restart_the_planes_and_keep_nothing_of_their_steps():
    x0, _, graph = _crossing(3)
    state = dataclasses.replace(initial_state(x0, 4, graph), planes=torch.ones(3, 4, dtype=torch.float64),
                                plane_gradient=torch.ones(3, 4, dtype=torch.float64),
                                plane_rho=torch.ones(3, 4, dtype=torch.float64))
    shifted = state.shifted()
    assert shifted.planes is None and shifted.plane_gradient is None and shifted.plane_rho is None


def test_messages_carry_the_planes_multipliers():
    s = ControllerSettings(admm_coupling="copies", method="nominal", horizon=13)
    assert message_size(s, 2) == 2 * 14 * 2
    assert message_size(s.replace(admm_coupling="planes"), 2) == 13
    # the variances (and the rows) are agreed once per step, not sent with every iteration's offsets
    assert message_size(s.replace(admm_coupling="planes", method="gp-chance"), 4) == 13


def test_planes_refuse_what_they_do_not_support_yet():
    with pytest.raises(GpmpcError, match="config key 'admm_coupling'.*relinearize=false"):
        Config(relinearize=True)
    with pytest.raises(GpmpcError, match="controller setting 'admm_coupling'.*relinearize=false"):
        ControllerSettings(relinearize=True)


def test_a_mixed_team_crosses_the_vortex_on_planes_without_violation():
    """2 double-integrator drones (radius 0.2) and 2 single-integrator robots (0.3) alternating on a
    circle through the vortex, learned GPs, noiseless: every agent arrives and every pair keeps
    ``r_k + r_j`` (the plane halves carry each pair's own distance)."""
    cfg = Config(scenario="circle", num_agents=4, noise_std=0.0, admm_coupling="planes", pair_buffer=0.01,
                 models=["double-integrator", "single-integrator"] * 2, radii=[0.2, 0.3] * 2, gp_iters=20)
    m = compute_metrics(simulate(cfg))
    assert m["violations"] == 0 and m["arrival_step_max"] is not None


def test_tuning_gradients_through_the_planes_match_finite_differences():
    """``gpmpc tune``'s objective through the unrolled plane steps (4 iterations, 2 MPC steps, sum
    margins): d loss / d (log rho, the three pair splits) against Richardson-extrapolated central
    differences (rho, the inverse step of the planes, moves the loss little in 4 iterations)."""
    from tests.tuning.test_tuner import _gradient_and_differences, _small_objective
    from torch_gpmpc.tuning import TuneSettings, TuningParameters

    settings = TuneSettings(admm_iters=4, mpc_steps=2)
    objective = _small_objective([0], settings, pair_margin="sum", admm_coupling="planes")
    params = TuningParameters(3, rho=5.0)
    with torch.no_grad():
        params.theta[0, 1], params.theta[0, 2], params.theta[1, 2] = 0.3, -0.2, 0.1
    objective(params).loss.backward()
    grad, fd = _gradient_and_differences(objective, params)
    assert abs(grad[0]) > 1e-7 and all(abs(g) > 1e-4 for g in grad[1:]), grad
    for g, d in zip(grad, fd, strict=True):
        assert abs(g - d) <= 1e-6 * abs(d) + 1e-10, (grad, fd)


def test_paper_scenario_with_planes_arrives_safely_noiseless():
    """The paper's three agents (learned GPs, sound margins) through the vortex without noise: every
    agent arrives, no pair closer than r_safe less the consensus tolerance."""
    cfg = Config(noise_std=0.0, admm_coupling="planes", gp_iters=20)
    m = compute_metrics(simulate(cfg))
    assert m["arrival_step_max"] is not None and m["arrival_step_max"] <= 60
    assert m["min_pair_distance"] > cfg.r_safe - cfg.admm_tol
    assert m["fallback_steps"] == 0


@pytest.mark.parametrize("changes", [{}, {"rho": 5.0, "admm_max_iter": 8}])
def test_compiled_plane_iterations_give_the_torch_paths_closed_loop_bit_for_bit(changes):
    """``admm_compiled`` runs a step's plane iterations after its first on the kept problems: the
    same plans and states as every iteration through the torch path (8 agents crossing, noisy)."""
    cfg = Config(scenario="circle", num_agents=8, method="nominal", admm_coupling="planes", max_steps=25, **changes)
    fast, reference = simulate(cfg), simulate(cfg.replace(admm_compiled=False))
    assert np.array_equal(fast.plans, reference.plans) and np.array_equal(fast.states, reference.states)
    assert np.array_equal(fast.admm_iterations, reference.admm_iterations)
    assert fast.admm_iterations.max() > 2  # compiled iterations ran


def test_a_capped_crossing_on_planes_needs_no_fallback():
    """The scale issue's capped crossing: 8 agents crossing on a circle, 2 iterations a step,
    noiseless: half the steps stop unconverged, yet their plans keep their planes, so the fallback is
    the exception (a step without an iterate whose halves held: measured 2 of 84), no pair comes
    closer than r_safe, and every agent arrives."""
    cfg = Config(scenario="circle", num_agents=8, admm_max_iter=2, noise_std=0.0, gp_samples=50, gp_iters=20,
                 admm_coupling="planes")
    m = compute_metrics(simulate(cfg))
    assert m["converged_fraction"] < 0.9 and m["fallback_steps"] <= 4
    assert m["violations"] == 0 and m["min_pair_distance"] >= cfg.r_safe
    assert all(a is not None for a in m["arrival_steps"])


def test_a_time_budget_stops_every_step_early_and_its_plans_stay_safe():
    """``admm_time_budget_ms``: a budget the first iteration already spends stops every step at its
    second (the last goes through the torch path); with planes the plans still keep every pair."""
    cfg = Config(noise_std=0.0, admm_coupling="planes", admm_time_budget_ms=1e-6, gp_iters=20)
    out = simulate(cfg)
    m = compute_metrics(out)
    assert int(np.max(out.admm_iterations)) == 2
    assert m["violations"] == 0 and m["arrival_step_max"] is not None
    with pytest.raises(GpmpcError, match="admm_time_budget_ms"):
        Config(admm_time_budget_ms=0)
