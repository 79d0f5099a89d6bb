"""Simulated multirotors as a plant: RotorPy vehicles tracking the MPC's plans.

This is how quadrotor teams fly: a planner at 5-10 Hz above a tracking controller at hundreds of
Hz. Each control step, every vehicle gets the flat-output setpoint of its agent's planned step
(the planning model is a 3D double integrator: from the measured position p and velocity v under
the planned acceleration a, ``p(s) = p + v s + a s^2 / 2``, ``v(s) = v + a s``, yaw 0) and RotorPy's
SE(3) geometric controller tracks it at ``plant_rate_hz`` on RotorPy's rigid-body model (rotor and
parasitic drag, motor lag, thrust limits) in the configured wind. Every ``dt`` the plant returns
the sampled (p, v), with optional Gaussian sensor noise, and with a lag model (the last command as
states, :func:`check_planning_model`) the command it applied, exactly.

What the double integrator does not know (drag, wind, tracking lag) is the residual the GPs learn.
RotorPy (MIT licence) is an optional dependency: ``pip install -e ".[rotorpy]"``.

Randomness: RotorPy draws from NumPy's global generator (motor noise, Dryden gusts); the plant
keeps its own seeded state and swaps it in only while it flies, so runs are reproducible and
nothing outside changes.
"""

from __future__ import annotations

import contextlib
import math
from dataclasses import dataclass
from typing import Any, Iterator

import numpy as np
import torch
from torch import Tensor

from torch_gpmpc.config.model_spec import ModelSpec
from torch_gpmpc.config.plant import VEHICLES, WINDS
from torch_gpmpc.dynamics.systems import NominalModel
from torch_gpmpc.errors import GpmpcError

#: Frequency of the ``sine`` wind on every axis (Hz): a slow gust cycle of 10 s.
SINE_WIND_HZ = 0.1
#: Turbulence intensity of the ``dryden`` wind on every axis (m/s), about its mean ``plant_wind_speed``.
DRYDEN_SIGMA = 0.3
GRAVITY = 9.81
INSTALL_HINT = 'pip install -e ".[rotorpy]" (or pip install rotorpy)'


def require_rotorpy() -> None:
    """Raise a clear error when RotorPy is not installed."""
    try:
        import rotorpy  # noqa: F401
    except ImportError as exc:
        raise GpmpcError(f"plant=rotorpy needs the optional RotorPy simulator; install it with {INSTALL_HINT}") from exc


def check_planning_model(spec: ModelSpec) -> None:
    """The RotorPy plant flies a 3D double integrator (p, v) with acceleration inputs, optionally with
    the last command as three more states (``w' = u``, :attr:`ModelSpec.input_memory`: a model of the
    vehicle's tracking lag, ``examples/rotorpy/crazyflie_lag.toml``).

    Raises:
        GpmpcError: naming the model and what it must be.
    """
    dt, n = spec.dt, spec.state_dim
    eye, zero = np.eye(3), np.zeros((3, 3))
    A = np.block([[eye, dt * eye], [zero, eye]])
    B = np.vstack([0.5 * dt * dt * eye, dt * eye])
    if n == 9:  # the double integrator and the last command
        A = np.block([[A, np.zeros((6, 3))], [np.zeros((3, 9))]])
        B = np.vstack([B, eye])
    ok = (n in (6, 9) and spec.input_dim == 3 and tuple(spec.position) == (0, 1, 2)
          and np.allclose(np.array(spec.A), A, atol=1e-9) and np.allclose(np.array(spec.B), B, atol=1e-9))
    if ok and not set(spec.residual) <= {3, 4, 5}:
        raise GpmpcError(f"plant=rotorpy: model {spec.name!r} has residual rows {list(spec.residual)}; the GPs learn "
                         "the velocity rows only (residual = [3, 4, 5] or a subset): the position and the last "
                         "command are known exactly")
    if not ok:
        raise GpmpcError(f"plant=rotorpy flies a 3D double integrator (states p, v; inputs the accelerations: "
                         f"A = [[I, dt I], [0, I]], B = [[dt^2/2 I], [dt I]], position = [0, 1, 2]), optionally "
                         f"with the last command as states 6-8 (A rows and columns 0, B rows I); model {spec.name!r} "
                         f"is not one{_first_difference(spec, A, B)}. "
                         "Use the built-in double-integrator in 3D (dim = 3) or a model file like "
                         "examples/rotorpy/crazyflie.toml or crazyflie_lag.toml")


def _first_difference(spec: ModelSpec, A: np.ndarray, B: np.ndarray) -> str:
    """Where a model of the expected sizes first differs from the double integrator (A, B), e.g.
    ``" (A[3][6] = 0.05, expected 0)"``; ``""`` for other sizes."""
    for name, got, want in (("A", np.array(spec.A), A), ("B", np.array(spec.B), B)):
        if got.shape != want.shape:
            return ""
        bad = np.argwhere(~np.isclose(got, want, atol=1e-9))
        if len(bad):
            i, j = bad[0]
            return f" ({name}[{i}][{j}] = {got[i, j]:g}, expected {want[i, j]:g})"
    return ""


