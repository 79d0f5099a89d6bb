"""The public step API (Controller), the per-agent step, one ADMM iteration, the centralized
planner and the distributed agent, all built from a model object.

Independent answers: the message-size formula 2 (T+1) n (+ T), the centralized cvxpy solve of
the same convexified step, central finite differences for the gradients.
"""

from __future__ import annotations

import dataclasses

import pytest
import torch

from tests.helpers import ConstantVarianceGP
from torch_gpmpc import ADMM, Controller, ControllerSettings, LocalStep, ModelSpec
from torch_gpmpc.config import Config
from torch_gpmpc.coordination.centralized import CentralizedPlanner, plan_cost, solve_centralized
from torch_gpmpc.coordination.distributed.agent import AgentController
from torch_gpmpc.coordination.graph import communication_graph
from torch_gpmpc.errors import GpmpcError

F64 = torch.float64


def swap(model: ModelSpec, horizon: int, gap: float = 1.0):
    """Two agents swapping places on the x axis, slightly off-line (K, n) and (K, T+1, n)."""
    from torch_gpmpc.dynamics.systems import NominalModel

    nominal = NominalModel(model)
    p0 = torch.tensor([[-gap, 0.05], [gap, -0.05]], dtype=F64)
    s = torch.linspace(0, 1, horizon + 1, dtype=F64)[None, :, None]
    path = p0[:, None] + s * (-2 * p0[:, None])
    return nominal.states_at(p0), nominal.reference_states(path)


def test_double_integrator_from_a_model_spec_reports_its_own_message_size_and_uncertainty():
    model = ModelSpec.double_integrator(dim=2, dt=0.1, u_max=2.0)
    ctrl = Controller(model, settings=ControllerSettings(admm_coupling="copies", method="nominal", horizon=5))
    assert ctrl.message_size == 48 == 2 * (5 + 1) * 4
    assert ctrl.uncertainty == "propagated"
    chance = Controller(model, gps=[ConstantVarianceGP(0.01)] * 2, settings=ControllerSettings(admm_coupling="copies", horizon=5))
    assert chance.message_size == 48 + 5  # the T projected variances of the sum margin
    assert Controller(ModelSpec.single_integrator(2), settings=ControllerSettings(
        method="nominal", horizon=5)).uncertainty == "pointwise"
    # the same model through a default Config: the model decides, not the config's model string
    admm = ADMM(LocalStep(Config(admm_coupling="copies", horizon=5, method="nominal"), model))
    assert admm.agent_step.message_size == 48 and admm.agent_step.uncertainty == "propagated"


def test_controller_step_is_the_admm_step_and_reaches_the_centralized_optimum():
    model = ModelSpec.double_integrator(dim=2)
    settings = ControllerSettings(admm_coupling="copies", method="nominal", horizon=8, admm_max_iter=300, admm_tol=1e-5,
                                  admm_rel_tol=0.0)
    x0, xref = swap(model, 8)
    ctrl = Controller(model, settings=settings)
    step = ctrl.step(x0, xref)
    admm = ADMM(LocalStep(settings, model))
    again = admm.solve_step(x0, xref, communication_graph(x0[:, :2], None))
    torch.testing.assert_close(step.plans, again.plans, rtol=0, atol=0)
    assert step.converged and tuple(step.inputs.shape) == (2, 8, 2)
    central = solve_centralized(step.problem, communication_graph(x0[:, :2], None), ctrl.model)
    admm_cost = plan_cost(step.plans, step.inputs, xref, settings.alpha)
    assert admm_cost == pytest.approx(plan_cost(central.plans, central.inputs, xref, settings.alpha), rel=1e-3)
    # the warm start is kept, detached, for the next step
    assert ctrl.warm is not None and not ctrl.warm.plans.requires_grad
    ctrl.reset()
    assert ctrl.warm is None


