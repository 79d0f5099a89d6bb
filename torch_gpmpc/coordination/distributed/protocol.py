"""The distributed backend's wire protocol: message kinds, tags, sizes and the telemetry record.

Every message is a point-to-point float64 tensor of a size both ends know, so no
headers are sent. One step, between the world (rank 0) and the agents:

============================  ===============================  ===========================
message                       size (float64 numbers)           when
============================  ===============================  ===========================
world -> agent k: sensing     ``3 + D + (K-1)``: command,      every step
                              step, number of neighbours, own
                              state ``x_k``, neighbour ids
agent k -> neighbour j: copy  ``2 (T+1) D``: ``y_{kj,k}``      every ADMM iteration
                              (eq. 19), plus T projected
                              variances for the ``sum`` and
                              ``joint`` pair margins
agent k -> world: residuals   2: max ``||y_{e,k} - z_e||`` and every ADMM iteration
                              max ``rho ||z_e - z_e_prev||``
world -> agent k: decision    3: the global maxima and the     every ADMM iteration
                              stop flag
agent k -> neighbour j: plan  ``(T+1) D``: k's warm-start      once, when the edge appears
                              plan
agent k -> world: telemetry   :func:`telemetry_size`: input    every step
                              ``u_k``, plan, inputs, counters
============================  ===============================  ===========================

With ``admm_coupling = planes`` the copy is replaced by k's T plane offsets ``w_{kj,k}``, and
three messages are added per step and neighbour:

============================  ===============================  ===========================
message                       size (float64 numbers)           when
============================  ===============================  ===========================
agent k -> neighbour j:       T: k's projected variances of    every step, before the
variances                     the step (``sum``/``joint``)     first iteration
agent k -> neighbour j: rows  ``T + T D``: k's row bounds and  every step, after the
                              normals on the edge              variances
agent k -> neighbour j: final ``(T+1) D``: k's plan at the     every step, after the
plan                          step's last iteration            stop decision
============================  ===============================  ===========================

The global stopping test is a max over all edges of two floats per iteration, routed
through rank 0 (reduce, then broadcast) rather than a gloo collective so that a crashed
agent cannot block it.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass

import torch
from torch import Tensor

from torch_gpmpc.config.schema import Config
from torch_gpmpc.control.problem import FAILURE_KINDS

DTYPE = torch.float64
#: Bytes of one float64 number on the wire.
FLOAT_BYTES = 8
#: Default seconds a receive waits for a peer before the peer counts as lost.
DEFAULT_TIMEOUT_S = 30.0
#: Default seconds for start-up (process launch, GP training, solver build).
DEFAULT_SETUP_TIMEOUT_S = 300.0
#: Largest team the message tags can address.
MAX_AGENTS = 1024


class Kind(enum.IntEnum):
    """Message kinds; a message's tag is ``kind * 2**20 + src * MAX_AGENTS + dst``."""

    MISSION = 1
    READY = 2
    SENSE = 3
    RESID = 4
    DECIDE = 5
    TELEM = 6
    COPY = 7
    PLAN = 8
    VARIANCE = 9
    ROWS = 10
    FINAL_PLAN = 11
    APPLIED_PLAN = 12
    REPLAN_SEEDS = 13
    REPLAN = 14


#: Commands in the first entry of the sensing message.
CMD_STOP, CMD_STEP = 0.0, 1.0

#: Counters in the telemetry message, after u (D), plan X ((T+1) D) and inputs U (T D).
TELEMETRY_KEYS = ("slack_max", "state_slack_max", "infeasible", "failed", *[f"failed_{k}" for k in FAILURE_KINDS],
                  "solve_time", "max_margin", "iterations_total", "copy_bytes", "reduce_bytes",
                  "plan_bytes", "telemetry_bytes", "comm_time", "setup_s", "gp_fit_s", "fallback", "unsafe_plan")


def tag(kind: Kind, src: int = 0, dst: int = 0) -> int:
    """The message tag of ``kind`` from agent (or rank) ``src`` to ``dst``."""
    return int(kind) * (1 << 20) + src * MAX_AGENTS + dst


def rank_of(k: int, per_process: int) -> int:
    """The rank hosting agent ``k`` when every agent process hosts ``per_process`` agents."""
    return 1 + k // per_process


def sensing_size(num_agents: int, dim: int, horizon: int) -> int:
    """Numbers in one sensing message (world -> agent, once per step): command, step, neighbour
    count, own state (D), reference window ((T+1) D), neighbour ids (up to K-1)."""
    return 3 + dim + (horizon + 1) * dim + num_agents - 1


def residual_size(cfg: Config) -> int:
    """Numbers in one residual message (agent -> world, every ADMM iteration): primal, dual and
    their ratios (the same for every configuration)."""
    return 4


def decision_size(cfg: Config) -> int:
    """Numbers in one decision message (world -> agent, every ADMM iteration): primal, dual, stop,
    and whether the team settles who re-plans after this stop (the same for every configuration)."""
    return 4


def replan_seeds_size(num_agents: int) -> int:
    """Numbers in one agent's fallback message (agent -> world, after a stop on plans not known to
    be safe): whether it must re-plan, and per agent id whether its plan leaves its cell towards
    that neighbour (:func:`~torch_gpmpc.coordination.fallback.fallback_seeds`)."""
    return 1 + num_agents


def telemetry_size(cfg: Config) -> int:
    """Numbers in one telemetry message (agent -> world, once per step)."""
    T, D, Du = cfg.horizon, cfg.state_dim, cfg.input_dim
    return Du + (T + 1) * D + T * Du + len(TELEMETRY_KEYS)


@dataclass
class Telemetry:
    """What an agent reports to the world at the end of a step.

    Attributes:
        u: the input it applies, shape (Du,).
        plan: its planned states, shape (T+1, D).
        inputs: its planned inputs, shape (T, Du).
        counters: ``{key: value}`` for every key of :data:`TELEMETRY_KEYS`.
    """

    u: Tensor
    plan: Tensor
    inputs: Tensor
    counters: dict[str, float]

    def pack(self) -> Tensor:
        """The message, a float64 vector of :func:`telemetry_size` numbers."""
        values = torch.tensor([float(self.counters[key]) for key in TELEMETRY_KEYS], dtype=DTYPE)
        return torch.cat([self.u, self.plan.flatten(), self.inputs.flatten(), values])

    @classmethod
    def unpack(cls, vec: Tensor, cfg: Config) -> "Telemetry":
        """Read a message packed by :meth:`pack`."""
        T, D, Du = cfg.horizon, cfg.state_dim, cfg.input_dim
        u = vec[:Du]
        plan = vec[Du:Du + (T + 1) * D].reshape(T + 1, D)
        end = Du + (T + 1) * D + T * Du
        inputs = vec[Du + (T + 1) * D:end].reshape(T, Du)
        counters = dict(zip(TELEMETRY_KEYS, vec[end:].tolist()))
        return cls(u, plan, inputs, counters)
