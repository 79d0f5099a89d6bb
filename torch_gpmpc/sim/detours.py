"""Detour references: bend each agent's straight-line reference around the round obstacles on it.

A local MPC that tracks a straight line through an obstacle parks in front of it: the obstacle's
linearized row faces back along the line, and nothing in the cost says which way round to go.
So each reference point within ``clearance`` of a disc (a sphere or vertical cylinder, in the
x1-x2 plane) moves sideways, perpendicular to the agent's line, onto the circle of radius
``clearance`` round it, on a fixed side: away from the obstacle's centre as seen from the line,
or to the left of the direction of travel when the centre is on the line (a consistent side
rule: two agents meeting head on at an obstacle both keep to their own left).

The side depends only on the scenario (the line and the obstacle), never on the noisy state, so
it cannot flip from step to step. Each agent shapes only its own reference from the obstacles
it knows: decentralized, and safety still comes from the constraint rows, not from the
reference. Boxes are left alone: a reference through a wall needs a route
(:mod:`~torch_gpmpc.sim.routes`), not a bend.
"""

from __future__ import annotations

import torch
from torch import Tensor

from torch_gpmpc.config.obstacles import ObstacleField


def detour_clearance(r_safe: float, radii: Tensor, margin: float) -> Tensor:
    """How far beyond an obstacle's radius each agent's bent reference stays: its body radius plus
    ``margin`` (one obstacle row's chance margin), and at least ``r_safe``. A reference inside the
    rows' margins has the agent ride them, where every large push of noise is a hit.

    Args:
        r_safe: the run's. radii: (K,) body radii. margin: metres (0 without chance margins).

    Returns:
        (K,) clearances.
    """
    return torch.clamp(radii + margin, min=r_safe)


def detour_reference(field: ObstacleField, window: Tensor, starts: Tensor, targets: Tensor,
                     clearance_extra: float | Tensor) -> Tensor:
    """The reference window with its points bent round the discs they pass through.

    Args:
        field: the obstacles (only ``sphere`` and ``cylinder`` ones bend the reference).
        window: reference positions, shape (K, N, P), P >= 2.
        starts, targets: the agents' lines, shapes (K, P) each (their x1-x2 direction sets the side).
        clearance_extra: how far beyond an obstacle's radius the bent points stay: a number, or one
            per agent, (K,) (:func:`detour_clearance`); never farther than the agent's target (a
            target near an obstacle stays where it is).

    Returns:
        The bent window, shape (K, N, P) (a new tensor; coordinates beyond x1-x2 unchanged).
    """
    out = window.clone()
    direction = (targets - starts)[:, :2]
    length = torch.linalg.vector_norm(direction, dim=-1, keepdim=True)
    moving = length[:, 0] > 1e-9
    if not bool(moving.any()):
        return out
    d = torch.where(moving[:, None], direction / length.clamp(min=1e-12), torch.zeros_like(direction))  # (K, 2)
    left = torch.stack([-d[:, 1], d[:, 0]], dim=-1)  # (K, 2): d turned by +90 degrees
    extra = torch.as_tensor(clearance_extra, dtype=window.dtype, device=window.device).expand(window.shape[0])
    for o in field.obstacles:
        if o.kind not in ("sphere", "cylinder"):
            continue
        centre = torch.tensor(o.center[:2], dtype=window.dtype, device=window.device)
        # never bend a line round an obstacle nearer its target than the clearance: the end would move
        target_gap = torch.linalg.vector_norm(targets[:, :2] - centre, dim=-1)  # (K,)
        clearance = torch.clamp(target_gap, max=o.radius + extra)[:, None]  # (K, 1)
        centre_side = ((centre - starts[:, :2]) * left).sum(-1)  # (K,): > 0 when the centre is left of the line
        side = torch.where(centre_side > 1e-9, -1.0, 1.0).to(window.dtype)  # pass away from it, else left
        rel = out[..., :2] - centre  # (K, N, 2)
        along = (rel * d[:, None]).sum(-1)  # (K, N)
        inside = moving[:, None] & (torch.linalg.vector_norm(rel, dim=-1) < clearance)
        # inside the circle |lateral| < sqrt(clearance^2 - along^2): move onto it, on the chosen side
        lateral = side[:, None] * torch.sqrt((clearance ** 2 - along ** 2).clamp(min=0))
        bent = centre + along[..., None] * d[:, None] + lateral[..., None] * left[:, None]
        out[..., :2] = torch.where(inside[..., None], bent, out[..., :2])
    return out


