"""Run configuration: one frozen dataclass with flat keys, strict loading.

Keys work the same in a TOML/YAML/JSON file and as ``--set NAME=VALUE``. Unknown
keys and wrong types raise :class:`~torch_gpmpc.errors.GpmpcError` naming the
nearest valid key; out-of-range values raise naming the allowed range
(:mod:`~torch_gpmpc.config.fields` checks every settings class the same way).
"""

from __future__ import annotations

import dataclasses
import warnings
import typing
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping

from torch_gpmpc.config.fields import Applies, Rules, build, check_keys, coerce_lists, validate, warn_ignored
from torch_gpmpc.config.model_spec import (
    BUILTIN_MODELS, CONTROL_KEYS, MODEL_SUFFIXES, ModelSpec, check_model_name, parse_model, resolve_model,
)
from torch_gpmpc.config.obstacles import FOREST_GAP_EXTRA, ObstacleField, doorway_extent, forest_extent
from torch_gpmpc.config.cost_table import CostTable
from torch_gpmpc.config.workspace import Workspace
from torch_gpmpc.config.plant import DEFAULT_GP_SAMPLES, PLANTS, VEHICLES, WINDS
from torch_gpmpc.config.team import TeamSpec, team_spec
from torch_gpmpc.config.settings import (
    CONTROLLER_CHOICES, CONTROLLER_CONDITIONS, CONTROLLER_RANGES, METHOD_NAMES, ControllerSettings, GPFitSettings, check_coupling,
    check_risk_mode, controller_keys, parse_world, resolve_uncertainty,
)
from torch_gpmpc.errors import GpmpcError

METHODS = METHOD_NAMES
REFERENCES = ("line", "target")
SCENARIOS = ("paper", "circle", "random", "forest", "doorway")


