"""An agent process: hosts one or more agents, moves their messages, runs until told to stop.

Started by the world's launcher as ``python -m torch_gpmpc.coordination.distributed.agent_process``
(or by torchrun with ``RANK``/``WORLD_SIZE``/``MASTER_*`` set); it needs no arguments: the
world sends each rank its mission (the run configuration, its agents' starts and
reference paths). Messages between agents hosted by the same process are delivered in
memory but counted the same.
"""

from __future__ import annotations

import json
import logging
import os
import sys
import time

import torch
from torch import Tensor

from torch_gpmpc.config.schema import from_mapping
from torch_gpmpc.coordination.distributed.agent import AgentController
from torch_gpmpc.coordination.distributed.protocol import (
    CMD_STOP, DEFAULT_SETUP_TIMEOUT_S, DTYPE, FLOAT_BYTES, Kind, decision_size, rank_of, residual_size,
    sensing_size, tag, telemetry_size,
)
from torch_gpmpc.coordination.distributed.transport import Network, destroy_group, init_group
from torch_gpmpc.dynamics.methods import Method
from torch_gpmpc.dynamics.team import team_system_from_config

log = logging.getLogger(__name__)

#: Exit codes of an agent process.
EXIT_OK, EXIT_LOST_WORLD, EXIT_SETUP_FAILED = 0, 3, 4


class _LostWorld(Exception):
    """The world process stopped answering."""


def agent_gp(cfg, k: int, gp_model: str | None = None):
    """Agent k's own residual GP: loaded from ``gp_model``, or trained by the one per-agent
    recipe (:func:`~torch_gpmpc.gp.fit.fit_agent_gp`) in this process, from its own data."""
    from torch_gpmpc.gp import fit_agent_gp, load_model_gp

    if gp_model:
        return load_model_gp(gp_model, cfg.model_spec())
    return fit_agent_gp(cfg, team_system_from_config(cfg), k)


