"""Anderson acceleration of a step's ADMM: the mix against closed forms on affine maps, its
restarts, and accelerated steps against the plain ones and an independent centralized solve."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from torch_gpmpc.config.schema import Config
from torch_gpmpc.coordination.acceleration import AndersonAcceleration, anderson_mix
from torch_gpmpc.coordination.admm import ADMM, ADMMState, initial_state
from torch_gpmpc.coordination.agent_step import LocalStep
from torch_gpmpc.coordination.centralized import plan_cost, solve_centralized
from torch_gpmpc.coordination.graph import communication_graph
from torch_gpmpc.config.model_spec import ModelSpec
from torch_gpmpc.errors import GpmpcError

F64 = torch.float64


def _affine_map(n: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    """``F(v) = M v + c`` with spectral radius 0.95 (a slow contraction, like a crowded step's ADMM)."""
    gen = torch.Generator().manual_seed(seed)
    Q, _ = torch.linalg.qr(torch.randn(n, n, generator=gen, dtype=F64))
    M = Q @ torch.diag(torch.linspace(-0.95, 0.95, n, dtype=F64)) @ Q.T
    return M, torch.randn(n, generator=gen, dtype=F64)


@pytest.mark.parametrize("n", [1, 3, 6])
def test_mix_solves_an_affine_fixed_point_in_n_plus_one_steps(n):
    """On an affine map type-II Anderson with a full memory is GMRES on ``(I - M) v = c`` (Walker
    & Ni 2011): the fixed point after n + 1 mixes, where the plain iteration has barely moved."""
    M, c = _affine_map(n, seed=n)
    fixed = torch.linalg.solve(torch.eye(n, dtype=F64) - M, c)
    points, images, v = [], [], torch.zeros(n, dtype=F64)
    for _ in range(n + 1):
        points.append(v)
        images.append(M @ v + c)
        v = anderson_mix(images, points, regularization=0.0)
    assert torch.allclose(v, fixed, atol=1e-9, rtol=0)
    plain = torch.zeros(n, dtype=F64)
    for _ in range(n + 1):
        plain = M @ plain + c
    assert float((plain - fixed).norm()) > 1e-3 * float(fixed.norm())


def test_mix_falls_back_to_the_plain_image_without_history_or_on_degenerate_differences():
    v, f = torch.tensor([1.0, 2.0], dtype=F64), torch.tensor([3.0, 4.0], dtype=F64)
    assert anderson_mix([f], [v]) is f
    assert anderson_mix([f, f], [v, v]) is f  # no change between iterates: dG = 0
    nan = torch.tensor([float("nan"), 0.0], dtype=F64)
    assert anderson_mix([f, nan], [v, v]) is nan  # non-finite: the plain image


def _two_agent_state(rho: float | None = None) -> ADMMState:
    x0 = torch.tensor([[-1.0, 0.0], [1.0, 0.0]], dtype=F64)
    graph = communication_graph(x0, None)
    state = initial_state(x0, 4, graph)
    if rho is not None:
        state = dataclasses.replace(state, rho=torch.full((graph.num_edges,), rho, dtype=F64))
    return state


def _moved(state, dz: float, rho: float | None = None):
    out = dataclasses.replace(state, z=state.z + dz, lam=state.lam + dz)
    return out if rho is None else dataclasses.replace(out, rho=torch.full_like(state.rho, rho))


def test_history_restarts_on_a_penalty_change_and_on_residual_growth():
    acc = AndersonAcceleration(memory=3)
    s0 = _two_agent_state(rho=20.0)
    s1 = _moved(s0, 1.0)
    s2 = _moved(s1, 0.5)
    acc.next_input(s0, s1)
    acc.next_input(s1, s2)
    assert acc.restarts == 0 and acc.history == 2
    acc.next_input(s2, _moved(s2, 0.25, rho=40.0))  # residual balancing changed the map
    assert acc.restarts == 1 and acc.history == 1
    s3 = _moved(s2, 0.25, rho=40.0)
    acc.next_input(s3, _moved(s3, 10.0))  # the residual grew 40x
    assert acc.restarts == 2 and acc.history == 1


def test_accelerated_input_keeps_everything_but_the_consensus_and_duals():
    acc = AndersonAcceleration(memory=2)
    s0 = _two_agent_state()
    s1 = _moved(s0, 1.0)
    s2 = _moved(s1, 0.5)
    acc.next_input(s0, s1)
    out = acc.next_input(s1, s2)
    assert out.plans is s2.plans and out.inputs is s2.inputs and out.edges is s2.edges
    assert out.z.shape == s2.z.shape and out.lam.shape == s2.lam.shape
    assert not torch.equal(out.z, s2.z)  # mixed: the moves halve, so the mix jumps ahead


def test_steps_reach_the_same_optimum_in_fewer_iterations():
    """A crossing of four agents, solved cold to a tight tolerance with and without acceleration:
    the same plans (1e-5), and both within 1 % of an independent centralized cvxpy solve."""
    T = 8
    spec = ModelSpec.single_integrator(2)
    x0 = torch.tensor([[-1.5, 0.1], [1.5, -0.1], [0.1, 1.5], [-0.1, -1.5]], dtype=F64)
    xref = (-x0)[:, None].expand(4, T + 1, 2).clone()
    graph = communication_graph(x0, None)
    plain = ADMM(LocalStep(Config(method="nominal", horizon=T, admm_tol=1e-7, admm_rel_tol=0.0,
                                  admm_max_iter=2000).controller_settings(), spec))
    fast = plain.with_settings(admm_acceleration="anderson")
    a = plain.solve_step(x0, xref, graph)
    b = fast.solve_step(x0, xref, graph)
    assert a.converged and b.converged
    assert b.iterations < a.iterations
    assert torch.allclose(a.plans, b.plans, atol=1e-5, rtol=0)
    s = plain.settings
    central = solve_centralized(b.problem, graph, plain.nominal, 2.0, s.alpha, s.slack_penalty)
    for res in (a, b):
        cost = plan_cost(res.plans, res.inputs, xref, s.alpha, problem=res.problem)
        assert abs(cost / central.cost - 1.0) < 0.01


def test_the_setting_is_checked():
    with pytest.raises(GpmpcError, match="admm_acceleration"):
        Config(admm_acceleration="nesterov")
    with pytest.raises(GpmpcError, match="admm_anderson_memory"):
        Config(admm_anderson_memory=0)
