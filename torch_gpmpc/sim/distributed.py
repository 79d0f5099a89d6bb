"""The distributed backend's world: one process per agent (or group), this process steps
the true system.

``gpmpc run --backend distributed`` runs Algorithm 1 the way it would run on robots.
Rank 0 is the **world**: it runs the one closed loop (:func:`~.closed_loop.run_closed_loop`)
with a :class:`RemotePlanner` that acts as each agent's sensors and collects their
inputs; ranks ``1..P`` host the agents (:mod:`torch_gpmpc.coordination.distributed`).
The messages are listed in :mod:`~torch_gpmpc.coordination.distributed.protocol`.

Faults: every receive has a deadline; a peer that does not answer is lost for good. A
lost agent's vehicle executes the rest of its last plan open loop, then holds (u = 0);
the others treat it as an obstacle following its last shared plan. The run always ends
with a :class:`DistributedReport` naming the lost agents and the step they were lost at.

Equality with the in-process backend: an agent's local step is the in-process batched
step's row k, so for the same seed the states are equal whenever every agent has the
same number of neighbours (e.g. the complete graph) and the solver treats a batch's
problems independently.

Launching: without ``RANK``/``WORLD_SIZE`` in the environment this process becomes rank 0
and spawns the agent processes on a free 127.0.0.1 port; with them (torchrun, or a
manual multi-host launch) it must be rank 0 and every other rank hosts
``ceil(K / (WORLD_SIZE - 1))`` agents.
"""

from __future__ import annotations

import json
import logging
import math
import os
import shutil
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np
import torch
from torch import Tensor

from torch_gpmpc.config.schema import Config
from torch_gpmpc.control.problem import FAILURE_KINDS
from torch_gpmpc.coordination.distributed.launch import reap, spawn_agents
from torch_gpmpc.coordination.distributed.protocol import (
    CMD_STEP, CMD_STOP, DEFAULT_SETUP_TIMEOUT_S, DEFAULT_TIMEOUT_S, DTYPE, FLOAT_BYTES, MAX_AGENTS, Kind,
    Telemetry, rank_of, replan_seeds_size, residual_size, sensing_size, tag, telemetry_size,
)
from torch_gpmpc.coordination.distributed.transport import Network, destroy_group, env_rank, free_port, init_group
from torch_gpmpc.coordination.fallback import replanning_from_seeds
from torch_gpmpc.coordination.penalty import should_stop
from torch_gpmpc.coordination.agent_step import message_size
from torch_gpmpc.coordination.graph import Graph
from torch_gpmpc.coordination.state import StepResult, shift_in_time
from torch_gpmpc.dynamics.team import team_system_from_config
from torch_gpmpc.errors import GpmpcError
from torch_gpmpc.sim.closed_loop import StepCallback, run_closed_loop
from torch_gpmpc.sim.metrics import pair_distances
from torch_gpmpc.sim.rollout import Rollout
from torch_gpmpc.sim.scenarios import Scenario, make_scenario, with_scenario_world

log = logging.getLogger(__name__)


