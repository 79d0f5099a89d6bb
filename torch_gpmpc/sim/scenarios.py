"""Scenarios: where the agents start, where they go, and the reference they track.

Shapes use K = agents, D = state dimension, T = horizon, R = ``ref_points``.

Generated scenarios (``Config.scenario``):

* ``paper``: K = 3 starts on a circle of radius ``circle_radius`` at angles
  2*pi*k/K in the x1-x2 plane (third coordinate 0 in 3D), targets the antipodes
  (the straight paths all cross the centre).
* ``circle``: the same construction for any K = ``num_agents``.
* ``random``: K starts and K targets uniform in ``[-circle_radius, circle_radius]^D`` (with a
  ``workspace``: inside it, ``r_safe / 2`` from its faces), drawn from a generator seeded with
  ``Config.seed``; starts are pairwise at least ``max(min_separation, r_safe)`` apart, and so
  are targets.
* ``forest``: K agents start on the line x1 = -R, spread ``max(min_separation, r_safe) +
  forest_gap / 2`` apart along x2 (centred), and cross to x1 = +R at the same x2, through
  ``num_obstacles`` discs of radius ``FOREST_TREE_RADIUS`` (vertical cylinders in 3D) placed
  uniformly, seeded with ``Config.seed``, in the band ``|x1| <= R - 1``; trees keep a free gap of
  at least ``r_safe + forest_gap`` (default 1.0) between each other, so an agent whose chance
  margins are at most ``forest_gap / 2`` fits through every gap. R and the band's height grow
  with the trees, the gap and the lanes (:func:`~torch_gpmpc.config.obstacles.forest_extent`; at
  least ``circle_radius``). The lines are paced to at most ``FOREST_PACE`` (0.65) of the input
  bound's speed (more points than ``ref_points`` where needed,
  :func:`~torch_gpmpc.config.obstacles.forest_ref_points`).
* ``doorway``: two rooms ``|x1| <= X`` (X = ``circle_radius``) split by a wall at x1 = 0 of
  thickness ``DOORWAY_WALL r_safe`` with one gap of width ``DOORWAY_GAP r_safe`` at x2 = 0,
  narrower than two agents side by side; the workspace is the two rooms. ``ceil(K/2)`` agents
  start in a column at x1 = -(X - 1), the others at x1 = X - 1, lanes
  ``max(min_separation, r_safe)`` apart, and each goes to its mirror image in the other room
  (the groups swap rooms). References are routed through the gap, where agents take turns
  (:mod:`~torch_gpmpc.sim.routes`, :mod:`~torch_gpmpc.sim.path_following`).

A scenario file (JSON or TOML) overrides ``Config.scenario``::

    starts = [[4.0, 0.0], [-2.0, 3.4641016]]     # K x D
    targets = [[-4.0, 0.0], [2.0, -3.4641016]]   # K x D
    reference = "line"                           # optional: "line" | "target"
    ref_points = 50                              # optional, >= 2
    name = "two agents"                          # optional label
    workspace = {"min": [-5, -5], "max": [5, 5]} # optional soft box on the positions (P numbers each)
    obstacles = [{"center": [0, 1], "radius": 0.5},  # optional: discs/spheres, vertical cylinders
                 {"min": [1, -2], "max": [2, -1]}]   # ({..., "z": [zmin, zmax]}) and boxes
    radii = [0.2, 0.3]                           # optional: body radius per agent (default r_safe / 2)
    models = ["double-integrator", "robot.toml"] # optional: model per agent (a mixed team; files
                                                 # relative to this file's folder)
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from torch_gpmpc.config.fields import nearest_key
from torch_gpmpc.config.obstacles import (
    DOORWAY_GAP, DOORWAY_WALL, FOREST_TREE_RADIUS, ObstacleField, doorway_extent, forest_extent, forest_lane_spacing,
    forest_ref_points, forest_spacing,
)
from torch_gpmpc.config.reader import read_table
from torch_gpmpc.config.schema import REFERENCES, Config
from torch_gpmpc.config.workspace import Workspace
from torch_gpmpc.coordination.bodies import pair_distances
from torch_gpmpc.errors import GpmpcError

logger = logging.getLogger(__name__)

#: Keys a scenario file may contain.
SCENARIO_KEYS = ("starts", "targets", "reference", "ref_points", "name", "workspace", "obstacles", "radii",
                 "models")
#: Largest allowed absolute coordinate in a scenario file.
MAX_COORDINATE = 1e4
#: Candidates drawn per batch, and batches tried per agent, by ``random`` scenarios.
_RANDOM_BATCH = 256
_RANDOM_BATCHES = 40


@dataclass(frozen=True, eq=False)
class Scenario:
    """Starts, targets and reference of one closed-loop run.

    Attributes:
        starts: initial positions, float64, shape (K, D).
        targets: final targets, float64, shape (K, D).
        reference_kind: ``line`` (straight line start -> target over ``ref_points``
            points, then hold the target) or ``target`` (constant target).
        ref_points: R, the number of points of the straight-line reference (>= 2).
        name: a label (``paper``, ``circle``, ``random`` or the file's stem).
        workspace: a soft box on the positions the controller keeps to, or ``None``.
        obstacles: static obstacles the agents keep their body radius from, or ``None``.
        radii: the agents' body radii (K,), or ``None`` (the config's ``radii``, else ``r_safe / 2``).
        models: the agents' models (K built-in names or model files: a mixed team), or ``None`` (the
            config's ``models``, else its ``model``).
    """

    starts: Tensor
    targets: Tensor
    reference_kind: str = "line"
    ref_points: int = 50
    name: str = "custom"
    workspace: Workspace | None = None
    obstacles: ObstacleField | None = None
    radii: tuple[float, ...] | None = None
    models: tuple[str, ...] | None = None

    def __post_init__(self) -> None:
        starts = torch.as_tensor(self.starts, dtype=torch.float64)
        targets = torch.as_tensor(self.targets, dtype=torch.float64)
        if starts.ndim != 2 or starts.shape != targets.shape or starts.shape[0] < 1:
            raise GpmpcError(
                f"Scenario: starts and targets must both have shape (K, D) with K >= 1, "
                f"got {tuple(starts.shape)} and {tuple(targets.shape)}"
            )
        for key, mat in (("starts", starts), ("targets", targets)):
            if not bool(torch.isfinite(mat).all()) or bool((mat.abs() > MAX_COORDINATE).any()):
                raise GpmpcError(f"Scenario: {key} must be finite coordinates within +-{MAX_COORDINATE:g}")
        if self.reference_kind not in REFERENCES:
            raise GpmpcError(f"Scenario: reference_kind {self.reference_kind!r} is not one of {REFERENCES}")
        if int(self.ref_points) < 2:
            raise GpmpcError(f"Scenario: ref_points must be >= 2, got {self.ref_points}")
        object.__setattr__(self, "starts", starts)
        object.__setattr__(self, "targets", targets)
        object.__setattr__(self, "ref_points", int(self.ref_points))

    @property
    def num_agents(self) -> int:
        """K."""
        return int(self.starts.shape[0])

    @property
    def dim(self) -> int:
        """D."""
        return int(self.starts.shape[1])

    def reference_window(self, t: int, horizon: int) -> Tensor:
        """Reference positions x_ref^{t}, ..., x_ref^{t+T} of every agent.

        For ``line``, point i is ``start + (target - start) * min(i, R-1) / (R-1)``, so
        the reference reaches the target at i = R-1 and holds it afterwards. For
        ``target`` every point is the target.

        Args:
            t: current time step, >= 0.
            horizon: T, >= 0.

        Returns:
            Tensor of shape (K, T+1, D), float64.
        """
        if t < 0 or horizon < 0:
            raise ValueError(f"reference_window: need t >= 0 and horizon >= 0, got t={t}, horizon={horizon}")
        steps = torch.arange(int(t), int(t) + int(horizon) + 1)
        return self._reference_at(steps)

    def reference_path(self) -> Tensor:
        """The whole reference x_ref^0, ..., x_ref^{R-1}.

        Returns:
            Tensor of shape (K, R, D), float64 (for ``target`` every point is the target).
        """
        return self._reference_at(torch.arange(self.ref_points))

    def _reference_at(self, steps: Tensor) -> Tensor:
        """Reference at integer time indices ``steps`` (N,) -> (K, N, D)."""
        if self.reference_kind == "target":
            return self.targets[:, None, :].expand(-1, steps.numel(), -1).clone()
        last = self.ref_points - 1
        frac = steps.clamp(max=last).to(torch.float64) / last  # (N,)
        delta = self.targets - self.starts  # (K, D)
        return self.starts[:, None, :] + frac[None, :, None] * delta[:, None, :]

    def to_dict(self) -> dict[str, Any]:
        """Plain dict in the scenario-file format (JSON-serializable)."""
        return {
            "name": self.name,
            "starts": self.starts.tolist(),
            "targets": self.targets.tolist(),
            "reference": self.reference_kind,
            "ref_points": self.ref_points,
            **({} if self.workspace is None else {"workspace": self.workspace.to_table()}),
            **({} if self.obstacles is None else {"obstacles": self.obstacles.to_table()}),
            **({} if self.radii is None else {"radii": list(self.radii)}),
            **({} if self.models is None else {"models": list(self.models)}),
        }


def make_scenario(cfg: Config, path: str | Path | None = None) -> Scenario:
    """Build the scenario of a run.

    Args:
        cfg: run configuration (``scenario``, ``num_agents``, ``dim``, ``circle_radius``,
            ``min_separation``, ``r_safe``, ``seed``, ``reference``, ``ref_points``).
        path: optional scenario file (JSON or TOML); when given it overrides
            ``cfg.scenario``, and its ``reference``/``ref_points`` override the config's.

    Returns:
        The :class:`Scenario`.

    Raises:
        GpmpcError: a bad scenario file, starts closer than ``r_safe``, or a random
            scenario that cannot be placed with the requested separation.
    """
    if path is not None:
        return load_scenario_file(path, cfg)
    if cfg.scenario == "paper":
        starts, targets = circle_positions(3, cfg.position_dim, cfg.circle_radius)
    elif cfg.scenario == "circle":
        starts, targets = circle_positions(cfg.num_agents, cfg.position_dim, cfg.circle_radius)
    elif cfg.scenario == "random":
        starts, targets = random_positions(cfg)
    elif cfg.scenario == "forest":
        return forest_scenario(cfg)
    elif cfg.scenario == "doorway":
        return doorway_scenario(cfg)
    else:  # pragma: no cover - Config already restricts the choices
        raise GpmpcError(f"config key 'scenario': unknown scenario {cfg.scenario!r}")
    _check_start_separation(starts, pair_distances(cfg.radii, cfg.r_safe, starts.shape[0]),
                            f"scenario {cfg.scenario!r}",
                            "raise circle_radius, lower num_agents or lower r_safe (or radii)")
    return Scenario(starts, targets, cfg.reference, cfg.ref_points, cfg.scenario)


def circle_positions(num_agents: int, dim: int, radius: float) -> tuple[Tensor, Tensor]:
    """Starts on a circle in the x1-x2 plane at angles 2*pi*k/K, targets the antipodes.

    Args:
        num_agents: K.
        dim: D (>= 2); coordinates beyond the second are 0.
        radius: circle radius.

    Returns:
        ``(starts, targets)``, each float64 of shape (K, D).
    """
    angles = 2.0 * math.pi * torch.arange(num_agents, dtype=torch.float64) / num_agents
    starts = torch.zeros(num_agents, dim, dtype=torch.float64)
    starts[:, 0] = radius * torch.cos(angles)
    starts[:, 1] = radius * torch.sin(angles)
    return starts, -starts


def forest_scenario(cfg: Config) -> Scenario:
    """The ``forest`` scenario (module docstring): lanes across a seeded field of trees.

    Raises:
        GpmpcError: the trees cannot be placed with their gaps in the band.
    """
    P, K = cfg.position_dim, cfg.num_agents
    R, half_height = forest_extent(K, cfg.num_obstacles, cfg.circle_radius, cfg.min_separation, cfg.r_safe,
                                   cfg.forest_gap)
    lanes = (torch.arange(K, dtype=torch.float64) - (K - 1) / 2) * forest_lane_spacing(
        cfg.min_separation, cfg.r_safe, cfg.forest_gap)
    starts = torch.zeros(K, P, dtype=torch.float64)
    starts[:, 0], starts[:, 1] = -R, lanes
    targets = starts.clone()
    targets[:, 0] = R
    centres = _place_trees(cfg, R - 1.0, half_height)
    trees = [{"center": c, "radius": FOREST_TREE_RADIUS} for c in centres.tolist()]
    if P == 3:  # vertical cylinders through the agents' height
        trees = [{**t, "z": [-half_height, half_height]} for t in trees]
    ref_points = forest_ref_points(2 * R, cfg.u_max, cfg.dt, cfg.ref_points)
    return Scenario(starts, targets, cfg.reference, ref_points, "forest", obstacles=ObstacleField.parse(trees))


def doorway_scenario(cfg: Config) -> Scenario:
    """The ``doorway`` scenario (module docstring): two groups swap rooms through one narrow gap."""
    P, K = cfg.position_dim, cfg.num_agents
    X, H = doorway_extent(K, cfg.circle_radius, cfg.min_separation, cfg.r_safe)
    sep = max(cfg.min_separation, cfg.r_safe)
    left = (K + 1) // 2
    starts = torch.zeros(K, P, dtype=torch.float64)
    for first, count, x1 in ((0, left, -(X - 1)), (left, K - left, X - 1)):
        starts[first:first + count, 0] = x1
        starts[first:first + count, 1] = (torch.arange(count, dtype=torch.float64) - (count - 1) / 2) * sep
    targets = starts.clone()
    targets[:, 0] = -starts[:, 0]
    half_wall, half_gap = DOORWAY_WALL * cfg.r_safe / 2, DOORWAY_GAP * cfg.r_safe / 2
    height = [] if P == 2 else [H]
    walls = [{"min": [-half_wall, half_gap] + [-h for h in height], "max": [half_wall, H] + height},
             {"min": [-half_wall, -H] + [-h for h in height], "max": [half_wall, -half_gap] + height}]
    workspace = Workspace((-X, -H) + tuple(-h for h in height), (X, H) + tuple(height))
    _check_start_separation(starts, pair_distances(cfg.radii, cfg.r_safe, K), "scenario 'doorway'",
                            "raise min_separation or lower the radii")
    return Scenario(starts, targets, cfg.reference, cfg.ref_points, "doorway", workspace=workspace,
                    obstacles=ObstacleField.parse(walls))


def _place_trees(cfg: Config, half_width: float, half_height: float) -> Tensor:
    """``num_obstacles`` seeded tree centres (x1, x2) in the band, pairwise at least
    ``forest_spacing(r_safe, forest_gap)`` apart -> (O, 2)."""
    gen = torch.Generator().manual_seed(cfg.seed)
    spacing = forest_spacing(cfg.r_safe, cfg.forest_gap)
    scale = torch.tensor([half_width, half_height], dtype=torch.float64)
    trees = _separated_points(
        cfg.num_obstacles, 2, spacing, lambda: (torch.rand(_RANDOM_BATCH, 2, generator=gen, dtype=torch.float64) * 2 - 1) * scale)
    if trees.shape[0] < cfg.num_obstacles:  # pragma: no cover - the band is sized to leave room (FOREST_FILL)
        raise GpmpcError(f"scenario 'forest': could not place tree {trees.shape[0]} of {cfg.num_obstacles} "
                         f"{spacing:g} from the others in the band {2 * half_width:g} x {2 * half_height:g}; "
                         "lower num_obstacles")
    return trees


def _separated_points(count: int, dim: int, sep: float, draw) -> Tensor:
    """Up to ``count`` points pairwise >= ``sep`` apart by rejection sampling: each point is the first
    acceptable candidate of ``draw()`` ((N, dim) float64 candidates), at most ``_RANDOM_BATCHES``
    draws per point; stops at the first point it cannot place -> (<= count, dim)."""
    points = torch.empty(0, dim, dtype=torch.float64)
    for _ in range(count):
        for _ in range(_RANDOM_BATCHES):
            cand = draw()
            ok = (torch.cdist(cand, points) >= sep).all(dim=1) if points.shape[0] else \
                torch.ones(cand.shape[0], dtype=torch.bool)
            if ok.any():
                points = torch.cat([points, cand[ok.nonzero()[0]]], dim=0)
                break
        else:
            break
    return points


def random_positions(cfg: Config) -> tuple[Tensor, Tensor]:
    """Seeded random starts and targets in ``[-circle_radius, circle_radius]^D``, or, with a
    ``workspace``, inside it (kept ``r_safe / 2`` from its faces: the classic random-transition
    test at the density ``num_agents`` / the workspace's volume).

    Starts are pairwise at least ``max(min_separation, r_safe)`` apart, and so are
    targets (rejection sampling, at most ``_RANDOM_BATCH * _RANDOM_BATCHES`` tries per agent).

    Returns:
        ``(starts, targets)``, each float64 of shape (K, D).

    Raises:
        GpmpcError: the separation cannot be met within the bounded number of tries.
    """
    gen = torch.Generator().manual_seed(cfg.seed)
    sep = max(cfg.min_separation, cfg.r_safe)
    starts = _sample_separated(cfg, sep, gen, "start")
    targets = _sample_separated(cfg, sep, gen, "target")
    return starts, targets


def _sampling_box(cfg: Config) -> tuple[Tensor, Tensor]:
    """Lower and upper corners (D,) of the region ``random`` scenarios draw from."""
    if cfg.workspace is None:
        upper = torch.full((cfg.position_dim,), cfg.circle_radius, dtype=torch.float64)
        return -upper, upper
    lower = torch.tensor(cfg.workspace.lower, dtype=torch.float64) + cfg.r_safe / 2
    upper = torch.tensor(cfg.workspace.upper, dtype=torch.float64) - cfg.r_safe / 2
    if bool((lower >= upper).any()):
        raise GpmpcError(f"scenario 'random': the workspace {cfg.workspace.to_table()} leaves no room for an agent "
                         f"of radius r_safe/2 = {cfg.r_safe / 2:g}; enlarge it")
    return lower, upper


def _sample_separated(cfg: Config, sep: float, gen: torch.Generator, what: str) -> Tensor:
    """K points uniform in the sampling box, pairwise >= ``sep`` apart -> (K, D)."""
    lower, upper = _sampling_box(cfg)

    def draw() -> Tensor:
        unit = torch.rand(_RANDOM_BATCH, cfg.position_dim, generator=gen, dtype=torch.float64)
        # without a workspace, the historical expression (bit for bit: earlier results stay reproducible)
        return (unit * 2 - 1) * upper if cfg.workspace is None else lower + unit * (upper - lower)

    points = _separated_points(cfg.num_agents, cfg.position_dim, sep, draw)
    if points.shape[0] < cfg.num_agents:
        raise GpmpcError(
            f"scenario 'random': could not place the {what} of agent {points.shape[0]} at least {sep:g} from the "
            f"other {what}s in the box {lower.tolist()} .. {upper.tolist()} within {_RANDOM_BATCH * _RANDOM_BATCHES} "
            f"tries; lower min_separation (or r_safe) or num_agents, or raise circle_radius (or the workspace)"
        )
    return points


# ---------------------------------------------------------------------------
# scenario files


def load_scenario_file(path: str | Path, cfg: Config) -> Scenario:
    """Read and validate a JSON or TOML scenario file (format: module docstring).

    Raises:
        GpmpcError: one clear message naming the file, the field and the fix.
    """
    path = Path(path)
    where = f"scenario file {str(path)!r}"
    data = read_table(path, "scenario file", suffixes=(".json", ".toml"),
                      expect="a table with keys 'starts' and 'targets'")
    for key in data:
        if key not in SCENARIO_KEYS:
            raise GpmpcError(f"{where}: unknown key {key!r}; did you mean {nearest_key(key, SCENARIO_KEYS)!r}? "
                             f"(valid keys: {', '.join(SCENARIO_KEYS)})")
    for key in ("starts", "targets"):
        if key not in data:
            raise GpmpcError(f"{where}: missing key {key!r}; give {key} as a K x D list of numbers")
    starts = _parse_matrix(data["starts"], "starts", where)
    targets = _parse_matrix(data["targets"], "targets", where)
    _check_shapes(starts, targets, cfg.position_dim, where)
    reference = _parse_reference(data.get("reference", cfg.reference), where)
    ref_points = _parse_ref_points(data.get("ref_points", cfg.ref_points), where)
    name = data.get("name", path.stem)
    if not isinstance(name, str):
        raise GpmpcError(f"{where}: 'name' must be a string, got {name!r}")
    radii = _parse_radii(data["radii"], starts.shape[0], where) if "radii" in data else None
    required = pair_distances(radii if radii is not None else cfg.radii, cfg.r_safe, starts.shape[0])
    _check_start_separation(starts, required, where, "move them apart or lower r_safe (or radii)")
    _warn_close_targets(targets, required, where)
    workspace = None
    if "workspace" in data:
        workspace = Workspace.parse(data["workspace"], where)
        workspace.check_dim(cfg.position_dim, where)
    obstacles = None
    if "obstacles" in data:
        obstacles = ObstacleField.parse(data["obstacles"], f"{where}: obstacles")
        obstacles.check_dim(cfg.position_dim, f"{where}: obstacles")
    models = _parse_models(data["models"], starts.shape[0], path.parent, where) if "models" in data else None
    if starts.shape[0] != cfg.num_agents:
        logger.info("%s has %d agents; it overrides num_agents=%d", where, starts.shape[0], cfg.num_agents)
    return Scenario(starts, targets, reference, ref_points, name, workspace, obstacles, radii, models)


def with_scenario_world(cfg: Config, scenario: Scenario) -> Config:
    """``cfg`` with the scenario's workspace, obstacles, radii and models, where it has them (they
    override the config's ``workspace``, ``obstacles``, ``radii`` and ``models``).

    Raises:
        GpmpcError: ``radii`` or ``models`` whose length is not the scenario's team size.
    """
    changes = {}
    if scenario.workspace is not None and scenario.workspace != cfg.workspace:
        changes["workspace"] = scenario.workspace.to_table()
    if scenario.obstacles is not None and scenario.obstacles != cfg.obstacles:
        changes["obstacles"] = scenario.obstacles.to_table()
    if scenario.radii is not None and scenario.radii != cfg.radii:
        changes["radii"] = list(scenario.radii)
    if scenario.models is not None and scenario.models != cfg.models:
        changes["models"] = list(scenario.models)
    out = cfg.replace(**changes) if changes else cfg
    out.controller_settings().check_team(scenario.num_agents, "config key")
    if out.models is not None and len(out.models) != scenario.num_agents:
        raise GpmpcError(f"config key 'models': {len(out.models)} models for {scenario.num_agents} agents; "
                         "give one model per agent")
    return out


def _parse_matrix(value: Any, key: str, where: str) -> Tensor:
    """A K x D list of finite numbers within +-MAX_COORDINATE -> float64 (K, D)."""
    if not isinstance(value, list) or not value:
        raise GpmpcError(f"{where}: {key!r} must be a non-empty K x D list of numbers, got {value!r}")
    rows = []
    for k, row in enumerate(value):
        if not isinstance(row, list):
            raise GpmpcError(f"{where}: {key}[{k}] must be a list of D numbers, got {row!r}")
        rows.append([_parse_number(x, f"{key}[{k}][{d}]", where) for d, x in enumerate(row)])
    lengths = {len(r) for r in rows}
    if len(lengths) != 1:
        lens = ", ".join(str(len(r)) for r in rows)
        raise GpmpcError(f"{where}: {key!r} is ragged (row lengths {lens}); give every row D numbers")
    return torch.tensor(rows, dtype=torch.float64)


def _parse_number(x: Any, name: str, where: str) -> float:
    """One finite coordinate with |x| <= MAX_COORDINATE."""
    if isinstance(x, bool) or not isinstance(x, (int, float)):
        raise GpmpcError(f"{where}: {name} is {x!r} ({type(x).__name__}); give a number")
    value = float(x)
    if not math.isfinite(value):
        raise GpmpcError(f"{where}: {name} is {value!r}, not finite; give a finite number")
    if abs(value) > MAX_COORDINATE:
        raise GpmpcError(f"{where}: {name} = {value:g} exceeds {MAX_COORDINATE:g} in absolute value; "
                         f"use coordinates within +-{MAX_COORDINATE:g}")
    return value


def _check_shapes(starts: Tensor, targets: Tensor, dim: int, where: str) -> None:
    """Same K for starts and targets, and D equal to the config's ``dim``."""
    if starts.shape[0] != targets.shape[0]:
        raise GpmpcError(f"{where}: 'starts' has {starts.shape[0]} agents but 'targets' has "
                         f"{targets.shape[0]}; give one target per start")
    for key, mat in (("starts", starts), ("targets", targets)):
        if mat.shape[1] != dim:
            raise GpmpcError(f"{where}: {key!r} rows have {mat.shape[1]} coordinates but the config has "
                             f"dim = {dim}; give {dim} coordinates per row or --set dim={mat.shape[1]}")


def _parse_reference(value: Any, where: str) -> str:
    if value not in REFERENCES:
        raise GpmpcError(f"{where}: 'reference' is {value!r}; use one of {', '.join(REFERENCES)}")
    return value


def _parse_ref_points(value: Any, where: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < 2:
        raise GpmpcError(f"{where}: 'ref_points' is {value!r}; give an integer >= 2")
    return value


def _name(required: Tensor) -> str:
    """How an error names a required distance: ``r_safe`` without radii (every pair's the same,
    the diagonal included), else the pair's sum of radii."""
    return "r_safe" if bool((required == required[0, 0]).all()) else "the sum of their radii"


def _parse_radii(value: Any, num_agents: int, where: str) -> tuple[float, ...]:
    """``radii``: K numbers in (0, 1000]."""
    if not isinstance(value, list) or len(value) != num_agents:
        raise GpmpcError(f"{where}: 'radii' must be a list of {num_agents} body radii (one per agent), got {value!r}")
    radii = tuple(_parse_number(r, f"radii[{k}]", where) for k, r in enumerate(value))
    for k, r in enumerate(radii):
        if not 0 < r <= 1e3:
            raise GpmpcError(f"{where}: radii[{k}] = {r:g}; give a body radius in (0, 1000]")
    return radii


def _parse_models(value: Any, num_agents: int, folder: Path, where: str) -> tuple[str, ...]:
    """``models``: K built-in names or model files (a relative file that exists next to the scenario
    file is taken from there)."""
    if not isinstance(value, list) or len(value) != num_agents or not all(isinstance(v, str) for v in value):
        raise GpmpcError(f"{where}: 'models' must be a list of {num_agents} model names or files (one per agent), "
                         f"got {value!r}")
    return tuple(str(folder / v) if not Path(v).is_absolute() and (folder / v).is_file() else v for v in value)


def _closest_pair(points: Tensor, required: Tensor) -> tuple[int, int, float, float]:
    """The pair (i, j) whose distance falls furthest short of its required distance, its distance
    and its requirement."""
    k = points.shape[0]
    i, j = torch.triu_indices(k, k, offset=1)
    dist = (points[i] - points[j]).norm(dim=1)  # (pairs,)
    p = int(torch.argmin(dist - required[i, j]))
    return int(i[p]), int(j[p]), float(dist[p]), float(required[i[p], j[p]])


def _check_start_separation(starts: Tensor, required: Tensor, where: str, fix: str) -> None:
    """Raise if two starts are closer than their required distance ``required`` (K, K) (names the
    pair that falls furthest short)."""
    if starts.shape[0] < 2:
        return
    i, j, d, need = _closest_pair(starts, required)
    if d < need:
        raise GpmpcError(f"{where}: starts of agents {i} and {j} are {d:.4g} apart, closer than {_name(required)} "
                         f"= {need:g}; {fix}")


def _warn_close_targets(targets: Tensor, required: Tensor, where: str) -> None:
    """Targets closer than their required distance cannot all be reached safely: warn (not an error)."""
    if targets.shape[0] < 2:
        return
    i, j, d, need = _closest_pair(targets, required)
    if d < need:
        logger.warning("%s: targets of agents %d and %d are %.4g apart, closer than %s = %g; "
                       "they cannot both be reached without a violation", where, i, j, d, _name(required), need)
