"""Distributed backend: one process per agent (or per group of agents) plus a world process.

``gpmpc run --backend distributed`` runs Algorithm 1 of the paper the way it would run
on real robots. Rank 0 is the **world**: it steps the true system ``x' = f + g + w``
and acts as each agent's sensors. Ranks ``1..P`` host the agents (``agents_per_process``
agents each, default 1). All messages are point-to-point ``torch.distributed`` sends of
float64 tensors over the ``gloo`` backend (127.0.0.1 by default).

What is exchanged (and nothing else):

============================  ===============================  ===========================
message                       size (float64 numbers)           when
============================  ===============================  ===========================
world -> agent k: sensing     ``3 + D + (K-1)``: step, own     every step
                              state ``x_k``, ids of agents in
                              communication range
agent k -> neighbour j: copy  ``2 (T+1) D``: ``y_{kj,k}``      every ADMM iteration
                              (eq. 19), own plan in its own
                              half, copy of j's plan in the
                              other
agent k -> world: residuals   2: max ``||y_{e,k} - z_e||`` and every ADMM iteration
                              max ``rho ||z_e - z_e_prev||``
                              over k's edges
world -> agent k: residuals   3: the global maxima and the     every ADMM iteration
                              stop flag
agent k -> neighbour j: plan  ``(T+1) D``: k's warm-start      once, when the edge appears
                              plan (linearization point and
                              initial ``z_e``)
agent k -> world: actuation   ``D + (T+1) D + T D + 16``:      every step
                              input ``u_k`` plus telemetry
                              for the record (plan, counters)
============================  ===============================  ===========================

Each agent computes ``z_e`` (eq. 28, both ends compute the same mean of the same two
copies) and its *own* ``lambda_{e,k}`` (eq. 29) locally. No agent ever receives
another agent's covariance, GP or data: each agent trains (or loads) its own GP in its
own process. The global stopping test needs the largest primal (and dual) residual
over all edges: that is an all-reduce (max) of two floats per iteration; it is routed
through rank 0 (reduce, then broadcast back) rather than a gloo collective so that a
crashed agent cannot block it. The world's step command doubles as the step barrier.

The collision rows need the neighbour's current plan: it is the neighbour's own half of
its copy message, so it costs nothing extra.

Bytes: every agent counts the bytes of every logical message it sends (messages
between agents hosted by the same process are delivered in memory but counted the
same). Per ADMM iteration agent k sends ``8 * 2 (T+1) D |N_k|`` bytes of copies plus
16 bytes of residuals; no headers (shapes and dtypes are fixed by the protocol).

Faults: every receive has a deadline (``timeout_s``); a peer that does not answer, or
whose connection closes, is marked dead for good. A dead neighbour is treated as an
obstacle following its last shared plan (shifted by one step per step, holding its last
point): its missing copy is replaced by ``[own plan; last shared plan]``, so consensus
drives the agent's copy onto that plan. The world applies a dead agent's last planned
inputs open loop (then zero input). The run always ends with a report
(:class:`DistributedReport`) naming the lost agents and the step they were lost at.

Equality with the in-process backend: the per-agent local step reuses the library
(:func:`~torch_gpmpc.control.linearize.linearize_plan`, :func:`~torch_gpmpc.control.risk.collision_normals`,
:func:`~torch_gpmpc.control.risk.chance_margins`, :func:`~torch_gpmpc.coordination.admm.slot_risks`,
:func:`~torch_gpmpc.coordination.admm.adapt_state`, ``ADMM._solve/_count_failures/_fallback/
_edge_copies``, :func:`~torch_gpmpc.control.solvers.conic.get_local_mpc`), and diffcp solves a batch one
problem at a time, so for the same seed the states equal the in-process run's to the
last bit whenever every agent has the same number of neighbours (e.g. the complete
graph). With a communication radius, an agent with fewer neighbours than the largest
degree solves a problem without the in-process backend's padding slots; it is the same
problem, but the solver's iterates may differ in the last digits.

Each agent sees its neighbourhood as a *star graph* over the global agent ids (only its
own edges) and keeps an :class:`~torch_gpmpc.coordination.admm.ADMMState` over all K ids in which only
its own row and its neighbours' plan rows are meaningful; that is what lets it call the
batched library functions unchanged.

Launching: without ``RANK``/``WORLD_SIZE`` in the environment, the calling process
becomes rank 0 and spawns the agent processes itself on a free 127.0.0.1 port. With
them (``torchrun`` or a manual multi-host launch with ``MASTER_ADDR``, ``MASTER_PORT``,
``RANK``, ``WORLD_SIZE``), rank 0 runs the world and every other rank hosts
``ceil(K / (WORLD_SIZE - 1))`` agents; agent ranks need no arguments (the world sends
each its mission: the run configuration and its own start and target).
"""

from __future__ import annotations

import dataclasses
import datetime
import json
import logging
import math
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np
import torch
from torch import Tensor

from torch_gpmpc.coordination.admm import (
    ADMM, ADMMState, StepResult, _shift, adapt_state, consensus_update, initial_state, slot_risks,
)
from torch_gpmpc.config.schema import Config, from_mapping
from torch_gpmpc.dynamics.methods import Method
from torch_gpmpc.errors import GpmpcError
from torch_gpmpc.coordination.graph import Graph, communication_graph, graph_from_edges
from torch_gpmpc.sim.metrics import pair_distances
from torch_gpmpc.control.problem import FAILURE_KINDS, LocalProblemData, LocalSolution
from torch_gpmpc.sim.rollout import Rollout
from torch_gpmpc.sim.scenarios import Scenario, make_scenario
from torch_gpmpc.dynamics.systems import make_system

log = logging.getLogger(__name__)

DTYPE = torch.float64
#: Bytes of one float64 number on the wire.
FLOAT_BYTES = 8
#: Default seconds a receive waits for a peer before the peer counts as lost.
DEFAULT_TIMEOUT_S = 30.0
#: Default seconds for start-up (process launch, GP training, layer build).
DEFAULT_SETUP_TIMEOUT_S = 300.0
#: Largest team the message tags can address.
MAX_AGENTS = 1024