@dataclass
class DistributedReport:
    """What the distributed run measured beyond the rollout.

    Attributes:
        processes: agent processes (world excluded).
        agents_per_process: agents hosted per process.
        lost_agents: agent id -> step at which the world lost it.
        lost_reasons: agent id -> the transport's reason.
        exit_codes: agent rank -> process exit code (local launch only; None if unknown).
        per_agent: agent id -> the agent's counters (bytes, times, iterations).
        setup_s: seconds from sending the missions until every agent was ready (GP
            training, solver build).
        launch_s: seconds until every agent process had joined the process group (local launch).
        log_dir: where the agent processes' logs are (local launch), if kept.
    """

    processes: int
    agents_per_process: int
    lost_agents: dict[int, int] = field(default_factory=dict)
    lost_reasons: dict[int, str] = field(default_factory=dict)
    exit_codes: dict[int, int | None] = field(default_factory=dict)
    per_agent: dict[int, dict[str, float]] = field(default_factory=dict)
    setup_s: float = 0.0
    launch_s: float = 0.0
    log_dir: str | None = None

    def metrics(self, rollout: Rollout, cfg: Config) -> dict[str, Any]:
        """Extra ``metrics.json`` keys (the contract keys come from ``compute_metrics``)."""
        K = rollout.num_agents
        per_it, copy_it, reduce_it, plan_b, tel_step, solve_it, comm_it = [], [], [], [], [], [], []
        for k in range(K):
            c = self.per_agent.get(k, {})
            its = max(c.get("iterations_total", 0.0), 1.0)
            steps = max(c.get("telemetry_bytes", 0.0) / (FLOAT_BYTES * telemetry_size(cfg)), 1.0)
            copy_it.append(c.get("copy_bytes", 0.0) / its)
            reduce_it.append(c.get("reduce_bytes", 0.0) / its)
            per_it.append(copy_it[-1] + reduce_it[-1])
            plan_b.append(c.get("plan_bytes", 0.0))
            tel_step.append(c.get("telemetry_bytes", 0.0) / steps)
            solve_it.append(c.get("solve_time", 0.0) / its)
            comm_it.append(c.get("comm_time", 0.0) / its)
        alive = [k for k in range(K) if k not in self.lost_agents]
        dists = pair_distances(rollout.positions[:, alive]) if len(alive) > 1 else np.zeros((0, 0))
        return {
            "backend": "distributed",
            "processes": self.processes,
            "agents_per_process": self.agents_per_process,
            "bytes_sent_per_agent_per_iteration": per_it,
            "bytes_sent_per_agent_per_iteration_mean": float(np.mean(per_it)) if per_it else 0.0,
            "copy_bytes_per_agent_per_iteration": copy_it,
            "reduce_bytes_per_agent_per_iteration": reduce_it,
            "plan_exchange_bytes_per_agent": plan_b,
            "telemetry_bytes_per_agent_per_step": tel_step,
            "agent_solve_s_per_iteration": solve_it,
            "agent_comm_s_per_iteration": comm_it,
            "launch_s": self.launch_s,
            "setup_s": self.setup_s,
            "lost_agents": sorted(self.lost_agents),
            "lost_at_step": {str(k): v for k, v in sorted(self.lost_agents.items())},
            "violations_among_remaining": int(np.count_nonzero(dists < cfg.r_safe)) if dists.size else 0,
            "min_pair_distance_among_remaining": float(dists.min()) if dists.size else None,
        }

    def summary(self) -> str:
        """One human line about faults (empty when none)."""
        if not self.lost_agents:
            return ""
        parts = [f"agent {k} at step {t} ({self.lost_reasons.get(k, 'no answer')})"
                 for k, t in sorted(self.lost_agents.items())]
        logs = f"; agent logs in {self.log_dir}" if self.log_dir else ""
        return ("lost " + ", ".join(parts) + "; the others treated them as obstacles following their "
                "last shared plans" + logs)

