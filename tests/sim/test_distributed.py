"""Distributed backend: one process per agent group plus a world process (torch.distributed, gloo).

Independent answers: the in-process backend (same seed -> same states), the message-size
formula 8 * 2 (T+1) D |N_k| bytes per agent and iteration, and a killed agent process.
"""

from __future__ import annotations

import json
import os
import signal

import numpy as np
import pytest
import torch

from torch_gpmpc.coordination.agent_step import LocalStep
from torch_gpmpc.coordination.admm import ADMM
from torch_gpmpc.cli import main
from torch_gpmpc.config import Config, load_config
from torch_gpmpc.coordination.distributed.agent import AgentController
from torch_gpmpc.coordination.fallback import replanning_from_seeds
from torch_gpmpc.coordination.penalty import should_stop
from torch_gpmpc.sim.distributed import simulate_distributed
from torch_gpmpc.errors import GpmpcError
from torch_gpmpc.coordination.graph import communication_graph
from torch_gpmpc.sim.metrics import CONTRACT_KEYS, compute_metrics, pair_distances
from torch_gpmpc.sim.scenarios import make_scenario
from torch_gpmpc.dynamics.systems import clip_norm
from torch_gpmpc.sim.closed_loop import noise_sequence, simulate
from torch_gpmpc.dynamics.systems import make_system
from torch_gpmpc.gp.offset import offset_corrected
from torch_gpmpc.gp.online import OnlineLearning

QUICK = {"admm_coupling": "copies", "method": "gp-chance", "max_steps": 3, "admm_max_iter": 5, "gp_iters": 5}


def hand_driven(cfg: Config) -> tuple:
    """``(scenario, system, admm, agents, noise)``: the in-process ADMM of ``cfg``'s scenario and one
    AgentController per agent, to be driven by hand (no processes)."""
    sc = make_scenario(cfg)
    K = sc.num_agents
    system = make_system(cfg.dim, cfg.noise_std, cfg.wind_scale)
    admm = ADMM(LocalStep(cfg, system.nominal, cfg.method))
    agents = [AgentController(k, K, cfg, sc.reference_path()[k]) for k in range(K)]
    return sc, system, admm, agents, noise_sequence(cfg, K)


def begin_agents(agents: list, t: int, x: torch.Tensor) -> None:
    """Every agent of a complete graph begins step t at its state in x and learns its neighbours'
    plans (the step's set-up of the agent protocol, by hand)."""
    K = len(agents)
    new = {k: agents[k].begin_step(t, x[k].clone(), [j for j in range(K) if j != k]) for k in range(K)}
    for k in range(K):
        for j in new[k]:
            agents[j].set_neighbour_plan(k, agents[k].own_plan().clone())
    for a in agents:
        a.finish_setup()


def drive_agents(agents: list, t: int, x: torch.Tensor, iterations: int) -> list:
    """One step of the agent protocol by hand (no processes): :func:`begin_agents`, then
    ``iterations`` ADMM iterations; returns each iteration's per-agent ``update`` results."""
    K = len(agents)
    begin_agents(agents, t, x)
    residuals = []
    for _ in range(iterations):
        own = {k: agents[k].solve() for k in range(K)}
        residuals.append([agents[k].update({j: own[j][k] for j in own[k]}) for k in range(K)])
    return residuals


@pytest.mark.parametrize("input_rate_weight", [0.0, 0.3])
def test_agent_controllers_reproduce_batched_admm_bit_for_bit(input_rate_weight):
    """No processes: K AgentControllers exchanging copies by hand give ADMM.solve_step's
    residuals and inputs exactly (the local step is the batched step's row k; with an input-rate
    weight each agent's second step uses its own applied input)."""
    # clarabel solves each problem alone, so batch 3 and batch 1 agree bit for bit; with the fast
    # solver a residual differs in its last bit (5.1e-2 +- 7e-18): its kernel solves each problem
    # alone, so the batched torch preparation (condensing, matrix products) rounds by batch size
    cfg = load_config(None, {"admm_coupling": "copies", "method": "nominal", "max_steps": 2, "admm_max_iter": 4,
                             "solver": "clarabel",
                             "input_rate_weight": input_rate_weight})
    sc, system, admm, agents, noise = hand_driven(cfg)
    x, warm = sc.starts.clone(), None
    with torch.no_grad():
        for t in range(2):
            res = admm.solve_step(x, sc.reference_window(t, cfg.horizon), communication_graph(x, None), warm=warm)
            warm = res.state.shifted()
            residuals = drive_agents(agents, t, x, res.iterations)
            assert [max(o[0] for o in out) for out in residuals] == res.primal_residuals
            assert [max(o[1] for o in out) for out in residuals] == res.dual_residuals
            u = torch.stack([a.end_step().u for a in agents])
            assert torch.equal(u, res.inputs[:, 0])
            x = system.step(x, clip_norm(u, cfg.u_max), noise=noise[t])