# message kinds (tag = kind * 2**20 + src * 1024 + dst)
_MISSION, _READY, _SENSE, _RESID, _DECIDE, _TELEM, _COPY, _PLAN = range(1, 9)
# commands in the sensing message
_CMD_STOP, _CMD_STEP = 0.0, 1.0
# counters in the telemetry message, after u (D), plan X ((T+1) D) and inputs U (T D)
_TELEM_KEYS = ("slack_max", "infeasible", "failed", *[f"failed_{k}" for k in FAILURE_KINDS],
               "solve_time", "max_margin", "iterations_total", "copy_bytes", "reduce_bytes",
               "plan_bytes", "telemetry_bytes", "comm_time", "setup_s", "gp_fit_s")


def _tag(kind: int, src: int = 0, dst: int = 0) -> int:
    return kind * (1 << 20) + src * MAX_AGENTS + dst


# ----------------------------------------------------------------------------- data & GP
def agent_gp(cfg: Config, k: int, gp_model: str | None = None):
    """Agent k's own residual GP, trained (or loaded) in the agent's process.

    The data are exactly agent k's rows of :func:`~torch_gpmpc.sim.closed_loop.train_agent_gps`'s
    data set (``collect_transitions`` with seed ``2 seed + 1``, fitted with seed
    ``seed + k``). That recipe draws every agent's samples from one generator in agent
    order, so agent k replays (and discards) the draws of agents ``0..k-1``; it never
    sees another agent's data or model.

    Args:
        cfg: run configuration.
        k: agent id.
        gp_model: a model file from ``gpmpc fit-gp`` to load instead (every agent loads it).

    Returns:
        A fitted :class:`~torch_gpmpc.gp.model.ResidualGP`.
    """
    from torch_gpmpc.data.transitions import collect_transitions
    from torch_gpmpc.gp.model import ResidualGP, fit_residual_gp

    if gp_model:
        return ResidualGP.load(gp_model, expected_dim=cfg.dim, expected_input_dim=cfg.dim)
    if cfg.gp_inputs != "state":
        raise GpmpcError("config key 'gp_inputs': the controller needs state-input GPs; use gp_inputs=state")
    system = make_system(cfg.dim, cfg.noise_std, cfg.wind_scale)
    data = collect_transitions(system, num_agents=k + 1, samples=cfg.gp_samples,
                               seed=2 * cfg.seed + 1, u_max=cfg.u_max, box=cfg.circle_radius)
    inputs, y = data.for_agent(k).residuals(system.nominal)
    return fit_residual_gp(inputs, y, optimizer=cfg.gp_optimizer, iters=cfg.gp_iters, seed=cfg.seed + k)


def agent_problem_data(admm: ADMM, k: int, x0: Tensor, xref: Tensor, state: ADMMState, graph: Graph,
                       rho: Tensor, eps_self: Tensor) -> tuple[LocalProblemData, Tensor]:
    """Agent k's local problem: row k of :meth:`ADMM._problem_data`, computed alone.

    Args:
        admm: the agent's :class:`ADMM` (its ``gps`` holds only ``gps[k]``; others are ``None``).
        k: agent id.
        x0: measured state, shape (D,).
        xref: reference window, shape (1, T+1, D).
        state: the agent's view, plans (K, T+1, D) with rows k and its neighbours valid.
        graph: the agent's star graph (its own edges, global ids).
        rho: ADMM penalty, scalar tensor.
        eps_self: the agent's risk per slot, shape (1, M).

    Returns:
        ``(data with batch 1, largest chance margin (scalar))``.
    """
    return admm._problem_data(x0[None], xref, state, graph, rho, eps_self, rows=slice(k, k + 1))


def _rows_like(v: Tensor, num_rows: int) -> Tensor:
    """An uninitialised (num_rows, *v.shape[1:]) tensor whose rows have ``v[0]``'s memory layout.

    The layer returns plans in a column-major layout, and some torch kernels (e.g. the
    norm in :func:`~torch_gpmpc.control.risk.collision_normals`) round differently in the last
    bit for other layouts; keeping the layer's layout keeps the agent's arithmetic
    identical to the in-process backend's.
    """
    inner = v[0]
    order = sorted(range(inner.dim()), key=lambda d: inner.stride(d), reverse=True)
    buf = v.new_empty((num_rows, *[inner.shape[d] for d in order]))
    return buf.permute(0, *[order.index(d) + 1 for d in range(inner.dim())])


def _embed(sol: LocalSolution, k: int, state: ADMMState) -> LocalSolution:
    """Place a batch-1 solution in row k of a K-row solution (other rows: the known plans,
    ``ok``), so the batched ``ADMM`` helpers can be applied to the agent's view."""
    num_agents = state.plans.shape[0]
    values: dict[str, Any] = {}
    for f in dataclasses.fields(LocalSolution):
        v = getattr(sol, f.name)
        if not isinstance(v, Tensor):
            values[f.name] = v
            continue
        full = _rows_like(v, num_agents)
        if f.name == "X":
            full.copy_(state.plans)
        elif f.name == "U":
            full.copy_(state.inputs)
        elif f.name == "ok":
            full.fill_(True)
        else:
            full.zero_()
        full[k] = v[0]
        values[f.name] = full
    return LocalSolution(**values)