@dataclass(frozen=True)
class PlantSettings:
    """How the RotorPy plant flies (the config keys ``plant_*`` and ``wind_change_step``).

    Attributes:
        vehicle: ``crazyflie`` or ``hummingbird`` (RotorPy's parameter sets).
        wind: ``none``, ``constant``, ``sine`` (amplitude ``wind_speed`` per axis at
            :data:`SINE_WIND_HZ`) or ``dryden`` (mean ``wind_speed``, intensity :data:`DRYDEN_SIGMA`).
        wind_speed: (3,) m/s.
        rate_hz: the tracking controller's and the simulator's rate.
        sensor_noise: standard deviation of the measured position (m) and velocity (m/s).
        wind_change_step: control step from which the wind is turned 90 degrees about the vertical
            axis (``None``: never).
        seed: seeds the sensor noise and RotorPy's own draws.
    """

    vehicle: str = "crazyflie"
    wind: str = "none"
    wind_speed: tuple[float, float, float] = (0.0, 0.0, 0.0)
    rate_hz: float = 100.0
    sensor_noise: float = 0.0
    wind_change_step: int | None = None
    seed: int = 0

    @classmethod
    def from_config(cls, cfg, seed: int | None = None) -> "PlantSettings":
        """The settings of a run :class:`~torch_gpmpc.config.schema.Config` (seed: ``2 seed``, the
        noise stream, unless given)."""
        return cls(cfg.plant_vehicle, cfg.plant_wind, tuple(cfg.plant_wind_speed), cfg.plant_rate_hz,
                   cfg.plant_sensor_noise, cfg.wind_change_step, 2 * cfg.seed if seed is None else seed)


def vehicle_params(name: str) -> dict:
    """RotorPy's parameter dict of ``name`` (one of :data:`VEHICLES`)."""
    require_rotorpy()
    if name == "crazyflie":
        from rotorpy.vehicles.crazyflie_params import quad_params
    elif name == "hummingbird":
        from rotorpy.vehicles.hummingbird_params import quad_params
    else:
        raise GpmpcError(f"plant_vehicle {name!r} is not one of {', '.join(VEHICLES)}")
    return dict(quad_params)


class TurningWind:
    """A RotorPy wind turned 90 degrees about the vertical axis from time ``change_time`` on (s)."""

    def __init__(self, base: Any, change_time: float | None) -> None:
        self.base, self.change_time = base, change_time

    def update(self, t: float, position: np.ndarray) -> np.ndarray:
        """Wind (3,) in world coordinates at time t."""
        w = np.asarray(self.base.update(t, position), dtype=float)
        if self.change_time is not None and t >= self.change_time - 1e-9:
            w = np.array([-w[1], w[0], w[2]])
        return w


def make_wind(settings: PlantSettings, dt: float) -> TurningWind:
    """One vehicle's wind (a new generator each: Dryden gusts are independent per vehicle)."""
    from rotorpy.wind.default_winds import ConstantWind, NoWind, SinusoidWind

    speed = np.asarray(settings.wind_speed, dtype=float)
    if settings.wind == "none":
        base = NoWind()
    elif settings.wind == "constant":
        base = ConstantWind(*speed)
    elif settings.wind == "sine":
        base = SinusoidWind(amplitudes=speed, frequencies=np.full(3, SINE_WIND_HZ), phase=np.zeros(3))
    elif settings.wind == "dryden":
        from rotorpy.wind.dryden_winds import DrydenGust
        base = DrydenGust(dt=1.0 / settings.rate_hz, avg_wind=speed, sig_wind=np.full(3, DRYDEN_SIGMA))
    else:
        raise GpmpcError(f"plant_wind {settings.wind!r} is not one of {', '.join(WINDS)}")
    change = None if settings.wind_change_step is None else settings.wind_change_step * dt
    return TurningWind(base, change)


def hover_state(position: np.ndarray, params: dict) -> dict:
    """RotorPy state dict of a vehicle hovering at ``position`` (3,)."""
    hover = math.sqrt(params["mass"] * GRAVITY / (params["num_rotors"] * params["k_eta"]))
    return {"x": np.array(position, dtype=float), "v": np.zeros(3), "q": np.array([0.0, 0.0, 0.0, 1.0]),
            "w": np.zeros(3), "wind": np.zeros(3), "rotor_speeds": np.full(params["num_rotors"], hover)}


def flat_output(p: np.ndarray, v: np.ndarray, a: np.ndarray, s: float) -> dict:
    """The double integrator's setpoint ``s`` seconds into the step (position, velocity, acceleration)."""
    zero = np.zeros(3)
    return {"x": p + v * s + 0.5 * a * s * s, "x_dot": v + a * s, "x_ddot": a, "x_dddot": zero,
            "x_ddddot": zero, "yaw": 0.0, "yaw_dot": 0.0}


