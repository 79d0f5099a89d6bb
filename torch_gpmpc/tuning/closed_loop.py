"""Tuning judged in closed loop: default and tuned settings on held-out seeds, noisy and noiseless.

The objective of :mod:`.objective` is a proxy (a few unrolled ADMM iterations around the
crossing); what a user cares about is the closed loop. :func:`closed_loop_comparison`
runs whole scenarios with the configuration ``gpmpc run`` would use before and after
tuning (``tuned.json``'s ``config``) and summarizes them for ``tuned.json``'s
``closed_loop``; :func:`not_worse` is the acceptance rule.
"""

from __future__ import annotations

from typing import Any, Callable, Sequence

import numpy as np

from torch_gpmpc.config.schema import Config

#: Tuned arrival may exceed the default's by at most this fraction ("not worse").
ARRIVAL_SLACK = 0.05


def summarize(metrics: Sequence[dict]) -> dict[str, Any]:
    """``{arrival_step_max_mean, violations_total, admm_iterations_mean, runs}`` over runs.

    A run whose last agent never arrives counts as arriving at its final step (``steps``),
    so a failure to arrive makes the mean worse instead of vanishing from it.
    """
    arrivals = [m["arrival_step_max"] if m["arrival_step_max"] is not None else m["steps"] for m in metrics]
    return {
        "arrival_step_max_mean": float(np.mean(arrivals)),
        "violations_total": int(sum(m["violations"] for m in metrics)),
        "admm_iterations_mean": float(np.mean([m["admm_iterations_mean"] for m in metrics])),
        "runs": len(metrics),
        "never_arrived": int(sum(m["arrival_step_max"] is None for m in metrics)),
    }


def closed_loop_comparison(default: Config, tuned: Config, seeds: Sequence[int], noise_levels: Sequence[float],
                           run: Callable[[Config], dict]) -> dict[str, Any]:
    """Run both configurations on every (seed, noise level); summarize each.

    Args:
        default: the configuration before tuning.
        tuned: the configuration after tuning (same scenario, tuned ``rho`` and ``risk_split``).
        seeds: held-out run seeds (the noise sequence and the GP data follow the seed).
        noise_levels: process-noise standard deviations, e.g. ``(cfg.noise_std, 0.0)``.
        run: one closed-loop run of a configuration -> its ``metrics.json`` dict.

    Returns:
        ``{"default": summary, "tuned": summary, "seeds": [...], "noise_std": [...],
        "not_worse": bool}`` with :func:`summarize`'s summaries.
    """
    out: dict[str, Any] = {}
    for name, cfg in (("default", default), ("tuned", tuned)):
        out[name] = summarize([run(cfg.replace(seed=int(s), noise_std=float(n))) for s in seeds for n in noise_levels])
    out["seeds"], out["noise_std"] = [int(s) for s in seeds], [float(n) for n in noise_levels]
    out["not_worse"] = not_worse(out["default"], out["tuned"])
    return out


def not_worse(default: dict, tuned: dict) -> bool:
    """Tuned arrives within :data:`ARRIVAL_SLACK` of the default and has no more violations."""
    return (tuned["arrival_step_max_mean"] <= (1 + ARRIVAL_SLACK) * default["arrival_step_max_mean"]
            and tuned["violations_total"] <= default["violations_total"])