def test_input_rate_term_uses_the_applied_input_and_admm_reaches_the_centralized_optimum():
    """With ``input_rate_weight`` the second step's problems carry the first step's applied inputs
    as U_{-1}, and ADMM stops at the centralized optimum of that cost (1e-3)."""
    model = ModelSpec.double_integrator(dim=2)
    settings = ControllerSettings(admm_coupling="copies", method="nominal", horizon=8, admm_max_iter=300, admm_tol=1e-5,
                                  admm_rel_tol=0.0, input_rate_weight=0.5)
    x0, xref = swap(model, 8)
    ctrl = Controller(model, settings=settings)
    first = ctrl.step(x0, xref)
    assert first.problem.u_prev is None  # a cold start: U_{-1} = 0
    x1 = x0 @ model_matrix(model, "A").T + first.inputs[:, 0] @ model_matrix(model, "B").T
    second = ctrl.step(x1, xref)
    torch.testing.assert_close(second.problem.u_prev, first.inputs[:, 0], rtol=0, atol=0)
    graph = communication_graph(x1[:, :2], None)
    central = solve_centralized(second.problem, graph, ctrl.model, input_rate_weight=0.5)
    cost = plan_cost(second.plans, second.inputs, xref, settings.alpha, 0.5, first.inputs[:, 0])
    assert second.converged
    assert cost == pytest.approx(plan_cost(central.plans, central.inputs, xref, settings.alpha, 0.5,
                                           first.inputs[:, 0]), rel=1e-3)
    plain = Controller(model, settings=settings.replace(input_rate_weight=0.0))
    plain.step(x0, xref)
    assert float((plain.step(x1, xref).inputs - second.inputs).abs().max()) > 1e-3


def model_matrix(model: ModelSpec, name: str) -> torch.Tensor:
    return torch.tensor(getattr(model, name), dtype=F64)


def test_iterate_is_pure_and_the_step_is_its_loop():
    model = ModelSpec.single_integrator(2)
    settings = ControllerSettings(admm_coupling="copies", method="nominal", horizon=6, admm_max_iter=7, admm_tol=1e-9)
    admm = ADMM(LocalStep(settings, model))
    x0, xref = swap(model, 6)
    graph = communication_graph(x0, None)
    ctx, state = admm.prepare(x0, xref, graph)
    before = dataclasses.replace(state, plans=state.plans.clone(), z=state.z.clone(), lam=state.lam.clone())
    first, stats_a = admm.iterate(ctx, state)
    again, stats_b = admm.iterate(ctx, state)
    assert torch.equal(first.plans, again.plans) and torch.equal(first.lam, again.lam)
    assert float(stats_a.primal) == float(stats_b.primal)
    assert torch.equal(state.plans, before.plans) and torch.equal(state.lam, before.lam)  # not mutated
    for _ in range(6):
        first, _ = admm.iterate(ctx, first)
    step = admm.solve_step(x0, xref, graph)
    assert step.iterations == 7 and not step.converged
    torch.testing.assert_close(step.state.z, first.z, rtol=0, atol=0)


def test_step_gradients_to_rho_and_split_match_finite_differences():
    model = ModelSpec.single_integrator(2)
    settings = ControllerSettings(admm_coupling="copies", method="nominal-chance", horizon=6, admm_max_iter=8, admm_tol=1e-12,
                                  admm_dual_tol=1e-12, r_safe=0.5)
    ctrl = Controller(model, gps=[ConstantVarianceGP(0.02), ConstantVarianceGP(0.05)], settings=settings)
    x0, xref = swap(model, 6, gap=0.6)

    def cost(rho, split):  # 8 iterations, unconverged: no safety fallback (its plans do not depend on rho)
        ctrl.reset()
        step = ctrl.step(x0, xref, rho=rho, risk_split=split, safety_fallback=False)
        return ((step.plans - xref) ** 2).sum()

    rho = torch.tensor(5.0, dtype=F64, requires_grad=True)
    split = torch.tensor(0.3, dtype=F64, requires_grad=True)
    cost(rho, split).backward()
    with torch.no_grad():
        fd_rho = (cost(5.0 + 1e-5, 0.3) - cost(5.0 - 1e-5, 0.3)) / 2e-5
        fd_split = (cost(5.0, 0.3 + 1e-6) - cost(5.0, 0.3 - 1e-6)) / 2e-6
    assert abs(float(split.grad)) > 1e-3  # the collision rows bind
    assert float(rho.grad) == pytest.approx(float(fd_rho), rel=1e-4)
    assert float(split.grad) == pytest.approx(float(fd_split), rel=1e-4)


