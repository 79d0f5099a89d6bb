"""ADMM stopping and penalty adaptation against hand computations (Boyd et al. 2011 §3.3-3.4),
and the default settings' step optimum against an independent centralized cvxpy solve."""

from __future__ import annotations

import math

import pytest
import torch

from torch_gpmpc.config.schema import Config
from torch_gpmpc.coordination.admm import consensus_update
from torch_gpmpc.coordination.centralized import plan_cost, solve_centralized
from torch_gpmpc.coordination.controller import Controller
from torch_gpmpc.coordination.penalty import (
    RHO_BOUNDS, balance_penalty, edge_residuals, should_stop, starting_penalties, checks_dual, unconverged_edges,
)
from torch_gpmpc.dynamics.systems import system_from_config
from torch_gpmpc.gp import fit_agent_gps
from torch_gpmpc.sim.closed_loop import ADMMPlanner, run_closed_loop
from torch_gpmpc.sim.scenarios import make_scenario

F64 = torch.float64


def _residuals(primal, dual, eps_p=1.0, eps_d=1.0):
    from torch_gpmpc.coordination.penalty import EdgeResiduals

    t = lambda v: torch.tensor(v, dtype=F64)  # noqa: E731
    return EdgeResiduals(t(primal), t(dual), t(eps_p), t(eps_d))


def test_balancing_doubles_halves_or_keeps_each_edge_on_the_residual_ratios():
    rho = torch.tensor([4.0, 4.0, 4.0, 4.0], dtype=F64)
    # ratios primal/dual: 20 (double), 1/20 (halve), 5 (keep), 1/5 (keep)
    res = _residuals([20.0, 1.0, 5.0, 1.0], [1.0, 20.0, 1.0, 5.0])
    assert balance_penalty(rho, res).tolist() == [8.0, 2.0, 4.0, 4.0]
    # the ratios, not the raw residuals: a primal residual 5x the dual one, with a primal tolerance
    # 10x tighter than the dual one, is 50x off balance
    res = _residuals([5.0], [1.0], eps_p=[0.1], eps_d=[1.0])
    assert balance_penalty(torch.tensor([4.0], dtype=F64), res).tolist() == [8.0]


def test_balancing_stays_within_bounds_and_passes_gradients_to_the_start():
    low, high = RHO_BOUNDS
    rho = torch.tensor([high, low], dtype=F64)
    assert balance_penalty(rho, _residuals([100.0, 1.0], [1.0, 100.0])).tolist() == [high, low]
    start = torch.tensor(3.0, dtype=F64, requires_grad=True)
    rho = starting_penalties(None, start, 2)
    out = balance_penalty(balance_penalty(rho, _residuals([100.0, 1.0], [1.0, 1.0])),
                          _residuals([100.0, 1.0], [1.0, 1.0]))
    out.sum().backward()
    assert out.tolist() == [12.0, 3.0]
    assert start.grad.item() == pytest.approx(5.0)  # d(4 s + s)/ds


def test_starting_penalties_keep_carried_edges_and_start_new_ones():
    carried = torch.tensor([2.5, float("nan")], dtype=F64)
    assert starting_penalties(carried, torch.tensor(20.0, dtype=F64), 2).tolist() == [2.5, 20.0]
    assert starting_penalties(None, torch.tensor(20.0, dtype=F64), 3).tolist() == [20.0] * 3


def test_tolerances_are_absolute_plus_relative_and_both_ends_know_them():
    torch.manual_seed(0)
    E, T1, n = 3, 5, 2
    copies = torch.randn(E, 2, 2, T1, n, dtype=F64)
    z = torch.randn(E, 2, T1, n, dtype=F64)
    lam0 = torch.zeros(E, 2, 2, T1, n, dtype=F64)
    rho = torch.tensor([1.0, 2.0, 4.0], dtype=F64)
    z_new, lam, primal, dual = consensus_update(copies, z, lam0, rho)
    # duals start at zero and each update adds rho (y - z), which sums to zero over the ends
    torch.testing.assert_close(lam[:, 0], -lam[:, 1])
    torch.testing.assert_close(lam, rho[:, None, None, None, None] * (copies - z_new[:, None]))
    cfg = Config(admm_coupling="copies", admm_tol=1e-3, admm_rel_tol=1e-2)
    res = edge_residuals(copies, z_new, lam[:, 1].flatten(1).norm(dim=1), primal, dual, cfg)
    for e in range(E):
        size = max(copies[e, 0].norm(), copies[e, 1].norm(), z_new[e].norm())
        assert float(res.eps_primal[e]) == pytest.approx(1e-3 + 1e-2 * float(size))
        assert float(res.eps_dual[e]) == pytest.approx(1e-2 + 1e-2 * float(lam[e, 0].norm()))
        assert float(res.primal[e]) == pytest.approx(max(float((copies[e, a] - z_new[e]).norm()) for a in (0, 1)))
        assert float(res.dual[e]) == pytest.approx(float(rho[e] * (z_new[e] - z[e]).norm()))
    # the paper's rule is absolute only
    paper = edge_residuals(copies, z_new, lam[:, 0].flatten(1).norm(dim=1), primal, dual,
                           cfg.replace(admm_stop="primal", admm_rel_tol=1e-4))  # its relative part unused
    assert paper.eps_primal.tolist() == [1e-3] * E


