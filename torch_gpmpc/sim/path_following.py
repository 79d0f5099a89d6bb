"""Following routes: progress-indexed references, and turn-taking at passages.

An agent whose route bends round a wall or runs through a passage
(:mod:`~torch_gpmpc.sim.routes`) does not track a clock: its reference starts where it is along
its route (its *progress*, the arc length of its nearest route point ahead, never decreasing)
and runs ahead at the route's speed. A clock-driven reference would run ahead of an agent that
waits, and pull it straight at the wall.

**Turn-taking.** Two agents meeting head on in a passage narrower than two of them stop face to
face for good (neither row lets the other by). So each agent stops its reference ``wait`` before
its next passage until it may go, and goes when no agent using the same passage the other way
(a passage midpoint within ``2 r_safe``, directions opposed)

* is going (committed and not yet through), or
* is ready (at its own wait point) and has a lower index.

Agents going the same way follow each other through. The rule is decentralized: an agent decides
from what its neighbours in the communication graph state (their next passage's midpoint and
direction, and whether they are ready or going: a few numbers per agent); the closed loop computes
every agent's decision from one snapshot per step, as each agent would from its messages. Safety
still comes from the constraint rows; the rule only orders the agents. Deadlock-free for one
passage: among the ready agents the lowest index goes, a going agent is never waited on by an
agent going the same way, and every going agent leaves the passage on its route.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from torch_gpmpc.config.obstacles import ObstacleField
from torch_gpmpc.config.settings import agent_radii
from torch_gpmpc.config.workspace import Workspace
from torch_gpmpc.sim.routes import PASSAGE_MARGIN, arc_lengths, box_footprints, passages, route, walk

#: How far the projection of an agent onto its route may look ahead, in steps of its speed.
_LOOKAHEAD_STEPS = 20
#: Samples of that look-ahead.
_PROJECTION_SAMPLES = 101


class PathFollower:
    """Progress-indexed references along each agent's route, with turn-taking at passages.

    Args:
        routes: per agent, its route corners (C_k, P) (``C_k = 2`` for a straight line).
        stretches: per agent, its passages as arc intervals ``(a, b)``.
        speeds: per agent, the reference's advance per step (K,).
        r_safe: the pair distance (passages match within ``2 r_safe``).
        wait: how far before a passage an agent waits its turn (arc length).
    """

    def __init__(self, routes: list[np.ndarray], stretches: list[list[tuple[float, float]]], speeds: np.ndarray,
                 r_safe: float, wait: float) -> None:
        self.routes, self.stretches = routes, stretches
        self.lengths = np.array([arc_lengths(r)[-1] for r in routes])
        self.speeds = np.maximum(np.asarray(speeds, dtype=np.float64), 1e-3)
        self.r_safe, self.wait = r_safe, wait
        K = len(routes)
        self.followed = np.array([r.shape[0] > 2 or bool(s) for r, s in zip(routes, stretches)])
        self.progress = np.zeros(K)
        self.stage = np.zeros(K, dtype=int)  # index of each agent's next passage
        self.going = np.zeros(K, dtype=bool)

    @classmethod
    def plan(cls, field: ObstacleField | None, workspace: Workspace | None, starts: Tensor, targets: Tensor,
             r_safe: float, speed_steps: int, radii: tuple[float, ...] | None = None) -> "PathFollower | None":
        """Route every agent (clearance from boxes: its body radius plus ``PASSAGE_MARGIN``);
        ``None`` when no route bends or has a passage (then the scenario's own references are
        unchanged).

        Args:
            starts, targets: (K, P). speed_steps: the reference covers a route in this many steps.
            radii: the body radii (K,) (default ``r_safe / 2`` each).
        """
        lower, upper = box_footprints(field)
        if lower.shape[0] == 0:
            return None
        body = agent_radii(radii, r_safe, starts.shape[0])
        routes = [route(s, g, lower, upper, b + PASSAGE_MARGIN, workspace)
                  for s, g, b in zip(starts.numpy(), targets.numpy(), body)]
        stretches = [passages(r, lower, upper, r_safe, workspace) for r in routes]
        speeds = np.array([arc_lengths(r)[-1] for r in routes]) / max(speed_steps, 1)
        follower = cls(routes, stretches, speeds, r_safe, wait=2 * r_safe)
        return follower if follower.followed.any() else None

    def _next(self, k: int) -> tuple[float, float] | None:
        """Agent k's next passage (arc interval), or ``None``."""
        return self.stretches[k][self.stage[k]] if self.stage[k] < len(self.stretches[k]) else None

    @property
    def queued(self) -> np.ndarray:
        """Agents holding before a passage, not yet allowed through (K,) bool."""
        return np.array([self._next(k) is not None and not self.going[k] for k in range(len(self.routes))])

    def update(self, positions: Tensor, adjacency: Tensor) -> None:
        """Advance progress from the measured positions (K, P), then let agents take their turns
        (``adjacency`` (K, K) bool: who hears whom)."""
        pos = positions.detach().cpu().numpy()
        for k in np.flatnonzero(self.followed):
            arcs = self.progress[k] + np.linspace(0.0, _LOOKAHEAD_STEPS * self.speeds[k], _PROJECTION_SAMPLES)
            points = walk(self.routes[k], arcs)
            self.progress[k] = max(self.progress[k], float(arcs[np.argmin(np.linalg.norm(points - pos[k], axis=-1))]))
            while (stretch := self._next(k)) is not None and self.progress[k] > stretch[1]:
                self.stage[k] += 1
                self.going[k] = False
        self._take_turns(adjacency.detach().cpu().numpy().astype(bool))

    def _take_turns(self, hears: np.ndarray) -> None:
        """Let ready agents go when no opposing agent is going or ready with a lower index."""
        K = len(self.routes)
        ahead = [self._next(k) for k in range(K)]
        mids = np.full((K, 2), np.nan)
        dirs = np.zeros((K, 2))
        for k, stretch in enumerate(ahead):
            if stretch is not None:
                a, b = walk(self.routes[k], np.array(stretch))[:, :2]
                mids[k], dirs[k] = (a + b) / 2, b - a
        ready = np.array([s is not None and not self.going[k] and self.progress[k] >= s[0] - self.wait - self.r_safe / 2
                          for k, s in enumerate(ahead)])
        going_before = self.going.copy()
        for k in np.flatnonzero(ready):
            opposed = hears[k] & (np.linalg.norm(mids - mids[k], axis=-1) < 2 * self.r_safe) \
                & ((dirs @ dirs[k]) < 0)
            opposed[k] = False
            if not (opposed & going_before).any() and not (opposed & ready & (np.arange(K) < k)).any():
                self.going[k] = True

    def shape(self, window: Tensor) -> Tensor:
        """Reference windows (K, N, P) with the followed agents' rows replaced by their routes from
        their progress on, at their speed, held at their wait point while queued."""
        if not self.followed.any():
            return window
        out = window.clone()
        steps = np.arange(window.shape[1])
        for k in np.flatnonzero(self.followed):
            stretch = self._next(k)
            hold = self.lengths[k] if stretch is None or self.going[k] else max(stretch[0] - self.wait, 0.0)
            arcs = np.minimum(self.progress[k] + steps * self.speeds[k], max(hold, self.progress[k]))
            out[k] = torch.as_tensor(walk(self.routes[k], arcs), dtype=window.dtype, device=window.device)
        return out

    def rejoin_points(self, like: Tensor) -> Tensor:
        """Where a detour should lead back to (K, P): a followed agent's route point ``2 r_safe``
        ahead of its progress (its target would be through a wall), others' NaN."""
        out = torch.full_like(like, float("nan"))
        for k in np.flatnonzero(self.followed):
            point = walk(self.routes[k], np.array([self.progress[k] + 2 * self.r_safe]))[0]
            out[k] = torch.as_tensor(point, dtype=like.dtype)
        return out