# ----------------------------------------------------------------------------- one agent
class AgentController:
    """One agent's side of Algorithm 1: its state, its GP, its local solve and updates.

    No communication happens here; the hosting process moves the messages.

    Args:
        k: agent id.
        num_agents: K (ids are global).
        cfg: run configuration.
        mission: a one-agent :class:`~torch_gpmpc.sim.scenarios.Scenario` (own start, target,
            reference).
        gp: the agent's own residual GP (or ``None`` if the method needs none).
    """

    def __init__(self, k: int, num_agents: int, cfg: Config, mission: Scenario, gp=None) -> None:
        self.k, self.num_agents, self.cfg, self.mission = k, num_agents, cfg, mission
        system = make_system(cfg.dim, cfg.noise_std, cfg.wind_scale)
        wind = system.wind if Method.parse(cfg.method).needs_wind else None
        # indexed by agent id; this process holds only its own GP
        gps = None if gp is None else [gp if j == k else None for j in range(self.num_agents)]
        self.admm = ADMM(cfg, cfg.method, system.nominal, wind, gps)
        self.rho = torch.as_tensor(cfg.rho, dtype=DTYPE)
        self.state: ADMMState | None = None
        self.known = torch.zeros(num_agents, dtype=torch.bool)
        self.nbrs: list[int] = []
        self.dead: set[int] = set()
        self.graph = graph_from_edges(num_agents, [])
        self.counters = dict.fromkeys(_TELEM_KEYS, 0.0)

    # --- step set-up
    def begin_step(self, t: int, x0: Tensor, nbr_ids: list[int]) -> list[int]:
        """Take the measurement; return the neighbours new to this agent (plan exchange).

        Args:
            t: step.
            x0: own measured state, shape (D,).
            nbr_ids: ids of agents in communication range.
        """
        cfg, k, K = self.cfg, self.k, self.num_agents
        self.x0 = x0
        self.xref = self.mission.reference_window(t, cfg.horizon)
        if self.state is None:  # cold start: the plan is to stay (initial_state's rule)
            own = initial_state(x0[None], cfg.horizon, graph_from_edges(1, []))
            plans = x0.new_zeros(K, cfg.horizon + 1, cfg.dim)
            inputs = x0.new_zeros(K, cfg.horizon, cfg.dim)
            plans[k], inputs[k] = own.plans[0], own.inputs[0]
            self.state = ADMMState(plans, inputs, torch.zeros(0, 2, dtype=torch.long),
                                   x0.new_zeros(0, 2, cfg.horizon + 1, cfg.dim),
                                   x0.new_zeros(0, 2, 2, cfg.horizon + 1, cfg.dim))
        else:
            self.state = ADMMState(self.state.plans.clone(), self.state.inputs, self.state.edges,
                                   self.state.z, self.state.lam)
        self.known[k] = True
        self._next_nbrs = sorted(int(j) for j in nbr_ids if int(j) != k)
        return [j for j in self._next_nbrs if j not in self.nbrs]

    def own_plan(self) -> Tensor:
        """The warm-start plan sent to new neighbours, shape (T+1, D)."""
        return self.state.plans[self.k]

    def set_neighbour_plan(self, j: int, plan: Tensor) -> None:
        """Store neighbour j's plan (T+1, D) (from a plan message or its copy's own half)."""
        self.state.plans[j] = plan
        self.known[j] = True

    def finish_setup(self) -> None:
        """Build the star graph of this step, carry z/lambda over (``adapt_state``)."""
        cfg, k = self.cfg, self.k
        nbrs = []
        for j in self._next_nbrs:
            if j in self.dead and not bool(self.known[j]):
                log.warning("agent %d: agent %d is in range but lost and never shared a plan; ignored", k, j)
                continue
            nbrs.append(j)
        self.nbrs = nbrs
        self.graph = graph_from_edges(self.num_agents, [(k, j) for j in nbrs])
        self.state = adapt_state(self.state, self.graph)
        self.eps_self = slot_risks(self.graph, cfg.eps, cfg.risk_split)[k:k + 1]
        self.layer = self.admm._layer(self.graph.num_slots)
        self.frozen = self.state.plans
        self.result = StepResult(plans=self.state.plans, inputs=self.state.inputs, state=self.state,
                                 iterations=0, converged=False)
        m = torch.arange(self.graph.num_slots)
        self.slot_e = self.graph.slot_edge[k, m]
        self.slot_a = self.graph.slot_side[k, m]

    # --- one ADMM iteration
    def solve(self) -> dict[int, Tensor]:
        """Local solve (27) and fallback; returns own copies ``y_{kj,k}`` (2, T+1, D) per neighbour."""
        cfg, k, state = self.cfg, self.k, self.state
        lin_state = state if cfg.relinearize else ADMMState(self.frozen, state.inputs, state.edges,
                                                             state.z, state.lam)
        data, max_margin = agent_problem_data(self.admm, k, self.x0, self.xref, lin_state, self.graph,
                                              self.rho, self.eps_self)
        t0 = time.perf_counter()
        sol = self.admm._solve(self.layer, data)
        self.result.solve_time_s += time.perf_counter() - t0
        full = _embed(sol, k, state)
        self.admm._count_failures(full, self.result)
        full = self.admm._fallback(full, state, self.graph)
        self.result.infeasible_solves += int((full.slack_active | ~full.ok)[k])
        self.result.max_margin = float(max_margin)
        self.solution = full
        self.copies = self.admm._edge_copies(full, self.graph) if self.graph.num_edges else None
        return {j: self.copies[self.slot_e[m], self.slot_a[m]].clone() for m, j in enumerate(self.nbrs)}

    def update(self, received: dict[int, Tensor | None]) -> tuple[float, float]:
        """Consensus (28) and own duals (29) from the neighbours' copies.

        Args:
            received: neighbour id -> its copy ``y_{kj,j}`` (2, T+1, D), or ``None`` if lost.

        Returns:
            ``(largest ||y_{e,k} - z_e|| over own edges, largest rho ||z_e - z_e_prev||)``.
        """
        k, state, sol = self.k, self.state, self.solution
        plans = sol.X.clone()  # row k: own plan; neighbour rows are overwritten below (same layout)
        inputs = state.inputs.clone()
        inputs[k] = sol.U[k]
        if self.graph.num_edges:
            copies = self.copies
            for m, j in enumerate(self.nbrs):
                e, a = self.slot_e[m], self.slot_a[m]
                msg = received.get(j)
                if msg is None:  # lost neighbour: an obstacle following its last shared plan
                    msg = torch.empty_like(copies[e, a])
                    msg[a], msg[1 - a] = sol.X[k], state.plans[j]
                else:
                    plans[j] = msg[1 - a]
                copies[e, 1 - a] = msg
            z_new, lam, gap_norms, dual_norms = consensus_update(copies, state.z, state.lam, self.rho)
            lam[self.slot_e, 1 - self.slot_a] = 0.0  # the neighbour's dual is the neighbour's
            primal = gap_norms[self.slot_e, self.slot_a].max()
            dual = dual_norms.max()
        else:
            z_new, lam = state.z, state.lam
            primal = dual = self.x0.new_zeros(())
        self.state = ADMMState(plans, inputs, self.graph.edges, z_new, lam)
        self.result.iterations += 1
        self.counters["iterations_total"] += 1
        return float(primal), float(dual)

    def end_step(self) -> Tensor:
        """Telemetry of the step (input first) and shift the state for the next warm start.

        Returns:
            float64 vector ``[u (D), X ((T+1) D), U (T D), counters]``.
        """
        k, res, c = self.k, self.result, self.counters
        slack = self.solution.slack[k] if hasattr(self, "solution") else torch.zeros(0)
        c["slack_max"] = float(slack.max()) if slack.numel() else 0.0
        c["infeasible"], c["failed"] = res.infeasible_solves, res.failed_solves
        for kind in FAILURE_KINDS:
            c[f"failed_{kind}"] = res.failed_by_kind.get(kind, 0)
        c["solve_time"], c["max_margin"] = res.solve_time_s, res.max_margin
        vec = torch.cat([self.state.inputs[k, 0], self.state.plans[k].flatten(), self.state.inputs[k].flatten(),
                         torch.tensor([float(c[key]) for key in _TELEM_KEYS], dtype=DTYPE)])
        self.state = self.state.shifted()
        return vec