def test_agent_controllers_reproduce_the_buffered_voronoi_fallback():
    """Three agents almost touching, ADMM capped at 2 iterations: both backends re-plan the same
    agents (the world closes the agents' seeds as the in-process rule does), each from the
    neighbours' plans before their own fallback, and apply
    the same inputs (clarabel: batch and single solves agree bit for bit); after the fallback the
    agents send each other the plans they apply, so the next steps start from the in-process warm
    start and apply the same inputs too."""
    cfg = load_config(None, {"admm_coupling": "copies", "method": "nominal", "scenario": "circle", "num_agents": 3,
                             "circle_radius": 0.32, "reference": "target",
                             "admm_max_iter": 2, "solver": "clarabel", "noise_std": 0.0, "wind_scale": 0.0})
    sc = make_scenario(cfg)
    K = sc.num_agents
    system = make_system(cfg.dim, cfg.noise_std, cfg.wind_scale)
    admm = ADMM(LocalStep(cfg, system.nominal, cfg.method))
    agents = [AgentController(k, K, cfg, sc.reference_path()[k]) for k in range(K)]
    x, warm, fallbacks = sc.starts.clone(), None, 0
    with torch.no_grad():
        for t in range(4):  # the fallback acts at t = 1
            res = admm.solve_step(x, sc.reference_window(t, cfg.horizon), communication_graph(x, None), warm=warm)
            warm, fallbacks = res.state.shifted(), fallbacks + int(res.fallback)
            drive_agents(agents, t, x, res.iterations)
            for a in agents:
                a.check_safety(not res.converged)  # the world's word: settle who re-plans
            assert all(a.fallback_possible == (not res.converged) for a in agents)
            if not res.converged:  # the world's closure of the seeds, then the applied plans
                seeds = torch.stack([a.replan_seeds() for a in agents]) > 0.5
                replan = replanning_from_seeds(seeds[:, 0], seeds[:, 1:], communication_graph(x, None))
                for a, decided in zip(agents, replan.tolist()):
                    a.replan(decided)
                applied = {k: agents[k].own_plan().clone() for k in range(K)}
                for k in range(K):
                    agents[k].take_applied_plans({j: applied[j] for j in range(K) if j != k})
            u = torch.stack([a.end_step().u for a in agents])
            assert torch.equal(u, res.inputs[:, 0])
            x = system.step(x, clip_norm(u, cfg.u_max))
    assert fallbacks >= 1


def _exchange(own: dict) -> dict:
    """Deliver every agent's messages ``{k: {j: msg}}`` by hand: ``{j: {k: msg}}``."""
    return {j: {k: msgs[j] for k, msgs in own.items() if j in msgs} for j in own}