@dataclass(frozen=True)
class Config(ControllerSettings):
    """All tunable settings of a run: the controller's (:class:`ControllerSettings`) and the run's own.
    Defaults are the paper scenario. The controller's keys, from ``horizon`` to ``safety_fallback``, are
    :class:`ControllerSettings`'s, which this class extends; its own are these.

    Attributes:
        u_max: bound on the Euclidean norm of each input.
        noise_std: standard deviation s of the process noise w ~ N(0, s^2 I).
        goal_tol: an agent has arrived when within this distance of its target.
        max_steps: closed-loop step cap.
        scenario: ``paper``, ``circle``, ``random``, ``forest`` or ``doorway`` (obstacles and
            walls: :mod:`~torch_gpmpc.sim.scenarios`).
        num_agents: K (the paper scenario has 3).
        seed: seed for data, noise and scenario generation.
        dim: position dimension (2 or 3) of the built-in models; the single integrator's state
            and input have this dimension, the double integrator's state has twice it.
        model: the agent model: ``single-integrator`` (the paper), ``double-integrator`` (state
            ``[p, v]``, input acceleration), a model file path (TOML/JSON, see
            :mod:`~torch_gpmpc.config.model_spec`), a :class:`ModelSpec`, or a model table
            (a mapping with the model file's keys). ``dim``, ``dt`` and ``u_max`` shape the
            built-in models only: with a model file, table or ModelSpec they are ignored, and
            setting them warns.
        dt: sampling time of the double integrator (s).
        reference: ``line`` (straight line over ``ref_points`` steps, then hold) or ``target``.
        ref_points: number of points of the straight-line reference.
        circle_radius: radius of the start circle of ``paper``/``circle`` scenarios (and the
            half-width of ``random`` ones).
        gp_box: half-width of the box the GP training states are drawn from (the paper's data
            recipe); ``null``: :attr:`scenario_extent` (``circle_radius``, or the forest's
            half-length), so the data cover the scenario.
        min_separation: minimum start (and target) separation of ``random`` scenarios.
        gp_samples: training transitions per agent (null: the plant's, ``DEFAULT_GP_SAMPLES``: the
            paper's 100 on the model plant, 400 per RotorPy vehicle).
        gp_inputs: ``state`` (paper) or ``state_input``.
        gp_optimizer: ``lbfgs`` (paper) or ``adam``.
        gp_iters: optimizer iterations for GP fitting.
        wind_scale: amplitude of the vortex wind g (paper: 0.1).
        models: a mixed team: one model per agent (built-in names or model files, K of them), or
            null (every agent has ``model``); overrides ``model``. Models of different sizes are
            lifted to the largest (:mod:`~torch_gpmpc.config.team`); they must share ``dt``, the
            position indices and the number of residual rows. A scenario file's ``models`` set it.
        num_obstacles: the cylinders (discs in 2D) of ``scenario = forest``.
        forest_gap: the free gap ``scenario = forest`` keeps between two trees beyond ``r_safe``
            (room for an agent's chance margins on both sides; a wider gap also lengthens the band,
            whose trees keep the same share of it, and widens the lanes by half of it).
        deadlock_detour: an agent stuck behind a neighbour (no progress for 10 steps) detours
            round it on a fixed side (:class:`~torch_gpmpc.sim.detours.DeadlockBreaker`).
        plant: what the closed loop steps: ``model`` (the model's true system, the paper's world)
            or ``rotorpy`` (simulated multirotors tracking the plans,
            :mod:`~torch_gpmpc.dynamics.rotorpy_plant`; needs a 3D double-integrator model).
        plant_vehicle: RotorPy's ``crazyflie`` or ``hummingbird`` parameters.
        plant_wind: ``none``, ``constant``, ``sine`` or ``dryden``.
        plant_wind_speed: the wind's velocity [wx, wy, wz] in m/s (the amplitude of ``sine``, the
            mean of ``dryden``).
        plant_rate_hz: the rate of RotorPy's tracking controller and simulator.
        plant_sensor_noise: standard deviation of the measured position (m) and velocity (m/s).
        wind_change_step: the control step from which the plant's wind (RotorPy's, or the model
            plant's vortex) is turned 90 degrees about the vertical axis (null: never).
        gp_online: each agent adds its own observed transitions to its GP during the run
            (:mod:`~torch_gpmpc.gp.online`).
        gp_online_budget: the online points each agent keeps (the oldest leave first).
        gp_online_refit_every: re-fit the online GPs' hyperparameters every this many steps (0: never).
        gp_online_max_input_change: add only transitions whose input changed by at most this (norm,
            input units) since the agent's previous step (null: the model file's ``[control]`` value,
            else every transition; a value above any input change, say 1e9: every transition).
        disturbance_drift: offset-free tracking: each agent estimates a constant disturbance on
            its residual rows from its own one-step prediction errors, a Kalman filter of a random
            walk of this standard deviation per step (raw units; :mod:`~torch_gpmpc.gp.offset`).
            0: no estimate; null: the model file's ``[control]`` value, else 0.
        input_rate_weight: beta, the weight of the input changes (see :class:`ControllerSettings`);
            null: the model file's ``[control]`` value, else 0.

    Examples:
        >>> from torch_gpmpc import Config
        >>> cfg = Config(model="double-integrator", dim=3, scenario="circle", num_agents=6)
        >>> cfg.state_dim, cfg.input_dim, cfg.uncertainty_mode
        (6, 3, 'propagated')
        >>> cfg.controller_settings().horizon
        13

    The keys whose default depends on the run (a model file's ``[control]`` table,
    :data:`~torch_gpmpc.config.model_spec.CONTROL_KEYS`, and ``gp_samples`` by plant) are filled in
    when the configuration is built: after it they hold the values the run uses, which ``to_dict``
    writes; :meth:`stated_dict` writes them null, as stated, so a configuration rebuilt from it with
    another model or plant fills them from that one.
    """

    u_max: float = 2.0
    noise_std: float = 0.1
    goal_tol: float = 0.1
    max_steps: int = 150
    scenario: str = "paper"
    num_agents: int = 3
    seed: int = 0
    dim: int = 2
    model: str | ModelSpec = "single-integrator"
    dt: float = 0.1
    reference: str = "line"
    ref_points: int = 50
    circle_radius: float = 4.0
    gp_box: float | None = None
    min_separation: float = 1.0
    gp_samples: int | None = None
    gp_inputs: str = "state"
    gp_optimizer: str = "lbfgs"
    gp_iters: int = 50
    wind_scale: float = 0.1
    models: tuple[str, ...] | None = None
    num_obstacles: int = 20
    forest_gap: float = FOREST_GAP_EXTRA
    deadlock_detour: bool = True
    plant: str = "model"
    plant_vehicle: str = "crazyflie"
    plant_wind: str = "none"
    plant_wind_speed: tuple[float, ...] = (0.0, 0.0, 0.0)
    plant_rate_hz: float = 100.0
    plant_sensor_noise: float = 0.0
    wind_change_step: int | None = None
    gp_online: bool = False
    gp_online_budget: int = 200
    gp_online_refit_every: int = 0
    gp_online_max_input_change: float | None = None
    disturbance_drift: float | None = None
    input_rate_weight: float | None = None

    def __new__(cls, *args: Any, **kwargs: Any) -> "Config":
        """Refuse a misspelt keyword with the nearest valid key, as config files and ``--set`` do (the
        dataclass's ``__init__`` would raise a bare ``TypeError``)."""
        check_keys(kwargs, [f.name for f in dataclasses.fields(cls)], "config key")
        return super().__new__(cls)

    def __post_init__(self) -> None:
        if isinstance(self.model, dict):  # an inline model table (a config file's [model])
            object.__setattr__(self, "model", parse_model(self.model, "config key 'model'"))
        parse_world(self, "config key")
        coerce_lists(self)  # plant_wind_speed = [1, 0, 0], radii = [0.2, 0.3] from Python, TOML or --set
        run_defaults = _run_defaults(self)  # skips what validate refuses next, with the key named
        object.__setattr__(self, "_default_values", run_defaults)  # replace's warnings compare against them
        object.__setattr__(self, "_filled", _fill_defaults(self, run_defaults))
        validate(self, RULES)
        check_risk_mode(self.risk_mode, self.method, self.pair_margin, "config key")
        check_coupling(self.admm_coupling, self.relinearize, "config key")
        if isinstance(self.model, str):
            check_model_name(self.model)
        if self.models is not None:
            for name in self.models:
                check_model_name(name, "models")
            self.team()  # refuses models that cannot plan together
        if self.workspace is not None:
            self.workspace.check_dim(self.position_dim, "config key 'workspace'")
        if self.obstacles is not None:
            self.obstacles.check_dim(self.position_dim, "config key 'obstacles'")
        if self.scenario == "paper" and self.num_agents != 3:
            raise GpmpcError(
                f"config key 'num_agents': the paper scenario has 3 agents, got {self.num_agents}; "
                "use scenario=circle or scenario=random for other team sizes"
            )
        warn_ignored(self, CONFIG_CONDITIONS, "config key", run_defaults)

    def model_spec(self) -> ModelSpec:
        """The agent model of this run (built-in, read from the model file, or given); with
        ``models``, agent 0's model lifted to the team's sizes (every agent's state and input
        then have its sizes, position and number of residual rows)."""
        if self.models is not None:
            return self.team().agent_spec(0)
        if isinstance(self.model, ModelSpec):
            return self.model
        return resolve_model(self.model, self.dim, self.dt, self.u_max)

    def team(self) -> TeamSpec | None:
        """The team's models lifted to common sizes (:func:`~torch_gpmpc.config.team.team_spec`), or
        ``None`` without ``models``."""
        if self.models is None:
            return None
        return team_spec([resolve_model(name, self.dim, self.dt, self.u_max) for name in self.models])

    def controller_settings(self) -> ControllerSettings:
        """The controller's settings (the keys of :class:`ControllerSettings`); the keys were checked, and
        any ignored one warned about, when this configuration was built."""
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)
            return ControllerSettings(**{key: getattr(self, key) for key in controller_keys()})

    def gp_fit_settings(self) -> GPFitSettings:
        """How the agents' GPs are fitted (``gp_samples``, ``gp_iters``, ``gp_optimizer``, the
        data box ``gp_box`` (default :attr:`scenario_extent`), ``seed``)."""
        box = self.scenario_extent if self.gp_box is None else self.gp_box
        return GPFitSettings(self.gp_samples, self.gp_iters, self.gp_optimizer, box, self.seed)

    @property
    def scenario_extent(self) -> float:
        """Half-width of the region the built-in scenario spans: ``circle_radius``, the
        ``forest``'s half-length (:func:`~torch_gpmpc.config.obstacles.forest_extent`), the
        ``doorway``'s larger half-side, or for a ``random`` scenario in a workspace the largest
        coordinate of the workspace."""
        if self.scenario == "random" and self.workspace is not None:
            return max(abs(v) for v in self.workspace.lower + self.workspace.upper)
        if self.scenario == "doorway":
            return max(doorway_extent(self.num_agents, self.circle_radius, self.min_separation, self.r_safe))
        if self.scenario != "forest":
            return self.circle_radius
        return forest_extent(self.num_agents, self.num_obstacles, self.circle_radius, self.min_separation,
                             self.r_safe, self.forest_gap)[0]

    @property
    def offset_drift(self) -> float:
        """The ``disturbance_drift`` in effect: 0 for a method whose predictions do not use the GP
        mean (``nominal*``, ``nonlinear*``), which has no residual mean to correct."""
        return self.disturbance_drift if _predicts_with_gp(self) else 0.0

    @property
    def uncertainty_mode(self) -> str:
        """The covariance model in use: ``uncertainty`` with ``auto`` resolved (see above)."""
        return resolve_uncertainty(self.uncertainty, self.model_spec())

    @property
    def state_dim(self) -> int:
        """n, the model's state dimension (``dim`` for the single integrator)."""
        return self.model_spec().state_dim

    @property
    def input_dim(self) -> int:
        """m, the model's input dimension."""
        return self.model_spec().input_dim

    @property
    def position_dim(self) -> int:
        """P, the dimension of positions (scenarios, collision rows, arrival)."""
        return self.model_spec().position_dim

    def replace(self, **changes: Any) -> "Config":
        """Return a copy with ``changes`` applied (same checks as loading); of the keys a change leaves
        ignored, only the changed ones warn (the rest warned when this configuration was built)."""
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)
            out = from_mapping({**self.stated_dict(), **changes})
        warn_ignored(out, {k: v for k, v in CONFIG_CONDITIONS.items() if k in changes}, "config key",
                     out._default_values)
        return out

    def stated_dict(self) -> dict[str, Any]:
        """:meth:`to_dict` with the keys filled from the model file and the plant null, as stated: a
        configuration rebuilt from it (with another model, team or plant) fills them again."""
        filled = getattr(self, "_filled", frozenset())  # a Config unpickled from an older version has none
        return {k: (None if k in filled else v) for k, v in self.to_dict().items()}

    def to_dict(self) -> dict[str, Any]:
        """Plain dict of all keys (JSON-serializable; a :class:`ModelSpec` becomes its model table)."""
        out = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}
        if isinstance(self.model, ModelSpec):
            out["model"] = self.model.to_table()
        if self.workspace is not None:
            out["workspace"] = self.workspace.to_table()
        if self.obstacles is not None:
            out["obstacles"] = self.obstacles.to_table()
        if self.cost is not None:
            out["cost"] = self.cost.to_table()
        return out