class RemotePlanner:
    """The world's planner: sends each agent its measurement, relays the global residuals
    until ADMM stops, and collects every agent's input and plan.

    Args:
        cfg: run configuration.
        net: rank 0's :class:`~torch_gpmpc.coordination.distributed.transport.Network`.
        num_agents: K.
        per: agents per agent process.
        timeout_s: seconds a receive waits before the peer counts as lost.
        report: the run's report (lost agents and per-agent counters are written into it).
    """

    def __init__(self, cfg: Config, net: Network, num_agents: int, per: int, timeout_s: float,
                 report: DistributedReport) -> None:
        self.cfg, self.net, self.num_agents, self.per = cfg, net, num_agents, per
        self.timeout_s, self.report = timeout_s, report
        T, D = cfg.horizon, cfg.state_dim
        self.last_plan = torch.zeros(num_agents, T + 1, D, dtype=DTYPE)
        self.open_loop = [torch.zeros(0, cfg.input_dim, dtype=DTYPE) for _ in range(num_agents)]

    @property
    def lost(self) -> dict[int, int]:
        """Lost agent -> the step it was lost at."""
        return self.report.lost_agents

    def _live(self) -> list[int]:
        return [k for k in range(self.num_agents) if k not in self.lost]

    def _mark_lost(self, t: int) -> None:
        for k in self._live():
            r = rank_of(k, self.per)
            if r in self.net.dead:
                self.lost[k] = t
                self.report.lost_reasons[k] = self.net.dead[r]
                log.warning("world: lost agent %d at step %d; it continues open loop on its last plan", k, t)

    def plan(self, t: int, x: Tensor, xref: Tensor, graph: Graph) -> StepResult | None:
        """One step: sensing (with each agent's reference window ``xref`` (K, T+1, D): the
        closed loop shapes it, round obstacles and through passages, from what the agent and its
        neighbours know), the ADMM iterations' stop decisions, telemetry."""
        self._mark_lost(t)
        if not self._live():
            log.error("world: every agent is lost; ending the run at step %d", t)
            return None
        self._send_sensing(t, x, xref, graph)
        res = self._decide_iterations(t, graph)
        self._collect(t, res)
        res.messages = message_size(self.cfg.controller_settings(), self.cfg.state_dim) * graph.degrees()
        res.lost_agents = sorted(self.lost)
        return res

    def _send_sensing(self, t: int, x: Tensor, xref: Tensor, graph: Graph) -> None:
        K, D, T = self.num_agents, self.cfg.state_dim, self.cfg.horizon
        adj = graph.adjacency()
        sends = []
        ref_end = 3 + D + (T + 1) * D
        for k in self._live():
            ids = [j for j in range(K) if bool(adj[k, j])]
            msg = torch.full((sensing_size(K, D, T),), -1.0, dtype=DTYPE)
            msg[0], msg[1], msg[2] = CMD_STEP, t, len(ids)
            msg[3:3 + D] = x[k]
            msg[3 + D:ref_end] = xref[k].reshape(-1)
            msg[ref_end:ref_end + len(ids)] = torch.tensor(ids, dtype=DTYPE)
            sends.append((msg, rank_of(k, self.per), tag(Kind.SENSE, 0, k)))
        self.net.exchange(sends, [], self.timeout_s)

    def _decide_iterations(self, t: int, graph: Graph) -> StepResult:
        """Reduce the agents' residuals each iteration and broadcast the stop decision; after a stop
        on plans not known to be safe, settle who re-plans (:meth:`_settle_replanning`)."""
        cfg, K, T = self.cfg, self.num_agents, self.cfg.horizon
        res = StepResult(plans=self.last_plan, inputs=torch.zeros(K, T, cfg.input_dim, dtype=DTYPE), state=None,
                         iterations=0, converged=False)
        deadline = None if cfg.admm_time_budget_ms is None else time.perf_counter() + cfg.admm_time_budget_ms / 1000
        for it in range(1, cfg.iteration_cap + 1):
            self._mark_lost(t)
            got = self.net.exchange([], [((residual_size(cfg),), rank_of(k, self.per), tag(Kind.RESID, k))
                                         for k in self._live()], 2 * self.timeout_s + 5.0)
            vals = [g for g in got if g is not None]
            self._mark_lost(t)
            primal = max((float(v[0]) for v in vals), default=0.0)
            dual = max((float(v[1]) for v in vals), default=0.0)
            ratios = [max((float(v[i]) for v in vals), default=0.0) for i in (2, 3)]
            res.primal_residuals.append(primal)
            res.dual_residuals.append(dual)
            res.iterations = it
            res.converged = should_stop(*ratios, cfg)
            out_of_time = deadline is not None and time.perf_counter() > deadline
            stop = 2.0 if res.converged else (1.0 if it == cfg.iteration_cap or out_of_time else 0.0)
            settle = stop > 0 and self._may_replan(res, graph)
            decision = [primal, dual, stop, float(settle)]
            self.net.exchange([(torch.tensor(decision, dtype=DTYPE), rank_of(k, self.per),
                                tag(Kind.DECIDE, 0, k)) for k in self._live()], [], self.timeout_s)
            if settle:
                self._settle_replanning(t, graph)
            if stop > 0:
                return res
        return res

    def _may_replan(self, res: StepResult, graph: Graph) -> bool:
        """Whether the step stopped on plans not known to be jointly safe (the in-process
        :meth:`~torch_gpmpc.coordination.admm.ADMM.solve_step`'s test): with planes, no iterate had
        every half held (a team dual level below 1); with copies, no convergence."""
        if not graph.num_edges:
            return False
        if self.cfg.admm_coupling == "planes":
            return not any(d < 1.0 for d in res.dual_residuals)
        return not res.converged

    def _settle_replanning(self, t: int, graph: Graph) -> None:
        """Collect every live agent's fallback seeds and cell exits, and tell each whether it
        re-plans (:func:`~torch_gpmpc.coordination.fallback.fallback_agents`' rule: the closure
        needs the whole graph, one reduce like the stop decision's)."""
        K = self.num_agents
        live = self._live()
        got = self.net.exchange([], [((replan_seeds_size(K),), rank_of(k, self.per), tag(Kind.REPLAN_SEEDS, k))
                                     for k in live], 2 * self.timeout_s + 5.0)
        self._mark_lost(t)
        seeds, exits = torch.zeros(K, dtype=torch.bool), torch.zeros(K, K, dtype=torch.bool)
        for k, vec in zip(live, got):
            if vec is not None:
                seeds[k], exits[k] = vec[0] > 0.5, vec[1:] > 0.5
        replan = replanning_from_seeds(seeds, exits, graph)
        self.net.exchange([(replan[k:k + 1].to(DTYPE), rank_of(k, self.per), tag(Kind.REPLAN, 0, k))
                           for k in self._live()], [], self.timeout_s)

    def _collect(self, t: int, res: StepResult) -> None:
        """Telemetry of every live agent: inputs, plans and counters into ``res``."""
        cfg, K = self.cfg, self.num_agents
        live = self._live()
        tel = self.net.exchange([], [((telemetry_size(cfg),), rank_of(k, self.per), tag(Kind.TELEM, k))
                                     for k in live], 2 * self.timeout_s + 5.0)
        self._mark_lost(t)
        inputs = torch.zeros(K, cfg.horizon, cfg.input_dim, dtype=DTYPE)
        plans = self.last_plan.clone()
        margins, slacks, state_slacks = [], [], []
        reported = set()
        for k, vec in zip(live, tel):
            if vec is None:
                continue
            rec = Telemetry.unpack(vec, cfg)
            inputs[k, 0], plans[k] = rec.u, rec.plan
            self.open_loop[k] = rec.inputs[1:]
            self.report.per_agent[k] = rec.counters
            c = rec.counters
            res.infeasible_solves += int(c["infeasible"])
            res.failed_solves += int(c["failed"])
            for kind in FAILURE_KINDS:
                res.failed_by_kind[kind] = res.failed_by_kind.get(kind, 0) + int(c[f"failed_{kind}"])
            res.solve_time_s = max(res.solve_time_s, c["solve_time"])
            margins.append(c["max_margin"])
            res.fallback = res.fallback or c["fallback"] > 0.5
            res.unsafe_plan = res.unsafe_plan or c["unsafe_plan"] > 0.5
            slacks.append(c["slack_max"])
            state_slacks.append(c["state_slack_max"])
            reported.add(k)
        for k in range(K):
            if k not in reported:  # lost: its vehicle executes the rest of its last plan, then holds
                if self.open_loop[k].shape[0]:
                    inputs[k, 0], self.open_loop[k] = self.open_loop[k][0], self.open_loop[k][1:]
                plans[k] = shift_in_time(self.last_plan[k], dim=0)
        res.max_margin = max(margins, default=0.0)
        res.slack_max = max(slacks, default=0.0)
        res.state_slack_max = max(state_slacks, default=0.0)
        res.plans, res.inputs = plans, inputs
        self.last_plan = plans

    def stop(self) -> None:
        """Tell every live agent the run is over."""
        K, D = self.num_agents, self.cfg.state_dim
        self.net.exchange([(torch.full((sensing_size(K, D, self.cfg.horizon),), CMD_STOP, dtype=DTYPE), rank_of(k, self.per),
                            tag(Kind.SENSE, 0, k)) for k in self._live()], [], self.timeout_s)