def telemetry_size(cfg: Config) -> int:
    """Numbers in one telemetry message (agent -> world, once per step)."""
    T, D = cfg.horizon, cfg.dim
    return D + (T + 1) * D + T * D + len(_TELEM_KEYS)


def _unpack_telemetry(vec: Tensor, cfg: Config) -> tuple[Tensor, Tensor, Tensor, dict[str, float]]:
    T, D = cfg.horizon, cfg.dim
    u = vec[:D]
    X = vec[D:D + (T + 1) * D].reshape(T + 1, D)
    U = vec[D + (T + 1) * D:D + (2 * T + 1) * D].reshape(T, D)
    counters = dict(zip(_TELEM_KEYS, vec[D + (2 * T + 1) * D:].tolist()))
    return u, X, U, counters


# ----------------------------------------------------------------------------- transport
class _Net:
    """Point-to-point float64 messages with deadlines; marks unresponsive ranks dead."""

    def __init__(self, rank: int) -> None:
        import torch.distributed as dist

        self.dist = dist
        self.rank = rank
        self.dead: dict[int, str] = {}  # rank -> reason

    def _lost(self, peer: int, exc: BaseException | str) -> None:
        if peer not in self.dead:
            reason = str(exc).splitlines()[0][:200] if str(exc) else type(exc).__name__
            self.dead[peer] = reason
            log.warning("rank %d: lost contact with rank %d (%s)", self.rank, peer, reason)

    def exchange(self, sends: list[tuple[Tensor, int, int]], recvs: list[tuple[tuple[int, ...], int, int]],
                 timeout_s: float, dtype: torch.dtype = DTYPE) -> list[Tensor | None]:
        """Post all sends and receives, then wait for them before one deadline.

        Args:
            sends: ``(tensor, dst rank, tag)``.
            recvs: ``(shape, src rank, tag)``.
            timeout_s: seconds until the deadline.

        Returns:
            One tensor per receive, ``None`` where the peer was (or became) unreachable.
        """
        deadline = time.monotonic() + timeout_s
        send_works = []
        for tensor, dst, tag in sends:
            if dst in self.dead:
                continue
            try:
                send_works.append((self.dist.isend(tensor.contiguous(), dst, tag=tag), dst, tensor))
            except RuntimeError as exc:
                self._lost(dst, exc)
        posted = []
        for shape, src, tag in recvs:
            if src in self.dead:
                posted.append(None)
                continue
            buf = torch.empty(shape, dtype=dtype)
            try:
                posted.append((self.dist.irecv(buf, src, tag=tag), src, buf))
            except RuntimeError as exc:
                self._lost(src, exc)
                posted.append(None)
        out: list[Tensor | None] = []
        for item in posted:
            if item is None:
                out.append(None)
                continue
            work, src, buf = item
            if src in self.dead or not self._wait(work, src, deadline):
                out.append(None)
            else:
                out.append(buf)
        for work, dst, _ in send_works:
            if dst not in self.dead:
                self._wait(work, dst, deadline)
        return out

    def _wait(self, work, peer: int, deadline: float) -> bool:
        remaining = max(deadline - time.monotonic(), 0.01)
        try:
            ok = work.wait(datetime.timedelta(seconds=remaining))
        except RuntimeError as exc:
            self._lost(peer, exc)
            return False
        if ok is False:
            self._lost(peer, "no answer within the deadline")
            return False
        return True

    def send_bytes(self, payload: bytes, dst: int, tag: int, timeout_s: float) -> None:
        data = torch.frombuffer(bytearray(payload), dtype=torch.uint8)
        self.exchange([(torch.tensor([float(data.numel())], dtype=DTYPE), dst, tag)], [], timeout_s)
        self.exchange([(data, dst, tag + 1)], [], timeout_s)

    def recv_bytes(self, src: int, tag: int, timeout_s: float) -> bytes | None:
        (n,) = self.exchange([], [((1,), src, tag)], timeout_s)
        if n is None:
            return None
        (data,) = self.exchange([], [((int(n.item()),), src, tag + 1)], timeout_s, dtype=torch.uint8)
        return None if data is None else bytes(data.numpy().tobytes())