def test_controller_refuses_bad_input_naming_the_field():
    model = ModelSpec.double_integrator(dim=2)
    with pytest.raises(GpmpcError, match="needs one residual model per agent"):
        Controller(model)  # gp-chance without GPs
    ctrl = Controller(model, settings=ControllerSettings(method="nominal", horizon=4))
    x0, xref = swap(model, 4)
    with pytest.raises(GpmpcError, match=r"xref must have shape \(2, 5, 4\)"):
        ctrl.step(x0, xref[:, :3])
    with pytest.raises(GpmpcError, match=r"x must have shape \(K, 4\)"):
        ctrl.step(x0[:, :2], xref)
    with pytest.raises(GpmpcError, match="controller setting 'horizon'"):
        ControllerSettings(horizon=0)
    with pytest.raises(GpmpcError, match="did you mean 'admm_tol'"):
        ControllerSettings().replace(admm_tl=1e-3)


def test_controllers_own_their_solvers():
    model = ModelSpec.single_integrator(2)
    a = Controller(model, settings=ControllerSettings(method="nominal"))
    b = Controller(model, settings=ControllerSettings(method="nominal"))
    assert a.agent_step.solver(1) is a.agent_step.solver(1)
    assert a.agent_step.solver(1) is not b.agent_step.solver(1)


def test_centralized_planner_takes_the_per_agent_step():
    model = ModelSpec.double_integrator(dim=2)
    step = LocalStep(ControllerSettings(method="nominal", horizon=6), model)
    planner = CentralizedPlanner(step, relinearizations=2)
    x0, xref = swap(model, 6)
    graph = communication_graph(x0[:, :2], None)
    res = planner.plan(0, x0, xref, graph)
    assert res.converged and res.iterations == 2 and tuple(res.inputs.shape) == (2, 6, 2)
    again = solve_centralized(res.problem, graph, step.nominal)
    torch.testing.assert_close(res.plans, again.plans, rtol=0, atol=1e-7)
    assert planner.warm is not None  # the shifted plans linearize the next step


def test_distributed_agent_builds_only_its_per_agent_step():
    cfg = Config(admm_coupling="copies", model="double-integrator", horizon=5, method="nominal", scenario="circle", num_agents=3)
    agent = AgentController(0, 3, cfg, torch.zeros(10, 2, dtype=F64))
    assert isinstance(agent.local, LocalStep)
    assert agent.message_size == 2 * 6 * 4 and agent.local.uncertainty == "propagated"


def test_per_agent_step_bounds_are_r_safe_plus_both_margins_in_closed_form():
    """Pointwise variance v in every direction: each row carries 2 Phi^-1(1 - eps/2) sqrt(v) (sum margin,
    the neighbour's variance reported as the agent's own before the first exchange)."""
    from torch_gpmpc.coordination.agent_step import slot_risks
    from torch_gpmpc.coordination.state import initial_state

    settings = ControllerSettings(horizon=4, margin_variance="latent")
    step = LocalStep(settings, ModelSpec.single_integrator(2), gps=[ConstantVarianceGP(0.04)] * 3)
    x0 = torch.tensor([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]], dtype=F64)
    graph = communication_graph(x0, None)
    state = initial_state(x0, 4, graph)
    assembled = step.assemble(x0, x0[:, None].expand(3, 5, 2), state, graph, torch.tensor(20.0, dtype=F64),
                              slot_risks(graph, 0.1, 0.5))
    q = float(torch.special.ndtri(torch.tensor(1 - 0.05, dtype=F64)))
    expected = 0.5 + 2 * q * 0.2
    torch.testing.assert_close(assembled.data.bounds, torch.full_like(assembled.data.bounds, expected))
    assert tuple(assembled.own_variance.shape) == (3, 2, 4)
    torch.testing.assert_close(assembled.own_variance, torch.full((3, 2, 4), 0.04, dtype=F64))