@pytest.mark.parametrize("admm_max_iter", [40, 3])
def test_agent_controllers_reproduce_the_plane_admm(admm_max_iter):
    """No processes: with ``admm_coupling = planes`` each agent agrees on the step's variances and
    rows with its neighbours once, then sends T multipliers per iteration, and its final plan: the
    in-process plane steps' residuals and inputs (the fast solver: batch 1 against batch 4 rounds
    differently in the last bits), uncapped and capped at 3 iterations (the last safe plans, the
    safety check on the final plans); every agent with its offset estimate, updated from its own
    measurements as the in-process OnlineLearning updates them all."""
    from torch_gpmpc.gp import fit_agent_gps

    cfg = load_config(None, {"method": "gp-chance", "scenario": "circle", "num_agents": 4, "circle_radius": 1.5,
                             "admm_coupling": "planes", "admm_max_iter": admm_max_iter, "gp_samples": 30,
                             "gp_iters": 5, "max_steps": 8, "disturbance_drift": 0.01})
    sc = make_scenario(cfg)
    K = sc.num_agents
    system = make_system(cfg.dim, cfg.noise_std, cfg.wind_scale)
    gps = fit_agent_gps(cfg, system, K)
    corrected = offset_corrected(gps, cfg.offset_drift)  # each agent's offset estimate, in process
    learning = OnlineLearning(corrected, system.nominal, online=False)
    admm = ADMM(LocalStep(cfg, system.nominal, cfg.method, None, corrected))
    agents = [AgentController(k, K, cfg, sc.reference_path()[k], gps[k]) for k in range(K)]
    noise = noise_sequence(cfg, K)
    kept = []  # the solves each agent made on its kept problem (compiled) rather than through torch

    def counted(solve_kept):
        def solve(*args):
            sol = solve_kept(*args)
            kept.append(sol is not None)
            return sol
        return solve

    for a in agents:
        a._solve_kept = counted(a._solve_kept)
    x, warm, iterations = sc.starts.clone(), None, []
    with torch.no_grad():
        for t in range(cfg.max_steps):
            res = admm.solve_step(x, sc.reference_window(t, cfg.horizon), communication_graph(x, None), warm=warm)
            warm = res.state.shifted()
            begin_agents(agents, t, x)
            variances = _exchange({k: agents[k].step_variances() for k in range(K)})
            for k in range(K):
                agents[k].take_step_variances(variances[k])
            rows = _exchange({k: agents[k].plane_rows() for k in range(K)})
            for k in range(K):
                agents[k].take_plane_rows(rows[k])
            primal = []
            for it in range(res.iterations):
                touches = _exchange({k: agents[k].solve() for k in range(K)})
                assert all(m.shape == (cfg.horizon,) for msgs in touches.values() for m in msgs.values())
                residuals = [agents[k].update(touches[k]) for k in range(K)]
                primal.append(max(r[0] for r in residuals))
                decision = torch.tensor([primal[-1], max(r[1] for r in residuals), float(it == res.iterations - 1)])
                for a in agents:
                    a.keep_safe_plan(decision)
            plans = _exchange({k: {j: agents[k].own_plan().clone() for j in agents[k].nbrs} for k in range(K)})
            for k in range(K):
                agents[k].take_final_plans(plans[k])
                agents[k].check_safety(res.converged)
            # a residual is a multiplier difference over 2 rho: the solver's tolerance, not rounding
            np.testing.assert_allclose(primal, res.primal_residuals, rtol=0, atol=1e-9)
            u = torch.stack([a.end_step().u for a in agents])
            assert torch.allclose(u, res.inputs[:, 0], rtol=0, atol=1e-10)
            iterations.append(res.iterations)
            x_prev, x = x, system.step(x, clip_norm(u, cfg.u_max), noise=noise[t])
            learning.observe(x_prev, clip_norm(u, cfg.u_max), x)
    assert max(iterations) > 10 if admm_max_iter == 40 else set(iterations) == {3}
    assert len(kept) == K * sum(n - 1 for n in iterations) and all(kept)  # every later solve compiled


def test_bad_arguments_raise_before_launching():
    cfg = Config(method="nominal", max_steps=1)
    with pytest.raises(GpmpcError, match="agents_per_process"):
        simulate_distributed(cfg, agents_per_process=0)
    with pytest.raises(GpmpcError, match="timeout"):
        simulate_distributed(cfg, timeout_s=0)


def run_both_backends(keys: dict, out) -> tuple:
    """``gpmpc run --backend distributed`` with config ``keys`` into ``out`` (three agent processes
    and this one as the world), then the same run in process: ``(cfg, in-process rollout)``."""
    args = ["run", "--backend", "distributed", "--timeout", "60", "--no-figures", "--out", str(out)]
    for key, value in keys.items():
        args += ["--set", f"{key}={value}"] if key != "method" else ["--method", value]
    assert main(args) == 0
    cfg = load_config(None, keys)
    return cfg, simulate(cfg)


