"""Settings of a tuning run (``gpmpc tune``), checked by the same machinery as the run
configuration; on the command line ``--set tune.NAME=VALUE``, in a file a ``[tune]`` table."""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any, Mapping

from torch_gpmpc.config.fields import Rules, build, validate
from torch_gpmpc.errors import GpmpcError


@dataclass(frozen=True)
class TuneSettings:
    """Settings of a tuning run (flat keys; on the command line ``--set tune.NAME=VALUE``).

    Attributes:
        seeds: training instance seeds.
        heldout_seeds: seeds of held-out instances (evaluated before and after tuning).
        closed_loop_seeds: seeds of the closed-loop comparison after tuning: whole runs with
            the default and the tuned settings, noisy (the config's ``noise_std``) and noiseless,
            written to ``tuned.json``'s ``closed_loop`` (empty: skip it).
        admm_iters: ADMM iterations unrolled per MPC step (fixed, no early stop).
        mpc_steps: closed-loop MPC steps per instance (noise fixed by the seed).
        warmup_iters: gradient-free ADMM iterations before the unrolled ones (0 = none).
        warm_start: start each instance from the previous step's converged ADMM iterate
            (as the closed loop does; ``tuning.instances.with_warm_starts``) instead of a cold start.
        warm_rho: rho of the warm-start solve (the converged point does not depend on it).
        warm_tol: primal and dual tolerance of the warm-start solve.
        warm_max_iter: iteration cap of the warm-start solve.
        crossing_distance: instances start where the reference is this far from the
            point where the straight paths cross (``paper``: the centre).
        perturb_std: standard deviation of the seeded perturbation of the start state.
        w_primal: weight of the final primal residual.
        w_dual: weight of the final dual residual.
        w_cost: weight of the mean planned cost per agent.
        w_distance: weight of the softplus penalty on planned distances below r_safe.
        distance_width: softplus width beta of that penalty.
        optimizer: ``adam`` or ``lbfgs``.
        lr: learning rate (Adam) or step length (L-BFGS).
        lr_decay: Adam's learning rate is multiplied by this every iteration.
        tune_rho: optimize log rho.
        tune_split: optimize the per-edge split logits.
        grid_points: after tuning, also evaluate a grid of this many rho values
            log-spaced in ``[grid_min, grid_max]`` (split from the config) as a
            baseline (0 = no grid search).
        grid_min: smallest grid rho.
        grid_max: largest grid rho.
    """

    seeds: tuple[int, ...] = (0, 1)
    heldout_seeds: tuple[int, ...] = (100, 101)
    closed_loop_seeds: tuple[int, ...] = (100, 101)
    admm_iters: int = 6
    mpc_steps: int = 1
    warmup_iters: int = 0
    warm_start: bool = True
    warm_rho: float = 2.0
    warm_tol: float = 1e-3
    warm_max_iter: int = 300
    crossing_distance: float = 1.0
    perturb_std: float = 0.2
    w_primal: float = 1.0
    w_dual: float = 1.0
    w_cost: float = 0.01
    w_distance: float = 10.0
    distance_width: float = 0.05
    optimizer: str = "adam"
    lr: float = 0.2
    lr_decay: float = 0.95
    tune_rho: bool = True
    tune_split: bool = True
    grid_points: int = 0
    grid_min: float = 1.0
    grid_max: float = 200.0

    def __post_init__(self) -> None:
        object.__setattr__(self, "seeds", _int_tuple(self.seeds, "seeds"))
        object.__setattr__(self, "heldout_seeds", _int_tuple(self.heldout_seeds, "heldout_seeds"))
        object.__setattr__(self, "closed_loop_seeds", _int_tuple(self.closed_loop_seeds, "closed_loop_seeds"))
        validate(self, TUNE_RULES)
        if self.grid_max < self.grid_min:
            raise GpmpcError(f"tune setting 'grid_max': {self.grid_max!r} is out of range; use a number >= grid_min")

    @classmethod
    def from_mapping(cls, data: Mapping[str, Any]) -> "TuneSettings":
        """Build from a flat mapping; unknown keys raise naming the nearest valid key."""
        return build(cls, data, TUNE_RULES)

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON-serializable dict."""
        out = asdict(self)
        out["seeds"], out["heldout_seeds"] = list(self.seeds), list(self.heldout_seeds)
        out["closed_loop_seeds"] = list(self.closed_loop_seeds)
        return out


def _int_tuple(value: Any, name: str) -> tuple[int, ...]:
    """A single integer or a list of integers as a tuple (``--set tune.seeds=3`` or ``=[0,1]``)."""
    if isinstance(value, int) and not isinstance(value, bool):
        return (value,)
    if isinstance(value, (list, tuple)) and all(isinstance(v, int) and not isinstance(v, bool) for v in value):
        return tuple(value)
    raise GpmpcError(f"tune setting '{name}': expected a list of integers, got {value!r}")


TUNE_RULES = Rules(
    what="tune setting",
    prefix="tune.",
    choices={"optimizer": ("adam", "lbfgs")},
    ranges={
        "seeds": (lambda v: len(v) >= 1 and min(v) >= 0, "a non-empty list of integers >= 0"),
        "heldout_seeds": (lambda v: all(s >= 0 for s in v), "a list of integers >= 0"),
        "closed_loop_seeds": (lambda v: all(s >= 0 for s in v), "a list of integers >= 0"),
        "admm_iters": (lambda v: v >= 1, "an integer >= 1"),
        "mpc_steps": (lambda v: v >= 1, "an integer >= 1"),
        "warmup_iters": (lambda v: v >= 0, "an integer >= 0"),
        "warm_rho": (lambda v: v > 0, "a number > 0"),
        "warm_tol": (lambda v: v > 0, "a number > 0"),
        "warm_max_iter": (lambda v: v >= 1, "an integer >= 1"),
        "crossing_distance": (lambda v: v >= 0, "a number >= 0"),
        "perturb_std": (lambda v: v >= 0, "a number >= 0"),
        "w_primal": (lambda v: v >= 0, "a number >= 0"),
        "w_dual": (lambda v: v >= 0, "a number >= 0"),
        "w_cost": (lambda v: v >= 0, "a number >= 0"),
        "w_distance": (lambda v: v >= 0, "a number >= 0"),
        "distance_width": (lambda v: v > 0, "a number > 0"),
        "lr": (lambda v: v > 0, "a number > 0"),
        "lr_decay": (lambda v: 0 < v <= 1, "a number in (0, 1]"),
        "grid_points": (lambda v: v >= 0, "an integer >= 0"),
        "grid_min": (lambda v: v > 0, "a number > 0"),
    },
)
