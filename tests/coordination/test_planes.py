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
    PlaneGeometry, lost_end_offsets, midpoint_planes, plane_consensus, plane_geometry, plane_offsets, plane_problem,
    plane_residuals,
)
from torch_gpmpc.coordination.state import adapt_state, initial_state
from torch_gpmpc.dynamics.systems import NominalModel
from torch_gpmpc.errors import GpmpcError
from torch_gpmpc.sim.closed_loop import simulate
from torch_gpmpc.sim.metrics import compute_metrics

TIGHT = dict(admm_tol=1e-7, admm_dual_tol=1e-7, admm_rel_tol=0.0, admm_max_iter=3000)


def _crossing(num_agents: int = 4):
    """``num_agents`` on a circle of radius 1, each heading for its antipode (all pairs coupled)."""
    angles = 2 * torch.pi * torch.arange(num_agents, dtype=torch.float64) / num_agents
    x0 = torch.stack([angles.cos(), angles.sin()], dim=1)
    xref = x0[:, None] + torch.linspace(0, 1, 9, dtype=torch.float64)[None, :, None] * (-2 * x0)[:, None]
    return x0, xref, communication_graph(x0, None)


@pytest.mark.parametrize("method", ["nominal", "nominal-chance"])
def test_planes_reach_the_centralized_optimum_and_the_copies_plans(method):
    """Run to a tight tolerance from a cold start, the plane consensus gives the plans of an
    independent centralized cvxpy solve of the same step problem (1e-4), and the copies' plans."""
    from tests.helpers import ConstantVarianceGP

    cfg = Config(horizon=8, rho=5.0, noise_std=0.0, **TIGHT)
    gps = [ConstantVarianceGP(0.01)] * 4 if method.endswith("chance") else None
    x0, xref, graph = _crossing()
    planes = ADMM(LocalStep(cfg.replace(admm_coupling="planes"), NominalModel(2), method, None, gps)).solve_step(x0, xref, graph)
    copies = ADMM(LocalStep(cfg, NominalModel(2), method, None, gps)).solve_step(x0, xref, graph)
    assert planes.converged and copies.converged
    central = solve_centralized(planes.problem, graph, NominalModel(2), cfg.u_max, cfg.alpha, cfg.slack_penalty)
    np.testing.assert_allclose(planes.plans.numpy(), central.plans.numpy(), atol=1e-4)
    np.testing.assert_allclose(planes.plans.numpy(), copies.plans.numpy(), atol=1e-4)
    assert planes.slack_max < 1e-6
    # a pair row is active: the coupling is really tested
    data, (k, m) = planes.problem, torch.nonzero(graph.active, as_tuple=True)
    gap = (data.normals[k, m] * (central.plans[k, 1:] - central.plans[graph.slot_nbr[k, m], 1:])).sum(-1) - data.bounds[k, m]
    assert float(gap.min()) < 1e-5
    assert planes.iterations < copies.iterations


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


def test_plane_problem_rows_are_halves_on_the_edge_normal_and_offsets_read_the_copies():
    """The local problems of the planes: slot rows ``+-n`` with bound d/2, copies pulled towards
    ``c n``; an agent whose half is slack leaves its copy at the target (offset = c exactly), and
    one whose half binds keeps ``n^T X = c + d/2`` (checked on a solve)."""
    data = crossing_instance(batch=2, num_neighbors=1, method="nominal").problem_data()
    graph = graph_from_edges(2, [(0, 1)])
    # make the two slots one edge's ends: agent 1's normal is agent 0's negated
    data = dataclasses.replace(data, normals=torch.stack([data.normals[0], -data.normals[0]]),
                               bounds=torch.stack([data.bounds[0], data.bounds[0] + 0.1]))
    geometry = plane_geometry(data, graph)
    assert torch.equal(geometry.distance, data.bounds[1])  # the larger end's bound
    targets = torch.zeros(1, 2, data.bounds.shape[-1], dtype=torch.float64)
    targets[0, 1] = 0.3
    problem = plane_problem(data, geometry, targets, torch.tensor([50.0], dtype=torch.float64))
    assert torch.equal(problem.normals[1], -problem.normals[0]) and torch.equal(problem.bounds[0], geometry.distance / 2)
    assert float(problem.rho) == 0.0 and torch.equal(problem.rho_nbr, torch.full((2, 1), 50.0, dtype=torch.float64))
    np.testing.assert_allclose((geometry.normals[0] * problem.z_nbr[0, 0, 1:]).sum(-1), targets[0, 0])
    np.testing.assert_allclose((geometry.normals[0] * problem.z_nbr[1, 0, 1:]).sum(-1), targets[0, 1])
    from torch_gpmpc import make_local_solver

    sol = make_local_solver(13, 2, 1, NominalModel(2), 2.0, 1e-3)(problem)
    assert bool(sol.ok.all())
    offsets = plane_offsets(sol, geometry, targets[:, 0])
    half = geometry.distance[0] / 2
    own = (geometry.normals[0] * sol.X[0, 1:]).sum(-1)
    other = (geometry.normals[0] * sol.X[1, 1:]).sum(-1)
    # lo's half n^T X_lo >= w_lo + d/2, hi's half n^T X_hi <= w_hi - d/2 (up to the solver's tolerance)
    assert float((own - offsets[0, 0] - half).min()) > -1e-6
    assert float((offsets[0, 1] - half - other).min()) > -1e-6
    slack_lo = own - offsets[0, 0] - half > 1e-4
    np.testing.assert_allclose(offsets[0, 0][slack_lo], targets[0, 0][slack_lo], atol=1e-6)


