"""ADMM's compiled iterations (``admm_compiled``) against the torch path they replace: the same
closed loops bit for bit, each pass against the torch functions it mirrors, and the hand-back to the
torch path whenever something is unusual."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from torch_gpmpc.coordination.agent_step import LocalStep
from torch_gpmpc.config.schema import Config
from torch_gpmpc.control.problem import LocalProblemData
from torch_gpmpc.control.solvers.canonical import canonicalize
from torch_gpmpc.control.solvers.interior_point import InteriorPointMPC
from torch_gpmpc.coordination import steady
from torch_gpmpc.control.solvers.repeated import ConsensusBuffers
from torch_gpmpc.coordination.admm import ADMM
from torch_gpmpc.coordination.agent_step import edge_copies
from torch_gpmpc.coordination.graph import communication_graph
from torch_gpmpc.dynamics.systems import NominalModel
from torch_gpmpc.sim.closed_loop import simulate

F64 = torch.float64
QUADROTOR = str(Path(__file__).resolve().parents[2] / "examples" / "quadrotor" / "quadrotor.toml")
ROLLOUT_FIELDS = ("states", "inputs", "plans", "admm_iterations", "converged", "slack_max", "chance_margin",
                  "pair_separation", "fallback")


def _count_compiled(monkeypatch) -> list[int]:
    """Counts the compiled iterations that returned a next iterate."""
    counts = [0]
    original = steady.SteadyIterations.iterate

    def counted(self, state):
        out = original(self, state)
        counts[0] += out is not None
        return out

    monkeypatch.setattr(steady.SteadyIterations, "iterate", counted)
    return counts


@pytest.mark.parametrize("cfg", [
    Config(admm_coupling="copies", max_steps=30),  # the paper scenario, gp-chance with learned GPs
    # the README's quadrotor demo's model (speed limit) on a circle of 8: seven neighbours each
    Config(admm_coupling="copies", model=QUADROTOR, scenario="circle", num_agents=8, method="nominal",
           noise_std=0.0, max_steps=25),
], ids=["paper", "quadrotor-circle-8"])
def test_compiled_iterations_give_the_torch_paths_closed_loop_bit_for_bit(cfg, monkeypatch):
    reference = simulate(dataclasses.replace(cfg, admm_compiled=False))
    compiled_count = _count_compiled(monkeypatch)
    compiled = simulate(cfg)
    assert compiled_count[0] > reference.admm_iterations.sum() / 2  # most iterations were compiled
    for name in (*ROLLOUT_FIELDS, "primal_residuals", "dual_residuals"):  # one update function: the same bits
        a, b = getattr(reference, name), getattr(compiled, name)
        assert np.array_equal(np.asarray(a, dtype=float), np.asarray(b, dtype=float), equal_nan=True), name


def _random_iterate(K: int, T: int, n: int, seed: int, radius: float = 10.0):
    gen = torch.Generator().manual_seed(seed)
    x0 = torch.randn(K, n, generator=gen, dtype=F64) * 1.5
    graph = communication_graph(x0[:, :2], radius)
    E = graph.num_edges
    z = torch.randn(E, 2, T + 1, n, generator=gen, dtype=F64)
    lam = torch.randn(E, 2, 2, T + 1, n, generator=gen, dtype=F64)
    rho = 2.0 ** torch.randint(-3, 6, (E,), generator=gen).to(F64) * 1.3
    return x0, graph, z, lam, rho, gen


@pytest.mark.parametrize("K,radius", [(3, 10.0), (9, 10.0), (9, 2.0)])
def test_written_terms_are_canonicalizes_consensus_terms(K, radius):
    """What a compiled iteration writes into the kept problems is what canonicalization computes from
    the assembled problems' gathers (written here independently), bit for bit."""
    T, n = 5, 2
    x0, graph, z, lam, rho, gen = _random_iterate(K, T, n, seed=K, radius=radius)
    M = graph.num_slots
    xref = torch.randn(K, T + 1, n, generator=gen, dtype=F64)
    rho_slots = rho[graph.slot_edge]
    r, c, side = torch.arange(K)[:, None], torch.arange(M)[None, :], graph.slot_side
    z_slot, lam_mine = z[graph.slot_edge], lam[graph.slot_edge][r, c, side]
    data = LocalProblemData(
        x0=x0, xref=xref, dyn_A=torch.eye(n, dtype=F64).expand(K, T, n, n), dyn_c=torch.zeros(K, T, n, dtype=F64),
        normals=torch.zeros(K, M, T, n, dtype=F64), bounds=torch.zeros(K, M, T, dtype=F64), active=graph.active,
        rho=rho_slots, z_own=z_slot[r, c, side], z_nbr=z_slot[r, c, 1 - side], lam_own=lam_mine[r, c, side],
        lam_nbr=lam_mine[r, c, 1 - side])
    canon = canonicalize(data, NominalModel(n).B(F64, torch.device("cpu")))
    buffers = ConsensusBuffers(c_x=np.empty(K), l_x=np.empty((K, T * n)), rho_y=np.ones((K, M + 1)),
                               w_y=np.zeros((K, M + 1, T, n)), y0=np.empty((K, M, n)))  # one state-row slot
    cfg = Config(admm_coupling="copies").controller_settings()
    kept = dataclasses.replace(data, z_own=torch.zeros_like(data.z_own), lam_nbr=torch.ones_like(data.lam_nbr))
    iterations = steady.SteadyIterations(cfg, graph, kept, torch.tensor(20.0, dtype=F64), cfg.admm_tol,
                                         SimpleNamespace(buffers=buffers))
    iterations.write_terms(SimpleNamespace(z=z, lam=lam, rho=rho))
    assert np.array_equal(buffers.c_x, canon.c_x.numpy()) and np.array_equal(buffers.l_x, canon.l_x.numpy())
    assert np.array_equal(buffers.rho_y[:, :M], canon.rho_y.numpy())
    assert np.array_equal(buffers.w_y[:, :M], canon.w_y.numpy()) and np.array_equal(buffers.y0, canon.y0.numpy())
    assert (buffers.rho_y[:, M:] == 1).all() and (buffers.w_y[:, M:] == 0).all()  # the state-row slot stays
    assert radius > 5 or not graph.active.all()  # the sparse graph covers inactive slots