def test_admm_state_carries_kept_edges_and_starts_new_ones_from_the_plans():
    from torch_gpmpc.coordination.graph import graph_from_edges
    from torch_gpmpc.coordination.state import adapt_state, initial_state

    x0 = torch.tensor([[0.0, 0.0], [1.0, 0.0], [2.0, 0.0]], dtype=F64)
    old = graph_from_edges(3, [(0, 1)])
    state = initial_state(x0, 3, old)
    state = dataclasses.replace(state, lam=state.lam + 1.0, rho=torch.tensor([7.0], dtype=F64),
                                pvar=torch.ones(1, 2, 3, dtype=F64))
    new = graph_from_edges(3, [(0, 1), (1, 2)])
    moved = adapt_state(state, new)
    assert torch.equal(moved.edges, new.edges)
    e01 = new.edges.tolist().index([0, 1])
    e12 = new.edges.tolist().index([1, 2])
    assert torch.all(moved.lam[e01] == 1.0) and torch.all(moved.lam[e12] == 0.0)
    assert float(moved.rho[e01]) == 7.0 and torch.isnan(moved.rho[e12])
    torch.testing.assert_close(moved.z[e12], moved.plans[[1, 2]])
    assert torch.isnan(moved.pvar[e12]).all() and torch.all(moved.pvar[e01] == 1.0)
    shifted = state.shifted()
    torch.testing.assert_close(shifted.plans[:, :-1], state.plans[:, 1:])
    assert not state.detached().lam.requires_grad


@pytest.mark.parametrize("solver", ["fast", "clarabel"])
def test_a_stated_cost_through_admm_reaches_the_centralized_optimum(solver):
    """Controller(cost=QuadraticCost(...)): the problems carry the cost, ADMM converges to the
    centralized solve of the same cost (1e-3), and the plan differs from the default cost's."""
    from torch_gpmpc import QuadraticCost

    model = ModelSpec.double_integrator(dim=2)
    settings = ControllerSettings(admm_coupling="copies", method="nominal", horizon=8, admm_max_iter=300, admm_tol=1e-5,
                                  admm_rel_tol=0.0, solver=solver)
    cost = QuadraticCost(Q=torch.tensor([2.0, 1.0, 0.2, 0.1], dtype=F64), R=0.05,
                         P=torch.diag(torch.tensor([20.0, 20.0, 1.0, 1.0], dtype=F64)),
                         u_ref=torch.tensor([0.1, 0.0], dtype=F64))
    x0, xref = swap(model, 8)
    ctrl = Controller(model, settings=settings, cost=cost)
    step = ctrl.step(x0, xref)
    assert step.converged and step.problem.cost_Q is not None
    torch.testing.assert_close(step.problem.cost_P[0], cost.P)
    central = solve_centralized(step.problem, communication_graph(x0[:, :2], None), ctrl.model)
    admm_cost = plan_cost(step.plans, step.inputs, xref, settings.alpha, problem=step.problem)
    assert admm_cost == pytest.approx(plan_cost(central.plans, central.inputs, xref, settings.alpha,
                                                problem=step.problem), rel=1e-3)
    default = Controller(model, settings=settings).step(x0, xref)
    assert float((default.inputs - step.inputs).abs().max()) > 1e-3


def test_per_agent_costs_and_the_default_lqr_terminal_weight():
    from torch_gpmpc import QuadraticCost
    from torch_gpmpc.control.cost import lqr_terminal_weight

    model = ModelSpec.double_integrator(dim=2)
    x0, xref = swap(model, 6)
    settings = ControllerSettings(method="nominal", horizon=6)
    ctrl = Controller(model, settings=settings, cost=[QuadraticCost(Q=1.0, R=0.1), QuadraticCost(Q=5.0, R=0.1)])
    problem = ctrl.step(x0, xref).problem
    assert problem.cost_Q[0, 0, 0] == 1.0 and problem.cost_Q[1, 0, 0] == 5.0
    default = Controller(model, settings=settings).step(x0, xref).problem
    A, B = model_matrix(model, "A"), model_matrix(model, "B")
    torch.testing.assert_close(default.cost_P[0], lqr_terminal_weight(A, B, torch.eye(4, dtype=F64),
                                                                      1e-3 * torch.eye(2, dtype=F64)))
    paper = Controller(model, settings=settings.replace(terminal_cost="stage")).step(x0, xref).problem
    assert paper.cost_Q is None  # the paper's cost: ||X - Xref||^2 + alpha ||U||^2
    with pytest.raises(GpmpcError, match="one QuadraticCost for all agents or one per agent|3 costs"):
        Controller(model, settings=settings, cost=[QuadraticCost(Q=1.0, R=0.1)] * 3).step(x0, xref)
