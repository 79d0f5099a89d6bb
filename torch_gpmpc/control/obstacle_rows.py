"""Agent-obstacle rows: each obstacle near a plan becomes a linearized half-space on the positions.

For a plan point ``pbar`` and a convex obstacle O with closest point ``q`` and outward unit
normal ``n`` there (for ``pbar`` inside O: the nearest face's), ``n^T y <= n^T q`` for every
``y`` in O, so the row::

    n^T p_tau >= n^T q + radius + margin

keeps the agent's centre ``radius`` away from the whole obstacle, whatever the plan does
(like eq. 15 for the pairs, but sound without a margin on the linearization). The chance
margin ``Phi^{-1}(1 - obstacle_eps) sqrt(n^T Sigma n)`` is added by the caller. Only the agent
knows its rows: no message carries them.

Shapes: P = position dimension, O = obstacles, L = rows kept per agent, T = horizon.
"""

from __future__ import annotations

import torch
from torch import Tensor

from torch_gpmpc.config.obstacles import ObstacleField

#: Bound of an inert padding row (normal 0): ``0 >= INERT_BOUND`` always holds.
INERT_BOUND = -1.0


def _radial(offset: Tensor, radius: Tensor) -> tuple[Tensor, Tensor]:
    """Signed distance and outward normal of a ball of ``radius`` at ``offset = p - centre``."""
    length = torch.linalg.vector_norm(offset, dim=-1)
    fallback = torch.zeros_like(offset)
    fallback[..., 0] = 1.0  # a point at the centre leaves along the first axis
    normal = torch.where(length[..., None] > 1e-12, offset / length.clamp(min=1e-12)[..., None], fallback)
    return length - radius, normal


def _sphere(points: Tensor, center: Tensor, radius: Tensor) -> tuple[Tensor, Tensor]:
    """(N, P) points vs (S, P) centres -> signed distance (N, S) and normal (N, S, P)."""
    return _radial(points[:, None] - center, radius)


def _box(points: Tensor, lower: Tensor, upper: Tensor) -> tuple[Tensor, Tensor]:
    """(N, P) points vs (Bx, P) boxes -> signed distance (N, Bx) and normal (N, Bx, P)."""
    p = points[:, None]
    offset = p - torch.maximum(torch.minimum(p, upper), lower)  # exact: 0 on the box, the excess outside
    out_dist, out_normal = _radial(offset, torch.zeros((), dtype=p.dtype))
    # inside: leave through the face of least penetration
    pen = torch.cat([p - lower, upper - p], dim=-1)  # (N, Bx, 2P)
    depth, face = pen.min(dim=-1)
    P = p.shape[-1]
    in_normal = torch.zeros_like(out_normal)
    in_normal.scatter_(-1, (face % P)[..., None], torch.where(face < P, -1.0, 1.0).to(p.dtype)[..., None])
    inside = (offset == 0).all(-1)
    return torch.where(inside, -depth, out_dist), torch.where(inside[..., None], in_normal, out_normal)


def _cylinder(points: Tensor, axis: Tensor, radius: Tensor, zmin: Tensor, zmax: Tensor) -> tuple[Tensor, Tensor]:
    """(N, 3) points vs (C,) vertical cylinders -> signed distance (N, C) and normal (N, C, 3)."""
    p = points[:, None]
    r_dist, r_normal = _radial(p[..., :2] - axis, radius)  # (N, C), (N, C, 2)
    z = p[..., 2].expand_as(r_dist)
    z_excess = z - torch.minimum(torch.maximum(z, zmin), zmax)  # exact: 0 within [zmin, zmax]
    offset = torch.cat([r_dist.clamp(min=0)[..., None] * r_normal, z_excess[..., None]], dim=-1)
    out_dist, out_normal = _radial(offset, torch.zeros((), dtype=p.dtype))
    # inside: radial exit or through the top / bottom
    pen = torch.stack([-r_dist, zmax - z, z - zmin], dim=-1)  # (N, C, 3)
    depth, face = pen.min(dim=-1)
    zero = torch.zeros_like(z)[..., None]
    exits = torch.stack([torch.cat([r_normal, zero], -1), torch.cat([0 * r_normal, 1 + zero], -1),
                         torch.cat([0 * r_normal, -1 + zero], -1)], dim=-2)  # (N, C, 3 exits, 3)
    in_normal = exits.gather(-2, face[..., None, None].expand(*face.shape, 1, 3)).squeeze(-2)
    inside = (r_dist <= 0) & (z_excess == 0)
    return torch.where(inside, -depth, out_dist), torch.where(inside[..., None], in_normal, out_normal)