def test_plane_consensus_averages_moves_duals_and_measures_residuals():
    offsets = torch.tensor([[[1.0, 2.0], [3.0, 2.0]]], dtype=torch.float64)
    duals = torch.tensor([[[0.5, 0.0], [-0.5, 0.0]]], dtype=torch.float64)
    rho = torch.tensor([2.0], dtype=torch.float64)
    planes, new_duals, primal, dual = plane_consensus(offsets, torch.zeros(1, 2, dtype=torch.float64), duals, rho)
    # zeta = mean(w + mu / rho) = mean([1.25, 2], [2.75, 2]) = [2, 2]
    assert torch.equal(planes, torch.tensor([[2.0, 2.0]], dtype=torch.float64))
    assert torch.equal(new_duals, duals + 2.0 * (offsets - planes[:, None]))
    assert torch.equal(new_duals.sum(dim=1), torch.zeros(1, 2, dtype=torch.float64))  # the ends' duals cancel
    assert torch.equal(primal, torch.tensor([[1.0, 1.0]], dtype=torch.float64))  # max over tau
    assert torch.allclose(dual, torch.tensor([2.0 * 8 ** 0.5], dtype=torch.float64))
    settings = ControllerSettings(admm_tol=2.0, admm_rel_tol=0.0)
    res = plane_residuals(primal, dual, new_duals, settings)
    assert float(res.eps_primal) == 1.0 and float(res.primal_ratio) == 1.0  # tol / 2, no relative part


def test_midpoint_planes_split_the_linearization_plans():
    x0, _, graph = _crossing(2)
    state = initial_state(x0, 4, graph)
    data = crossing_instance(batch=2, num_neighbors=1, method="nominal", horizon=4).problem_data()
    n = (x0[0] - x0[1]) / (x0[0] - x0[1]).norm()
    data = dataclasses.replace(data, normals=torch.stack([n, -n])[:, None, None].expand(2, 1, 4, 2).clone())
    planes = midpoint_planes(plane_geometry(data, graph), state.plans, graph, [0, 1])
    np.testing.assert_allclose(planes, torch.full((1, 4), float(n @ (x0[0] + x0[1]) / 2)), atol=1e-15)


def test_plane_duals_are_carried_by_edge_and_shifted_planes_restart():
    x0, _, graph = _crossing(3)
    state = dataclasses.replace(initial_state(x0, 4, graph), planes=torch.ones(3, 4, dtype=torch.float64),
                                plane_duals=torch.arange(24, dtype=torch.float64).reshape(3, 2, 4))
    shifted = state.shifted()
    assert shifted.planes is None
    assert torch.equal(shifted.plane_duals[:, :, :3], state.plane_duals[:, :, 1:])
    assert torch.equal(shifted.plane_duals[:, :, 3], state.plane_duals[:, :, 3])
    kept = adapt_state(shifted, graph_from_edges(3, [(0, 2), (1, 2)]))  # edge (0, 1) dropped
    assert torch.equal(kept.plane_duals, shifted.plane_duals[1:])
    grown = adapt_state(kept, graph)  # edge (0, 1) back: it starts with zero duals
    assert torch.equal(grown.plane_duals[0], torch.zeros(2, 4, dtype=torch.float64))
    assert torch.equal(grown.plane_duals[1:], kept.plane_duals)


def test_messages_carry_the_planes_offsets():
    s = ControllerSettings(method="nominal", horizon=13)
    assert message_size(s, 2) == 2 * 14 * 2
    assert message_size(s.replace(admm_coupling="planes"), 2) == 13
    # the variances (and the rows) are agreed once per step, not sent with every iteration's offsets
    assert message_size(s.replace(admm_coupling="planes", method="gp-chance"), 4) == 13


@pytest.mark.parametrize("changes, key", [({"admm_acceleration": "anderson"}, "admm_coupling"),
                                          ({"relinearize": True}, "admm_coupling")])
def test_planes_refuse_what_they_do_not_support_yet(changes, key):
    with pytest.raises(GpmpcError, match=f"config key '{key}'"):
        Config(admm_coupling="planes", **changes)
    with pytest.raises(GpmpcError, match=f"controller setting '{key}'"):
        ControllerSettings(admm_coupling="planes", **changes)


