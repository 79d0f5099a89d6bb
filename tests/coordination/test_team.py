"""Mixed teams: models lifted to common sizes, one local step per model, one consensus ADMM.

Independent answers: the unlifted model's own plan (lifting must not change it), and the
one-model ADMM (a team whose groups share one model must plan exactly as that model's step).
"""

from __future__ import annotations

import json

import pytest
import torch

from tests.helpers import ConstantVarianceGP
from torch_gpmpc import ADMM, Controller, ControllerSettings, LocalStep, ModelSpec
from torch_gpmpc.config import Config
from torch_gpmpc.config.team import TeamSpec, lift_spec, team_spec
from torch_gpmpc.coordination.graph import communication_graph
from torch_gpmpc.coordination.mission_risk import starting_budgets
from torch_gpmpc.coordination.team_step import TeamStep
from torch_gpmpc.dynamics.systems import NominalModel
from torch_gpmpc.dynamics.team import TeamNominal
from torch_gpmpc.errors import GpmpcError

F64 = torch.float64
DI, SI = ModelSpec.double_integrator(2), ModelSpec.single_integrator(2)


def crossing(nominal, K: int, horizon: int, radius: float = 1.5):
    """K agents on a circle heading for the antipodes: states (K, n) and references (K, T+1, n)."""
    angle = torch.arange(K, dtype=F64) * 2 * torch.pi / K + 0.1
    p0 = radius * torch.stack([angle.cos(), angle.sin()], dim=1)
    s = torch.linspace(0, 0.6, horizon + 1, dtype=F64)[None, :, None]
    return nominal.states_at(p0), nominal.reference_states(p0[:, None] * (1 - 2 * s))


def test_a_lifted_model_plans_exactly_as_the_model():
    settings = ControllerSettings(method="nominal", horizon=8)
    x0, xref = crossing(NominalModel(SI), 2, 8)
    own = Controller(SI, settings=settings).step(x0, xref)
    lifted = lift_spec(SI, 4, 3)
    pad = lambda t: torch.cat([t, torch.zeros(*t.shape[:-1], 2, dtype=F64)], dim=-1)  # noqa: E731
    step = Controller(lifted, settings=settings).step(pad(x0), pad(xref))
    torch.testing.assert_close(step.plans[..., :2], own.plans, rtol=0, atol=1e-7)
    assert step.plans[..., 2:].abs().max() == 0 and step.inputs[..., 2].abs().max() < 1e-7
    torch.testing.assert_close(step.inputs[..., :2], own.inputs, rtol=0, atol=1e-6)


@pytest.mark.parametrize("method", ["nominal", "gp-chance"])
def test_a_team_split_into_groups_of_one_model_plans_as_that_model(method):
    # the team step's split, assembly per group and merge in agent order must be exact
    settings = ControllerSettings(method=method, horizon=6, admm_max_iter=30)
    team = TeamSpec(models=(DI, DI), group_of=(0, 1, 1, 0), own_dims=((4, 2), (4, 2)))
    gps = [ConstantVarianceGP(0.002 * (k + 1)) for k in range(4)] if method == "gp-chance" else None
    x0, xref = crossing(TeamNominal(team), 4, 6)
    graph = communication_graph(x0[:, :2], None)
    one = ADMM(LocalStep(settings, DI, gps=gps)).solve_step(x0, xref, graph)
    split = ADMM(TeamStep(settings, team, gps=gps)).solve_step(x0, xref, graph)
    assert split.iterations == one.iterations
    torch.testing.assert_close(split.plans, one.plans, rtol=0, atol=1e-9)
    torch.testing.assert_close(split.inputs, one.inputs, rtol=0, atol=1e-9)