def _run_defaults(cfg: Config) -> dict[str, Any]:
    """The defaults of the keys whose default depends on the run: those of :data:`CONTROL_KEYS` from
    the model file's ``[control]`` table, else the package's (a team's model files must agree);
    ``gp_samples`` from the plant (:data:`DEFAULT_GP_SAMPLES`)."""
    names = list(cfg.models) if isinstance(cfg.models, (list, tuple)) else [cfg.model]
    tables = [dict(_model_control(name)) for name in names]
    plant = cfg.plant if isinstance(cfg.plant, str) else "model"
    out: dict[str, Any] = {"gp_samples": DEFAULT_GP_SAMPLES.get(plant, DEFAULT_GP_SAMPLES["model"])}
    for key, default in CONTROL_KEYS.items():
        values = {table.get(key, default) for table in tables}
        if len(values) > 1 and getattr(cfg, key) is None:
            raise GpmpcError(f"config key {key!r}: the team's models give it different values "
                             f"({', '.join(map(repr, sorted(values, key=str)))}; a model without it counts as "
                             f"{default!r}); set {key} in the configuration")
        out[key] = values.pop() if len(values) == 1 else None  # disagreeing files, the key set: no default
    return out


def _fill_defaults(cfg: Config, defaults: dict[str, Any]) -> frozenset[str]:
    """Set every unset (null) key of ``defaults`` (:func:`_run_defaults`) to its default; the keys set."""
    filled = frozenset(key for key in defaults if getattr(cfg, key) is None)
    for key in filled:
        object.__setattr__(cfg, key, defaults[key])
    return filled