def test_stopping_rules():
    both, paper = Config(admm_coupling="copies"), Config(admm_coupling="copies", admm_stop="primal")
    assert checks_dual(both) and not checks_dual(paper) and checks_dual(paper.replace(admm_dual_tol=1e-2))
    assert should_stop(0.5, 0.5, both) and not should_stop(0.5, 2.0, both) and not should_stop(2.0, 0.5, both)
    assert should_stop(0.5, 2.0, paper) and not should_stop(0.5, 2.0, paper.replace(admm_dual_tol=1e-2))
    assert not should_stop(math.nan, 0.0, both)


def test_unconverged_edges_count_what_the_stopping_test_waits_for():
    res = _residuals([0.5, 2.0, 0.5, math.nan, 0.99], [0.5, 0.5, 3.0, 0.5, 0.2])
    both, paper = Config(admm_coupling="copies"), Config(admm_coupling="copies", admm_stop="primal")
    assert unconverged_edges(res, both) == 3  # primal 2.0, dual 3.0, and NaN
    assert unconverged_edges(res, paper) == 2  # the paper's rule does not test the dual residual
    assert unconverged_edges(_residuals([0.5], [0.5]), both) == 0


@pytest.fixture(scope="module")
def paper_crossing():
    """The paper scenario, noiseless, default settings, through the crossing: the step results."""
    cfg = Config(admm_coupling="copies", noise_std=0.0, max_steps=34)
    system = system_from_config(cfg)
    controller = Controller.for_run(cfg, system, fit_agent_gps(cfg, system, cfg.num_agents))
    admm, planner = controller.admm, ADMMPlanner(controller)
    results = []
    plan = planner.plan
    planner.plan = lambda t, x, xref, graph: results.append((xref, graph, plan(t, x, xref, graph))) or results[-1][2]
    run_closed_loop(cfg, make_scenario(cfg), system, planner)
    return cfg, admm, results


@pytest.mark.parametrize("step", [10, 18, 22, 26, 30])
def test_default_admm_stops_within_one_percent_of_the_centralized_optimum(paper_crossing, step):
    """At steps through the crossing, after ADMM stops with the default settings (adaptive rho,
    primal-dual stop), the plans' total cost is within 1 % of an independent centralized cvxpy
    solve of the same convexified step problem, and the plans nearly satisfy its coupling rows."""
    cfg, admm, results = paper_crossing
    xref, graph, res = results[step]
    assert res.converged and res.iterations < cfg.iteration_cap
    central = solve_centralized(res.problem, graph, admm.nominal, cfg.u_max, cfg.alpha, cfg.slack_penalty)
    cost = plan_cost(res.plans, res.inputs, xref, cfg.alpha, problem=res.problem)
    assert abs(cost / central.cost - 1.0) < 0.01, (cost, central.cost)
    # the consensus plans keep the collision rows up to the primal tolerance
    data, k_idx = res.problem, torch.nonzero(graph.active, as_tuple=True)
    nbr = graph.slot_nbr[k_idx]
    gap = (data.normals[k_idx] * (res.plans[k_idx[0], 1:] - res.plans[nbr, 1:])).sum(-1) - data.bounds[k_idx]
    assert float(gap.min()) > -5e-3


def test_each_step_counts_its_unconverged_edges_per_iteration(paper_crossing):
    """One count per iteration; a converged step ends at 0, a step stopped at its cap does not."""
    cfg, admm, results = paper_crossing
    for _, graph, res in results:
        assert len(res.unconverged_edges) == res.iterations
        assert all(0 <= c <= graph.num_edges for c in res.unconverged_edges)
        assert (res.unconverged_edges[-1] == 0) == res.converged
    xref, graph, res = results[18]
    capped = admm.solve_step(res.plans[:, 0], xref, graph, max_iter=1)
    assert not capped.converged and capped.unconverged_edges == [graph.num_edges]