def send_missions(net: Network, cfg: Config, scenario: Scenario, gp_model: str | None, world_size: int,
                  per: int, timeout_s: float, setup_timeout_s: float, report: DistributedReport) -> None:
    """Send each agent rank its mission (config, its agents' starts and reference paths) and
    wait until every agent is ready (GP trained, solver built).

    Raises:
        GpmpcError: an agent process failed during set-up.
    """
    K = scenario.num_agents
    paths = scenario.reference_path()
    agents_of = {r: [k for k in range(K) if rank_of(k, per) == r] for r in range(1, world_size)}
    t_setup = time.perf_counter()
    for r, agents in agents_of.items():
        own = {str(k): {"start": scenario.starts[k].tolist(), "reference": paths[k].tolist()} for k in agents}
        payload = {"config": cfg.to_dict(), "agents": agents, "missions": own, "num_agents": K,
                   "agents_per_process": per, "timeout_s": timeout_s, "gp_model": gp_model}
        net.send_bytes(json.dumps(payload).encode(), r, tag(Kind.MISSION, r), setup_timeout_s)
    busy = [r for r, agents in agents_of.items() if agents]
    ready = net.exchange([], [((1,), r, tag(Kind.READY, r)) for r in busy], setup_timeout_s)
    bad = [r for r, v in zip(busy, ready) if v is None or float(v[0]) != 1.0]
    if bad:
        raise GpmpcError(f"distributed run: agent process(es) of rank {bad} failed during set-up "
                         f"(GP training or solver build); see their logs"
                         + (f" in {report.log_dir}" if report.log_dir else ""))
    report.setup_s = time.perf_counter() - t_setup