def _model_control(model: Any) -> tuple[tuple[str, float], ...]:
    """The ``[control]`` pairs of a model: a ModelSpec's, an existing model file's; none for a built-in
    (or a value the checks after filling refuse, naming the key)."""
    if isinstance(model, ModelSpec):
        return model.control
    if not isinstance(model, str) or Path(model).suffix.lower() not in MODEL_SUFFIXES or not Path(model).is_file():
        return ()
    return resolve_model(model, 2, 0.1, 1.0).control  # dim, dt and u_max shape built-ins only


def _builtin_model(cfg) -> bool:
    return cfg.models is not None or (isinstance(cfg.model, str) and cfg.model in BUILTIN_MODELS)


def _needs_gp(cfg) -> bool:
    return cfg.method not in ("nominal", "nonlinear")


def _predicts_with_gp(cfg) -> bool:
    return cfg.method in ("gp", "gp-chance")


_MODEL_RULE = Applies("model", _builtin_model, "the model defines its own state, sampling time and input bound")
_PLANT_RULE = Applies("plant", lambda c: c.plant == "rotorpy", "it configures the RotorPy plant")
_GP_DATA_RULE = Applies("method", _needs_gp, "this method learns no residual GP")
_ONLINE_RULE = Applies("gp_online", lambda c: c.gp_online, "it configures the online GP updates")

