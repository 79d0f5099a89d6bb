"""Agent-obstacle rows: geometry in closed form, every row a supporting half-space of its obstacle
(so it separates the whole obstacle), the controller's rows and chance margins against hand
computations, and a local solve with them against a direct cvxpy solve."""

from __future__ import annotations

import math

import cvxpy as cp
import numpy as np
import pytest
import torch

from torch_gpmpc import ControllerSettings, LocalStep, ModelSpec
from torch_gpmpc.config.obstacles import ObstacleField
from torch_gpmpc.control.obstacle_rows import INERT_BOUND, obstacle_geometry, obstacle_rows
from torch_gpmpc.coordination.agent_step import slot_risks
from torch_gpmpc.coordination.graph import communication_graph
from torch_gpmpc.coordination.state import initial_state
from torch_gpmpc.errors import GpmpcError
from tests.helpers import ConstantVarianceGP

F64 = torch.float64


def t(*rows):
    return torch.tensor(rows, dtype=F64)


def test_sphere_box_and_cylinder_distances_and_normals_in_closed_form():
    field = ObstacleField.parse([{"center": [0, 0, 0], "radius": 1}, {"min": [2, 2, 2], "max": [3, 4, 5]},
                                 {"center": [0, 5], "radius": 1, "z": [0, 2]}])
    points = t([3, 4, 0], [4, 5, 6], [2.5, 2.2, 3], [0, 7, 1], [0, 5.5, 3], [0, 5.2, 1.9])
    dist, normal = obstacle_geometry(field, points)
    # sphere: |p| - 1 along p / |p|
    assert dist[0, 0] == pytest.approx(4.0) and torch.allclose(normal[0, 0], t(0.6, 0.8, 0))
    # box: outside a corner (distance to (3, 4, 5)), and inside (nearest face y = 2, exit -y)
    assert dist[1, 1] == pytest.approx(math.sqrt(3)) and torch.allclose(normal[1, 1], t(1, 1, 1) / math.sqrt(3))
    assert dist[2, 1] == pytest.approx(-0.2) and torch.allclose(normal[2, 1], t(0, -1, 0))
    # cylinder: beside it (radial), above it (vertical), inside near the top
    assert dist[3, 2] == pytest.approx(1.0) and torch.allclose(normal[3, 2], t(0, 1, 0))
    assert dist[4, 2] == pytest.approx(1.0) and torch.allclose(normal[4, 2], t(0, 0, 1))
    assert dist[5, 2] == pytest.approx(-0.1) and torch.allclose(normal[5, 2], t(0, 0, 1))



def test_several_cylinders_at_once_match_one_at_a_time():
    tables = [{"center": [0, 5], "radius": 1, "z": [0, 2]}, {"center": [2, -1], "radius": 0.5, "z": [-1, 1]},
              {"center": [-3, 0], "radius": 0.7, "z": [0, 4]}]
    points = (torch.rand(50, 3, generator=torch.Generator().manual_seed(1), dtype=F64) * 2 - 1) * 4
    dist, normal = obstacle_geometry(ObstacleField.parse(tables), points)
    for i, table in enumerate(tables):
        d, n = obstacle_geometry(ObstacleField.parse([table]), points)
        torch.testing.assert_close(dist[:, i], d[:, 0])
        torch.testing.assert_close(normal[:, i], n[:, 0])


@pytest.mark.parametrize("table", [
    {"center": [0.3, -0.2, 0.1], "radius": 0.8},
    {"min": [-1.0, -0.5, -0.2], "max": [0.5, 1.0, 0.7]},
    {"center": [0.2, 0.1], "radius": 0.7, "z": [-0.4, 0.6]},
])
def test_every_row_is_a_supporting_half_space_of_its_obstacle(table):
    """For plan points outside and inside, ``n^T y <= b - radius`` for every point y of the obstacle:
    the row keeps the agent's centre ``radius`` from the whole obstacle, not only from one point."""
    gen = torch.Generator().manual_seed(0)
    field = ObstacleField.parse([table])
    plan = (torch.rand(8, 6, 3, generator=gen, dtype=F64) * 2 - 1) * 1.5  # (B, T, P), some inside
    normals, bounds = obstacle_rows(field, plan, radius=0.25, num_rows=1)
    cloud = (torch.rand(20000, 3, generator=gen, dtype=F64) * 2 - 1) * 2.0
    inside = obstacle_geometry(field, cloud)[0][:, 0] <= 0
    members = cloud[inside]
    assert members.shape[0] > 300
    assert bool((obstacle_geometry(field, plan)[0] <= 0).any()), "no plan point inside: the inside case is untested"
    support = torch.einsum("bltp,np->bltn", normals, members).amax(-1)  # (B, 1, T)
    assert bool((support <= bounds - 0.25 + 1e-12).all())
    assert torch.allclose(normals.norm(dim=-1), torch.ones_like(bounds))