def _rank_of(k: int, per_process: int) -> int:
    return 1 + k // per_process


# ----------------------------------------------------------------------------- agent process
def run_agent_process(rank: int, world_size: int, timeout_s: float | None = None,
                      setup_timeout_s: float = DEFAULT_SETUP_TIMEOUT_S) -> int:
    """Body of an agent rank (> 0): receive the mission, train own GPs, run until STOP.

    The process group must already be initialised. Returns an exit code (0 = clean stop,
    3 = lost the world process, 4 = failed during set-up).
    """
    net = _Net(rank)
    raw = net.recv_bytes(0, _tag(_MISSION, rank), setup_timeout_s)
    if raw is None:
        log.error("rank %d: no mission from the world process (rank 0)", rank)
        return 3
    mission = json.loads(raw.decode())
    agents: list[int] = mission["agents"]
    if not agents:
        log.info("rank %d: no agents to host; exiting", rank)
        return 0
    cfg = from_mapping(mission["config"])
    K, per = int(mission["num_agents"]), int(mission["agents_per_process"])
    timeout_s = float(mission["timeout_s"] if timeout_s is None else timeout_s)
    T, D = cfg.horizon, cfg.dim
    controllers: dict[int, AgentController] = {}
    status = 1.0
    try:
        for k in agents:
            t0 = time.perf_counter()
            a = mission["missions"][str(k)]
            scen = Scenario(torch.tensor([a["start"]], dtype=DTYPE), torch.tensor([a["target"]], dtype=DTYPE),
                            reference_kind=mission["reference"], ref_points=mission["ref_points"])
            needs = Method.parse(cfg.method).needs_gp
            gp = agent_gp(cfg, k, mission.get("gp_model")) if needs else None
            fit_s = time.perf_counter() - t0
            ctrl = AgentController(k, K, cfg, scen, gp)
            ctrl.admm._layer(0)  # build the layers before the clock starts
            ctrl.counters["gp_fit_s"] = fit_s
            ctrl.counters["setup_s"] = time.perf_counter() - t0
            controllers[k] = ctrl
    except Exception:  # noqa: BLE001 - reported to the world, then the process exits
        log.exception("rank %d: set-up failed", rank)
        status = 0.0
    net.exchange([(torch.tensor([status], dtype=DTYPE), 0, _tag(_READY, rank))], [], setup_timeout_s)
    if status == 0.0:
        return 4
    sense_len = 3 + D + (K - 1)
    world_wait = setup_timeout_s
    local = set(agents)
    while True:
        # -- sensing (also the step barrier)
        msgs = net.exchange([], [((sense_len,), 0, _tag(_SENSE, 0, k)) for k in agents], world_wait)
        world_wait = max(4 * timeout_s, 60.0)
        if any(m is None for m in msgs):
            log.error("rank %d: lost the world process (rank 0); stopping", rank)
            return 3
        if float(msgs[0][0]) == _CMD_STOP:
            return 0
        t0_comm = time.perf_counter()
        t = int(msgs[0][1])
        new_edges: dict[int, list[int]] = {}
        for k, m in zip(agents, msgs):
            n = int(m[2])
            nbr_ids = [int(v) for v in m[3 + D:3 + D + n]]
            new_edges[k] = controllers[k].begin_step(t, m[3:3 + D].clone(), nbr_ids)
        # -- plan exchange on new edges (linearization points and initial z_e)
        sends, recvs, rmeta = [], [], []
        for k in agents:
            ctrl = controllers[k]
            for j in new_edges[k]:
                rj = _rank_of(j, per)
                if rj in net.dead:
                    ctrl.dead.add(j)
                    continue
                ctrl.counters["plan_bytes"] += FLOAT_BYTES * (T + 1) * D
                if j in local:
                    controllers[j].set_neighbour_plan(k, ctrl.own_plan().clone())
                else:
                    sends.append((ctrl.own_plan().clone(), rj, _tag(_PLAN, k, j)))
                    recvs.append(((T + 1, D), rj, _tag(_PLAN, j, k)))
                    rmeta.append((k, j))
        for (k, j), plan in zip(rmeta, net.exchange(sends, recvs, timeout_s)):
            if plan is None:
                controllers[k].dead.add(j)
            else:
                controllers[k].set_neighbour_plan(j, plan)
        for k in agents:
            controllers[k].finish_setup()
        comm_time = time.perf_counter() - t0_comm
        # -- ADMM iterations
        while True:
            own = {k: controllers[k].solve() for k in agents}
            t0_comm = time.perf_counter()
            sends, recvs, rmeta = [], [], []
            mailbox: dict[tuple[int, int], Tensor] = {}
            for k in agents:
                ctrl = controllers[k]
                for j, copy in own[k].items():
                    if j in ctrl.dead or _rank_of(j, per) in net.dead:
                        ctrl.dead.add(j)
                        continue
                    ctrl.counters["copy_bytes"] += FLOAT_BYTES * copy.numel()
                    if j in local:
                        mailbox[(k, j)] = copy
                    else:
                        sends.append((copy, _rank_of(j, per), _tag(_COPY, k, j)))
                        recvs.append(((2, T + 1, D), _rank_of(j, per), _tag(_COPY, j, k)))
                        rmeta.append((k, j))
            received: dict[int, dict[int, Tensor | None]] = {k: {} for k in agents}
            for (k, j), msg in zip(rmeta, net.exchange(sends, recvs, timeout_s)):
                received[k][j] = msg
                if msg is None:
                    controllers[k].dead.add(j)
            for (src, dst), msg in mailbox.items():
                received[dst][src] = msg
            resid = {}
            for k in agents:
                resid[k] = controllers[k].update(received[k])
            # -- global max residuals: reduce at rank 0, broadcast back
            sends = [(torch.tensor(resid[k], dtype=DTYPE), 0, _tag(_RESID, k)) for k in agents]
            for k in agents:
                controllers[k].counters["reduce_bytes"] += 2 * FLOAT_BYTES
            decisions = net.exchange(sends, [((3,), 0, _tag(_DECIDE, 0, k)) for k in agents],
                                     max(4 * timeout_s, 60.0))
            comm_time += time.perf_counter() - t0_comm
            if any(d is None for d in decisions):
                log.error("rank %d: lost the world process (rank 0); stopping", rank)
                return 3
            if float(decisions[0][2]) > 0.5:  # stop flag
                for k in agents:
                    controllers[k].result.converged = bool(decisions[0][2] > 1.5)
                break
        # -- actuation + telemetry
        sends = []
        for k in agents:
            ctrl = controllers[k]
            ctrl.counters["comm_time"] += comm_time / len(agents)
            ctrl.counters["telemetry_bytes"] += FLOAT_BYTES * telemetry_size(cfg)
            sends.append((ctrl.end_step(), 0, _tag(_TELEM, k)))
        net.exchange(sends, [], timeout_s)


