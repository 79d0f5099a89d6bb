"""Routes round walls: the shortest polyline from an agent's start to its target that keeps a
clearance from every box, and the narrow stretches (passages) along it.

A straight reference through a wall parks the agent in front of the wall: a box's linearized row
faces back along the line and nothing in the cost says which way round. So, like a grid-free
global planner, each agent routes its reference over a visibility graph in the x1-x2 plane:
the nodes are its start, its target and the corners of every box grown by ``clearance``; an edge
joins two nodes whose segment does not cross the inside of any grown box; the route is the
shortest path (``scipy.sparse.csgraph.dijkstra``). Boxes count by their x1-x2 footprint (in 3D a
box is treated as a wall through every height: conservative). Discs and cylinders do not enter
the graph: :mod:`~torch_gpmpc.sim.detours` bends references round them.

A *passage* is a stretch of a route where two agents cannot pass side by side: the nearest walls
on its left and right (boxes and the workspace's faces) leave less than ``2 r_safe +
2 PASSAGE_MARGIN`` of width.
:mod:`~torch_gpmpc.sim.path_following` makes agents take turns there.
"""

from __future__ import annotations

import numpy as np

from torch_gpmpc.config.obstacles import ObstacleField
from torch_gpmpc.config.workspace import Workspace

#: Extra width per side, beyond two bodies, below which a stretch of a route is a passage.
PASSAGE_MARGIN = 0.1
#: Arc-length spacing at which routes are sampled to find passages.
_SAMPLE = 0.02
#: How far outside its grown box a corner node sits (so edges along a face do not cross it).
_CORNER_OUTSET = 1e-7


def box_footprints(field: ObstacleField | None) -> tuple[np.ndarray, np.ndarray]:
    """The x1-x2 footprints of the field's boxes -> ``(lower, upper)``, each (B, 2)."""
    boxes = [] if field is None else [o for o in field.obstacles if o.kind == "box"]
    lower = np.array([b.lower[:2] for b in boxes], dtype=np.float64).reshape(-1, 2)
    upper = np.array([b.upper[:2] for b in boxes], dtype=np.float64).reshape(-1, 2)
    return lower, upper


def point_box_distance(points: np.ndarray, lower: np.ndarray, upper: np.ndarray) -> np.ndarray:
    """Euclidean distance of points (N, 2) to boxes (B, 2) each (0 inside) -> (N, B)."""
    gap = np.maximum(np.maximum(lower[None] - points[:, None], points[:, None] - upper[None]), 0.0)
    return np.linalg.norm(gap, axis=-1)


def segments_cross(p: np.ndarray, q: np.ndarray, lower: np.ndarray, upper: np.ndarray) -> np.ndarray:
    """Whether each segment p->q crosses the open inside of each box (slab test).

    Args:
        p, q: segment ends, (N, 2) each.
        lower, upper: boxes, (N, B, 2) each (one box set per segment) or (B, 2).

    Returns:
        Bool (N, B): True when a piece of positive length of the segment lies inside the box.
    """
    lower = np.broadcast_to(lower, (p.shape[0],) + lower.shape[-2:])
    upper = np.broadcast_to(upper, lower.shape)
    d = (q - p)[:, None, :]  # (N, 1, 2)
    p = p[:, None, :]
    t_in = np.zeros(lower.shape[:2])
    t_out = np.ones(lower.shape[:2])
    inside_flat = np.ones(lower.shape[:2], dtype=bool)
    with np.errstate(divide="ignore", invalid="ignore"):
        for a in range(2):
            flat = np.abs(d[..., a]) < 1e-12
            ta = (lower[..., a] - p[..., a]) / d[..., a]
            tb = (upper[..., a] - p[..., a]) / d[..., a]
            t_in = np.where(flat, t_in, np.maximum(t_in, np.minimum(ta, tb)))
            t_out = np.where(flat, t_out, np.minimum(t_out, np.maximum(ta, tb)))
            inside_flat &= ~flat | ((p[..., a] > lower[..., a] + 1e-12) & (p[..., a] < upper[..., a] - 1e-12))
    return inside_flat & (t_out - t_in > 1e-9)


def route(start: np.ndarray, target: np.ndarray, lower: np.ndarray, upper: np.ndarray, clearance: float,
          workspace: Workspace | None = None) -> np.ndarray:
    """The shortest polyline from ``start`` to ``target`` keeping ``clearance`` from every box.

    Args:
        start, target: (P,) positions (the route runs in x1-x2; further coordinates are
            interpolated along it by arc length).
        lower, upper: box footprints (B, 2) each (:func:`box_footprints`).
        clearance: how far the route keeps from the boxes (where its ends allow: an end closer
            than ``clearance`` to a box shrinks that box's growth for the edges leaving it).
        workspace: corners outside it are not used.

    Returns:
        The route's corners, (C, P) with C >= 2, from ``start`` to ``target``; the straight line
        ``[start, target]`` when it crosses no grown box, or when no route exists.
    """
    start, target = np.asarray(start, dtype=np.float64), np.asarray(target, dtype=np.float64)
    ends = np.stack([start[:2], target[:2]])
    if lower.shape[0] == 0 or not segments_cross(ends[:1], ends[1:], lower - clearance, upper + clearance).any():
        return np.stack([start, target])
    corners = _corner_nodes(lower, upper, clearance, workspace)
    nodes = np.concatenate([ends, corners])  # start = 0, target = 1
    grow = np.minimum(clearance, point_box_distance(nodes, lower, upper) * (1 - 1e-9))  # (N, B)
    i, j = np.triu_indices(nodes.shape[0], k=1)
    pair_grow = np.minimum(grow[i], grow[j])[..., None]  # (pairs, B, 1)
    blocked = segments_cross(nodes[i], nodes[j], lower[None] - pair_grow, upper[None] + pair_grow).any(axis=1)
    length = np.linalg.norm(nodes[i] - nodes[j], axis=-1)
    graph = np.zeros((nodes.shape[0], nodes.shape[0]))
    graph[i[~blocked], j[~blocked]] = np.maximum(length[~blocked], 1e-12)
    from scipy.sparse.csgraph import dijkstra  # here: importing scipy.sparse costs every run 0.1 s

    dist, pred = dijkstra(graph, directed=False, indices=0, return_predecessors=True)
    if not np.isfinite(dist[1]):
        return np.stack([start, target])
    order = [1]
    while order[-1] != 0:
        order.append(int(pred[order[-1]]))
    plane = nodes[order[::-1]]
    return _lift(plane, start, target)


