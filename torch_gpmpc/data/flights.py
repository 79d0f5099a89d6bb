"""Transitions logged from simulated flights (``gpmpc collect --plant rotorpy``).

Each agent flies its own RotorPy vehicle alone, on an excitation trajectory: random velocity
setpoints under the planning model's speed limit, reached under its input bound and a jerk limit
(:func:`fly_excitation`). Every control step logs the
measured planning state x, the commanded acceleration u and the next measured state: the rows of
the planning model (a 3D double integrator) that ``fit-gp`` and the run's GPs learn the residual
``x' - (A x + B u)`` from (drag, wind, tracking lag).
"""

from __future__ import annotations

import dataclasses

import torch
from torch import Tensor

from torch_gpmpc.data.transitions import MIN_SAMPLES, Transitions
from torch_gpmpc.dynamics.rotorpy_plant import PlantSettings, RotorPyPlant
from torch_gpmpc.dynamics.systems import NominalModel, project_input
from torch_gpmpc.errors import GpmpcError

#: Control steps between velocity-setpoint changes.
SETPOINT_STEPS = 20
#: Time constant of the pull toward the velocity setpoint (s).
TAU_V = 0.5
#: Largest change of the commanded acceleration per second (m/s^3): a quadrotor realizes a
#: commanded acceleration only after its attitude and motor lag (about 0.1 s for the Crazyflie), so
#: abrupt excitation mostly logs that lag, which the planning state cannot explain (measured: at 10
#: the residuals' std doubles and 400-row GPs predict a wrong-signed residual at hover). 3 is about
#: the rate of smooth plans (examples/rotorpy/swap.toml: rms 2.6 m/s^3 at input_rate_weight 1, 2 at 2).
JERK = 3.0
#: Share of the setpoints that are hover (v = 0): every mission ends hovering at its goal, in the wind,
#: and a GP that saw little slow flight mispredicts there (a steady offset at the goal).
HOVER_SHARE = 0.25
#: Vertical half-range of the flights (m); the horizontal one is ``box``.
Z_RANGE = 1.0


def limit_speed(v: Tensor, a: Tensor, dt: float, v_max: float | None) -> Tensor:
    """Scale the acceleration a (3,) so that ``||v + a dt|| <= v_max`` (``a`` unchanged without a limit)."""
    if v_max is None:
        return a
    v_next = v + a * dt
    speed = float(v_next.norm())
    if speed <= v_max:
        return a
    return (v_next * (v_max / speed) - v) / dt


def velocity_setpoint(p: Tensor, v_max: float, scale: Tensor, generator: torch.Generator) -> Tensor:
    """A random velocity (3,): 0 (hover) with probability :data:`HOVER_SHARE`, else of speed uniform
    up to ``v_max``, turned toward the centre when the vehicle is outside the flight region
    ``|p_i| <= scale_i``."""
    d = torch.randn(3, generator=generator, dtype=torch.float64)
    outside = p.abs() > scale
    d[outside] = -p[outside].sign() * d[outside].abs()
    r = float(torch.rand(1, generator=generator, dtype=torch.float64))
    if r < HOVER_SHARE and not bool(outside.any()):
        return torch.zeros(3, dtype=torch.float64)
    return d / d.norm().clamp_min(1e-12) * v_max * max(r - HOVER_SHARE, 0.0) / (1.0 - HOVER_SHARE)


def fly_excitation(nominal: NominalModel, settings: PlantSettings, samples: int, box: float,
                   generator: torch.Generator) -> tuple[Tensor, Tensor, Tensor]:
    """One vehicle's excitation flight of ``samples`` control steps: random velocity setpoints under
    the speed limit (a share of them hover, :func:`velocity_setpoint`), held :data:`SETPOINT_STEPS`
    steps each, reached with time constant :data:`TAU_V` under the input bound and the jerk limit
    :data:`JERK`.

    Returns:
        ``(x (N, n), u (N, 3), x_next (N, n))`` measured planning states (n = 6, or 9 with the last
        command) and commanded accelerations.
    """
    spec, dt = nominal.spec, nominal.spec.dt
    v_max = 1.0 if spec.state_bound_norm is None else float(spec.state_bound_norm)
    scale = torch.tensor([box, box, Z_RANGE], dtype=torch.float64)
    plant = RotorPyPlant(nominal, settings)
    x = plant.reset((2 * torch.rand(1, 3, generator=generator, dtype=torch.float64) - 1) * scale)
    xs, us, xns = [], [], []
    a = torch.zeros(3, dtype=torch.float64)
    for t in range(samples):
        p, v = x[0, :3], x[0, 3:6]
        if t % SETPOINT_STEPS == 0 or bool((p.abs() > scale).any()):
            target = velocity_setpoint(p, v_max, scale, generator)
        want = project_input(limit_speed(v, (target - v) / TAU_V, dt, spec.state_bound_norm), spec)
        step = want - a
        a = project_input(a + step * min(1.0, JERK * dt / max(float(step.norm()), 1e-12)), spec)
        x_next = plant.step(t, x, a[None])
        xs.append(x[0])
        us.append(a)
        xns.append(x_next[0])
        x = x_next
    return torch.stack(xs), torch.stack(us), torch.stack(xns)


def collect_flights(nominal: NominalModel, settings: PlantSettings, num_agents: int = 4, samples: int = 100,
                    box: float = 4.0, agents: range | None = None) -> Transitions:
    """Excitation flights of ``num_agents`` vehicles, ``samples`` control steps each.

    Agent k flies with its own generator (seed ``settings.seed + k``) and its own RotorPy state,
    so its rows do not depend on the other agents: ``agents=range(k, k + 1)`` gives exactly agent
    k's rows of the team's log (what an agent in its own process collects).

    Args:
        nominal: the planning model (a 3D double integrator).
        settings: vehicle, wind and rate of the flights (the wind does not change during them).
        num_agents: K (the ``agent`` ids run over ``agents``, default ``range(K)``).
        samples: N control steps per agent.
        box: horizontal half-width of the flight region (m).

    Returns:
        Transitions with N rows per agent (agent order).
    """
    if int(samples) < MIN_SAMPLES:
        raise GpmpcError(f"samples must be >= {MIN_SAMPLES} per agent, got {samples}; e.g. --samples 100")
    agents = range(int(num_agents)) if agents is None else agents
    xs, us, xns, ids = [], [], [], []
    for k in agents:
        own = dataclasses.replace(settings, wind_change_step=None, seed=settings.seed + k)
        gen = torch.Generator().manual_seed(settings.seed + k)
        x, u, xn = fly_excitation(nominal, own, int(samples), box, gen)
        xs.append(x)
        us.append(u)
        xns.append(xn)
        ids.append(torch.full((int(samples),), k, dtype=torch.int64))
    return Transitions(torch.cat(xs), torch.cat(us), torch.cat(xns), torch.cat(ids),
                       source=f"rotorpy {settings.vehicle} flights, wind {settings.wind} "
                              f"{list(settings.wind_speed)} (seed {settings.seed})")