@pytest.mark.parametrize("adaptive", [True, False])
def test_copies_update_is_eqs_28_29_with_residual_balancing_and_any_end_knows_the_tolerances(adaptive):
    """:func:`copies_update` (the one update of the torch path, the compiled iterations and the
    distributed agents) against the equations written out: consensus the mean of the two copies,
    each end's duals plus rho times its gap, residuals, and the penalty doubled, halved or kept by
    the ratio of the ratios; an agent that knows only its own ends' duals gets the same tolerances."""
    from torch_gpmpc.coordination.consensus import copies_update
    from torch_gpmpc.coordination.penalty import RHO_BALANCE, RHO_FACTOR

    K, T, n = 9, 4, 3
    _, graph, z, lam, rho, gen = _random_iterate(K, T, n, seed=4, radius=2.0)
    lam = torch.stack([lam[:, 0], -lam[:, 0]], dim=1)  # the two ends' duals sum to zero, as ADMM keeps them
    X = torch.randn(K, T + 1, n, generator=gen, dtype=F64)
    Y = torch.randn(K, graph.num_slots, T + 1, n, generator=gen, dtype=F64)
    cfg = Config(admm_coupling="copies", admm_tol=0.3, admm_rel_tol=0.05,
                 rho_update="adaptive" if adaptive else "fixed").controller_settings()
    rho_now = rho if adaptive else torch.tensor(7.5, dtype=F64)
    copies = edge_copies(SimpleNamespace(X=X, Y=Y), graph)
    update = copies_update(copies, z, lam, rho_now, cfg, tol=0.1)
    rho_e = (rho if adaptive else torch.full((graph.num_edges,), 7.5, dtype=F64))[:, None, None, None, None]
    mean = (copies[:, 0] + copies[:, 1]) / 2
    torch.testing.assert_close(update.z, mean, rtol=0, atol=1e-15)
    torch.testing.assert_close(update.lam, lam + rho_e * (copies - mean[:, None]), rtol=0, atol=1e-12)
    primal = (copies - mean[:, None]).flatten(2).norm(dim=2).amax(dim=1)
    torch.testing.assert_close(update.residuals.primal, primal, rtol=1e-14, atol=0)
    size = torch.stack([copies[:, 0].flatten(1).norm(dim=1), copies[:, 1].flatten(1).norm(dim=1),
                        mean.flatten(1).norm(dim=1)]).amax(dim=0)
    torch.testing.assert_close(update.stop.eps_primal, 0.1 + 0.05 * size, rtol=1e-14, atol=0)
    if adaptive:
        p, d = update.residuals.primal_ratio, update.residuals.dual_ratio
        factor = torch.where(p > RHO_BALANCE * d, RHO_FACTOR, torch.where(d > RHO_BALANCE * p, 1 / RHO_FACTOR, 1.0))
        torch.testing.assert_close(update.rho, rho * factor, rtol=0, atol=0)
        assert not torch.equal(update.rho, rho)  # some penalties moved
    else:
        assert update.rho is None
    k = 4  # one agent's view: its own ends only
    m = torch.nonzero(graph.active[k]).flatten()
    ends = (graph.slot_edge[k, m], graph.slot_side[k, m])
    mine = copies_update(copies, z, lam, rho_now, cfg, tol=0.1, ends=ends)
    torch.testing.assert_close(mine.stop.eps_dual[ends[0]], update.stop.eps_dual[ends[0]], rtol=1e-14, atol=0)