# ----------------------------------------------------------------------------- report
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
        dists = pair_distances(rollout.states[:, alive]) if len(alive) > 1 else np.zeros((0, 0))
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


# ----------------------------------------------------------------------------- world
def _run_world(cfg: Config, scenario: Scenario, gp_model: str | None, world_size: int, per: int,
               timeout_s: float, setup_timeout_s: float, on_step, tb, report: DistributedReport) -> Rollout:
    from torch_gpmpc.sim.closed_loop import _clip_norm, _log_step, _Recorder

    K, T, D = scenario.num_agents, cfg.horizon, cfg.dim
    net = _Net(0)
    ranks = list(range(1, world_size))
    agents_of = {r: [k for k in range(K) if _rank_of(k, per) == r] for r in ranks}
    missions = {str(k): {"start": scenario.starts[k].tolist(), "target": scenario.targets[k].tolist()}
                for k in range(K)}
    t_setup = time.perf_counter()
    for r in ranks:
        own = {str(k): missions[str(k)] for k in agents_of[r]}  # each rank: only its own missions
        payload = {"config": cfg.to_dict(), "agents": agents_of[r], "missions": own, "num_agents": K,
                   "agents_per_process": per, "timeout_s": timeout_s, "gp_model": gp_model,
                   "reference": scenario.reference_kind, "ref_points": scenario.ref_points}
        net.send_bytes(json.dumps(payload).encode(), r, _tag(_MISSION, r), setup_timeout_s)
    busy = [r for r in ranks if agents_of[r]]
    ready = net.exchange([], [((1,), r, _tag(_READY, r)) for r in busy], setup_timeout_s)
    bad = [r for r, v in zip(busy, ready) if v is None or float(v[0]) != 1.0]
    if bad:
        raise GpmpcError(f"distributed run: agent process(es) of rank {bad} failed during set-up "
                         f"(GP training or solver build); see their logs"
                         + (f" in {report.log_dir}" if report.log_dir else ""))
    report.setup_s = time.perf_counter() - t_setup

    system = make_system(cfg.dim, cfg.noise_std, cfg.wind_scale)
    from torch_gpmpc.sim.closed_loop import noise_sequence

    noise = noise_sequence(cfg, K)
    recorder = _Recorder(cfg, K)
    lost: dict[int, int] = report.lost_agents
    last_plan = torch.zeros(K, T + 1, D, dtype=DTYPE)
    open_loop = [torch.zeros(0, D, dtype=DTYPE) for _ in range(K)]

    def alive(k: int) -> bool:
        return k not in lost

    def mark_lost(t: int) -> None:
        for k in range(K):
            if alive(k) and _rank_of(k, per) in net.dead:
                lost[k] = t
                report.lost_reasons[k] = net.dead[_rank_of(k, per)]
                log.warning("world: lost agent %d at step %d; it continues open loop on its last plan", k, t)

    start = time.perf_counter()
    x = scenario.starts.clone()
    states = [x]
    with torch.no_grad():
        for t in range(cfg.max_steps):
            if bool(((x - scenario.targets).norm(dim=1) < cfg.goal_tol).all()):
                break
            mark_lost(t)
            if not any(alive(k) for k in range(K)):
                log.error("world: every agent is lost; ending the run at step %d", t)
                break
            graph = communication_graph(x, cfg.comm_radius)
            adj = graph.adjacency()
            sends = []
            for k in range(K):
                if not alive(k):
                    continue
                ids = [j for j in range(K) if bool(adj[k, j])]
                msg = torch.full((3 + D + K - 1,), -1.0, dtype=DTYPE)
                msg[0], msg[1], msg[2] = _CMD_STEP, t, len(ids)
                msg[3:3 + D] = x[k]
                msg[3 + D:3 + D + len(ids)] = torch.tensor(ids, dtype=DTYPE)
                sends.append((msg, _rank_of(k, per), _tag(_SENSE, 0, k)))
            net.exchange(sends, [], timeout_s)
            res = StepResult(plans=last_plan, inputs=torch.zeros(K, T, D, dtype=DTYPE), state=None,
                             iterations=0, converged=False)
            for it in range(1, cfg.admm_max_iter + 1):
                mark_lost(t)
                live = [k for k in range(K) if alive(k)]
                got = net.exchange([], [((2,), _rank_of(k, per), _tag(_RESID, k)) for k in live],
                                   2 * timeout_s + 5.0)
                vals = [g for g in got if g is not None]
                mark_lost(t)
                primal = max((float(v[0]) for v in vals), default=0.0)
                dual = max((float(v[1]) for v in vals), default=0.0)
                res.primal_residuals.append(primal)
                res.dual_residuals.append(dual)
                res.iterations = it
                converged = primal < cfg.admm_tol and (cfg.admm_dual_tol is None or dual < cfg.admm_dual_tol)
                stop = 2.0 if converged else (1.0 if it == cfg.admm_max_iter else 0.0)
                res.converged = converged
                net.exchange([(torch.tensor([primal, dual, stop], dtype=DTYPE), _rank_of(k, per),
                               _tag(_DECIDE, 0, k)) for k in range(K) if alive(k)], [], timeout_s)
                if stop > 0:
                    break
            live = [k for k in range(K) if alive(k)]
            tel = net.exchange([], [((telemetry_size(cfg),), _rank_of(k, per), _tag(_TELEM, k)) for k in live],
                               2 * timeout_s + 5.0)
            mark_lost(t)
            u = torch.zeros(K, D, dtype=DTYPE)
            plans = last_plan.clone()
            margins, slacks = [], []
            for k, vec in zip(live, tel):
                if vec is None:
                    continue
                uk, X, U, c = _unpack_telemetry(vec, cfg)
                u[k], plans[k] = uk, X
                open_loop[k] = U[1:]
                report.per_agent[k] = c
                res.infeasible_solves += int(c["infeasible"])
                res.failed_solves += int(c["failed"])
                for kind in FAILURE_KINDS:
                    res.failed_by_kind[kind] = res.failed_by_kind.get(kind, 0) + int(c[f"failed_{kind}"])
                res.solve_time_s = max(res.solve_time_s, c["solve_time"])
                margins.append(c["max_margin"])
                slacks.append(c["slack_max"])
            for k in range(K):
                if not alive(k) or k not in live or tel[live.index(k)] is None:
                    # lost: its vehicle executes the rest of its last plan, then holds (u = 0)
                    if open_loop[k].shape[0]:
                        u[k], open_loop[k] = open_loop[k][0], open_loop[k][1:]
                    plans[k] = _shift(last_plan[k], dim=0)
            res.max_margin = max(margins, default=0.0)
            res.slack_max = max(slacks, default=0.0)
            res.plans = plans
            res.messages = 2 * (T + 1) * D * graph.degrees()
            u = _clip_norm(u, cfg.u_max)
            x = system.step(x, u, noise=noise[t])
            states.append(x)
            last_plan = plans
            info = recorder.record(t, res, adj, u, x)
            info["lost_agents"] = sorted(lost)
            if tb is not None:
                _log_step(tb, t, info, res)
            if on_step is not None:
                on_step(t, info)
        net.exchange([(torch.full((3 + D + K - 1,), _CMD_STOP, dtype=DTYPE), _rank_of(k, per),
                       _tag(_SENSE, 0, k)) for k in range(K) if alive(k)], [], timeout_s)
    wall = time.perf_counter() - start
    return recorder.rollout(torch.stack(states), scenario.targets, wall, cfg.method)