def obstacle_geometry(field: ObstacleField, points: Tensor) -> tuple[Tensor, Tensor]:
    """Signed distance from each point to each obstacle's surface and the outward unit normal at
    the obstacle's closest point (the nearest face's for a point inside).

    Args:
        field: the obstacles (O of them), stated in P coordinates.
        points: positions, shape (..., P).

    Returns:
        ``(distance (..., O), normal (..., O, P))``; ``distance < 0`` inside an obstacle. The
        closest point is ``points - distance * normal``.
    """
    lead, P = points.shape[:-1], points.shape[-1]
    flat = points.reshape(-1, P)
    kw = {"dtype": points.dtype, "device": points.device}
    dist = flat.new_empty(flat.shape[0], len(field))
    normal = flat.new_empty(flat.shape[0], len(field), P)
    by_kind: dict[str, list[int]] = {}
    for i, o in enumerate(field.obstacles):
        by_kind.setdefault(o.kind, []).append(i)
    for kind, idx in by_kind.items():
        obs = [field.obstacles[i] for i in idx]

        def stack(attr):  # one attribute of this kind's obstacles as a tensor
            return torch.tensor([attr(o) for o in obs], **kw)

        if kind == "sphere":
            d, n = _sphere(flat, stack(lambda o: o.center), stack(lambda o: o.radius))
        elif kind == "box":
            d, n = _box(flat, stack(lambda o: o.lower), stack(lambda o: o.upper))
        else:
            d, n = _cylinder(flat, stack(lambda o: o.center), stack(lambda o: o.radius), stack(lambda o: o.lower[0]),
                             stack(lambda o: o.upper[0]))
        dist[:, idx], normal[:, idx] = d, n
    return dist.reshape(*lead, len(field)), normal.reshape(*lead, len(field), P)


def obstacle_rows(field: ObstacleField, plan_positions: Tensor, radius: float | Tensor, num_rows: int
                  ) -> tuple[Tensor, Tensor]:
    """The rows ``n^T p_tau >= b_tau`` of the ``num_rows`` obstacles nearest each plan (no margin).

    Args:
        field: the obstacles (O >= 0).
        plan_positions: the linearization points' positions at tau = 1..T, shape (B, T, P).
        radius: the agents' body radius (its centre keeps this far from every obstacle): a number,
            or one per agent as a (B, 1, 1) tensor.
        num_rows: L, rows per agent; obstacles beyond the L nearest (over the horizon) are left
            out, and missing ones are inert rows (normal 0, bound :data:`INERT_BOUND`).

    Returns:
        ``(normals (B, L, T, P), bounds (B, L, T))``, detached (the linearization points are fixed).
    """
    plan_positions = plan_positions.detach()
    B, T, P = plan_positions.shape
    normals = plan_positions.new_zeros(B, num_rows, T, P)
    bounds = plan_positions.new_full((B, num_rows, T), INERT_BOUND)
    if not len(field) or not num_rows:
        return normals, bounds
    dist, normal = obstacle_geometry(field, plan_positions)  # (B, T, O), (B, T, O, P)
    closest = plan_positions[:, :, None] - dist[..., None] * normal
    keep = min(num_rows, len(field))
    nearest = dist.amin(dim=1).topk(keep, dim=-1, largest=False).indices  # (B, keep)
    pick = nearest[:, None, :].expand(B, T, keep)
    n = normal.gather(2, pick[..., None].expand(B, T, keep, P))  # (B, T, keep, P)
    b = (n * closest.gather(2, pick[..., None].expand(B, T, keep, P))).sum(-1) + radius  # (B, T, keep)
    normals[:, :keep] = n.permute(0, 2, 1, 3)
    bounds[:, :keep] = b.permute(0, 2, 1)
    return normals, bounds