#: When each run key applies (with the controller's, :data:`CONTROLLER_CONDITIONS`); a key set while it
#: does not warns, naming the key that decides.
CONFIG_CONDITIONS: dict[str, tuple[Applies, ...]] = {
    **CONTROLLER_CONDITIONS,
    "model": (Applies("models", lambda c: c.models is None, "every agent has its own model"),),
    "dim": (_MODEL_RULE,),
    "u_max": (_MODEL_RULE,),
    "dt": (_MODEL_RULE, Applies("model", lambda c: c.models is not None or c.model != "single-integrator",
                                "the single integrator has the paper's B = 0.1 I")),
    **{key: (_PLANT_RULE,) for key in ("plant_vehicle", "plant_wind", "plant_wind_speed", "plant_rate_hz",
                                       "plant_sensor_noise")},
    "wind_scale": (Applies("plant", lambda c: c.plant == "model", "RotorPy's wind is plant_wind"),),
    **{key: (_GP_DATA_RULE,) for key in ("gp_samples", "gp_iters", "gp_optimizer", "gp_box")},
    "disturbance_drift": (Applies("method", _predicts_with_gp, "this method's predictions use no GP mean"),),
    **{key: (_ONLINE_RULE,) for key in ("gp_online_budget", "gp_online_refit_every", "gp_online_max_input_change")},
    **{key: (Applies("scenario", lambda c: c.scenario == "forest", "it shapes the forest"),)
       for key in ("num_obstacles", "forest_gap")},
    "min_separation": (Applies("scenario", lambda c: c.scenario == "random", "it spaces random draws"),),
    "ref_points": (Applies("reference", lambda c: c.reference == "line", "it paces the line reference"),),
}


_CHOICES = {
    **CONTROLLER_CHOICES,
    "scenario": SCENARIOS,
    "reference": REFERENCES,
    "gp_inputs": ("state", "state_input"),
    "gp_optimizer": ("lbfgs", "adam"),
    "plant": PLANTS,
    "plant_vehicle": VEHICLES,
    "plant_wind": WINDS,
}

