"""The multi-robot benchmark: success and failure causes over scenarios, team sizes and seeds.

In the form the multi-robot planning literature reports (the random-transition tests of the
DMPC line, MADER's and LSC's obstacle fields): a run **succeeds** when every agent is within
``goal_tol`` of its goal by the time limit (``max_steps``) with no collision, no obstacle hit
and no failed local solve. A failed run gets one cause, the first that applies of
``collision``, ``obstacle``, ``solver`` (a local solve failed and the agent flew its previous
plan), ``deadlock`` (some agent never arrived and was stuck at some step: ``deadlock_steps``)
and ``timeout`` (some agent never arrived). Beside it: transition time (the last agent's
arrival, seconds), total path length, and computation per agent and step (the run's wall time
over steps times agents: everything the controller did, in one process).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from torch_gpmpc.config.schema import Config
from torch_gpmpc.sim.experiments import Task
from torch_gpmpc.sim.scenarios import make_scenario

#: Failure causes, in the order they are checked.
FAILURE_CAUSES = ("collision", "obstacle", "solver", "deadlock", "timeout")
#: Columns of ``benchmark.csv``, in order.
CSV_COLUMNS = ("scenario", "agents", "seed", "success", "cause", "collisions", "obstacle_hits", "failed_solves",
               "deadlock_steps", "arrived", "transition_time_s", "path_length_total", "straight_line_total",
               "compute_ms_per_agent_step", "min_pair_distance", "min_obstacle_distance")


def benchmark_tasks(cfg: Config, scenarios: Sequence[str], agents: Sequence[int], seeds: int,
                    cache_dir: str) -> list[tuple[str, int, Task]]:
    """One run per (scenario, team size, seed ``cfg.seed .. cfg.seed + seeds - 1``).

    Args:
        cfg: the base configuration (``--set`` keys applied).
        scenarios: built-in scenario names or scenario files (a file fixes its own team size,
            so it runs once per seed whatever ``agents`` says).
        agents: team sizes K of the built-in scenarios.

    Returns:
        ``(scenario label, K, task)`` triples.
    """
    out = []
    for name in scenarios:
        if Path(name).suffix in (".json", ".toml"):
            size = make_scenario(cfg, name).num_agents  # validates the file before any run starts
            # the file's team overrides num_agents, as in ``gpmpc run --scenario``
            out += [(Path(name).stem, size, Task("bench", cfg.method, cfg.seed + s, cfg.rho, cfg.stated_dict(), cache_dir,
                                                 scenario_file=str(name))) for s in range(seeds)]
            continue
        for k in agents:
            config = {**cfg.stated_dict(), "scenario": name, "num_agents": int(k)}
            Config(**config)  # refuse a bad combination (paper with K != 3) before any run starts
            out += [(name, int(k), Task("bench", cfg.method, cfg.seed + s, cfg.rho, config, cache_dir))
                    for s in range(seeds)]
    return out


def run_outcome(metrics: dict[str, Any], scenario: str, dt: float) -> dict[str, Any]:
    """One ``benchmark.csv`` row from a run's ``metrics.json`` dict (columns :data:`CSV_COLUMNS`)."""
    arrived = metrics["arrival_step_max"] is not None
    causes = {
        "collision": metrics["violations"] > 0,
        "obstacle": metrics.get("obstacle_violations", 0) > 0,
        "solver": metrics.get("failed_local_solves", 0) > 0,
        "deadlock": not arrived and (metrics.get("deadlock_steps") or 0) > 0,
        "timeout": not arrived,
    }
    cause = next((c for c in FAILURE_CAUSES if causes[c]), "")
    steps, k = metrics["steps"], metrics["num_agents"]
    return {
        "scenario": scenario, "agents": k, "seed": metrics["seed"], "success": not cause, "cause": cause,
        "collisions": metrics["violations"], "obstacle_hits": metrics.get("obstacle_violations", 0),
        "failed_solves": metrics.get("failed_local_solves", 0), "deadlock_steps": metrics.get("deadlock_steps"),
        "arrived": sum(a is not None for a in metrics["arrival_steps"]),
        "transition_time_s": metrics["arrival_step_max"] * dt if arrived else None,
        "path_length_total": float(sum(metrics["path_length"])),
        "straight_line_total": float(sum(metrics["straight_line_length"])),
        "compute_ms_per_agent_step": 1000.0 * metrics["wall_time_s"] / max(steps * k, 1),
        "min_pair_distance": metrics["min_pair_distance"], "min_obstacle_distance": metrics.get("min_obstacle_distance"),
    }


def summary_rows(rows: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    """One row per (scenario, team size): runs, success rate, failure counts by cause, and the
    means of transition time and path length over successful runs and of compute over all runs."""
    groups: dict[tuple[str, int], list[dict[str, Any]]] = {}
    for row in rows:
        groups.setdefault((row["scenario"], row["agents"]), []).append(row)
    out = []
    for (scenario, k), runs in groups.items():
        ok = [r for r in runs if r["success"]]
        out.append({
            "scenario": scenario, "agents": k, "runs": len(runs), "success_rate": len(ok) / len(runs),
            **{f"fail_{c}": sum(r["cause"] == c for r in runs) for c in FAILURE_CAUSES},
            "transition_time_s": _mean([r["transition_time_s"] for r in ok]),
            "path_length_total": _mean([r["path_length_total"] for r in ok]),
            "compute_ms_per_agent_step": _mean([r["compute_ms_per_agent_step"] for r in runs]),
        })
    return out


def _mean(values: Sequence[float | None]) -> float | None:
    finite = [v for v in values if v is not None and math.isfinite(v)]
    return float(np.mean(finite)) if finite else None


def markdown_table(summary: Sequence[dict[str, Any]]) -> str:
    """The summary as a markdown table (success, failure causes, time, length, compute)."""
    def fmt(v, spec):
        return "-" if v is None else format(v, spec)

    head = ("| scenario | agents | runs | success | " + " | ".join(FAILURE_CAUSES)
            + " | transition time (s) | total path length | compute per agent-step (ms) |")
    lines = [head, "|" + "---|" * (7 + len(FAILURE_CAUSES))]
    for r in summary:
        lines.append(f"| {r['scenario']} | {r['agents']} | {r['runs']} | {r['success_rate']:.0%} | "
                     + " | ".join(str(r[f"fail_{c}"]) for c in FAILURE_CAUSES)
                     + f" | {fmt(r['transition_time_s'], '.2f')} | {fmt(r['path_length_total'], '.1f')} | "
                       f"{fmt(r['compute_ms_per_agent_step'], '.1f')} |")
    return "\n".join(lines)