def _corner_nodes(lower: np.ndarray, upper: np.ndarray, clearance: float, workspace: Workspace | None) -> np.ndarray:
    """Corners of the boxes grown by ``clearance`` (a hair further out), without those inside
    another grown box or outside the workspace -> (M, 2)."""
    out = clearance + _CORNER_OUTSET
    lo, hi = lower - out, upper + out
    corners = np.concatenate([np.stack([lo[:, 0], lo[:, 1]], -1), np.stack([hi[:, 0], lo[:, 1]], -1),
                              np.stack([hi[:, 0], hi[:, 1]], -1), np.stack([lo[:, 0], hi[:, 1]], -1)])
    keep = (point_box_distance(corners, lower, upper) >= clearance).all(axis=1)
    if workspace is not None:
        w_lo, w_hi = np.array(workspace.lower[:2]), np.array(workspace.upper[:2])
        keep &= ((corners >= w_lo) & (corners <= w_hi)).all(axis=1)
    return corners[keep]


def _lift(plane: np.ndarray, start: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Corners in x1-x2 (C, 2) -> (C, P), coordinates beyond x2 interpolated by arc length."""
    if start.shape[0] == 2:
        return plane
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(plane, axis=0), axis=-1))])
    frac = arc / max(arc[-1], 1e-12)
    rest = start[2:][None] + frac[:, None] * (target[2:] - start[2:])[None]
    return np.concatenate([plane, rest], axis=1)


def arc_lengths(corners: np.ndarray) -> np.ndarray:
    """Cumulative arc length at each corner of a polyline (C, P) -> (C,), starting at 0."""
    return np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(corners, axis=0), axis=-1))])


def walk(corners: np.ndarray, arc: np.ndarray) -> np.ndarray:
    """Points at arc lengths ``arc`` (N,) along the polyline ``corners`` (C, P), clamped to its
    ends -> (N, P)."""
    ends = arc_lengths(corners)
    arc = np.clip(arc, 0.0, ends[-1])
    seg = np.clip(np.searchsorted(ends, arc, side="right") - 1, 0, corners.shape[0] - 2)
    length = np.maximum(ends[seg + 1] - ends[seg], 1e-12)
    frac = ((arc - ends[seg]) / length)[:, None]
    return corners[seg] + frac * (corners[seg + 1] - corners[seg])


def passages(corners: np.ndarray, lower: np.ndarray, upper: np.ndarray, r_safe: float,
             workspace: Workspace | None = None) -> list[tuple[float, float]]:
    """The arc intervals ``(a, b)`` of a route where two agents cannot pass side by side.

    A route point is narrow when the nearest wall on its left plus the nearest wall on its right
    (seen along the route; boxes by footprint, and the workspace's faces in x1-x2) leave less than
    ``2 r_safe + 2 PASSAGE_MARGIN`` of width.

    Args:
        corners: the route (C, P). lower, upper: box footprints (B, 2). r_safe: the pair distance.
        workspace: its faces count as walls.

    Returns:
        Disjoint intervals in increasing order (empty when the route has no narrow stretch).
    """
    ends = arc_lengths(corners)
    total = ends[-1]
    if total <= 0 or lower.shape[0] == 0:
        return []
    arc = np.linspace(0.0, total, max(2, int(np.ceil(total / _SAMPLE)) + 1))
    points = walk(corners, arc)[:, :2]
    seg = np.clip(np.searchsorted(ends, arc, side="right") - 1, 0, corners.shape[0] - 2)
    heading = corners[seg + 1, :2] - corners[seg, :2]
    left = np.stack([-heading[:, 1], heading[:, 0]], -1)  # (N, 2), unnormalized: only its sign is used
    nearest = np.clip(points[:, None], lower[None], upper[None])  # (N, B, 2) closest box points
    if workspace is not None:
        w_lo, w_hi = np.array(workspace.lower[:2]), np.array(workspace.upper[:2])
        faces = []
        for a in range(2):
            for bound in (w_lo[a], w_hi[a]):
                face = points.copy()
                face[:, a] = bound
                faces.append(face)
        nearest = np.concatenate([nearest, np.stack(faces, axis=1)], axis=1)
    rel = nearest - points[:, None]
    dist = np.linalg.norm(rel, axis=-1)
    side = (rel * left[:, None]).sum(-1)
    width = np.where(side > 0, dist, np.inf).min(axis=1) + np.where(side < 0, dist, np.inf).min(axis=1)
    narrow = width < 2 * r_safe + 2 * PASSAGE_MARGIN
    out: list[tuple[float, float]] = []
    edges = np.flatnonzero(np.diff(np.concatenate([[0], narrow.astype(int), [0]])))
    for first, stop in zip(edges[::2], edges[1::2]):
        out.append((float(arc[first]), float(arc[stop - 1])))
    return out
