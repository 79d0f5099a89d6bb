"""Consensus ADMM against independent answers: a centralized cvxpy solve, a single-agent
cvxpy solve, closed-form linearizations, and the message count formula."""

from __future__ import annotations

import cvxpy as cp
import numpy as np
import pytest
import torch

from torch_gpmpc.coordination.admm import ADMM, initial_state
from torch_gpmpc.errors import GpmpcError
from torch_gpmpc.coordination.agent_step import LocalStep
from torch_gpmpc.config.schema import Config
from torch_gpmpc.coordination.graph import communication_graph, graph_from_edges
from torch_gpmpc.dynamics.systems import NominalModel, VortexWind

from tests.helpers import ConstantVarianceGP

NDTRI_95 = 1.6448536269514722  # Phi^-1(0.95)


def test_graph_slots_map_each_edge_to_both_ends():
    g = graph_from_edges(4, [(2, 0), (0, 1), (1, 2), (1, 0)])
    assert g.edges.tolist() == [[0, 1], [0, 2], [1, 2]]
    assert g.degrees().tolist() == [2, 2, 2, 0]
    for k in range(4):
        for m in range(g.num_slots):
            if g.active[k, m]:
                lo, hi = g.edges[g.slot_edge[k, m]].tolist()
                assert k == (lo if g.slot_side[k, m] == 0 else hi)
                assert int(g.slot_nbr[k, m]) == (hi if g.slot_side[k, m] == 0 else lo)
    assert not g.active[3].any()


def test_graph_slots_hold_each_agents_edges_in_edge_order_on_random_graphs():
    """The vectorized slot view against the definition, one edge at a time: agent k's slot m holds
    the m-th edge (in edge order) that has k as an end; unused slots are inactive and point at k."""
    gen = torch.Generator().manual_seed(3)
    for trial in range(50):
        K = int(torch.randint(1, 12, (1,), generator=gen))
        raw = torch.randint(0, K, (int(torch.randint(0, 30, (1,), generator=gen)), 2), generator=gen).tolist()
        g = graph_from_edges(K, [tuple(e) for e in raw])
        assert g.edges.tolist() == [list(p) for p in sorted({(min(i, j), max(i, j)) for i, j in raw if i != j})]
        for k in range(K):
            mine = [(e, 0 if lo == k else 1, hi if lo == k else lo) for e, (lo, hi) in enumerate(g.edges.tolist())
                    if k in (lo, hi)]
            assert g.active[k].tolist() == [m < len(mine) for m in range(g.num_slots)]
            for m in range(g.num_slots):
                expected = mine[m] if m < len(mine) else (0, 0, k)
                assert (int(g.slot_edge[k, m]), int(g.slot_side[k, m]), int(g.slot_nbr[k, m])) == expected


def test_communication_radius_selects_pairs():
    x = torch.tensor([[0.0, 0.0], [1.0, 0.0], [3.0, 0.0]], dtype=torch.float64)
    assert communication_graph(x, 1.5).edges.tolist() == [[0, 1]]
    assert communication_graph(x, None).edges.tolist() == [[0, 1], [0, 2], [1, 2]]
    assert communication_graph(x, 1.0).edges.tolist() == []  # strictly closer than the radius
    assert communication_graph(x[:1], 1.0).num_edges == 0 and communication_graph(x[:0], None).num_edges == 0