# (predicate, description of the allowed range); checked in __post_init__.
_RANGES: dict[str, tuple[typing.Callable[[Any], bool], str]] = {
    **CONTROLLER_RANGES,
    "u_max": (lambda v: v > 0, "a number > 0"),
    "noise_std": (lambda v: v >= 0, "a number >= 0"),
    "goal_tol": (lambda v: v > 0, "a number > 0"),
    "max_steps": (lambda v: 1 <= v <= 1_000_000, "an integer in [1, 1000000]"),
    "num_agents": (lambda v: 1 <= v <= 1000, "an integer in [1, 1000]"),
    "num_obstacles": (lambda v: 0 <= v <= 10_000, "an integer in [0, 10000]"),
    "forest_gap": (lambda v: 0 <= v <= 100, "a number in [0, 100] (metres)"),
    "seed": (lambda v: v >= 0, "an integer >= 0"),
    "dim": (lambda v: v in (2, 3), "2 or 3"),
    "ref_points": (lambda v: v >= 2, "an integer >= 2"),
    # the same bound as scenario-file coordinates (scenarios.MAX_COORDINATE)
    "circle_radius": (lambda v: 0 < v <= 1e4, "a number in (0, 10000]"),
    "gp_box": (lambda v: v is None or 0 < v <= 1e4, "a number in (0, 10000] or null (circle_radius)"),
    "min_separation": (lambda v: v >= 0, "a number >= 0"),
    # an exact GP costs O(N^3) time and O(N^2) memory per agent
    "gp_iters": (lambda v: v >= 1, "an integer >= 1"),
    "wind_scale": (lambda v: v >= 0, "a number >= 0"),
    "dt": (lambda v: 0 < v <= 10, "a number in (0, 10]"),
    "plant_wind_speed": (lambda v: len(v) == 3 and all(abs(w) <= 50 for w in v), "3 numbers [wx, wy, wz] in m/s, each within 50"),
    "plant_rate_hz": (lambda v: 1 <= v <= 10_000, "a number in [1, 10000]"),
    "plant_sensor_noise": (lambda v: v >= 0, "a number >= 0"),
    "models": (lambda v: v is None or len(v) >= 1, "a list of model names or files, one per agent, or null"),
    "wind_change_step": (lambda v: v is None or v >= 0, "an integer >= 0 or null (never)"),
    "gp_online_budget": (lambda v: 2 <= v <= 5000, "an integer in [2, 5000]"),
    "gp_online_refit_every": (lambda v: v >= 0, "an integer >= 0 (0: never re-fit)"),
    "gp_online_max_input_change": (lambda v: v is None or v > 0, "a number > 0 or null (add every transition)"),
    "disturbance_drift": (lambda v: 0 <= v <= 10, "a number in [0, 10] (0: no offset estimate); null: the model file's"),
    "input_rate_weight": (lambda v: v >= 0, "a number >= 0 (0: no input-rate term); null: the model file's, else 0"),
    "gp_samples": (lambda v: 2 <= v <= 5000, "an integer in [2, 5000]; null: the plant's (100, 400 with rotorpy)"),
}


RULES = Rules("config key", "", _CHOICES, _RANGES)


def from_mapping(data: Mapping[str, Any]) -> Config:
    """Build a :class:`Config` from a flat mapping; unknown keys raise.

    Raises:
        GpmpcError: unknown key (with the nearest valid key), wrong type or range.
    """
    return build(Config, _retire_deprecated(data), RULES)


def _retire_deprecated(data: Mapping[str, Any]) -> dict[str, Any]:
    """Map retired keys onto their replacements (with a warning naming the new key)."""
    data = dict(data)
    if "gp_noise_in_margin" in data:
        old = data.pop("gp_noise_in_margin")
        if not isinstance(old, bool):
            raise GpmpcError(f"config key 'gp_noise_in_margin': expected bool, got {old!r}; "
                             "better, use margin_variance=predictive|latent")
        new = "predictive" if old else "latent"
        # FutureWarning, not DeprecationWarning: Python shows it by default, and the reader is the user
        warnings.warn(f"config key 'gp_noise_in_margin' is deprecated; it means margin_variance={new}",
                      FutureWarning, stacklevel=3)
        data.setdefault("margin_variance", new)
    # a file written before Anderson acceleration was removed (a tuned.json holds every key) still loads
    # where it left it off; asking for it is refused (fields.REMOVED_KEYS)
    if data.get("admm_acceleration", "off") == "off" and "admm_acceleration" in data:
        data.pop("admm_acceleration")
        data.pop("admm_anderson_memory", None)
        warnings.warn("config key 'admm_acceleration' is retired (Anderson acceleration was removed); "
                      "delete it and admm_anderson_memory", FutureWarning, stacklevel=3)
    return data