# ----------------------------------------------------------------------------- launching
def env_rank() -> int | None:
    """``RANK`` from the environment when launched by torchrun or by hand, else ``None``."""
    if "RANK" in os.environ and "WORLD_SIZE" in os.environ:
        return int(os.environ["RANK"])
    return None


def is_agent_rank() -> bool:
    """Whether this process was launched (torchrun / env variables) as an agent rank (> 0)."""
    rank = env_rank()
    return rank is not None and rank > 0


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _init(rank: int, world_size: int, timeout_s: float, init_method: str = "env://") -> None:
    import torch.distributed as dist

    if dist.is_initialized():
        raise GpmpcError("distributed run: a torch.distributed process group is already initialised "
                         "in this process")
    dist.init_process_group("gloo", init_method=init_method, rank=rank, world_size=world_size,
                            timeout=datetime.timedelta(seconds=timeout_s))


def _destroy() -> None:
    import torch.distributed as dist

    if dist.is_initialized():
        try:
            dist.destroy_process_group()
        except Exception as exc:  # noqa: BLE001 - tearing down after a fault
            log.debug("destroy_process_group: %s", exc)


def agent_main(threads: int = 1) -> int:
    """Entry of an agent rank launched with ``RANK``/``WORLD_SIZE``/``MASTER_*`` set."""
    torch.set_num_threads(threads)
    torch.set_default_dtype(DTYPE)
    rank, world_size = int(os.environ["RANK"]), int(os.environ["WORLD_SIZE"])
    setup = float(os.environ.get("GPMPC_SETUP_TIMEOUT", DEFAULT_SETUP_TIMEOUT_S))
    _init(rank, world_size, setup)
    try:
        return run_agent_process(rank, world_size, setup_timeout_s=setup)
    finally:
        _destroy()