def test_cli_distributed_equals_inprocess_and_counts_bytes(tmp_path):
    """Three agent processes + the world (this process): same states as the in-process
    backend for the same seed (GP-chance: every agent trains its own GP); bytes match
    the formula 8 (2 (T+1) D + T) |N_k| per iteration (copy plus the T projected variances
    of the sum margin) plus the 16-byte residual report."""
    out = tmp_path / "dist"
    cfg, ref = run_both_backends(QUICK, out)
    with np.load(out / "rollout.npz", allow_pickle=False) as r:
        states, messages = r["states"], r["messages_per_iteration"]
        iterations = r["admm_iterations"]
        # the coordinator times each distributed step, and the agents' solves happen inside it
        assert r["step_time"].shape == (3,) and np.all(r["step_time"] >= r["solve_time"])
    assert states.shape == ref.states.shape
    diff = np.abs(states - ref.states).max()
    print(f"distributed vs in-process max |state difference| = {diff:.3e}")
    assert diff <= 1e-9
    assert np.array_equal(iterations, ref.admm_iterations)
    m = json.loads((out / "metrics.json").read_text())
    assert set(CONTRACT_KEYS) <= set(m)
    T, D, K = cfg.horizon, cfg.dim, 3
    copy_bytes = 8 * (2 * (T + 1) * D + T) * (K - 1)  # complete graph: |N_k| = K - 1
    assert m["copy_bytes_per_agent_per_iteration"] == [copy_bytes] * K
    assert m["reduce_bytes_per_agent_per_iteration"] == [32.0] * K  # primal, dual and their ratios
    assert m["bytes_sent_per_agent_per_iteration"] == [copy_bytes + 32.0] * K
    assert m["bytes_sent_per_agent_per_iteration_mean"] == copy_bytes + 32.0
    # once at t = 0, and after each capped step (which may have re-planned) the agent's fallback seeds
    # to the world (1 + K numbers) and the plans the agents apply
    capped = int((~np.asarray(ref.converged, dtype=bool)).sum())
    per_capped = 8 * (T + 1) * D * (K - 1) + 8 * (1 + K)
    assert capped > 0 and m["plan_exchange_bytes_per_agent"] == [8 * (T + 1) * D * (K - 1) + per_capped * capped] * K
    assert np.array_equal(messages, np.full((3, K), (2 * (T + 1) * D + T) * (K - 1)))
    assert m["backend"] == "distributed" and m["processes"] == 3 and m["lost_agents"] == []


def test_a_step_that_falls_back_keeps_the_distributed_run_equal_to_in_process(tmp_path):
    """The paper scenario with the defaults (planes at 5 iterations) has a step without a safe iterate
    (step 24, seed 1), whose agents settle through the world who re-plans; they send each other the
    plans they apply, and every later step equals the in-process run's."""
    out = tmp_path / "dist"
    cfg, ref = run_both_backends({"max_steps": 28, "seed": 1}, out)
    m = json.loads((out / "metrics.json").read_text())
    with np.load(out / "rollout.npz", allow_pickle=False) as r:
        states = r["states"]
    assert m["fallback_steps"] >= 1 and compute_metrics(ref)["fallback_steps"] == m["fallback_steps"]
    assert np.abs(states - ref.states).max() <= 1e-9


@pytest.mark.parametrize("model, refit_every", [("single-integrator", 0), ("single-integrator", 4),
                                               ("double-integrator", 0)])
def test_online_gps_learn_in_the_agent_processes_as_in_process(tmp_path, model, refit_every):
    """With ``gp_online`` every agent process keeps its own guarded online GP and learns from the
    transitions it makes, its offset estimate on top: the states equal the in-process run's, where
    one OnlineLearning updates every agent, also with the hyperparameters refitted every 4 steps in
    each process, and for the double integrator (GPs on its velocity rows). The wind turns at step 1
    and the learners are adopted within the run, which parts from a frozen one."""
    out = tmp_path / "dist"
    keys = {"method": "gp-chance", "max_steps": 12, "gp_iters": 5, "gp_online": True, "wind_scale": 0.5,
            "wind_change_step": 1, "disturbance_drift": 0.01, "gp_online_refit_every": refit_every,
            "model": model}
    cfg, ref = run_both_backends(keys, out)
    with np.load(out / "rollout.npz", allow_pickle=False) as r:
        states = r["states"]
    assert states.shape == ref.states.shape == (13, 3, 2 if model == "single-integrator" else 4)
    assert np.abs(states - ref.states).max() <= 1e-9
    frozen = simulate(cfg.replace(gp_online=False))
    assert np.abs(frozen.states - ref.states).max() > 0.1
    if refit_every:  # the refits moved the run (by 0.046 here): the processes did refit
        assert np.abs(simulate(cfg.replace(gp_online_refit_every=0)).states - ref.states).max() > 0.01


