"""``gpmpc collect``: log transitions of the true system (paper data recipe).

Thin over :func:`torch_gpmpc.data.collect.collect_transitions`; writes ``.npz`` or ``.csv``
by the suffix of ``--out``, atomically.
"""

from __future__ import annotations

import math
from pathlib import Path

from torch_gpmpc.data import MAX_COLLECT_ROWS, check_suffix, collect_transitions
from torch_gpmpc.errors import GpmpcError
from torch_gpmpc.config.model_spec import check_model_name, resolve_model
from torch_gpmpc.config.plant import DEFAULT_GP_SAMPLES
from torch_gpmpc.dynamics.systems import make_system


def _validate(args) -> None:
    """Check every argument before any work (raises GpmpcError); fills the plant's default ``--samples``."""
    if args.samples is None:
        args.samples = DEFAULT_GP_SAMPLES[args.plant]
    if Path(args.out).is_dir():
        raise GpmpcError(f"--out {args.out!r} is an existing directory; give a file path ending in .npz or .csv")
    check_suffix(args.out)
    if args.dim not in (2, 3):
        raise GpmpcError(f"--dim must be 2 or 3 (the vortex wind is defined for those), got {args.dim}")
    check_model_name(args.model)
    if args.agents < 1:
        raise GpmpcError(f"--agents must be >= 1, got {args.agents}")
    if args.samples < 2:
        raise GpmpcError(f"--samples must be >= 2 per agent, got {args.samples}")
    if args.agents * args.samples > MAX_COLLECT_ROWS:
        raise GpmpcError(f"--agents x --samples = {args.agents * args.samples} transitions is more than "
                         f"{MAX_COLLECT_ROWS}; lower --agents or --samples (the paper uses 100 per agent)")
    if not (math.isfinite(args.noise_std) and args.noise_std >= 0):
        raise GpmpcError(f"--noise-std must be a finite number >= 0, got {args.noise_std}")
    for flag, value in (("--u-max", args.u_max), ("--box", args.box), ("--dt", args.dt)):
        if not (math.isfinite(value) and value > 0):
            raise GpmpcError(f"{flag} must be a positive number, got {value}")


def main(args) -> int:
    """Collect ``--agents x --samples`` transitions and write them to ``--out``."""
    _validate(args)
    if args.plant == "rotorpy":
        return _collect_flights(args)
    if args.set:
        raise GpmpcError("--set configures the RotorPy flights; add --plant rotorpy (the model plant "
                         "takes --noise-std, --wind-scale, --dt and --u-max)")
    spec = resolve_model(args.model, args.dim, args.dt, args.u_max)
    system = make_system(spec, noise_std=args.noise_std, wind_scale=args.wind_scale)
    data = collect_transitions(system, num_agents=args.agents, samples=args.samples, seed=args.seed, box=args.box)
    data.save(args.out)
    bound = f"box={list(spec.input_box)}" if spec.input_box is not None else f"u_max={spec.input_norm:g}"
    print(f"wrote {args.out}: {data.num_samples} transitions ({args.agents} agents x {args.samples}), "
          f"model {spec.name} (D={spec.state_dim}, Du={spec.input_dim}), noise_std={args.noise_std:g}, "
          f"{bound}, box={args.box:g}, seed={args.seed}")
    return 0


def _collect_flights(args) -> int:
    """``--plant rotorpy``: excitation flights (:func:`~torch_gpmpc.data.flights.collect_flights`)."""
    from torch_gpmpc.config import load_config, parse_overrides
    from torch_gpmpc.data.flights import collect_flights
    from torch_gpmpc.dynamics.rotorpy_plant import PlantSettings, check_planning_model, require_rotorpy
    from torch_gpmpc.dynamics.systems import NominalModel

    require_rotorpy()
    spec = resolve_model(args.model, args.dim, args.dt, args.u_max)
    check_planning_model(spec)
    cfg = load_config(None, {**parse_overrides(args.set), "plant": "rotorpy", "seed": args.seed})
    settings = PlantSettings.from_config(cfg, seed=args.seed)
    data = collect_flights(NominalModel(spec), settings, num_agents=args.agents, samples=args.samples, box=args.box)
    data.save(args.out)
    print(f"wrote {args.out}: {data.num_samples} transitions ({args.agents} {settings.vehicle} flights x "
          f"{args.samples} steps of {spec.dt:g} s), model {spec.name}, wind {settings.wind} "
          f"{list(settings.wind_speed)} m/s, {settings.rate_hz:g} Hz, seed={args.seed}")
    return 0
