"""Calibration of the chance constraints: does a row that binds fail as often as it promises?
And, for a mission budget (``calibrate --mission``), does a whole run collide at most as often
as ``risk_budget`` promises (:func:`mission_tasks`, :func:`mission_entry`)?

For every (step, pair) whose tau = 1 collision row was active in the *applied* plans
(the planned separation within :data:`ACTIVE_TOL` of what the row required), record
whether the realized distance one step later is below ``r_safe``. For a sound formulation
the empirical rate is at most the pair's risk ``eps`` (up to binomial error); the paper's
formulation (``pair_margin = own``, ``margin_variance = latent``) is reported beside it.
Only the steps around the crossing matter, so the runs stop after :data:`CALIBRATION_STEPS`.
"""

from __future__ import annotations

import math
from typing import Any, Mapping, Sequence

import numpy as np
import scipy.stats

from torch_gpmpc.config.schema import Config
from torch_gpmpc.sim.experiments import PAPER_COORDINATION, PAPER_FORMULATION, Task, summarize_metrics
from torch_gpmpc.sim.metrics import compute_metrics, pair_distances
from torch_gpmpc.sim.rollout import Rollout

#: The formulations compared: the package's default margins and the paper's eq. 24 with latent variance,
#: both coordinated by the paper's copies, so that only the margins differ.
FORMULATIONS: dict[str, dict[str, str]] = {
    "sound": {"pair_margin": "sum", "margin_variance": "predictive", **PAPER_COORDINATION},
    "paper": PAPER_FORMULATION,
}
#: A row is active when the planned tau = 1 separation is within this of its required value.
ACTIVE_TOL = 1e-3
#: Closed-loop steps per run: the paper scenario's agents meet around steps 20-35.
CALIBRATION_STEPS = 45


def calibration_tasks(cfg: Config, eps_values: Sequence[float], runs: int, cache_dir: str,
                      steps: int = CALIBRATION_STEPS) -> list[tuple[str, float, Task]]:
    """One task per (formulation, eps, seed), seeds ``cfg.seed .. cfg.seed + runs - 1``.

    Returns:
        ``(formulation, eps, task)`` triples.
    """
    out = []
    for name, overrides in FORMULATIONS.items():
        for eps in eps_values:
            config = {**cfg.to_dict(), **overrides, "eps": float(eps), "max_steps": steps}
            out += [(name, float(eps), Task("calibration", cfg.method, cfg.seed + s, cfg.rho, config, cache_dir))
                    for s in range(runs)]
    return out


def active_outcomes(rollout: Rollout, tol: float = ACTIVE_TOL) -> tuple[int, int]:
    """``(active rows, violations among them)`` of one run.

    Raises:
        ValueError: the rollout does not record the applied plans' separations.
    """
    if rollout.pair_separation is None or rollout.pair_required is None:
        raise ValueError("the rollout has no pair_separation/pair_required (written by an older version)")
    sep, req = np.asarray(rollout.pair_separation), np.asarray(rollout.pair_required)
    r_safe = float(rollout.config.get("r_safe", Config().r_safe))
    realized = pair_distances(rollout.positions)[1:]  # (S, P): distance after step t
    active = np.isfinite(sep) & np.isfinite(req) & (np.abs(sep - req) <= tol)
    return int(active.sum()), int((active & (realized < r_safe)).sum())


def wilson_interval(violations: int, active: int, z: float = 1.959963984540054) -> tuple[float, float]:
    """The Wilson score interval (95 % by default) of a binomial rate ``violations / active``."""
    if active == 0:
        return 0.0, 1.0
    p = violations / active
    centre = (p + z * z / (2 * active)) / (1 + z * z / active)
    half = z * math.sqrt(p * (1 - p) / active + z * z / (4 * active * active)) / (1 + z * z / active)
    return max(0.0, centre - half), min(1.0, centre + half)


def calibration_rows(outcomes: Mapping[tuple[str, float], Sequence[tuple[int, int]]]) -> list[dict[str, Any]]:
    """The rows of ``calibration.json`` from per-run outcomes grouped by (formulation, eps).

    Each row: ``formulation, eps, active, violations, rate`` (``None`` without active rows),
    ``runs`` and the 95 % Wilson interval ``rate_low, rate_high``.
    """
    rows = []
    for (name, eps), runs in outcomes.items():
        active = sum(a for a, _ in runs)
        violations = sum(v for _, v in runs)
        low, high = wilson_interval(violations, active)
        rows.append({"formulation": name, "eps": eps, "active": active, "violations": violations,
                     "rate": violations / active if active else None, "runs": len(runs),
                     "rate_low": low, "rate_high": high})
    return rows


