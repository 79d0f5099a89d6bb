"""Static obstacles on the agents' positions: spheres (discs in 2D), vertical cylinders (3D) and
axis-aligned boxes, as given in a scenario file or the run configuration's ``obstacles`` key::

    obstacles = [
        {"center": [1.0, 0.0], "radius": 0.5},                       # a disc (2D) / sphere (3D)
        {"center": [0.0, 2.0], "radius": 0.3, "z": [0.0, 3.0]},      # a vertical cylinder (3D only)
        {"min": [-1.0, -3.0], "max": [1.0, -2.0]},                   # an axis-aligned box
    ]

Every shape is convex, so a supporting half-space at its closest point to a plan separates the
whole obstacle from that plan point (:mod:`torch_gpmpc.control.obstacle_rows` builds those rows).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from torch_gpmpc.errors import GpmpcError

#: The obstacle kinds, named by their keys.
OBSTACLE_KINDS = ("sphere", "cylinder", "box")


def _numbers(value: Any, what: str, where: str, length: int | None = None) -> tuple[float, ...]:
    """A non-empty list of finite numbers (of ``length`` entries, if given)."""
    if not isinstance(value, (list, tuple)) or not value or not all(
            isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in value):
        raise GpmpcError(f"{where}: obstacle {what} must be a non-empty list of finite numbers, got {value!r}")
    if length is not None and len(value) != length:
        raise GpmpcError(f"{where}: obstacle {what} must have {length} numbers, got {len(value)}")
    return tuple(float(v) for v in value)


@dataclass(frozen=True)
class Obstacle:
    """One convex obstacle.

    Attributes:
        kind: ``sphere`` (a disc in 2D), ``cylinder`` (vertical, 3D) or ``box``.
        center: sphere centre (P numbers) or cylinder axis (x, y); ``()`` for a box.
        radius: sphere or cylinder radius (0 for a box).
        lower, upper: the box corners (P numbers each), or the cylinder's ``(zmin,)`` and ``(zmax,)``.
    """

    kind: str
    center: tuple[float, ...] = ()
    radius: float = 0.0
    lower: tuple[float, ...] = ()
    upper: tuple[float, ...] = ()

    @classmethod
    def parse(cls, value: Any, where: str = "obstacle") -> "Obstacle":
        """Validate one obstacle table (the module docstring's three forms)."""
        if isinstance(value, Obstacle):
            return value
        if not isinstance(value, dict):
            raise GpmpcError(f"{where}: an obstacle is a table like {{\"center\": [...], \"radius\": r}} or "
                             f"{{\"min\": [...], \"max\": [...]}}, got {value!r}")
        keys = set(value)
        if keys == {"min", "max"}:
            lower = _numbers(value["min"], "min", where)
            upper = _numbers(value["max"], "max", where, len(lower))
            if any(lo >= hi for lo, hi in zip(lower, upper)):
                raise GpmpcError(f"{where}: obstacle box min must be < max in every coordinate, got {lower} and {upper}")
            return cls("box", lower=lower, upper=upper)
        if keys in ({"center", "radius"}, {"center", "radius", "z"}):
            center = _numbers(value["center"], "center", where)
            radius = value["radius"]
            if isinstance(radius, bool) or not isinstance(radius, (int, float)) or not radius > 0 \
                    or not math.isfinite(radius):
                raise GpmpcError(f"{where}: obstacle radius must be a finite number > 0, got {radius!r}")
            if "z" not in keys:
                return cls("sphere", center, float(radius))
            if len(center) != 2:
                raise GpmpcError(f"{where}: a cylinder's center is its axis [x, y] (2 numbers), got {list(center)}")
            zmin, zmax = _numbers(value["z"], "z", where, 2)
            if not zmin < zmax:
                raise GpmpcError(f"{where}: obstacle z must be [zmin, zmax] with zmin < zmax, got {[zmin, zmax]}")
            return cls("cylinder", center, float(radius), (zmin,), (zmax,))
        raise GpmpcError(f"{where}: obstacle keys {sorted(keys)} are none of the forms "
                         "{center, radius} (disc/sphere), {center, radius, z} (vertical cylinder), {min, max} (box)")

    def to_table(self) -> dict[str, Any]:
        """The table form (``parse(to_table())`` is equal)."""
        if self.kind == "box":
            return {"min": list(self.lower), "max": list(self.upper)}
        table: dict[str, Any] = {"center": list(self.center), "radius": self.radius}
        if self.kind == "cylinder":
            table["z"] = [self.lower[0], self.upper[0]]
        return table

    def position_dim(self) -> int | None:
        """The position dimension the obstacle is stated in (3 for a cylinder)."""
        return 3 if self.kind == "cylinder" else len(self.center or self.lower)


@dataclass(frozen=True)
class ObstacleField:
    """The static obstacles of a run (a tuple of :class:`Obstacle`).

    Examples:
        >>> field = ObstacleField.parse([{"center": [0, 0], "radius": 1}, {"min": [2, 2], "max": [3, 4]}])
        >>> [o.kind for o in field.obstacles]
        ['sphere', 'box']
    """

    obstacles: tuple[Obstacle, ...]

    @classmethod
    def parse(cls, value: Any, where: str = "obstacles") -> "ObstacleField":
        """Validate a list of obstacle tables (or pass an :class:`ObstacleField` through)."""
        if isinstance(value, ObstacleField):
            return value
        if not isinstance(value, (list, tuple)):
            raise GpmpcError(f"{where}: give the obstacles as a list of tables, got {value!r}")
        return cls(tuple(Obstacle.parse(v, f"{where}[{i}]") for i, v in enumerate(value)))

    def to_table(self) -> list[dict[str, Any]]:
        """The list form (``parse(to_table())`` is equal)."""
        return [o.to_table() for o in self.obstacles]

    def __len__(self) -> int:
        return len(self.obstacles)

    def check_dim(self, position_dim: int, where: str = "obstacles") -> None:
        """Refuse an obstacle not stated in the positions' dimension P."""
        for i, o in enumerate(self.obstacles):
            if o.position_dim() != position_dim:
                fix = "give a cylinder only with 3D positions" if o.kind == "cylinder" else \
                    f"give {position_dim} numbers per coordinate"
                raise GpmpcError(f"{where}[{i}]: a {o.kind} with {o.position_dim()} coordinates, but positions have "
                                 f"{position_dim}; {fix}")


#: ``forest`` trees: their radius, the default free gap kept between two trees beyond ``r_safe``
#: (config key ``forest_gap``; 1.5 m between trunks: an agent's body, 0.25, and an obstacle row's
#: margin of up to 0.5 on each side, 4.75 sigma at s = 0.1 with the default ``obstacle_eps``), the
#: fraction of the band their spacing discs fill, and the share of the input bound's speed the lanes'
#: line references ask (the rest is left for detours round the trees and for noise).
FOREST_TREE_RADIUS = 0.25
FOREST_GAP_EXTRA = 1.0
FOREST_FILL = 0.45
FOREST_PACE = 0.65


def forest_lane_spacing(min_separation: float, r_safe: float, gap: float = FOREST_GAP_EXTRA) -> float:
    """The distance between two ``forest`` lanes: ``max(min_separation, r_safe) + gap / 2``, so that
    neighbours start with room for their pair margins and can swerve round a tree without pressing
    on each other."""
    return max(min_separation, r_safe) + gap / 2


def forest_extent(num_agents: int, num_obstacles: int, circle_radius: float, min_separation: float,
                  r_safe: float, gap: float = FOREST_GAP_EXTRA) -> tuple[float, float]:
    """Half-length R (starts at x1 = -R, targets at +R) and half-height H of the ``forest`` band.

    The lanes are :func:`forest_lane_spacing` apart; the band ``|x1| <= R - 1``,
    ``|x2| <= H`` is long enough that the trees' spacing discs (diameter :func:`forest_spacing`)
    fill at most :data:`FOREST_FILL` of it, and never shorter than ``circle_radius``; ``gap`` is
    the free gap between two trees beyond ``r_safe`` (config ``forest_gap``).
    """
    lane_span = (num_agents - 1) * forest_lane_spacing(min_separation, r_safe, gap)
    half_height = max(lane_span / 2 + 1.0, circle_radius)
    spacing = forest_spacing(r_safe, gap)
    area = num_obstacles * math.pi * (spacing / 2) ** 2 / FOREST_FILL
    return max(circle_radius, area / (4 * half_height) + 1.0), half_height


def forest_spacing(r_safe: float, gap: float = FOREST_GAP_EXTRA) -> float:
    """The least distance between two ``forest`` tree centres: two trunks and a free gap of
    ``r_safe + gap`` between them."""
    return 2 * FOREST_TREE_RADIUS + r_safe + gap


def forest_ref_points(length: float, speed: float, dt: float, ref_points: int) -> int:
    """Points of a ``forest`` lane's line reference: ``ref_points``, or more where the line would
    otherwise ask more than :data:`FOREST_PACE` of ``speed`` (the input bound, m/s) over ``length``
    (m) at sample time ``dt`` (s)."""
    return max(ref_points, math.ceil(length / (FOREST_PACE * speed * dt)) + 1)


#: ``doorway``: the wall's thickness and its gap, in units of ``r_safe`` (the gap is narrower than
#: two agents side by side, ``2 r_safe``, and leaves one agent ``0.4 r_safe`` of room each side).
DOORWAY_WALL = 0.8
DOORWAY_GAP = 1.8


def doorway_extent(num_agents: int, circle_radius: float, min_separation: float, r_safe: float) -> tuple[float, float]:
    """Half-length X and half-height H of the ``doorway`` workspace ``|x1| <= X``, ``|x2| <= H``.

    Each room holds a column of ``ceil(K / 2)`` lanes ``max(min_separation, r_safe)`` apart, with a
    metre to spare above and below (H >= 2); X is ``circle_radius``.
    """
    lanes = (num_agents + 1) // 2
    half_height = max((lanes - 1) * max(min_separation, r_safe) / 2 + 1.0, 2.0)
    return circle_radius, half_height