def test_plane_distributed_run_equals_inprocess_and_counts_bytes(tmp_path):
    """``admm_coupling = planes`` across processes (two agents per process, so in-memory and gloo
    deliveries both): the in-process states and iterations; per iteration T offsets per neighbour,
    per step the variances, rows and final plan."""
    keys = {"method": "gp-chance", "scenario": "circle", "num_agents": 4, "circle_radius": 1.5,
            "admm_coupling": "planes", "max_steps": 6, "admm_max_iter": 30, "gp_iters": 5}
    out = tmp_path / "dist"
    args = ["run", "--backend", "distributed", "--agents-per-process", "2", "--timeout", "60", "--no-figures",
            "--out", str(out), "--method", keys["method"]]
    for key, value in keys.items():
        args += ["--set", f"{key}={value}"] if key != "method" else []
    assert main(args) == 0
    cfg = load_config(None, keys)
    ref = simulate(cfg)
    with np.load(out / "rollout.npz", allow_pickle=False) as r:
        states, iterations, messages = r["states"], r["admm_iterations"], r["messages_per_iteration"]
    assert np.abs(states - ref.states).max() <= 1e-9
    assert np.array_equal(iterations, ref.admm_iterations) and iterations.max() > 5
    T, D, K = cfg.horizon, cfg.dim, 4
    assert np.array_equal(messages, np.full((cfg.max_steps, K), T * (K - 1)))
    m = json.loads((out / "metrics.json").read_text())
    assert m["copy_bytes_per_agent_per_iteration"] == [8.0 * T * (K - 1)] * K
    per_step = T + (T + T * D) + (T + 1) * D  # variances, rows, final plan
    warm_plans = (T + 1) * D  # once, when the edge appears (t = 0)
    assert m["plan_exchange_bytes_per_agent"] == [8.0 * (K - 1) * (cfg.max_steps * per_step + warm_plans)] * K


@pytest.mark.parametrize("coupling", ["copies", "planes"])
def test_killed_agent_becomes_an_obstacle_and_the_run_reports_it(tmp_path, coupling):
    """No noise, no wind. Agent 2's process is killed at step 2; agents 0 and 1 (one
    process, messages in memory) go on, treat 2 as an obstacle on its last shared plan (with
    planes: 2's end of each plane votes where its half touches that plan),
    keep r_safe between themselves (to within admm_tol, as in the in-process tests), and
    the run ends with a report naming agent 2."""
    scen = tmp_path / "close.json"
    scen.write_text(json.dumps({"starts": [[1.5, 0.0], [-0.75, 1.299], [-0.75, -1.299]],
                                "targets": [[-1.5, 0.0], [0.75, -1.299], [0.75, 1.299]],
                                "reference": "line", "ref_points": 12}))
    cfg = Config(scenario="circle", num_agents=3, method="nominal", noise_std=0.0, wind_scale=0.0,
                 max_steps=9, admm_max_iter=20, admm_coupling=coupling)
    pids: dict[int, int] = {}

    def on_step(t: int, info: dict) -> None:
        if t == 1:
            os.kill(pids[2], signal.SIGKILL)  # rank 2 hosts agent 2 alone

    rollout, report = simulate_distributed(cfg, make_scenario(cfg, str(scen)), agents_per_process=2,
                                           timeout_s=20, on_launch=pids.update, on_step=on_step,
                                           log_dir=tmp_path / "agent_logs")
    assert rollout.num_steps == cfg.max_steps
    assert sorted(p.name for p in (tmp_path / "agent_logs").glob("rank*.log")) == ["rank1.log", "rank2.log"]
    assert set(report.lost_agents) == {2} and report.lost_agents[2] == 2
    assert report.exit_codes[2] == -signal.SIGKILL and report.exit_codes[1] == 0
    assert "agent 2 at step 2" in report.summary()
    remaining = pair_distances(rollout.states[:, [0, 1]])
    assert remaining.min() >= cfg.r_safe - cfg.admm_tol
    assert remaining.min() < cfg.r_safe + 0.1  # they really met
    m = report.metrics(rollout, cfg)
    assert m["lost_agents"] == [2] and m["lost_at_step"] == {"2": 2}
    # after the loss, 0 and 1 send copies (offsets) only to each other: between 1 and 2 neighbours' worth
    T, D = cfg.horizon, cfg.dim
    per_neighbour = T if coupling == "planes" else 2 * (T + 1) * D
    for k in (0, 1):
        assert 8 * per_neighbour < m["copy_bytes_per_agent_per_iteration"][k] < 8 * per_neighbour * 2
    assert report.log_dir is not None  # kept for inspection after a fault