class AgentHost:
    """The agents of one rank and their message exchange with neighbours and the world.

    Args:
        net: this rank's :class:`~.transport.Network`.
        mission: the decoded mission message (config, agents, their references, ...).
        timeout_s: seconds a receive waits before the peer counts as lost.
    """

    def __init__(self, net: Network, mission: dict, timeout_s: float) -> None:
        self.net = net
        self.cfg = from_mapping(mission["config"])
        self.agents: list[int] = mission["agents"]
        self.num_agents, self.per = int(mission["num_agents"]), int(mission["agents_per_process"])
        self.timeout_s = timeout_s
        self.mission = mission
        self.controllers: dict[int, AgentController] = {}

    def build(self) -> None:
        """Train (or load) each hosted agent's GP and build its controller and solver."""
        cfg = self.cfg
        for k in self.agents:
            t0 = time.perf_counter()
            reference = torch.tensor(self.mission["missions"][str(k)]["reference"], dtype=DTYPE)
            gp = agent_gp(cfg, k, self.mission.get("gp_model")) if Method.parse(cfg.method).needs_gp else None
            fit_s = time.perf_counter() - t0
            ctrl = AgentController(k, self.num_agents, cfg, reference, gp)
            ctrl.local.solver(0)  # build the solver before the clock starts
            ctrl.counters["gp_fit_s"] = fit_s
            ctrl.counters["setup_s"] = time.perf_counter() - t0
            self.controllers[k] = ctrl

    def serve(self, first_wait_s: float) -> int:
        """Serve steps until the world says stop; returns the exit code."""
        wait = first_wait_s
        try:
            while True:
                sensed = self._receive(sensing_size(self.num_agents, self.cfg.state_dim, self.cfg.horizon), Kind.SENSE, wait)
                wait = max(4 * self.timeout_s, 60.0)
                if float(sensed[0][0]) == CMD_STOP:
                    return EXIT_OK
                comm_time = self._begin_step(sensed)
                comm_time += self._iterate()
                self._send_telemetry(comm_time)
        except _LostWorld:
            log.error("rank %d: lost the world process (rank 0); stopping", self.net.rank)
            return EXIT_LOST_WORLD

    def _receive(self, size: int, kind: Kind, wait_s: float, sends: list | None = None) -> list[Tensor]:
        """One message of ``kind`` from the world per hosted agent (after ``sends``)."""
        msgs = self.net.exchange(sends or [], [((size,), 0, tag(kind, 0, k)) for k in self.agents], wait_s)
        if any(m is None for m in msgs):
            raise _LostWorld
        return msgs

    def _begin_step(self, sensed: list[Tensor]) -> float:
        """Take the measurements, exchange plans on new edges; returns the communication time."""
        cfg, D = self.cfg, self.cfg.state_dim
        ref_end = 3 + D + (cfg.horizon + 1) * D
        t0 = time.perf_counter()
        t = int(sensed[0][1])
        new_edges = {}
        for k, m in zip(self.agents, sensed):
            nbr_ids = [int(v) for v in m[ref_end:ref_end + int(m[2])]]
            xref = m[3 + D:ref_end].clone().reshape(cfg.horizon + 1, D)
            new_edges[k] = self.controllers[k].begin_step(t, m[3:3 + D].clone(), nbr_ids, xref)
        sends, recvs, meta = [], [], []
        for k in self.agents:
            ctrl = self.controllers[k]
            for j in new_edges[k]:
                rj = rank_of(j, self.per)
                if rj in self.net.dead:
                    ctrl.dead.add(j)
                    continue
                ctrl.counters["plan_bytes"] += FLOAT_BYTES * (cfg.horizon + 1) * D
                if j in self.controllers:
                    self.controllers[j].set_neighbour_plan(k, ctrl.own_plan().clone())
                else:
                    sends.append((ctrl.own_plan().clone(), rj, tag(Kind.PLAN, k, j)))
                    recvs.append(((cfg.horizon + 1, D), rj, tag(Kind.PLAN, j, k)))
                    meta.append((k, j))
        for (k, j), plan in zip(meta, self.net.exchange(sends, recvs, self.timeout_s)):
            if plan is None:
                self.controllers[k].dead.add(j)
            else:
                self.controllers[k].set_neighbour_plan(j, plan)
        for k in self.agents:
            self.controllers[k].finish_setup()
        if self.cfg.admm_coupling == "planes":
            self._agree_on_rows()
        return time.perf_counter() - t0

    def _agree_on_rows(self) -> None:
        """With planes: the step's variances (where the margins read them), then each edge's rows,
        so that both ends pose the same planes for the whole step."""
        T, D = self.cfg.horizon, self.cfg.state_dim
        first = self.controllers[self.agents[0]]
        if first.local.exchanges_variance:
            own = {k: self.controllers[k].step_variances() for k in self.agents}
            received = self._exchange_with_neighbours(own, Kind.VARIANCE, T, "plan_bytes")
            for k in self.agents:
                self.controllers[k].take_step_variances(received[k])
        own = {k: self.controllers[k].plane_rows() for k in self.agents}
        received = self._exchange_with_neighbours(own, Kind.ROWS, T + T * D, "plan_bytes")
        for k in self.agents:
            self.controllers[k].take_plane_rows(received[k])

    def _iterate(self) -> float:
        """ADMM iterations until the world's stop flag; returns the communication time."""
        comm_time = 0.0
        while True:
            own = {k: self.controllers[k].solve() for k in self.agents}
            t0 = time.perf_counter()
            received = self._exchange_with_neighbours(own, Kind.COPY, None, "copy_bytes")
            resid = {k: self.controllers[k].update(received[k]) for k in self.agents}
            sends = [(self.controllers[k].residual_message(resid[k]), 0, tag(Kind.RESID, k)) for k in self.agents]
            for k in self.agents:  # the whole message: residuals and their ratios
                self.controllers[k].counters["reduce_bytes"] += FLOAT_BYTES * residual_size(self.cfg)
            decisions = self._receive(decision_size(self.cfg), Kind.DECIDE, max(4 * self.timeout_s, 60.0), sends)
            comm_time += time.perf_counter() - t0
            for k, decision in zip(self.agents, decisions):
                self.controllers[k].keep_safe_plan(decision)
            stop, settle = float(decisions[0][2]), float(decisions[0][3]) > 0.5
            if stop > 0.5:
                if self.cfg.admm_coupling == "planes":  # the neighbours' last plans, for the safety check
                    received, seconds = self._exchange_own_plans(Kind.FINAL_PLAN, self.agents)
                    for k in self.agents:
                        self.controllers[k].take_final_plans(received[k])
                    comm_time += seconds
                for k in self.agents:
                    self.controllers[k].result.converged = stop > 1.5
                    self.controllers[k].check_safety(settle)
                if settle:
                    comm_time += self._settle_replanning()
                comm_time += self._exchange_applied_plans()
                return comm_time

    def _settle_replanning(self) -> float:
        """Send the world each hosted agent's fallback seeds and let those it names re-plan (the
        world closes the seeds over the graph, :mod:`torch_gpmpc.sim.distributed`); returns the
        communication time."""
        t0 = time.perf_counter()
        sends = []
        for k in self.agents:
            seeds = self.controllers[k].replan_seeds()
            self.controllers[k].counters["plan_bytes"] += FLOAT_BYTES * seeds.numel()
            sends.append((seeds, 0, tag(Kind.REPLAN_SEEDS, k)))
        decided = self._receive(1, Kind.REPLAN, max(4 * self.timeout_s, 60.0), sends)
        seconds = time.perf_counter() - t0
        for k, flag in zip(self.agents, decided):
            self.controllers[k].replan(bool(flag[0] > 0.5))
        return seconds

    def _exchange_applied_plans(self) -> float:
        """After a step that may have re-planned (every agent of the team knows whether it may), each
        agent sends its neighbours the plan it applies; returns the communication time."""
        agents = [k for k in self.agents if self.controllers[k].fallback_possible]
        if not agents:
            return 0.0
        received, seconds = self._exchange_own_plans(Kind.APPLIED_PLAN, agents)
        for k in agents:
            self.controllers[k].take_applied_plans(received[k])
        return seconds

    def _exchange_own_plans(self, kind: Kind, agents: list[int]) -> tuple[dict[int, dict[int, Tensor | None]], float]:
        """Hosted agents ``agents`` send each neighbour their current plan ((T+1) D numbers) as ``kind``
        and collect their neighbours'; returns what they received and the communication time."""
        t0 = time.perf_counter()
        own = {k: {j: self.controllers[k].own_plan().clone() for j in self.controllers[k].nbrs} if k in agents else {}
               for k in self.agents}
        received = self._exchange_with_neighbours(own, kind, (self.cfg.horizon + 1) * self.cfg.state_dim, "plan_bytes")
        return received, time.perf_counter() - t0

    def _exchange_with_neighbours(self, own: dict[int, dict[int, Tensor]], kind: Kind, size: int | None,
                                  counter: str) -> dict[int, dict[int, Tensor | None]]:
        """Send every hosted agent's message of ``kind`` to each of its neighbours and collect theirs
        (``None``: lost): ``size`` numbers each (``None``: the receiver's ``message_size``), the bytes
        sent counted in ``counter``."""
        sends, recvs, meta = [], [], []
        received: dict[int, dict[int, Tensor | None]] = {k: {} for k in self.agents}
        for k in self.agents:
            ctrl = self.controllers[k]
            for j, copy in own[k].items():
                if j in ctrl.dead or rank_of(j, self.per) in self.net.dead:
                    ctrl.dead.add(j)
                    continue
                ctrl.counters[counter] += FLOAT_BYTES * copy.numel()
                if j in self.controllers:
                    received[j][k] = copy
                else:
                    sends.append((copy, rank_of(j, self.per), tag(kind, k, j)))
                    recvs.append(((ctrl.message_size if size is None else size,), rank_of(j, self.per),
                                  tag(kind, j, k)))
                    meta.append((k, j))
        for (k, j), msg in zip(meta, self.net.exchange(sends, recvs, self.timeout_s)):
            received[k][j] = msg
            if msg is None:
                self.controllers[k].dead.add(j)
        return received

    def _send_telemetry(self, comm_time: float) -> None:
        sends = []
        for k in self.agents:
            ctrl = self.controllers[k]
            ctrl.counters["comm_time"] += comm_time / len(self.agents)
            ctrl.counters["telemetry_bytes"] += FLOAT_BYTES * telemetry_size(self.cfg)
            sends.append((ctrl.end_step().pack(), 0, tag(Kind.TELEM, k)))
        self.net.exchange(sends, [], self.timeout_s)