def _quadrotor_step(num_agents: int = 4):
    """A crossing of the demo's model: ``(admm, x0, xref, graph)``."""
    cfg = Config(admm_coupling="copies", model=QUADROTOR, scenario="circle", num_agents=num_agents, method="nominal", noise_std=0.0)
    admm = ADMM(LocalStep(cfg, cfg.model_spec()))
    angles = torch.arange(num_agents, dtype=F64) * (2 * torch.pi / num_agents)
    pos = torch.stack([torch.cos(angles), torch.sin(angles), torch.zeros_like(angles)], dim=1) * 1.2
    x0 = torch.cat([pos, -0.5 * pos], dim=1)
    xref = torch.cat([-pos, torch.zeros_like(pos)], dim=1)[:, None].expand(num_agents, cfg.horizon + 1, 6)
    return admm, x0, xref, communication_graph(x0[:, :3], None)


def test_a_step_hands_unusual_iterations_back_to_the_torch_path(monkeypatch):
    admm, x0, xref, graph = _quadrotor_step()
    reference = admm.with_settings(admm_compiled=False).solve_step(x0, xref, graph)
    assert reference.iterations > 5
    # a compiled iteration that finds something unusual (here: every other one) returns None and the
    # torch path takes that iteration: the same step
    original, calls = steady.SteadyIterations.iterate, [0]

    def every_other(self, state):
        calls[0] += 1
        return None if calls[0] % 2 else original(self, state)

    monkeypatch.setattr(steady.SteadyIterations, "iterate", every_other)
    result = admm.solve_step(x0, xref, graph)
    assert calls[0] > 2 and result.iterations == reference.iterations
    assert torch.equal(result.plans, reference.plans) and torch.equal(result.state.lam, reference.state.lam)


