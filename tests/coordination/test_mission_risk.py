"""The mission risk budget (``risk_mode = mission``): the allocation against hand-computed
numbers, the pair and obstacle bounds against their closed forms, the budget arithmetic through
ADMM (pairs and obstacle rows), and a single pair and a single agent beside a disc under Monte
Carlo meeting their bounds.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.stats import norm

from tests.helpers import ConstantVarianceGP
from torch_gpmpc import Controller, ControllerSettings, ModelSpec
from torch_gpmpc.config import Config
from torch_gpmpc.coordination.graph import communication_graph, graph_from_edges
from torch_gpmpc.coordination.mission_risk import (
    RISK_FLOOR, agent_charges, direction_risk_bounds, edge_allotments, obstacle_risk_bounds, pair_matrix,
    pair_risk_bounds, row_allotments, slot_risks_from_edges, starting_budgets,
)
from torch_gpmpc.errors import GpmpcError

F64 = torch.float64


def test_allocation_matches_a_hand_computed_case():
    """Path graph 0-1-2, remaining (0.03, 0.02, 0.01), pacing 10: degrees (1, 2, 1), so the
    ends get 0.03/10 = 0.003, 0.02/20 = 0.001 and 0.01/10 = 0.001; a pair bound of 0.002 on
    edge (0, 1) is charged 0.0015 to agent 0 and 0.0005 to agent 1."""
    graph = graph_from_edges(3, [(0, 1), (1, 2)])
    remaining = torch.tensor([0.03, 0.02, 0.01], dtype=F64)
    eps_edge = edge_allotments(remaining, graph, pacing=10)
    np.testing.assert_allclose(eps_edge.numpy(), [[0.003, 0.001], [0.001, 0.001]], rtol=1e-12)
    own, other = slot_risks_from_edges(graph, eps_edge)
    # agent 1's slots: neighbour 0 then neighbour 2 (slot order of graph_from_edges)
    nbrs = graph.slot_nbr[1][graph.active[1]].tolist()
    assert sorted(nbrs) == [0, 2]
    by_nbr = {j: (float(own[1, m]), float(other[1, m])) for m, j in enumerate(graph.slot_nbr[1].tolist())
              if graph.active[1, m]}
    assert by_nbr[0] == pytest.approx((0.001, 0.003)) and by_nbr[2] == pytest.approx((0.001, 0.001))
    charges = agent_charges(torch.tensor([0.002, 0.0], dtype=F64), eps_edge, graph)
    np.testing.assert_allclose(charges.numpy(), [0.0015, 0.0005, 0.0], rtol=1e-12, atol=1e-18)
    assert starting_budgets(4, 0.05).tolist() == [0.0125] * 4


def test_obstacle_rows_take_their_shares_of_the_allotment():
    """With L = 2 obstacle rows each agent splits its allotment over d_k + 2 rows: path 0-1-2,
    remaining (0.03, 0.02, 0.01), pacing 10 -> 0.03/30, 0.02/40, 0.01/30; with L = 0 the edges'
    risks are those of the hand-computed case above."""
    graph = graph_from_edges(3, [(0, 1), (1, 2)])
    remaining = torch.tensor([0.03, 0.02, 0.01], dtype=F64)
    np.testing.assert_allclose(row_allotments(remaining, graph, 10, obstacle_rows=2).numpy(),
                               [0.001, 0.0005, 0.01 / 30], rtol=1e-12)
    np.testing.assert_allclose(edge_allotments(remaining, graph, 10, obstacle_rows=2).numpy(),
                               [[0.001, 0.0005], [0.0005, 0.01 / 30]], rtol=1e-12)
    assert torch.equal(edge_allotments(remaining, graph, 10, obstacle_rows=0), edge_allotments(remaining, graph, 10))
    alone = graph_from_edges(1, [])
    assert row_allotments(torch.tensor([0.05], dtype=F64), alone, 10, obstacle_rows=3).item() == pytest.approx(0.05 / 30)


def test_obstacle_bound_is_the_tail_beyond_the_row_and_bounds_the_hits():
    """A disc of radius 0.3 at the origin and a body of radius 0.25: the row at the plan's point
    (0.9, 0.1) is ``n^T p >= 0.55`` (n the unit vector to the point). A next state held at the row's
    margin for eps = 0.01 (std 0.1) has the bound eps exactly, and 400k Gaussian draws around it
    hit the grown disc less often than eps (the disc lies beyond the half-space); an inert padding
    row (normal 0) adds nothing."""
    eps, std, grown = 0.01, 0.1, 0.55
    n = torch.tensor([0.9, 0.1], dtype=F64) / math.hypot(0.9, 0.1)
    nxt = n * (grown + norm.ppf(1 - eps) * std)
    plans = torch.stack([torch.zeros(2, dtype=F64), nxt, nxt])[None]  # (1, T+1 = 3, 2)
    normals = torch.zeros(1, 2, 2, 2, dtype=F64)
    normals[0, 0] = n  # row 0 at both horizon steps; row 1 inert
    bounds = torch.tensor([[[grown, grown], [-1.0, -1.0]]], dtype=F64)
    stds = torch.tensor([[[std, std], [0.0, 0.0]]], dtype=F64)
    assert obstacle_risk_bounds(plans, normals, bounds, stds).item() == pytest.approx(eps, rel=1e-9)
    draws = nxt.numpy() + np.random.default_rng(0).normal(0.0, std, (400_000, 2))
    rate = (np.linalg.norm(draws, axis=1) < grown).mean()
    assert 0.3 * eps < rate <= eps


def test_pair_bound_is_the_gaussian_tail_and_handles_zero_variance():
    sep = torch.tensor([1.0, 0.6, 0.4, 0.6, float("nan")], dtype=F64)
    var = torch.tensor([0.04, 0.0, 0.0, 0.01, 0.01], dtype=F64)
    bound = pair_risk_bounds(sep, var, r_safe=0.5)
    assert bound[0].item() == pytest.approx(norm.cdf(-2.5), rel=1e-12)
    assert bound[1].item() == 0.0 and bound[2].item() == 1.0
    assert bound[3].item() == pytest.approx(norm.cdf(-1.0), rel=1e-12)
    assert math.isnan(bound[4].item())
    matrix = pair_matrix(bound[:1], graph_from_edges(3, [(0, 2)]))
    assert matrix[0, 2] == matrix[2, 0] == bound[0] and math.isnan(matrix[0, 1].item())


def test_direction_bound_is_the_tail_along_the_pair_and_bounds_the_hits():
    """Two agents 0.8 m apart along (3, 4) / 5 with position covariances S_k, S_j: the bound is
    Phi(-(0.8 - 0.5) / sqrt(n^T (S_k + S_j) n)) in closed form, and above the Monte Carlo rate of
    the disc collision (200k draws)."""
    n = torch.tensor([0.6, 0.8], dtype=F64)
    positions = torch.stack([torch.zeros(2, dtype=F64), -0.8 * n])
    cov = torch.tensor([[[0.02, 0.005], [0.005, 0.01]], [[0.01, 0.0], [0.0, 0.03]]], dtype=F64)
    bound = direction_risk_bounds(positions, cov, torch.tensor([[0, 1]]), 0.5)
    variance = float(n @ (cov[0] + cov[1]) @ n)
    assert bound.item() == pytest.approx(norm.cdf(-0.3 / math.sqrt(variance)), rel=1e-12)
    gen = np.random.default_rng(0)
    total = (cov[0] + cov[1]).numpy()
    d = 0.8 * n.numpy() + gen.multivariate_normal(np.zeros(2), total, 200_000)
    rate = float((np.linalg.norm(d, axis=1) < 0.5).mean())
    assert rate <= bound.item() and rate >= 0.2 * bound.item()


def test_a_crowd_is_charged_only_what_its_applied_plans_risk():
    """40 agents crossing a disc of radius 6.3 under a mission budget (noise 0.02, 50 steps): the
    safety fallback re-plans agents in their Voronoi cells on some steps, and the step's collision
    normals then no longer describe their plans; along a stale normal a pair well apart can look
    closer than r_safe (a bound near 1 at a safe pair-step: 0.94 spent in all, none of it where
    plans fell short of their rows, when only the normals' bound was taken). Measured here: what
    the run spends outside its shortfall stays within the budget (not guaranteed in general: the
    rows' margins use the variance along the normal, the charge the smaller of two bounds)."""
    from torch_gpmpc.sim.closed_loop import simulate
    from torch_gpmpc.sim.metrics import compute_metrics

    cfg = Config(scenario="random", num_agents=40, circle_radius=6.3, comm_radius=2.5, noise_std=0.02,
                 risk_mode="mission", risk_budget=0.05, max_steps=50)
    m = compute_metrics(simulate(cfg))
    assert m["fallback_steps"] > 0
    assert m["risk_spent"] - m["risk_spent_shortfall"] <= cfg.risk_budget


def test_a_row_at_its_joint_margin_is_charged_exactly_its_allotment():
    """At the joint margin Phi^-1(1 - e_k - e_j) sqrt(s_k + s_j) the bound equals e_k + e_j."""
    e_k, e_j, s_k, s_j = 0.002, 0.001, 0.01, 0.03
    sep = 0.5 + norm.ppf(1 - e_k - e_j) * math.sqrt(s_k + s_j)
    bound = pair_risk_bounds(torch.tensor([sep], dtype=F64), torch.tensor([s_k + s_j], dtype=F64), 0.5)
    assert bound.item() == pytest.approx(e_k + e_j, rel=1e-9)


def _pair_run(steps: int, budget: float, pacing: int, var: float, r_safe: float = 0.5):
    """The allotments of a pair that stays at its joint margin for ``steps`` steps, charged by
    the module's own functions: per step (pair risk, required separation) and what is left."""
    graph = communication_graph(torch.tensor([[0.0, 0.0], [1.0, 0.0]], dtype=F64), None)
    remaining = starting_budgets(2, budget)
    risks, seps = [], []
    for _ in range(steps):
        eps_edge = edge_allotments(remaining, graph, pacing)
        total = float(eps_edge.sum())
        sep = r_safe + norm.ppf(1 - total) * math.sqrt(2 * var)
        bound = pair_risk_bounds(torch.tensor([sep], dtype=F64), torch.tensor([2 * var], dtype=F64), r_safe)
        remaining = (remaining - agent_charges(bound, eps_edge, graph)).clamp_min(RISK_FLOOR)
        risks.append(float(bound))
        seps.append(sep)
    return np.array(risks), np.array(seps), remaining


def test_monte_carlo_single_pair_meets_the_mission_bound_over_a_run():
    """Two agents held at their rows' required separation for 40 steps, each deviating by
    independent N(0, var I) noise at every step (the plan is re-made each step, as the closed
    loop does). The fraction of 200k runs with any collision is at most delta (binomial
    3-sigma allowance), and the budget is nearly spent (the promise is not vacuous)."""
    delta, steps, var, r_safe, N = 0.05, 40, 0.01, 0.5, 200_000
    risks, seps, remaining = _pair_run(steps, delta, pacing=10, var=var)
    assert risks.sum() <= delta + 1e-12 and float(remaining.sum()) > 0
    gen = np.random.default_rng(0)
    hit = np.zeros(N, dtype=bool)
    for sep in seps:
        d = np.array([sep, 0.0]) + gen.normal(0, math.sqrt(var), (N, 2)) - gen.normal(0, math.sqrt(var), (N, 2))
        hit |= np.linalg.norm(d, axis=1) < r_safe
    rate = hit.mean()
    assert rate <= delta + 3 * math.sqrt(delta * (1 - delta) / N)
    assert rate >= 0.8 * risks.sum() * 0.5  # the 2D disc is inside the half-space: same order, below


def test_budget_never_runs_out_and_charges_add_up_through_the_controller():
    """Two single integrators swapping through each other under a mission budget: every step's
    charges equal the pairs' bounds (what left the budget is what the pair risked), and with the
    rows holding no step spends more than 1/pacing of what remained."""
    model = ModelSpec.single_integrator(2, u_max=2.0)
    settings = ControllerSettings(horizon=8, risk_mode="mission", risk_budget=0.05, risk_pacing=5)
    gps = [ConstantVarianceGP(0.01, 2), ConstantVarianceGP(0.01, 2)]
    ctrl = Controller(model, gps=gps, settings=settings)
    x = torch.tensor([[-1.5, 0.05], [1.5, -0.05]], dtype=F64)
    xref = x.flip(0)[:, None].expand(2, 9, 2)
    left = starting_budgets(2, 0.05)
    total_bound = 0.0
    for _ in range(12):
        res = ctrl.step(x, xref)
        new_left = res.state.risk_left
        bound = float(torch.nan_to_num(res.pair_risk[0, 1]))
        total_bound += bound
        assert float((left - new_left).sum()) == pytest.approx(bound, rel=1e-9, abs=1e-15)
        if res.converged and not res.unsafe_plan:
            assert bool((new_left >= left * (1 - 1 / 5) - 1e-15).all())
        left = new_left
        x = res.plans[:, 1]
    assert 0 < total_bound <= 0.05
    assert float(left.sum()) == pytest.approx(0.05 - total_bound, rel=1e-9)
    ctrl.reset()  # a new mission starts with the whole budget
    assert ctrl.step(x, xref).state.risk_left.sum() <= 0.05


def test_obstacle_rows_are_charged_to_the_budget_through_the_controller():
    """One single integrator passing a disc under a mission budget (no neighbour): its obstacle
    row carries the margin of the allotment ``R / (pacing L)`` = 0.05 / 10 (against ``obstacle_eps``
    = 0.01 under ``pair_step``), every step's charge is the row's bound, and the bounds sum to what
    left the budget."""
    model = ModelSpec.single_integrator(2, u_max=2.0)
    disc = [{"center": [0.0, 0.3], "radius": 0.3}]
    gps = [ConstantVarianceGP(0.01, 2)]
    x = torch.tensor([[-1.5, 0.0]], dtype=F64)
    xref = torch.tensor([[1.5, 0.0]], dtype=F64)[:, None].expand(1, 9, 2)

    def controller(mode):
        return Controller(model, gps=gps, settings=ControllerSettings(
            horizon=8, risk_mode=mode, obstacles=disc, obstacle_rows=1,
            **({"risk_budget": 0.05, "risk_pacing": 10} if mode == "mission" else {"obstacle_eps": 0.01})))

    rows = {mode: controller(mode).step(x, xref).problem.halfspace_bounds for mode in ("pair_step", "mission")}
    ctrl = controller("mission")
    _, raw, _ = ctrl.admm.agent_step._obstacle_rows(x[:, None].expand(1, 9, 2), None, torch.arange(1))
    ratio = (rows["mission"] - raw) / (rows["pair_step"] - raw)  # the cold start linearizes at x for both
    np.testing.assert_allclose(ratio.numpy(), norm.ppf(1 - 0.005) / norm.ppf(1 - 0.01), rtol=1e-9)
    left, spent = starting_budgets(1, 0.05), 0.0
    for _ in range(15):
        res = ctrl.step(x, xref)
        assert res.obstacle_risk is not None and res.pair_risk is None
        charge = float(res.obstacle_risk.sum())
        assert float(left.sum() - res.state.risk_left.sum()) == pytest.approx(charge, rel=1e-9, abs=1e-15)
        if res.state_slack_max == 0.0:
            assert charge <= float(left.sum()) / 10 * (1 + 1e-9)  # the row holds: at most the allotment
        spent += charge
        left, x = res.state.risk_left, res.plans[:, 1]
    assert 0 < spent <= 0.05 and float(x[0, 0]) > 0.0  # it went past the disc


def test_mission_margins_exceed_pair_step_margins():
    """The mission's per-pair-step risk is far below eps = 0.1, so its rows ask for more room."""
    model = ModelSpec.single_integrator(2, u_max=2.0)
    x = torch.tensor([[-1.0, 0.0], [1.0, 0.0]], dtype=F64)
    xref = x.flip(0)[:, None].expand(2, 9, 2)
    gps = [ConstantVarianceGP(0.01, 2), ConstantVarianceGP(0.01, 2)]
    margins = {}
    for mode in ("pair_step", "mission"):
        ctrl = Controller(model, gps=gps, settings=ControllerSettings(horizon=8, risk_mode=mode))
        margins[mode] = ctrl.step(x, xref).max_margin
    assert margins["mission"] > 1.5 * margins["pair_step"]


@pytest.mark.parametrize("changes, field", [
    ({"method": "nominal"}, "chance margins"),
    ({"pair_margin": "own"}, "sound pair margin"),
])
def test_mission_refuses_what_cannot_carry_a_budget(changes, field):
    with pytest.raises(GpmpcError, match=f"risk_mode.*{field}"):
        Config(risk_mode="mission", **changes)
    with pytest.raises(GpmpcError, match=field):
        ControllerSettings(risk_mode="mission", **changes)
    with pytest.raises(GpmpcError, match="risk_budget"):
        Config(risk_mode="mission", risk_budget=1.5)


def test_distributed_backend_says_mission_is_in_process_only():
    from torch_gpmpc.sim.distributed import simulate_distributed

    with pytest.raises(GpmpcError, match="risk_mode.*in process"):
        simulate_distributed(Config(risk_mode="mission", max_steps=1))


def test_tune_refuses_to_tune_a_split_a_mission_does_not_have(tmp_path, capsys):
    from torch_gpmpc.cli import main

    assert main(["tune", "--set", "risk_mode=mission", "--out", str(tmp_path / "t")]) == 2
    assert "tune.tune_split=false" in capsys.readouterr().err