def run_agent_process(rank: int, world_size: int, timeout_s: float | None = None,
                      setup_timeout_s: float = DEFAULT_SETUP_TIMEOUT_S) -> int:
    """Body of an agent rank (> 0): receive the mission, train own GPs, serve until STOP.

    The process group must already be initialised. Returns an exit code (0 = clean stop,
    3 = lost the world process, 4 = failed during set-up).
    """
    net = Network(rank)
    raw = net.recv_bytes(0, tag(Kind.MISSION, rank), setup_timeout_s)
    if raw is None:
        log.error("rank %d: no mission from the world process (rank 0)", rank)
        return EXIT_LOST_WORLD
    mission = json.loads(raw.decode())
    if not mission["agents"]:
        log.info("rank %d: no agents to host; exiting", rank)
        return EXIT_OK
    host = AgentHost(net, mission, float(mission["timeout_s"] if timeout_s is None else timeout_s))
    status = 1.0
    try:
        host.build()
    except Exception:  # noqa: BLE001 - reported to the world, then the process exits
        log.exception("rank %d: set-up failed", rank)
        status = 0.0
    net.exchange([(torch.tensor([status], dtype=DTYPE), 0, tag(Kind.READY, rank))], [], setup_timeout_s)
    if status == 0.0:
        return EXIT_SETUP_FAILED
    return host.serve(setup_timeout_s)


def agent_main(threads: int = 1) -> int:
    """Entry of an agent rank launched with ``RANK``/``WORLD_SIZE``/``MASTER_*`` set."""
    torch.set_num_threads(threads)
    rank, world_size = int(os.environ["RANK"]), int(os.environ["WORLD_SIZE"])
    setup = float(os.environ.get("GPMPC_SETUP_TIMEOUT", DEFAULT_SETUP_TIMEOUT_S))
    init_group(rank, world_size, setup)
    try:
        return run_agent_process(rank, world_size, setup_timeout_s=setup)
    finally:
        destroy_group()


if __name__ == "__main__":  # pragma: no cover - process entry
    logging.basicConfig(level=logging.WARNING,
                        format=f"%(levelname)s rank{os.environ.get('RANK', '?')} %(name)s: %(message)s")
    sys.exit(agent_main())