def check_distributed(cfg: Config, num_agents: int, agents_per_process: int, timeout_s: float) -> None:
    """Refuse what the distributed backend cannot run, before any process or output exists.

    Raises:
        GpmpcError: naming the setting (config key or command-line flag) and the fix.
    """
    if num_agents > MAX_AGENTS:
        raise GpmpcError(f"distributed run: at most {MAX_AGENTS} agents, got {num_agents}")
    if cfg.risk_mode == "mission":
        raise GpmpcError("config key 'risk_mode': the mission budget runs in process only so far (its agents "
                         "would also exchange their step's risks and applied next states); drop "
                         "--backend distributed or use risk_mode=pair_step")
    if agents_per_process < 1:
        raise GpmpcError(f"--agents-per-process (agents_per_process) must be >= 1, got {agents_per_process}")
    if not timeout_s > 0:
        raise GpmpcError(f"--timeout must be > 0 seconds, got {timeout_s}")


def simulate_distributed(
    cfg: Config,
    scenario: Scenario | None = None,
    method: str | None = None,
    gp_model: str | None = None,
    on_step: StepCallback | None = None,
    tb=None,
    agents_per_process: int = 1,
    timeout_s: float = DEFAULT_TIMEOUT_S,
    setup_timeout_s: float = DEFAULT_SETUP_TIMEOUT_S,
    log_dir: str | Path | None = None,
    on_launch: Callable[[dict[int, int]], None] | None = None,
) -> tuple[Rollout, DistributedReport]:
    """Run one closed-loop scenario with one process per agent (group); this process is the world.

    Args:
        cfg: run configuration (seed, method, ADMM settings, ...).
        scenario: starts/targets/reference (default ``make_scenario(cfg)``).
        method: controller method (default ``cfg.method``).
        gp_model: a ``fit-gp`` model file every agent loads instead of training its own GP.
        on_step: called after every step with ``(t, StepInfo)`` (``lost_agents`` filled in).
        tb: a :class:`~torch_gpmpc.report.tensorboard.TBLogger` (or ``None``).
        agents_per_process: agents hosted by one process (local launch).
        timeout_s: seconds a receive waits before the peer counts as lost.
        setup_timeout_s: seconds allowed for start-up (launch, GP training).
        log_dir: where agent processes write their logs (local launch; default: a temporary
            directory, kept only if something failed).
        on_launch: called with ``{agent rank: pid}`` once the agent processes are started.

    Returns:
        ``(rollout, report)``; the states equal :func:`~.closed_loop.simulate`'s for the same seed.

    Raises:
        GpmpcError: bad arguments, or an agent process failed during set-up.
    """
    cfg = cfg.replace(method=method or cfg.method)
    scenario = scenario or make_scenario(cfg)
    cfg = with_scenario_world(cfg, scenario)
    K = scenario.num_agents
    check_distributed(cfg, K, agents_per_process, timeout_s)
    procs, tmp_logs = {}, None
    if env_rank() is not None:  # torchrun / manual launch: the agent ranks exist already
        world_size, per, report = _join_launched_world(K, setup_timeout_s)
    else:
        per = agents_per_process
        world_size = 1 + math.ceil(K / per)
        report = DistributedReport(processes=world_size - 1, agents_per_process=per)
        if log_dir is None:
            log_dir = tmp_logs = tempfile.mkdtemp(prefix="gpmpc_agents_")
        procs = _launch_local(cfg, world_size, setup_timeout_s, Path(log_dir), report, on_launch)
    ok = False
    try:
        net = Network(0)
        send_missions(net, cfg, scenario, gp_model, world_size, per, timeout_s, setup_timeout_s, report)
        planner = RemotePlanner(cfg, net, K, per, timeout_s, report)
        system = team_system_from_config(cfg)
        rollout = run_closed_loop(cfg, scenario, system, planner, on_step, tb)
        planner.stop()
        ok = True
    finally:
        t_end = time.perf_counter()
        destroy_group()
        if procs:
            reap(procs, 2 * timeout_s + 10.0 if ok else 1.0, report.exit_codes)
        log.info("distributed run: launch %.1f s, set-up %.1f s, shut-down %.1f s", report.launch_s,
                 report.setup_s, time.perf_counter() - t_end)
        if tmp_logs is not None and ok and not report.lost_agents and \
                all(c == 0 for c in report.exit_codes.values()):
            shutil.rmtree(tmp_logs, ignore_errors=True)
            report.log_dir = None
    if report.lost_agents:
        log.warning("distributed run: %s", report.summary())
    return rollout, report