def test_rows_keep_the_nearest_obstacles_and_pad_with_inert_rows():
    field = ObstacleField.parse([{"center": [5.0, 0.0], "radius": 1}, {"center": [1.5, 0.0], "radius": 1},
                                 {"center": [0.0, -3.0], "radius": 1}])
    plan = torch.zeros(1, 3, 2, dtype=F64)
    normals, bounds = obstacle_rows(field, plan, radius=0.25, num_rows=2)
    # nearest: the disc at 1.5 (distance 0.5), then the one at -3 (distance 2)
    assert torch.allclose(normals[0, 0], t(-1, 0).expand(3, 2)) and torch.allclose(bounds[0, 0], torch.full((3,), -0.25, dtype=F64))
    assert torch.allclose(normals[0, 1], t(0, 1).expand(3, 2)) and torch.allclose(bounds[0, 1], torch.full((3,), -1.75, dtype=F64))
    normals, bounds = obstacle_rows(field, plan, radius=0.25, num_rows=4)
    assert bool((normals[0, 3] == 0).all()) and bool((bounds[0, 3] == INERT_BOUND).all())


def test_bad_obstacles_are_refused_naming_the_field():
    with pytest.raises(GpmpcError, match="radius must be"):
        ObstacleField.parse([{"center": [0, 0], "radius": -1}])
    with pytest.raises(GpmpcError, match=r"obstacles\[1\].*none of the forms"):
        ObstacleField.parse([{"center": [0, 0], "radius": 1}, {"centre": [0, 0], "radius": 1}])
    with pytest.raises(GpmpcError, match="min must be < max"):
        ObstacleField.parse([{"min": [0, 0], "max": [1, -1]}])
    with pytest.raises(GpmpcError, match="only with 3D"):
        ObstacleField.parse([{"center": [0, 0], "radius": 1, "z": [0, 1]}]).check_dim(2)


def _one_agent_problem(solver: str, variance: float | None):
    """One single-integrator agent heading right through a disc just off its line, planned around
    the straight line: the local problem with its obstacle rows."""
    settings = ControllerSettings(horizon=6, method="gp-chance" if variance else "nominal", solver=solver,
                                  margin_variance="latent", obstacles=[{"center": [0.6, 0.05], "radius": 0.3}],
                                  obstacle_rows=2, terminal_cost="stage", **({"obstacle_eps": 0.05} if variance else {}))
    gps = [ConstantVarianceGP(variance)] if variance else None
    step = LocalStep(settings, ModelSpec.single_integrator(2), gps=gps)
    x0 = t([0.0, 0.0])
    graph = communication_graph(x0, None)
    state = initial_state(x0, 6, graph)
    line = torch.linspace(0, 1.2, 7, dtype=F64)
    state.plans[0] = torch.stack([line, torch.zeros_like(line)], -1)  # the linearization points
    xref = state.plans.clone()
    assembled = step.assemble(x0, xref, state, graph, torch.tensor(20.0, dtype=F64), slot_risks(graph, 0.1, 0.5))
    return step, assembled, graph, state


@pytest.mark.parametrize("variance", [None, 0.01])
def test_controller_rows_match_a_hand_computation(variance):
    _, assembled, _, state = _one_agent_problem("fast", variance)
    data = assembled.data
    c, r = np.array([0.6, 0.05]), 0.3
    margin = 0.0 if variance is None else float(torch.special.ndtri(torch.tensor(0.95, dtype=F64))) * math.sqrt(variance)
    for tau in range(1, 7):
        p = state.plans[0, tau].numpy()
        n = (p - c) / np.linalg.norm(p - c)
        q = c + r * n
        assert np.allclose(data.halfspace_normals[0, 0, tau - 1].numpy(), n)
        assert data.halfspace_bounds[0, 0, tau - 1].item() == pytest.approx(n @ q + 0.25 + margin)
    assert bool((data.halfspace_normals[0, 1] == 0).all())  # one obstacle, two rows: the second is inert


@pytest.mark.parametrize("solver", ["fast", "clarabel"])
def test_local_solve_with_obstacle_rows_matches_a_direct_cvxpy_solve(solver):
    step, assembled, graph, _ = _one_agent_problem(solver, 0.01)
    data = assembled.data
    sol = step.solve(step.solver(graph.num_slots), data)
    assert bool(sol.ok.all())
    npy = lambda v: v[0].detach().numpy()  # noqa: E731
    T, D = 6, 2
    B = step.nominal.B(dtype=F64).numpy() if data.dyn_B is None else None
    X, U = cp.Variable((T + 1, D)), cp.Variable((T, D))
    cost = cp.sum_squares(X - npy(data.xref)) + step.settings.alpha * cp.sum_squares(U)
    cons = [X[0] == npy(data.x0)]
    for tau in range(T):
        cons += [X[tau + 1] == npy(data.dyn_A)[tau] @ X[tau] + (B if B is not None else npy(data.dyn_B)[tau]) @ U[tau] + npy(data.dyn_c)[tau],
                 cp.norm(U[tau]) <= 2.0]
        for row in range(2):
            s = cp.Variable(nonneg=True)
            cons.append(npy(data.halfspace_normals)[row, tau] @ X[tau + 1] + s >= npy(data.halfspace_bounds)[row, tau])
            cost += step.settings.slack_penalty * s
    cp.Problem(cp.Minimize(cost), cons).solve(solver=cp.CLARABEL, tol_gap_abs=1e-11, tol_gap_rel=1e-11,
                                              tol_feas=1e-11)
    assert np.abs(sol.X[0].detach().numpy() - X.value).max() < 1e-6
    # the rows bind: the plan is pushed off the straight line, away from the disc
    assert X.value[3, 1] < -0.1