class RotorPyPlant:
    """K RotorPy multirotors, each tracking its agent's planned step (see the module docstring).

    Args:
        nominal: the planning model, a 3D double integrator (:func:`check_planning_model`).
        settings: vehicle, wind, rate, sensor noise, seed.

    Attributes:
        min_distance: the smallest distance between two vehicles' true positions seen at the
            simulator's rate since :meth:`reset` (``inf`` with one vehicle).
    """

    def __init__(self, nominal: NominalModel, settings: PlantSettings) -> None:
        require_rotorpy()
        check_planning_model(nominal.spec)
        if settings.rate_hz * nominal.spec.dt < 1 - 1e-9:
            raise GpmpcError(f"plant_rate_hz = {settings.rate_hz:g} is below one simulator step per control step "
                             f"(dt = {nominal.spec.dt:g} s); use plant_rate_hz >= {1 / nominal.spec.dt:g} (e.g. 100)")
        self.nominal = nominal
        self.settings = settings
        self.params = vehicle_params(settings.vehicle)
        self.substeps = max(1, round(settings.rate_hz * nominal.spec.dt))
        self._np_state = np.random.RandomState(settings.seed).get_state()
        self._gen = torch.Generator().manual_seed(int(settings.seed))
        self._states: list[dict] = []
        self._last_inputs = np.zeros((0, 3))  # (K, 3): the commands applied last (0 before the first)
        self.min_distance = math.inf

    @contextlib.contextmanager
    def _own_random_state(self) -> Iterator[None]:
        outside = np.random.get_state()
        np.random.set_state(self._np_state)
        try:
            yield
        finally:
            self._np_state = np.random.get_state()
            np.random.set_state(outside)

    @property
    def true_states(self) -> Tensor:
        """The vehicles' true (p, v), (K, 6), or (p, v, last command), (K, 9), for a lag model."""
        rows = [np.concatenate([s["x"], s["v"]]) for s in self._states]
        if self.nominal.spec.state_dim == 9:
            rows = [np.concatenate([r, u]) for r, u in zip(rows, self._last_inputs)]
        return torch.tensor(np.array(rows), dtype=torch.float64)

    def reset(self, starts: Tensor) -> Tensor:
        """Every vehicle hovering at its start (K, 3); returns the measured states (K, 6 or 9: the last
        command 0)."""
        from rotorpy.controllers.quadrotor_control import SE3Control
        from rotorpy.vehicles.multirotor import Multirotor

        starts = np.asarray(torch.as_tensor(starts, dtype=torch.float64))
        if starts.ndim != 2 or starts.shape[1] != 3:
            raise GpmpcError(f"plant=rotorpy flies in 3D; got starts of shape {starts.shape} (use a 3D scenario)")
        with self._own_random_state():
            self._states = [hover_state(p, self.params) for p in starts]
            self._vehicles = [Multirotor(self.params, initial_state=s) for s in self._states]
            self._controllers = [SE3Control(self.params) for _ in self._states]
            self._winds = [make_wind(self.settings, self.nominal.spec.dt) for _ in self._states]
        self._last_inputs = np.zeros((len(self._states), 3))
        self.min_distance = math.inf
        self._track_distance()
        return self._measure()

    def step(self, t: int, x: Tensor, u: Tensor, noise: Tensor | None = None) -> Tensor:
        """Fly control step ``t`` (the process noise ``noise`` is ignored: the physics is the noise)."""
        dt, h = self.nominal.spec.dt, 1.0 / self.settings.rate_hz
        x, u = np.asarray(x, dtype=float), np.asarray(u, dtype=float)
        self._last_inputs = u.copy()
        with self._own_random_state():
            for i in range(self.substeps):
                time = t * dt + i * h
                for k, state in enumerate(self._states):
                    state["wind"] = self._winds[k].update(time, state["x"])
                    control = self._controllers[k].update(time, state, flat_output(x[k, :3], x[k, 3:6], u[k], i * h))
                    self._states[k] = self._vehicles[k].step(state, control, h)
                self._track_distance()
        return self._measure()

    def _measure(self) -> Tensor:
        true = self.true_states
        if self.settings.sensor_noise == 0.0:
            return true
        noise = torch.zeros_like(true)  # the sensors see p and v; the vehicle knows the command it was given
        noise[:, :6] = self.settings.sensor_noise * torch.randn((len(true), 6), generator=self._gen,
                                                                dtype=torch.float64)
        return true + noise

    def _track_distance(self) -> None:
        if len(self._states) < 2:
            return
        p = np.array([s["x"] for s in self._states])
        d = np.linalg.norm(p[:, None] - p[None], axis=-1)
        d[np.diag_indices(len(p))] = np.inf
        self.min_distance = min(self.min_distance, float(d.min()))