def test_an_exception_in_a_compiled_solve_hands_the_iteration_to_the_torch_path(monkeypatch):
    from torch_gpmpc.control.solvers import repeated

    admm, x0, xref, graph = _quadrotor_step()
    reference = admm.solve_step(x0, xref, graph)
    original, calls = repeated.solve_points, [0]

    def third_raises(*args, **kwargs):
        calls[0] += 1
        if calls[0] == 3:
            raise FloatingPointError("injected")
        return original(*args, **kwargs)

    monkeypatch.setattr(repeated, "solve_points", third_raises)
    result = admm.solve_step(x0, xref, graph)
    assert calls[0] > 3 and result.failed_solves == 0 and result.iterations == reference.iterations
    assert torch.equal(result.plans, reference.plans)


def test_the_repeated_solve_declines_non_finite_terms_and_unconverged_problems():
    admm, x0, xref, graph = _quadrotor_step()
    ctx, state = admm.prepare(x0, xref, graph)
    state, stats = admm.iterate(ctx, state)
    solve = ctx.layer.repeated(stats.problem)
    assert solve is not None
    iterations = steady.SteadyIterations(admm.settings, graph, stats.problem, ctx.rho, ctx.tol, solve)
    assert iterations.iterate(state) is not None
    assert iterations.iterate(dataclasses.replace(state, lam=state.lam * float("nan"))) is None
    # a problem the kernel cannot solve within its cap (one interior-point iteration, cold)
    capped = InteriorPointMPC(ctx.layer.horizon, ctx.layer.dim, ctx.layer.num_neighbors, ctx.layer.nominal,
                              ctx.layer.u_max, ctx.layer.alpha, max_iter=1, constraints=ctx.layer.constraints)
    solve = capped.repeated(stats.problem)
    assert steady.SteadyIterations(admm.settings, graph, stats.problem, ctx.rho, ctx.tol, solve).iterate(
        dataclasses.replace(state, solver_point=None)) is None


@pytest.mark.parametrize("change", [
    {"admm_compiled": False}, {"relinearize": True}, {"solver": "clarabel"},
    {"solver_warm": False}])
def test_compiled_iterations_apply_only_where_they_give_the_same_step(change, monkeypatch):
    admm, x0, xref, graph = _quadrotor_step(3)
    counts = _count_compiled(monkeypatch)
    admm.with_settings(admm_max_iter=8).solve_step(x0, xref, graph)
    assert counts[0] > 0
    counts[0] = 0
    admm.with_settings(admm_max_iter=8, **change).solve_step(x0, xref, graph)
    assert counts[0] == 0


def test_compiled_iterations_stay_off_when_gradients_are_wanted(monkeypatch):
    admm, x0, xref, graph = _quadrotor_step(3)
    counts = _count_compiled(monkeypatch)
    rho = torch.tensor(20.0, dtype=F64, requires_grad=True)
    result = admm.with_settings(admm_max_iter=6).solve_step(x0, xref, graph, rho=rho)
    assert counts[0] == 0 and result.plans.requires_grad


@pytest.mark.parametrize("method, torch_path_iterations", [("nominal", 2), ("gp-chance", 3)])
def test_compiled_iterations_start_after_the_first_where_no_variances_are_exchanged(method, torch_path_iterations,
                                                                                    monkeypatch):
    """Without exchanged variances a step's problems are fixed from its first iteration, so only that
    one and the last run through the torch path; with them (the margins read the neighbours'
    variances reported at the first iteration) the first two and the last."""
    calls = [0]
    original = ADMM.iterate

    def counted(self, ctx, state):
        calls[0] += 1
        return original(self, ctx, state)

    monkeypatch.setattr(ADMM, "iterate", counted)
    rollout = simulate(Config(admm_coupling="copies", scenario="circle", num_agents=6, method=method, noise_std=0.0, max_steps=20,
                              **({} if method == "nominal" else {"gp_iters": 10})))
    expected = int(np.minimum(rollout.admm_iterations, torch_path_iterations).sum())
    assert rollout.admm_iterations.max() > torch_path_iterations and calls[0] == expected