@pytest.mark.slow
def test_longer_run_with_two_agents_per_process_equals_inprocess():
    """Paper scenario, nominal-chance, 12 steps of up to 30 ADMM iterations, agents 0 and 1
    in one process (messages in memory) and agent 2 in another: states equal."""
    cfg = load_config(None, {"method": "nominal-chance", "max_steps": 12, "admm_max_iter": 30, "gp_iters": 5})
    rollout, report = simulate_distributed(cfg, agents_per_process=2, timeout_s=60)
    ref = simulate(cfg)
    assert report.processes == 2 and not report.lost_agents
    assert np.abs(rollout.states - ref.states).max() <= 1e-9
    assert np.array_equal(rollout.admm_iterations, ref.admm_iterations)


def test_shaped_references_reach_the_agents_doorway():
    """The doorway's routed, turn-taking references are shaped by the closed loop and sent with
    the sensing message: two agents in one process follow them exactly as in process (the one
    waiting its turn included; without them both would drive straight at the wall)."""
    cfg = Config(scenario="doorway", num_agents=2, method="nominal", noise_std=0.0, wind_scale=0.0, max_steps=50)
    rollout, report = simulate_distributed(cfg, agents_per_process=2, timeout_s=60)
    ref = simulate(cfg)
    assert not report.lost_agents
    assert np.abs(rollout.states - ref.states).max() <= 1e-9
    crossed = rollout.states[-1, :, 0] * rollout.states[0, :, 0] < 0  # each now in the other room
    assert crossed.all()
    waited = np.abs(np.diff(rollout.states[15:25, 1, 0], axis=0)).max()  # agent 1 holds while 0 is in the gap
    assert waited < 1e-3


@pytest.mark.parametrize("coupling", ["copies", "planes"])
def test_a_mixed_team_runs_distributed_as_in_process(coupling):
    """Two double-integrator drones (radius 0.2) and a single-integrator robot (0.3), gp-chance with
    each agent's own learned GP: agents 0 and 1 in one process, agent 2 in another; each plans with its
    own model's step on lifted states (with planes, its rows' normals are lifted too), so the states
    and ADMM iterations equal the in-process TeamStep's (which solves each model's agents as one batch)."""
    cfg = Config(scenario="circle", num_agents=3, models=["double-integrator", "single-integrator", "double-integrator"],
                 radii=[0.2, 0.3, 0.2], max_steps=6, admm_max_iter=20, gp_samples=30, gp_iters=5,
                 admm_coupling=coupling, circle_radius=1.2 if coupling == "planes" else 4.0)
    rollout, report = simulate_distributed(cfg, agents_per_process=2, timeout_s=60)
    ref = simulate(cfg)
    assert report.processes == 2 and not report.lost_agents
    assert rollout.states.shape[-1] == 4 and float(np.abs(rollout.states[:, 1, 2:]).max()) == 0.0
    assert np.abs(rollout.states - ref.states).max() <= 1e-9
    assert np.array_equal(rollout.admm_iterations, ref.admm_iterations)
    assert rollout.admm_iterations.max() > 5  # the agents meet: the rows bind


def test_a_mixed_team_falls_back_distributed_as_in_process():
    """Three single integrators and a double integrator close together, the paper's copies capped
    at 2 iterations: the fallback re-plans on most steps, the single integrators inside their cells
    towards each other and against the double integrator's plan (its rows priced on the cells'
    scale), each distributed agent as a batch of one; the states equal the in-process run's."""
    cfg = Config(scenario="circle", num_agents=4, radii=[0.3, 0.3, 0.2, 0.3], max_steps=8, admm_max_iter=2,
                 models=["single-integrator", "single-integrator", "double-integrator", "single-integrator"],
                 method="nominal", noise_std=0.0, wind_scale=0.0, circle_radius=0.6, admm_coupling="copies",
                 reference="target")
    rollout, report = simulate_distributed(cfg, agents_per_process=2, timeout_s=60)
    ref = simulate(cfg)
    assert not report.lost_agents and int(np.sum(ref.fallback)) >= 5
    assert np.array_equal(rollout.fallback, ref.fallback)
    assert np.abs(rollout.states - ref.states).max() <= 1e-9