def test_drones_and_ground_robots_plan_with_their_own_dynamics_and_bounds():
    robot = ModelSpec.single_integrator(2, u_max=1.0)
    team = team_spec([DI, robot, DI, robot])
    settings = ControllerSettings(admm_coupling="copies", method="nominal-chance", horizon=8, admm_max_iter=60)
    gps = [ConstantVarianceGP(0.001)] * 4
    step = TeamStep(settings, team, gps=gps)
    x0, xref = crossing(step.nominal, 4, 8)
    res = ADMM(step).solve_step(x0, xref, communication_graph(x0[:, :2], None))
    X, U = res.plans, res.inputs
    for k in (1, 3):  # robots: p' = p + 0.1 u, ||u|| <= 1, no velocity state
        torch.testing.assert_close(X[k, 1:, :2], X[k, :-1, :2] + 0.1 * U[k, :, :2], rtol=0, atol=1e-7)
        assert X[k, :, 2:].abs().max() == 0 and U[k].norm(dim=-1).max() <= 1.0 + 1e-6
    for k in (0, 2):  # drones: the double integrator, ||a|| <= 2
        A, B = torch.tensor(DI.A, dtype=F64), torch.tensor(DI.B, dtype=F64)
        torch.testing.assert_close(X[k, 1:], X[k, :-1] @ A.T + U[k] @ B.T, rtol=0, atol=1e-7)
        assert U[k].norm(dim=-1).max() <= 2.0 + 1e-6
    assert step.message_size == 2 * 9 * 4 + 8  # lifted state, plus the T variances of the sum margin


def test_the_controller_takes_one_model_per_agent():
    settings = ControllerSettings(admm_coupling="copies", method="nominal", horizon=6)
    ctrl = Controller([DI, SI, DI], settings=settings)
    assert isinstance(ctrl.agent_step, TeamStep) and ctrl.model.dim == 4 and ctrl.message_size == 2 * 7 * 4
    x0, xref = crossing(ctrl.model, 3, 6)
    step = ctrl.step(x0, xref)
    again = ADMM(TeamStep(settings, team_spec([DI, SI, DI]))).solve_step(x0, xref, ctrl.graph(x0))
    torch.testing.assert_close(step.plans, again.plans, rtol=0, atol=0)
    assert isinstance(Controller([DI, DI], settings=settings).agent_step, LocalStep)  # one model: as before


def test_models_that_cannot_plan_together_are_refused_naming_the_fix():
    with pytest.raises(GpmpcError, match="sampling time"):
        team_spec([ModelSpec.double_integrator(2, dt=0.2), SI])
    with pytest.raises(GpmpcError, match="position indices"):
        team_spec([DI, ModelSpec.from_table({"A": [[1.0, 0], [0, 1]], "B": [[0.1, 0], [0, 0.1]], "position": [1, 0],
                                              "residual": [0, 1], "input_bound": {"norm": 1.0}})])
    with pytest.raises(GpmpcError, match="residual rows"):
        team_spec([DI, ModelSpec.from_table({"A": [[1.0, 0], [0, 1]], "B": [[0.1, 0], [0, 0.1]], "position": [0, 1],
                                              "residual": [0], "input_bound": {"norm": 1.0}})])
    with pytest.raises(GpmpcError, match="'models'.*does not exist"):
        Config(models=["double-integrator", "no-such-model.toml"])
    cfg = Config(scenario="circle", num_agents=3, models=["double-integrator", "single-integrator"])
    from torch_gpmpc.sim.closed_loop import simulate

    with pytest.raises(GpmpcError, match="2 models for 3 agents"):
        simulate(cfg.replace(method="nominal"))


def test_a_scenario_file_gives_each_agent_its_model(tmp_path):
    (tmp_path / "robot.toml").write_text(
        'A = [[1.0, 0.0], [0.0, 1.0]]\nB = [[0.1, 0.0], [0.0, 0.1]]\nposition = [0, 1]\nresidual = [0, 1]\n'
        '[input_bound]\nnorm = 1.0\n')
    path = tmp_path / "team.json"
    path.write_text(json.dumps({"starts": [[-1.5, 0.1], [1.5, -0.1]], "targets": [[1.5, 0.1], [-1.5, -0.1]],
                                "models": ["double-integrator", "robot.toml"]}))
    from torch_gpmpc.sim.closed_loop import simulate
    from torch_gpmpc.sim.metrics import compute_metrics
    from torch_gpmpc.sim.scenarios import make_scenario, with_scenario_world

    # exact nominal models; pair_buffer: the plans keep r_safe beyond the consensus tolerance
    cfg = Config(method="nominal", noise_std=0.0, wind_scale=0.0, max_steps=80, pair_buffer=0.005)
    scenario = make_scenario(cfg, path)
    assert scenario.models == ("double-integrator", str(tmp_path / "robot.toml"))
    assert with_scenario_world(cfg, scenario).team().own_dims == ((4, 2), (2, 2))
    rollout = simulate(cfg, scenario)
    metrics = compute_metrics(rollout)
    assert metrics["reached"] and metrics["violations"] == 0
    assert rollout.states.shape[-1] == 4 and float(abs(rollout.states[:, 1, 2:]).max()) == 0.0