def test_communication_graph_equals_the_pairwise_test_on_a_crowd():
    """The vectorized graph has exactly the edges of testing every pair by its distance."""
    x = 20 * torch.rand(300, 2, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    dist = torch.cdist(x, x)
    pairs = [[i, j] for i in range(300) for j in range(i + 1, 300) if float(dist[i, j]) < 2.5]
    graph = communication_graph(x, 2.5)
    assert len(pairs) > 1000 and graph.edges.tolist() == pairs
    assert (graph.degrees() == (dist < 2.5).sum(1) - 1).all()


def _centralized(cfg: Config, x0, xref, dyn_A, dyn_c, edges, normals, bounds):
    """All agents' convexified problems solved jointly, collision rows of both agents shared."""
    K, T, D = x0.shape[0], cfg.horizon, cfg.dim
    B = 0.1 * np.eye(D)
    X = [cp.Variable((T + 1, D)) for _ in range(K)]
    U = [cp.Variable((T, D)) for _ in range(K)]
    cost, cons = 0, []
    for k in range(K):
        cost += cp.sum_squares(X[k] - xref[k]) + cfg.alpha * cp.sum_squares(U[k])
        cons.append(X[k][0] == x0[k])
        for t in range(T):
            cons.append(X[k][t + 1] == dyn_A[k, t] @ X[k][t] + B @ U[k][t] + dyn_c[k, t])
            cons.append(cp.norm(U[k][t]) <= cfg.u_max)
    for (lo, hi) in edges:
        for t in range(1, T + 1):
            for k, j in ((lo, hi), (hi, lo)):
                cons.append(normals[(k, j)][t] @ (X[k][t] - X[j][t]) >= bounds[(k, j)][t])
    cp.Problem(cp.Minimize(cost), cons).solve(solver=cp.CLARABEL)
    return np.stack([x.value for x in X]), np.stack([u.value for u in U])


@pytest.mark.parametrize("method, pair_margin", [("nonlinear", "sum"), ("nominal-chance", "own"),
                                                 ("nominal-chance", "sum"), ("nominal-chance", "joint")])
def test_admm_matches_centralized_solution(method, pair_margin):
    """Frozen linearization (cold start: every plan holds x0), run to a tight tolerance; the
    pair margins against their closed forms (own: eq. 24; sum: m_k + m_j; joint:
    Phi^-1(1 - eps) sqrt(s_k + s_j)) in an independent centralized cvxpy solve."""
    # primal-only stopping can halt at a consensus that is not yet optimal:
    # demand the dual residual too.
    cfg = Config(admm_coupling="copies", horizon=6, rho=5.0, admm_tol=1e-7, admm_dual_tol=1e-7, admm_rel_tol=0.0, admm_max_iter=1500,
                 relinearize=False,
                 eps=0.1, noise_std=0.0, pair_margin=pair_margin, terminal_cost="stage",
                 **({} if pair_margin == "joint" else {"risk_split": 0.3}))  # joint has no split
    x0 = torch.tensor([[-0.6, 0.0], [0.6, 0.1], [0.0, 0.9]], dtype=torch.float64)
    xref = torch.stack([torch.linspace(0, 1, 7, dtype=torch.float64)[:, None] * (-x0[k] * 2) + x0[k] for k in range(3)])
    wind = VortexWind(0.1)
    var = 0.04
    gps = [ConstantVarianceGP(var)] * 3 if method.endswith("chance") else None
    admm = ADMM(LocalStep(cfg, NominalModel(2), method, wind if method == "nonlinear" else None, gps))
    graph = communication_graph(x0, None)
    res = admm.solve_step(x0, xref, graph)
    assert res.converged, res.primal_residuals[-5:]

    # Closed-form linearization at the cold start (plans hold x0).
    x0n, T = x0.numpy(), cfg.horizon
    if method == "nonlinear":
        jac = wind.jacobian(x0).numpy()
        dyn_A = np.repeat((np.eye(2) + jac)[:, None], T, axis=1)
        dyn_c = np.repeat((wind(x0).numpy() - np.einsum("kde,ke->kd", jac, x0n))[:, None], T, axis=1)
    else:
        dyn_A = np.repeat(np.eye(2)[None, None], 3, axis=0).repeat(T, axis=1)
        dyn_c = np.zeros((3, T, 2))
    normals, bounds = {}, {}
    for lo, hi in graph.edges.tolist():
        for k, j in ((lo, hi), (hi, lo)):
            r = x0n[k] - x0n[j]
            normals[(k, j)] = np.repeat((r / np.linalg.norm(r))[None], T + 1, axis=0)
            eps_k = cfg.eps * (cfg.risk_split if k == lo else 1 - cfg.risk_split)
            eps_j = cfg.eps - eps_k
            margin = 0.0
            if method.endswith("chance"):
                from scipy.stats import norm as normal_dist
                own = normal_dist.ppf(1 - eps_k) * np.sqrt(var)  # n^T (v I) n = v
                margin = {"own": own, "sum": own + normal_dist.ppf(1 - eps_j) * np.sqrt(var),
                          "joint": normal_dist.ppf(1 - cfg.eps) * np.sqrt(2 * var)}[pair_margin]
            bounds[(k, j)] = np.full(T + 1, cfg.r_safe + margin)
    X_c, U_c = _centralized(cfg, x0n, xref.numpy(), dyn_A, dyn_c, graph.edges.tolist(), normals, bounds)
    np.testing.assert_allclose(res.plans.numpy(), X_c, atol=1e-4)
    np.testing.assert_allclose(res.inputs.numpy(), U_c, atol=1e-4)
    assert res.slack_max < 1e-6
    # at least one collision row is active, so the coupling really is being tested
    gaps = [normals[(k, j)][t] @ (X_c[k, t] - X_c[j, t]) - bounds[(k, j)][t]
            for (k, j) in normals for t in range(1, T + 1)]
    assert min(gaps) < 1e-5


def test_one_agent_admm_equals_direct_mpc_solve():
    cfg = Config(horizon=8, num_agents=1, scenario="circle", noise_std=0.0, terminal_cost="stage")
    x0 = torch.tensor([[1.0, -2.0]], dtype=torch.float64)
    xref = torch.linspace(0, 1, 9, dtype=torch.float64)[None, :, None] * torch.tensor([[3.0, 3.0]], dtype=torch.float64)[:, None, :] + x0[:, None, :]
    wind = VortexWind(0.1)
    admm = ADMM(LocalStep(cfg.replace(relinearize=False), NominalModel(2), "nonlinear", wind, None))
    res = admm.solve_step(x0, xref, communication_graph(x0, None))
    assert res.iterations == 1 and res.converged
    # direct cvxpy solve with the same (closed-form) linearization at x0
    T = cfg.horizon
    jac = wind.jacobian(x0)[0].numpy()
    c = wind(x0)[0].numpy() - jac @ x0[0].numpy()
    X, U = cp.Variable((T + 1, 2)), cp.Variable((T, 2))
    cons = [X[0] == x0[0].numpy()]
    for t in range(T):
        cons += [X[t + 1] == (np.eye(2) + jac) @ X[t] + 0.1 * U[t] + c, cp.norm(U[t]) <= cfg.u_max]
    cp.Problem(cp.Minimize(cp.sum_squares(X - xref[0].numpy()) + cfg.alpha * cp.sum_squares(U)), cons).solve(
        solver=cp.CLARABEL)
    np.testing.assert_allclose(res.plans[0].numpy(), X.value, atol=1e-5)
    np.testing.assert_allclose(res.inputs[0].numpy(), U.value, atol=1e-5)


def test_messages_per_iteration_formula():
    cfg = Config(admm_coupling="copies", horizon=13, admm_max_iter=1)
    x0 = torch.tensor([[-1.0, 0.0], [1.0, 0.0], [0.0, 1.5]], dtype=torch.float64)
    graph = graph_from_edges(3, [(0, 1), (1, 2)])
    res = ADMM(LocalStep(cfg, cfg.model_spec(), "nominal")).solve_step(x0, x0[:, None].expand(-1, 14, -1), graph)
    # each agent sends its copy y_{kj,k} (2 (T+1) D numbers) to each neighbour
    assert res.messages.tolist() == [2 * 14 * 2 * 1, 2 * 14 * 2 * 2, 2 * 14 * 2 * 1]


def test_warm_start_shift_drops_first_point():
    x0 = torch.tensor([[0.0, 0.0], [1.0, 1.0]], dtype=torch.float64)
    state = initial_state(x0, 3, graph_from_edges(2, [(0, 1)]))
    state.plans = torch.arange(2 * 4 * 2, dtype=torch.float64).reshape(2, 4, 2)
    shifted = state.shifted()
    assert torch.equal(shifted.plans[:, :3], state.plans[:, 1:])
    assert torch.equal(shifted.plans[:, 3], state.plans[:, 3])


def test_obstacle_problem_keeps_the_neighbours_plans_fixed():
    """The safety fallback's solve: copies pinned to the neighbours' plans (within the
    slack price / FIXED_OBSTACLE_RHO), and every (softened) collision row holds against
    those plans, with the slack used only where the fixed obstacle leaves no room."""
    from torch_gpmpc.control.examples import crossing_instance
    from torch_gpmpc.control.solvers import make_local_solver
    from torch_gpmpc.coordination.fallback import FIXED_OBSTACLE_RHO, obstacle_problem

    inst = crossing_instance(3, 2, method="nominal", variance=0.01, seed=5)
    data = inst.problem_data()
    fixed = inst.xbar_nbr
    sol = make_local_solver(13, 2, 2, NominalModel(2), 2.0, 1e-3, 1e4, "fast")(obstacle_problem(data, fixed))
    assert bool(sol.ok.all())
    pinned = 1.01 * 1e4 / FIXED_OBSTACLE_RHO  # a copy moves at most slack price / rho
    assert float((sol.Y - fixed).abs().max()) < pinned
    gap = (data.normals * (sol.X[:, None, 1:] - fixed[:, :, 1:])).sum(-1) - data.bounds
    assert float((gap + sol.slack).min()) > -pinned
    assert float(sol.slack[gap > 1e-3].abs().max()) < 1e-6


def test_buffered_voronoi_cells_closed_form_and_the_re_plan_keeps_each_agent_in_its_half():
    from torch_gpmpc.control.solvers import make_local_solver
    from torch_gpmpc.coordination.fallback import cell_exits, cell_planes, cell_problem, cell_slots
    from torch_gpmpc.coordination.state import initial_state

    # two agents at (-1, 0) and (1, 0), bound 0.5: agent 0's cell is x <= -0.25, agent 1's x >= 0.25
    x0 = torch.tensor([[-1.0, 0.0], [1.0, 0.0]], dtype=torch.float64)
    graph = communication_graph(x0, None)
    plans = x0[:, None].repeat(1, 4, 1)
    n, m = cell_planes(plans, plans[graph.slot_nbr], [0, 1])
    torch.testing.assert_close(n[:, 0], torch.tensor([[-1.0, 0.0], [1.0, 0.0]], dtype=torch.float64))
    torch.testing.assert_close(m[:, 0], torch.zeros(2, dtype=torch.float64))
    bounds = torch.full((2, 1), 0.5, dtype=torch.float64)
    plans[0, 1, 0], plans[1, 1, 0] = -0.2, 0.3  # agent 0 steps over its plane, agent 1 stays inside
    assert cell_exits(plans, graph, bounds, 1e-3, [0, 1]).any(dim=1).tolist() == [True, False]
    assert cell_slots(torch.tensor([False, False]), graph).tolist() == [[True], [True]]
    assert cell_slots(torch.tensor([False, True]), graph).tolist() == [[False], [False]]  # a pair with momentum

    # both re-plan at once, heading straight at each other: each keeps to its half at every step
    T = 6
    nominal = NominalModel(2)
    state = initial_state(x0, T, graph)
    xref = x0.flip(0)[:, None].expand(2, T + 1, 2).clone()
    admm = ADMM(LocalStep(Config(method="nominal", horizon=T), nominal))
    ctx, state = admm.prepare(x0, xref, graph, None)
    assembled = admm.agent_step.assemble(x0, xref, state, graph, ctx.rho, ctx.eps_self)
    data = assembled.data
    sol = make_local_solver(T, 2, 1, nominal, 2.0, 1e-3, 1e4, "fast")(
        cell_problem(data, state.plans, state.plans[graph.slot_nbr], [0, 1]))
    assert bool(sol.ok.all()) and float(sol.slack.max()) < 1e-8
    # within what the pinned copies move (FIXED_OBSTACLE_RHO), here a few 1e-6
    assert float(sol.X[0, 1:, 0].max()) <= -0.25 + 1e-5 and float(sol.X[1, 1:, 0].min()) >= 0.25 - 1e-5
    assert float((sol.X[0, 1:] - sol.X[1, 1:]).norm(dim=-1).min()) >= 0.5 - 2e-5


def test_cell_rows_price_slack_by_danger_so_a_jam_opens_its_closest_pair_first():
    """Three agents on a line, every pair inside its bound 1.0: the middle one cannot keep both cell
    rows at tau = 1. With equal slack prices it is indifferent between them and tracking (a target
    on the left) sends it towards its 0.6 m neighbour; priced by danger ((b - c) / (d - c): 5 for the
    0.6 m pair, 1.43 for the 0.85 m pair, contact c = 0.5) it opens the closest pair instead, also
    when the close neighbour has momentum and its row is against that neighbour's plan."""
    from torch_gpmpc.control.solvers import make_local_solver
    from torch_gpmpc.coordination.fallback import (
        MAX_DANGER_WEIGHT, cell_problem, cell_slots, danger_weights, fallback_problem,
    )

    T = 6
    x0 = torch.tensor([[-0.6, 0.0], [0.0, 0.0], [0.85, 0.0]], dtype=torch.float64)
    graph = communication_graph(x0, None)
    nominal = NominalModel(2)
    admm = ADMM(LocalStep(Config(method="nominal", horizon=T, r_safe=1.0), nominal))
    xref = torch.tensor([[-3.0, 0.0], [-3.0, 0.0], [3.0, 0.0]], dtype=torch.float64)[:, None].expand(3, T + 1, 2).clone()
    ctx, state = admm.prepare(x0, xref, graph, None)
    data = admm.agent_step.assemble(x0, xref, state, graph, ctx.rho, ctx.eps_self).data
    nbr = state.plans[graph.slot_nbr]
    w = danger_weights(state.plans, nbr, data.bounds[:, :, 0], 0.5, [0, 1])
    torch.testing.assert_close(w, torch.tensor([[5.0, 1.0], [5.0, 0.5 / 0.35], [1.0, 0.5 / 0.35]], dtype=torch.float64))
    inside = danger_weights(state.plans, nbr, data.bounds[:, :, 0], 0.7, [0, 1])  # the 0.6 m pair in contact
    assert float(inside[0, 0]) == MAX_DANGER_WEIGHT

    solve = make_local_solver(T, 2, 2, nominal, 2.0, 1e-3, 1e4, "fast")
    equal = solve(cell_problem(data, state.plans, nbr, [0, 1]))
    priced = solve(fallback_problem(data, state.plans, nbr, [0, 1], graph.active, contact=0.5))
    assert bool(equal.ok.all()) and bool(priced.ok.all())
    # the outer agents step away at full speed either way
    torch.testing.assert_close(priced.X[[0, 2], 1, 0], torch.tensor([-0.8, 1.05], dtype=torch.float64))
    assert float(equal.X[1, 1, 0]) < 0.0  # towards the close neighbour: 0.735 m from it
    assert abs(float(priced.X[1, 1, 0]) - 0.2) < 1e-3  # away at full speed: its bound kept, 0.85 m to the other
    closest = lambda sol: float(torch.pdist(sol.X[:, 1]).min())  # noqa: E731
    assert closest(priced) > closest(equal) + 0.1
    # agent 0 with momentum: the middle agent's row towards it is against its plan, its row towards
    # agent 2 a cell; it prices both on one scale and still opens the close pair
    cells = cell_slots(torch.tensor([True, False, False]), graph)
    mixed = solve(fallback_problem(data, state.plans, nbr, [0, 1], cells, contact=0.5))
    assert bool(mixed.ok.all()) and abs(float(mixed.X[1, 1, 0]) - 0.2) < 1e-3
    # pairs outside their bounds keep weight 1: the re-plan is the unpriced one to the bit
    far = x0 * 3.0
    ctx, state = admm.prepare(far, xref, communication_graph(far, None), None)
    data = admm.agent_step.assemble(far, xref, state, graph, ctx.rho, ctx.eps_self).data
    a = solve(cell_problem(data, state.plans, state.plans[graph.slot_nbr], [0, 1]))
    b = solve(fallback_problem(data, state.plans, state.plans[graph.slot_nbr], [0, 1], graph.active, contact=0.5))
    assert torch.equal(a.X, b.X)


def test_fallback_solves_only_the_agents_that_replan():
    """The fallback's re-plans of a few agents of a batch (the other agents' problems are not
    solved) are the whole batch's solves of those agents, to round-off."""
    from torch_gpmpc.coordination.fallback import cell_problem

    T = 6
    x0 = torch.tensor([[-0.6, 0.0], [0.0, 0.3], [0.85, 0.0], [0.2, -0.7]], dtype=torch.float64)
    graph = communication_graph(x0, None)
    admm = ADMM(LocalStep(Config(method="nominal", horizon=T, r_safe=0.5), NominalModel(2)))
    xref = x0.flip(0)[:, None].expand(4, T + 1, 2).clone()
    ctx, state = admm.prepare(x0, xref, graph, None)
    data = admm.agent_step.assemble(x0, xref, state, graph, ctx.rho, ctx.eps_self).data
    posed = cell_problem(data, state.plans, state.plans[graph.slot_nbr], [0, 1])
    layer = admm.agent_step.solver(data.active.shape[1])
    whole = admm.agent_step.solve(layer, posed)
    rows = torch.tensor([3, 1])
    part = admm.agent_step.solve_agents(layer, posed, rows)
    assert bool(part.ok.all()) and part.X.shape == (2, T + 1, 2)
    torch.testing.assert_close(part.X, whole.X[rows], rtol=0, atol=1e-12)
    torch.testing.assert_close(part.U, whole.U[rows], rtol=0, atol=1e-12)


def test_a_capped_step_applies_the_replans_of_its_agents_and_keeps_the_rest():
    """Eight agents on a circle crossing at once and three far from them, ADMM capped at one
    iteration (copies): a step ends in the fallback, which re-plans some of the eight. Its applied plans equal those of re-planning the whole batch and keeping
    the named agents' solves (to round-off); an agent whose re-plan fails keeps the plan it had."""
    import dataclasses
    import functools
    import math

    from torch_gpmpc.control.problem import select_problems, select_solution

    T, K = 8, 8
    angle = torch.arange(K, dtype=torch.float64) * 2 * math.pi / K
    circle = 1.2 * torch.stack([angle.cos(), angle.sin()], dim=-1)
    far = torch.tensor([[10.0, 0.0], [10.0, 3.0], [-10.0, 0.0]], dtype=torch.float64)  # never re-plan
    x0 = torch.cat([far, circle])
    K = x0.shape[0]
    xref = torch.cat([far + 1.0, -circle])[:, None].expand(K, T + 1, 2).clone()
    cfg = Config(method="nominal", horizon=T, admm_coupling="copies", admm_max_iter=1)

    def step_with(solve_agents):
        """The first step of the crossing that ends in the fallback (the steps before it never call
        ``solve_agents``, so every variant reaches the same one)."""
        admm = ADMM(LocalStep(cfg, NominalModel(2)))
        admm.agent_step.solve_agents = functools.partial(solve_agents, admm.agent_step)
        x, warm = x0, None
        for _ in range(30):
            res = admm.solve_step(x, xref, communication_graph(x, None), warm=warm)
            if res.fallback or res.unsafe_plan:
                return res
            x, warm = res.plans[:, 1], res.state
        raise AssertionError("no step ended in the fallback")

    def subset(step, layer, data, rows):
        return step.solve(layer, select_problems(data, rows))

    def whole_batch(step, layer, data, rows):
        return select_solution(step.solve(layer, data), rows)

    def none_solved(step, layer, data, rows):
        sol = subset(step, layer, data, rows)
        return dataclasses.replace(sol, ok=torch.zeros_like(sol.ok))

    def first_fails(step, layer, data, rows):
        sol = subset(step, layer, data, rows)
        ok = sol.ok.clone()
        ok[0] = False
        return dataclasses.replace(sol, ok=ok)

    mine = step_with(subset)
    assert mine.fallback
    torch.testing.assert_close(mine.plans, step_with(whole_batch).plans, rtol=0, atol=1e-12)
    kept = step_with(none_solved)  # what the step applies when no re-plan succeeds
    replanned = (mine.plans - kept.plans).abs().amax(dim=(1, 2)) > 0
    assert bool(replanned.any()) and not bool(replanned[:3].any())
    partial = step_with(first_fails)
    first = int(replanned.nonzero()[0])
    torch.testing.assert_close(partial.plans[first], kept.plans[first], rtol=0, atol=0)
    rest = replanned.clone()
    rest[first] = False
    torch.testing.assert_close(partial.plans[rest], mine.plans[rest], rtol=0, atol=0)


def test_buffered_voronoi_fallback_keeps_a_capped_crowd_safe():
    """ADMM capped at 2 iterations in a crowded crossing (8 agents on a circle, noiseless): the
    fallback acts on most steps; no pair comes closer than r_safe and every agent arrives."""
    from torch_gpmpc.sim.closed_loop import simulate
    from torch_gpmpc.sim.metrics import compute_metrics

    cfg = Config(admm_coupling="copies", scenario="circle", num_agents=8, admm_max_iter=2, noise_std=0.0, gp_samples=50, gp_iters=20)
    m = compute_metrics(simulate(cfg))
    assert m["converged_fraction"] == 0.0 and m["fallback_steps"] > 20
    assert m["violations"] == 0 and m["min_pair_distance"] >= cfg.r_safe
    assert all(a is not None for a in m["arrival_steps"])
    with pytest.raises(GpmpcError, match="'safety_fallback'.*cells, obstacles"):
        cfg.replace(safety_fallback="cell")


def test_capped_admm_falls_back_to_safe_plans_in_closed_loop():
    """Two ADMM iterations per step (the cap binds at almost every step): the fallback
    re-plans at some steps and no pair comes closer than r_safe (noiseless crossing)."""
    from torch_gpmpc.sim.closed_loop import simulate
    from torch_gpmpc.sim.metrics import compute_metrics

    cfg = Config(admm_coupling="copies", admm_max_iter=2, max_steps=40, gp_iters=10, noise_std=0.0)
    m = compute_metrics(simulate(cfg))
    assert m["converged_fraction"] < 0.2
    assert m["fallback_steps"] > 0
    assert m["violations"] == 0 and m["min_pair_distance"] >= cfg.r_safe