class DeadlockBreaker:
    """Detects agents stuck behind a neighbour and sends them round it on a fixed side.

    Agent k is *stuck* at step t when it is farther than ``r_safe + goal_tol`` from its target,
    its distance to the target has not shrunk by ``goal_tol`` over the last ``window`` steps, and
    another agent is within ``r_safe + reach`` of it, ahead (towards its target). It then detours:
    its reference runs from where it is to a waypoint beside the blocking agent and on to its
    target, ``r_safe`` to the side of the pair's midpoint, on its left (seen along its way to
    the target) unless the blocker is on its left already. In an exactly symmetric head-on
    encounter both agents keep to their own left and pass. The detour ends at the waypoint or
    after ``hold`` steps.

    Each agent decides from its own progress and the position of the neighbour it already
    exchanges plans with: decentralized; safety still comes from the collision rows.

    Args:
        starts, targets: (K, P) the agents' lines. r_safe, goal_tol: the run's.
        speed: the detour reference's advance per step (the scenario line's).
    """

    def __init__(self, starts: Tensor, targets: Tensor, r_safe: float, goal_tol: float, speed: float,
                 window: int = 10, reach: float = 1.0, hold: int = 30) -> None:
        self.targets, self.r_safe, self.goal_tol, self.speed = targets, r_safe, goal_tol, max(speed, 1e-3)
        self.window, self.reach, self.hold = window, reach, hold
        self.history: list[Tensor] = []  # distances to target (K,) per step
        self.waypoint = torch.full_like(targets, float("nan"))
        self.until = torch.full((targets.shape[0],), -1, dtype=torch.long)

    def update(self, t: int, positions: Tensor, exempt: Tensor | None = None) -> None:
        """Record step t's positions (K, P); start detours for newly stuck agents, end finished ones.
        ``exempt`` (K,) bool: agents waiting on purpose (their turn at a passage) are not stuck."""
        dist = torch.linalg.vector_norm(positions - self.targets, dim=-1)
        self.history.append(dist)
        active = self.until >= t
        reached = torch.linalg.vector_norm(positions - self.waypoint, dim=-1) < self.r_safe / 2
        self.until = torch.where(active & reached, torch.full_like(self.until, -1), self.until)
        if len(self.history) <= self.window:
            return
        stalled = (dist > self.r_safe + self.goal_tol) & (self.history[-1 - self.window] - dist < self.goal_tol)
        if exempt is not None:
            stalled &= ~exempt
        for k in torch.nonzero(stalled & (self.until < t)).flatten().tolist():
            self._start_detour(k, t, positions)

    def _start_detour(self, k: int, t: int, positions: Tensor) -> None:
        """Aim agent k at a waypoint beside its nearest blocker ahead, if it has one."""
        way = self.targets[k] - positions[k]
        d = way / torch.linalg.vector_norm(way)
        rel = positions - positions[k]
        gap = torch.linalg.vector_norm(rel, dim=-1)
        ahead = ((rel * d).sum(-1) > 0) & (gap < self.r_safe + self.reach)
        ahead[k] = False
        if not bool(ahead.any()):
            return
        j = int(torch.where(ahead, gap, torch.full_like(gap, float("inf"))).argmin())
        left = torch.zeros_like(d)
        left[0], left[1] = -d[1], d[0]  # d turned by +90 degrees in the x1-x2 plane
        side = -1.0 if float((rel[j] * left).sum()) > 1e-9 else 1.0
        self.waypoint[k] = positions[k] + rel[j] / 2 + side * self.r_safe * left
        self.until[k] = t + self.hold

    def shape(self, t: int, window: Tensor, positions: Tensor, rejoin: Tensor | None = None) -> Tensor:
        """Reference windows (K, N, P) with the detouring agents' replaced by the polyline
        position -> waypoint -> target walked at ``speed`` per step (``rejoin`` (K, P): where to
        head after the waypoint instead of the target, where not NaN: a point on a routed agent's
        route, whose target may lie beyond a wall)."""
        active = torch.nonzero(self.until >= t).flatten().tolist()
        if not active:
            return window
        out = window.clone()
        steps = torch.arange(window.shape[1], dtype=window.dtype) * self.speed  # arc length per point
        for k in active:
            end = self.targets[k] if rejoin is None or bool(torch.isnan(rejoin[k]).any()) else rejoin[k]
            out[k] = _walk(torch.stack([positions[k], self.waypoint[k], end]), steps)
        return out


def _walk(corners: Tensor, arc: Tensor) -> Tensor:
    """Points at arc lengths ``arc`` (N,) along the polyline ``corners`` (C, P), held at its end -> (N, P)."""
    seg = torch.diff(corners, dim=0)
    length = torch.linalg.vector_norm(seg, dim=-1)
    ends = torch.cumsum(length, 0)
    out = corners[-1].expand(arc.shape[0], -1).clone()
    start = torch.zeros((), dtype=corners.dtype)
    for i in range(seg.shape[0]):
        on = (arc >= start) & (arc < ends[i])
        frac = ((arc - start) / length[i].clamp(min=1e-12)).clamp(0, 1)
        out[on] = corners[i] + frac[on, None] * seg[i]
        start = ends[i]
    return out