def test_a_lost_neighbour_votes_the_plane_that_touches_its_last_plan():
    """Closed form: the lost end's half holds with equality on its last shared plan (lo:
    ``n^T p = w + d/2``, hi: ``n^T p = w - d/2``), so the survivor is pushed to keep the whole row."""
    T = 4
    normals = torch.tensor([[0.6, 0.8]], dtype=torch.float64).expand(T, 2)
    geometry = PlaneGeometry(torch.tensor([0, 1]), torch.tensor([0, 0]), torch.tensor([0, 0]), torch.tensor([0, 1]),
                             torch.tensor([1.0, -1.0], dtype=torch.float64), normals[None].clone(),
                             torch.full((1, T), 0.7, dtype=torch.float64))
    plan = torch.arange(2 * (T + 1), dtype=torch.float64).reshape(T + 1, 2)
    along = (normals * plan[1:]).sum(-1)
    assert torch.allclose(lost_end_offsets(geometry, plan, 0, 1, [0, 1]), along + 0.35)
    assert torch.allclose(lost_end_offsets(geometry, plan, 0, 0, [0, 1]), along - 0.35)


def test_a_mixed_team_crosses_the_vortex_on_planes_without_violation():
    """2 double-integrator drones (radius 0.2) and 2 single-integrator robots (0.3) alternating on a
    circle through the vortex, learned GPs, noiseless: every agent arrives and every pair keeps
    ``r_k + r_j`` (the plane halves carry each pair's own distance)."""
    cfg = Config(scenario="circle", num_agents=4, noise_std=0.0, admm_coupling="planes", pair_buffer=0.01,
                 models=["double-integrator", "single-integrator"] * 2, radii=[0.2, 0.3] * 2, gp_iters=20)
    m = compute_metrics(simulate(cfg))
    assert m["violations"] == 0 and m["arrival_step_max"] is not None


def test_tuning_gradients_through_the_planes_match_finite_differences():
    """``gpmpc tune``'s objective through the unrolled plane ADMM (4 iterations, 2 MPC steps,
    adaptive rho, sum margins): d loss / d (log rho, the three pair splits) against Richardson-
    extrapolated central differences."""
    from tests.tuning.test_tuner import _gradient_and_differences, _small_objective
    from torch_gpmpc.tuning import TuneSettings, TuningParameters

    settings = TuneSettings(admm_iters=4, mpc_steps=2)
    objective = _small_objective([0], settings, pair_margin="sum", admm_coupling="planes")
    params = TuningParameters(3, rho=5.0)
    with torch.no_grad():
        params.theta[0, 1], params.theta[0, 2], params.theta[1, 2] = 0.3, -0.2, 0.1
    objective(params).loss.backward()
    grad, fd = _gradient_and_differences(objective, params)
    assert all(abs(g) > 1e-4 for g in grad), grad
    for g, d in zip(grad, fd, strict=True):
        assert abs(g - d) <= 1e-6 * abs(d), (grad, fd)


def test_paper_scenario_with_planes_arrives_safely_noiseless():
    """The paper's three agents (learned GPs, sound margins) through the vortex without noise: every
    agent arrives, no pair closer than r_safe less the consensus tolerance."""
    cfg = Config(noise_std=0.0, admm_coupling="planes", gp_iters=20)
    m = compute_metrics(simulate(cfg))
    assert m["arrival_step_max"] is not None and m["arrival_step_max"] <= 60
    assert m["min_pair_distance"] > cfg.r_safe - cfg.admm_tol
    assert m["converged_fraction"] > 0.95


@pytest.mark.parametrize("changes", [{}, {"rho_update": "fixed"}])
def test_compiled_plane_iterations_give_the_torch_paths_closed_loop_bit_for_bit(changes):
    """``admm_compiled`` runs a step's plane iterations after its second on the kept problems: the
    same plans and states as every iteration through the torch path (8 agents crossing, noisy)."""
    cfg = Config(scenario="circle", num_agents=8, method="nominal", admm_coupling="planes", max_steps=25, **changes)
    fast, reference = simulate(cfg), simulate(cfg.replace(admm_compiled=False))
    assert np.array_equal(fast.plans, reference.plans) and np.array_equal(fast.states, reference.states)
    assert np.array_equal(fast.admm_iterations, reference.admm_iterations)
    assert fast.admm_iterations.max() > 2  # compiled iterations ran


def test_the_fallback_keeps_a_capped_crowd_safe_on_planes():
    """The scale issue's fallback test with plane coupling: 8 agents crossing on a circle, ADMM capped
    at 2 iterations, noiseless: the fallback acts at many steps, no pair comes closer than r_safe, and
    every agent arrives."""
    cfg = Config(scenario="circle", num_agents=8, admm_max_iter=2, noise_std=0.0, gp_samples=50, gp_iters=20,
                 admm_coupling="planes")
    m = compute_metrics(simulate(cfg))
    assert m["fallback_steps"] > 10 and m["converged_fraction"] < 0.9
    assert m["violations"] == 0 and m["min_pair_distance"] >= cfg.r_safe
    assert all(a is not None for a in m["arrival_steps"])