def _join_launched_world(num_agents: int, setup_timeout_s: float) -> tuple[int, int, DistributedReport]:
    """Rank 0 of a torchrun / manual launch: ``(world size, agents per process, report)``."""
    if env_rank() != 0:
        raise GpmpcError("simulate_distributed runs the world and must be rank 0")
    world_size = int(os.environ["WORLD_SIZE"])
    if world_size < 2:
        raise GpmpcError("distributed run needs WORLD_SIZE >= 2 (the world plus agent processes)")
    per = math.ceil(num_agents / (world_size - 1))
    init_group(0, world_size, setup_timeout_s)
    return world_size, per, DistributedReport(processes=world_size - 1, agents_per_process=per)


def _launch_local(cfg: Config, world_size: int, setup_timeout_s: float, log_dir: Path,
                  report: DistributedReport, on_launch) -> dict:
    """Spawn the agent processes on this host and join them as rank 0."""
    log_dir.mkdir(parents=True, exist_ok=True)
    report.log_dir = str(log_dir)
    if cfg.solver == "fast":  # compile the kernel once here, not in every agent process
        from torch_gpmpc.control.solvers import ipm_kernel

        ipm_kernel.warm_up()
    port = free_port()
    procs = spawn_agents(world_size, port, setup_timeout_s, log_dir)
    if on_launch is not None:
        on_launch({r: p.pid for r, p in procs.items()})
    saved = os.environ.get("GLOO_SOCKET_IFNAME")
    if sys.platform.startswith("linux") and saved is None:
        os.environ["GLOO_SOCKET_IFNAME"] = "lo"
    try:
        t_launch = time.perf_counter()
        init_group(0, world_size, setup_timeout_s, init_method=f"tcp://127.0.0.1:{port}")
        report.launch_s = time.perf_counter() - t_launch
    except Exception:
        reap(procs, 1.0, report.exit_codes)
        raise
    finally:
        if saved is None:
            os.environ.pop("GLOO_SOCKET_IFNAME", None)
    return procs