def test_drones_and_ground_robots_of_different_radii_cross_the_vortex_with_learned_gps():
    # 2 double-integrator drones (radius 0.2) and 2 single-integrator robots (0.3) swap sides of the
    # paper's circle through the vortex, each with its own learned GP (gp-chance), noiseless
    from torch_gpmpc.sim.closed_loop import simulate
    from torch_gpmpc.sim.metrics import compute_metrics

    cfg = Config(scenario="circle", num_agents=4, noise_std=0.0, pair_buffer=0.01, gp_samples=40, gp_iters=20,
                 models=["double-integrator", "single-integrator"] * 2, radii=[0.2, 0.3, 0.2, 0.3])
    rollout = simulate(cfg)
    metrics = compute_metrics(rollout)
    assert metrics["reached"] and metrics["violations"] == 0 and metrics["failed_local_solves"] == 0
    assert metrics["min_pair_clearance"] >= 0.0
    assert float(abs(rollout.states[:, 1::2, 2:]).max()) == 0.0  # the robots have no velocity


@pytest.mark.slow
@pytest.mark.parametrize("noise_std", [0.0, 0.1])
def test_three_drones_and_three_robots_cross_safely_under_a_mission_budget(noise_std):
    # the mixed team (README "Mixed teams"): 0 violations measured on seeds 0-4 both ways
    from torch_gpmpc.sim.closed_loop import simulate
    from torch_gpmpc.sim.metrics import compute_metrics

    cfg = Config(scenario="circle", num_agents=6, noise_std=noise_std, pair_buffer=0.01, risk_mode="mission",
                 models=["double-integrator", "single-integrator"] * 3, radii=[0.2, 0.3] * 3)
    m = compute_metrics(simulate(cfg))
    assert m["violations"] == 0 and all(a is not None for a in m["arrival_steps"])


def test_a_mixed_team_charges_each_agent_its_own_obstacle_rows():
    """Under a mission budget a robot beside a disc and a drone far from it (no edge between them)
    are charged what each would be charged alone with its model and its share of the budget
    (1e-9): the team's obstacle bounds reach the right agents. (A drone's position at the next
    sample is certain, its residual acting on the velocity: its bound is 0 or 1.)"""
    disc = [{"center": [0.0, 0.35], "radius": 0.3}]
    x = {"DI": torch.tensor([[-0.6, -6.0, 0.5, 0.0]], dtype=torch.float64),
         "SI": torch.tensor([[-0.6, 0.0]], dtype=torch.float64)}

    def settings(budget):
        return ControllerSettings(horizon=6, risk_mode="mission", risk_budget=budget, obstacles=disc, comm_radius=2.0)

    def reference(x0):
        target = x0.clone()
        target[:, 0] = 1.5
        return target[:, None].expand(x0.shape[0], 7, x0.shape[1])

    alone = {name: Controller(spec, gps=[ConstantVarianceGP(0.01, 2)], settings=settings(0.025)).step(
        x[name], reference(x[name])).obstacle_risk for name, spec in (("DI", DI), ("SI", SI))}
    team = Controller([DI, SI], gps=[ConstantVarianceGP(0.01, 2), ConstantVarianceGP(0.01, 2)], settings=settings(0.05))
    x0 = torch.stack([x["DI"][0], torch.cat([x["SI"][0], torch.zeros(2, dtype=torch.float64)])])
    res = team.step(x0, reference(x0))
    assert float(alone["SI"]) > 1e-6 and float(alone["DI"]) == 0.0
    torch.testing.assert_close(res.obstacle_risk, torch.cat([alone["DI"], alone["SI"]]), rtol=1e-9, atol=1e-15)
    torch.testing.assert_close(starting_budgets(2, 0.05) - res.state.risk_left, res.obstacle_risk, rtol=1e-9, atol=1e-15)