def simulate_distributed(
    cfg: Config,
    scenario: Scenario | None = None,
    method: str | None = None,
    gp_model: str | None = None,
    on_step: Callable[[int, dict], None] | None = None,
    tb=None,
    agents_per_process: int = 1,
    timeout_s: float = DEFAULT_TIMEOUT_S,
    setup_timeout_s: float = DEFAULT_SETUP_TIMEOUT_S,
    log_dir: str | Path | None = None,
    on_launch: Callable[[dict[int, int]], None] | None = None,
) -> tuple[Rollout, DistributedReport]:
    """Run one closed-loop scenario with one process per agent (group); this process is the world.

    Without ``RANK``/``WORLD_SIZE`` in the environment the agent processes are started
    here (``python -m torch_gpmpc.coordination.distributed.world``, one per ``agents_per_process`` agents)
    on a free 127.0.0.1 port; with them (torchrun, multi-host) this must be rank 0 and
    the agent ranks are started by the launcher.

    Args:
        cfg: run configuration (seed, method, ADMM settings, ...).
        scenario: starts/targets/reference (default ``make_scenario(cfg)``).
        method: controller method (default ``cfg.method``).
        gp_model: a ``fit-gp`` model file every agent loads instead of training its own GP.
        on_step: called after every step with ``(t, info)`` (as :func:`~torch_gpmpc.sim.closed_loop.simulate`;
            info also has ``lost_agents``).
        tb: a :class:`~torch_gpmpc.report.tensorboard.TBLogger` (or ``None``).
        agents_per_process: agents hosted by one process (local launch).
        timeout_s: seconds a receive waits before the peer counts as lost.
        setup_timeout_s: seconds allowed for start-up (launch, GP training).
        log_dir: where agent processes write their logs (local launch; default: a temporary
            directory, kept only if something failed).
        on_launch: called with ``{agent rank: pid}`` once the agent processes are started.

    Returns:
        ``(rollout, report)``; states equal :func:`~torch_gpmpc.sim.closed_loop.simulate`'s for the same seed.

    Raises:
        GpmpcError: bad arguments, or an agent process failed during set-up.
    """
    method = method or cfg.method
    cfg = cfg.replace(method=method)
    scenario = scenario or make_scenario(cfg)
    K = scenario.num_agents
    if K > MAX_AGENTS:
        raise GpmpcError(f"distributed run: at most {MAX_AGENTS} agents, got {K}")
    if agents_per_process < 1:
        raise GpmpcError(f"agents_per_process must be >= 1, got {agents_per_process}")
    if not timeout_s > 0:
        raise GpmpcError(f"timeout must be > 0 seconds, got {timeout_s}")
    rank = env_rank()
    procs: dict[int, subprocess.Popen] = {}
    tmp_logs = None
    if rank is not None:  # torchrun / manual launch: agent ranks exist already
        if rank != 0:
            raise GpmpcError("simulate_distributed runs the world and must be rank 0")
        world_size = int(os.environ["WORLD_SIZE"])
        if world_size < 2:
            raise GpmpcError("distributed run needs WORLD_SIZE >= 2 (the world plus agent processes)")
        per = math.ceil(K / (world_size - 1))
        report = DistributedReport(processes=world_size - 1, agents_per_process=per)
        _init(0, world_size, setup_timeout_s)
    else:
        per = agents_per_process
        world_size = 1 + math.ceil(K / per)
        report = DistributedReport(processes=world_size - 1, agents_per_process=per)
        if log_dir is None:
            tmp_logs = tempfile.mkdtemp(prefix="gpmpc_agents_")
            log_dir = tmp_logs
        Path(log_dir).mkdir(parents=True, exist_ok=True)
        report.log_dir = str(log_dir)
        if cfg.solver == "fast":  # compile the kernel once here, not in every agent process
            from torch_gpmpc.control.solvers import ipm_kernel as ipm

            ipm.warm_up()
        port = _free_port()
        env = {**os.environ, "MASTER_ADDR": "127.0.0.1", "MASTER_PORT": str(port),
               "WORLD_SIZE": str(world_size), "GPMPC_SETUP_TIMEOUT": str(setup_timeout_s),
               "OMP_NUM_THREADS": "1"}
        if sys.platform.startswith("linux"):
            env.setdefault("GLOO_SOCKET_IFNAME", "lo")
        for r in range(1, world_size):
            with open(Path(log_dir) / f"rank{r}.log", "wb") as fh:
                procs[r] = subprocess.Popen([sys.executable, "-m", "torch_gpmpc.coordination.distributed.world"],
                                            env={**env, "RANK": str(r)}, stdout=fh, stderr=subprocess.STDOUT)
        if on_launch is not None:
            on_launch({r: p.pid for r, p in procs.items()})
        saved = os.environ.get("GLOO_SOCKET_IFNAME")
        if sys.platform.startswith("linux") and saved is None:
            os.environ["GLOO_SOCKET_IFNAME"] = "lo"
        try:
            t_launch = time.perf_counter()
            _init(0, world_size, setup_timeout_s, init_method=f"tcp://127.0.0.1:{port}")
            report.launch_s = time.perf_counter() - t_launch
        except Exception:
            _reap(procs, 1.0, report)
            raise
        finally:
            if saved is None:
                os.environ.pop("GLOO_SOCKET_IFNAME", None)
    ok = False
    t_end = None
    try:
        rollout = _run_world(cfg, scenario, gp_model, world_size, per, timeout_s, setup_timeout_s,
                             on_step, tb, report)
        ok = True
    finally:
        t_end = time.perf_counter()
        _destroy()
        if procs:
            _reap(procs, 2 * timeout_s + 10.0 if ok else 1.0, report)
        log.info("distributed run: launch %.1f s, set-up %.1f s, shut-down %.1f s", report.launch_s,
                 report.setup_s, time.perf_counter() - t_end)
        if tmp_logs is not None and ok and not report.lost_agents and \
                all(c == 0 for c in report.exit_codes.values()):
            shutil.rmtree(tmp_logs, ignore_errors=True)
            report.log_dir = None
    if report.lost_agents:
        log.warning("distributed run: %s", report.summary())
    return rollout, report


def _reap(procs: dict[int, subprocess.Popen], wait_s: float, report: DistributedReport) -> None:
    """Wait for the agent processes we started; terminate (then kill) any left, by pid."""
    deadline = time.monotonic() + wait_s
    for r, p in procs.items():
        try:
            report.exit_codes[r] = p.wait(timeout=max(deadline - time.monotonic(), 0.1))
        except subprocess.TimeoutExpired:
            log.warning("agent process rank %d (pid %d) did not exit; terminating it", r, p.pid)
            p.send_signal(signal.SIGTERM)
            try:
                report.exit_codes[r] = p.wait(timeout=5.0)
            except subprocess.TimeoutExpired:
                p.kill()
                report.exit_codes[r] = p.wait()


def main(argv: list[str] | None = None) -> int:
    """``python -m torch_gpmpc.coordination.distributed.world [gpmpc run options]``.

    As an agent rank (``RANK`` > 0 in the environment) it serves its agents and ignores
    the options; otherwise it is ``gpmpc run --backend distributed [options]``.
    """
    argv = list(sys.argv[1:] if argv is None else argv)
    if is_agent_rank():
        logging.basicConfig(level=logging.INFO if "-v" in argv or "--verbose" in argv else logging.WARNING,
                            format=f"%(levelname)s rank{os.environ['RANK']} %(name)s: %(message)s")
        return agent_main()
    from torch_gpmpc.cli.parser import main as cli_main

    return cli_main(["run", "--backend", "distributed", *argv])


if __name__ == "__main__":  # pragma: no cover - process entry
    from torch_gpmpc.coordination.distributed.world import main as _main

    sys.exit(_main())
