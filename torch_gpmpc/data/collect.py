"""The paper's data recipe: transitions of the true system at random states and inputs."""

from __future__ import annotations

import math

import torch
from torch import Tensor

from torch_gpmpc.data.transitions import MIN_SAMPLES, Transitions
from torch_gpmpc.dynamics.systems import TrueSystem, clip_norm
from torch_gpmpc.errors import GpmpcError

#: Most transitions :func:`collect_transitions` writes in one call (K x N); more is
#: almost always a typo and would exhaust memory before anything is written.
MAX_COLLECT_ROWS = 1_000_000


def sample_disc(n: int, dim: int, radius: float, generator: torch.Generator) -> Tensor:
    """Uniform samples from the ball ``||v|| < radius`` in ``dim`` dimensions.

    The direction is a normalized Gaussian and the radius ``radius * U^(1/dim)``
    (in 2D: ``radius * sqrt(U)``, area-uniform in the disc).

    Returns:
        samples, shape (n, dim), float64.
    """
    direction = torch.randn(n, dim, generator=generator, dtype=torch.float64)
    direction = direction / direction.norm(dim=1, keepdim=True).clamp_min(1e-300)
    r = radius * torch.rand(n, 1, generator=generator, dtype=torch.float64) ** (1.0 / dim)
    return r * direction


def collect_transitions(system: TrueSystem, num_agents: int = 3, samples: int = 100, seed: int = 0,
                        u_max: float | None = None, box: float = 4.0) -> Transitions:
    """The paper's data recipe, ``samples`` transitions per agent, for any linear model.

    Positions are uniform in ``[-box, box]^P``; the model's other states (velocities) uniform in
    ``[-1, 1]`` times its state bound (1 without one); inputs uniform in the model's input bound
    (the ball ``||v|| < u_max`` or the box); ``x_next = system.step(x, v)``, with one seeded
    ``torch.Generator`` for states, inputs and noise. For the paper's model this is its recipe.

    Args:
        system: the true system (nominal + wind + noise).
        num_agents: K; rows are tagged with agent ids 0..K-1.
        samples: N per agent.
        seed: seed of the generator.
        u_max: input norm bound (default: the model's; ignored with a box bound).
        box: half-width of the position box.

    Returns:
        Transitions with K*N rows (agent 0's rows first).

    Raises:
        GpmpcError: for non-positive counts or sizes.
    """
    spec = system.nominal.spec
    u_max = spec.input_norm if u_max is None else u_max
    if int(num_agents) < 1:
        raise GpmpcError(f"agents must be >= 1, got {num_agents}; e.g. --agents 3")
    if int(samples) < MIN_SAMPLES:
        raise GpmpcError(f"samples must be >= {MIN_SAMPLES} per agent, got {samples}; e.g. --samples 100")
    if int(num_agents) * int(samples) > MAX_COLLECT_ROWS:
        raise GpmpcError(f"agents x samples = {int(num_agents) * int(samples)} transitions is more than "
                         f"{MAX_COLLECT_ROWS}; lower --agents or --samples (the paper uses 100 per agent)")
    for name, value in (("u-max", u_max if spec.input_box is None else 1.0), ("box", box)):
        if not (math.isfinite(value) and value > 0):
            raise GpmpcError(f"{name} must be a positive number, got {value}")
    dim, du = system.nominal.dim, system.nominal.input_dim
    half = torch.full((dim,), 1.0 if spec.state_bound_norm is None else spec.state_bound_norm, dtype=torch.float64)
    half[list(spec.position)] = box
    gen = torch.Generator().manual_seed(int(seed))
    xs, us, xns, ids = [], [], [], []
    for k in range(int(num_agents)):
        x = (2.0 * torch.rand(int(samples), dim, generator=gen, dtype=torch.float64) - 1.0) * half
        if spec.input_box is None:
            u = sample_disc(int(samples), du, u_max, gen)
        else:
            u = (2.0 * torch.rand(int(samples), du, generator=gen, dtype=torch.float64) - 1.0) \
                * torch.tensor(spec.input_box, dtype=torch.float64)
            if spec.input_norm is not None:  # both bounds: the box's samples inside the ball
                u = clip_norm(u, u_max)
        xs.append(x)
        us.append(u)
        xns.append(system.step(x, u, generator=gen))
        ids.append(torch.full((int(samples),), k, dtype=torch.int64))
    return Transitions(torch.cat(xs), torch.cat(us), torch.cat(xns), torch.cat(ids),
                       source=f"collected (seed {seed})")