def mission_tasks(cfg: Config, budgets: Sequence[float], runs: int, cache_dir: str,
                  baseline_runs: int = 0) -> list[tuple[str, float, Task]]:
    """Whole runs (``max_steps`` of ``cfg``) under ``risk_mode = mission`` at each budget, seeds
    ``cfg.seed .. cfg.seed + runs - 1``, and ``baseline_runs`` of them under ``pair_step`` at
    ``cfg.eps`` (the comparison).

    Returns:
        ``(mode, budget or eps, task)`` triples.
    """
    out = []
    for budget in budgets:
        config = {**cfg.to_dict(), "risk_mode": "mission", "risk_budget": float(budget)}
        out += [("mission", float(budget), Task("mission", cfg.method, cfg.seed + s, cfg.rho, config, cache_dir))
                for s in range(runs)]
    config = {**cfg.to_dict(), "risk_mode": "pair_step"}
    out += [("pair_step", cfg.eps, Task("mission", cfg.method, cfg.seed + s, cfg.rho, config, cache_dir))
            for s in range(baseline_runs)]
    return out


def clopper_pearson(successes: int, trials: int, level: float = 0.95) -> tuple[float, float]:
    """The exact (Clopper-Pearson) two-sided interval of a binomial proportion."""
    if trials == 0:
        return 0.0, 1.0
    alpha = 1.0 - level
    low = 0.0 if successes == 0 else float(scipy.stats.beta.ppf(alpha / 2, successes, trials - successes + 1))
    high = 1.0 if successes == trials else float(scipy.stats.beta.ppf(1 - alpha / 2, successes + 1, trials - successes))
    return low, high


def mission_entry(mode: str, level: float, rollouts: Sequence[Rollout]) -> dict[str, Any]:
    """One row of the mission calibration (``rollouts``: at least one run): how many whole runs
    had any violation, with its Clopper-Pearson 95 % interval, beside what the runs cost (from
    :func:`~torch_gpmpc.sim.experiments.summarize_metrics`) and the pair-step rates of their
    active rows.

    Returns:
        ``risk_mode``, ``risk_budget`` (mission) or ``eps`` (pair_step), ``runs``,
        ``runs_with_violation``, ``rate``, ``ci95``, ``violations``, ``min_distance_worst``,
        ``risk_spent_mean``/``_max``, ``runs_every_agent_arrived``, ``arrival_mean`` (the last
        agent's arrival step over runs where every agent arrived), ``path_length_mean``,
        ``admm_converged_fraction``, and the active-row ``pair_step_active``/``_violations``/``_rate``.
    """
    metrics = [compute_metrics(r) for r in rollouts]
    summary = summarize_metrics(metrics)
    spent = [m["risk_spent"] for m in metrics if m["risk_spent"] is not None]
    active = [active_outcomes(r) for r in rollouts]
    rows = sum(a for a, _ in active)
    failed = sum(v for _, v in active)
    hit = summary["runs_with_violations"]
    return {
        "risk_mode": mode, ("risk_budget" if mode == "mission" else "eps"): level,
        "runs": len(metrics), "runs_with_violation": hit, "rate": hit / len(metrics),
        "ci95": list(clopper_pearson(hit, len(metrics))),
        "violations": summary["violations_total"],
        "min_distance_worst": summary["min_distance_worst"],
        "risk_spent_mean": float(np.mean(spent)) if spent else None,
        "risk_spent_max": float(np.max(spent)) if spent else None,
        "runs_every_agent_arrived": sum(m["arrival_step_max"] is not None for m in metrics),
        "arrival_mean": summary["arrival_step_max_mean"],
        "path_length_mean": summary["path_length_mean"],
        "admm_converged_fraction": float(np.mean([m["converged_fraction"] or 0.0 for m in metrics])),
        "pair_step_active": rows, "pair_step_violations": failed, "pair_step_rate": failed / rows if rows else None,
    }
