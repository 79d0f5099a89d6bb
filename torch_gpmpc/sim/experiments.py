"""Batches of closed-loop runs: cached by (kind, method, seed/rho, config hash), summarized.

Used by ``gpmpc reproduce``. A finished run is stored as its ``Rollout`` file under
``cache/`` (written atomically), so an interrupted reproduction resumes where it
stopped and a changed config never reuses a stale result.
"""

from __future__ import annotations

import concurrent.futures as cf
import hashlib
import json
import multiprocessing
import os
import sys
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from torch_gpmpc.config.schema import Config
from torch_gpmpc.sim.metrics import compute_metrics
from torch_gpmpc.sim.rollout import Rollout
from torch_gpmpc.threads import torch_threads


@dataclass(frozen=True)
class Task:
    """One closed-loop run to execute (picklable, for worker processes).

    Attributes:
        kind: ``run`` (a full paper run) or ``sweep`` (a short run with a fixed number of
            ADMM iterations for the rho study of Fig. 4).
        method: controller method.
        seed: run seed.
        rho: ADMM penalty.
        config: flat config dict (method, seed and rho are overridden by the fields above).
        cache_dir: where the rollout file goes.
        label: the table row this run belongs to (default: the method).
        scenario_file: a scenario file the run uses instead of ``config['scenario']`` ("" = none;
            its contents are part of the cache key).
    """

    kind: str
    method: str
    seed: int
    rho: float
    config: dict
    cache_dir: str
    label: str = ""
    scenario_file: str = ""

    @property
    def row(self) -> str:
        """The table row of this run."""
        return self.label or self.method

    @property
    def cfg(self) -> Config:
        """The effective configuration of this task. One base configuration serves every method of a
        study (the paper's margins for all six), so a key this method ignores is expected: not warned
        about again (the base configuration warned about the user's own)."""
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)
            return Config(**{**self.config, "method": self.method, "seed": self.seed, "rho": self.rho})

    @property
    def path(self) -> Path:
        """Cache file of this task's rollout."""
        key = config_hash(self.cfg)
        if self.scenario_file:
            text = Path(self.scenario_file).read_bytes()
            key = hashlib.sha256(key.encode() + text).hexdigest()[:12]
        tag = f"{self.kind}_{self.method}_s{self.seed}_rho{self.rho:g}_{key}"
        return Path(self.cache_dir) / f"{tag}.npz"


def config_hash(cfg: Config) -> str:
    """Short stable hash of every config key (12 hex digits)."""
    text = json.dumps(cfg.to_dict(), sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()[:12]


def sweep_config(base: Config, steps: int, iterations: int) -> dict:
    """Config of a Fig. 4 sweep run: ``steps`` closed-loop steps, exactly ``iterations``
    ADMM iterations each (the tolerance is set unreachably low so no step stops early), at the
    sweep's fixed rho (the paper's study; an adaptive rho would only start there)."""
    return {**base.to_dict(), "max_steps": steps, "admm_max_iter": iterations, "admm_tol": 1e-300,
            "admm_dual_tol": None, "rho_update": "fixed"}


#: The paper's cost: ``||X - Xref||^2 + alpha ||U||^2``, no terminal weight of its own (reproduce's runs).
PAPER_COST = {"terminal_cost": "stage"}
#: The paper's coordination: consensus ADMM on trajectory copies (eqs. 18-29), run towards convergence
#: (a null ``admm_max_iter`` gives the copies' 100; a user's own budget still applies).
PAPER_COORDINATION = {"admm_coupling": "copies"}
#: The paper's formulation (eq. 24 margins of the latent GP variance, its cost, its coordination, no
#: offset estimate): reproduce's six methods.
PAPER_FORMULATION = {"pair_margin": "own", "margin_variance": "latent", "disturbance_drift": 0.0, **PAPER_COST,
                     **PAPER_COORDINATION}
#: Label of the package's sound formulation (the defaults) in reproduce's table.
SOUND_LABEL = "gp-chance (sound)"


def execute(task: Task) -> str:
    """Run ``task`` unless its rollout is cached; return the rollout path (worker entry point).

    With ``solver = fast`` the compiled kernels are loaded first (numba's cache, 0.5-1 s once per
    process), so that a run's timed closed loop (its ``wall_time_s``, the benchmark's compute per
    agent-step) holds the controller's work and not a process's one-off load."""
    from torch_gpmpc.coordination import kernels
    from torch_gpmpc.sim.closed_loop import simulate
    from torch_gpmpc.sim.scenarios import make_scenario

    if not task.path.exists():
        if task.cfg.solver == "fast":
            kernels.warm_up()
        # small problems: extra threads only add overhead. The caller's count comes back after (workers=1
        # runs here, and its solver keeps the caller's thread count: run_tasks plans under planning_threads)
        with torch_threads(1):
            cfg = task.cfg
            simulate(cfg, make_scenario(cfg, task.scenario_file or None)).save(task.path)
    return str(task.path)


def run_tasks(tasks: Sequence[Task], workers: int, on_done: Callable[[Task], None] | None = None) -> None:
    """Execute every task whose rollout is not cached, in ``workers`` processes.

    Args:
        tasks: the runs.
        workers: parallel processes (1: in this process).
        on_done: called after each computed task (e.g. a progress bar).
    """
    todo = [task for task in tasks if not task.path.exists()]
    if workers <= 1:
        from torch_gpmpc.control.solvers.ipm_threads import planning_threads

        with planning_threads():  # in this process the solver keeps the caller's threads (--threads)
            for task in todo:
                execute(task)
                if on_done is not None:
                    on_done(task)
        return
    from torch_gpmpc.coordination import kernels

    kernels.warm_up()  # compile the kernels once here, not in every worker
    ctx = multiprocessing.get_context("spawn")
    with cf.ProcessPoolExecutor(max_workers=workers, mp_context=ctx, initializer=end_with_parent,
                                initargs=(os.getpid(),)) as pool:
        futures = {pool.submit(execute, task): task for task in todo}
        for fut in cf.as_completed(futures):
            fut.result()
            if on_done is not None:
                on_done(futures[fut])


def end_with_parent(parent_pid: int) -> None:
    """Have the kernel stop this worker process when ``parent_pid``, the process that started it,
    dies (Linux: ``prctl(PR_SET_PDEATHSIG, SIGTERM)``; elsewhere nothing).

    Without it a ``gpmpc reproduce`` or ``gpmpc benchmark`` killed by a job scheduler or ``kill``
    (SIGTERM or SIGKILL: no Python cleanup runs) left each worker finishing its current run, minutes
    of both cores for a result nobody reads. Its rollout would have been written atomically, so
    nothing half-written remains either way; the next call resumes from the cache.
    """
    if not sys.platform.startswith("linux"):
        return
    import ctypes
    import signal

    libc = ctypes.CDLL(None, use_errno=True)
    pr_set_pdeathsig = 1
    libc.prctl(pr_set_pdeathsig, int(signal.SIGTERM), 0, 0, 0)
    if os.getppid() != parent_pid:  # it died before the request took effect
        os.kill(os.getpid(), signal.SIGTERM)


def summarize(rollouts: Sequence[Rollout]) -> dict[str, Any]:
    """Aggregate the metrics of several runs of one method (one table row).

    Returns:
        ``runs``, ``reached_fraction``, ``time_to_target_mean``/``_std`` (over runs that
        arrived; None if none did), ``arrived_fraction`` and ``arrival_step_max_mean``/``_std``
        (per-agent arrival: the last agent's first step within goal_tol of its own target),
        ``fallback_steps_total``, ``unsafe_plan_steps_total``, ``min_distance_mean``/``_worst``, ``violations_total``,
        ``runs_with_violations``, ``path_length_mean`` (over agents and runs),
        ``straight_line_length``, ``admm_iterations_mean``/``_max``, ``wall_time_s_mean``.
    """
    return summarize_metrics([compute_metrics(r) for r in rollouts])


def summarize_metrics(metrics: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """:func:`summarize` of runs whose ``metrics.json`` dicts are already computed (at least one)."""
    arrived = [m["time_to_target"] for m in metrics if m["time_to_target"] is not None]
    every = [m["arrival_step_max"] for m in metrics if m["arrival_step_max"] is not None]
    dists = [m["min_pair_distance"] for m in metrics if m["min_pair_distance"] is not None]
    return {
        "runs": len(metrics),
        "reached_fraction": float(np.mean([m["reached"] for m in metrics])),
        "time_to_target_mean": float(np.mean(arrived)) if arrived else None,
        "time_to_target_std": float(np.std(arrived)) if arrived else None,
        "arrived_fraction": len(every) / len(metrics),
        "arrival_step_max_mean": float(np.mean(every)) if every else None,
        "arrival_step_max_std": float(np.std(every)) if every else None,
        "fallback_steps_total": int(sum(m["fallback_steps"] or 0 for m in metrics)),
        "unsafe_plan_steps_total": int(sum(m["unsafe_plan_steps"] or 0 for m in metrics)),
        "min_distance_mean": float(np.mean(dists)) if dists else None,
        "min_distance_worst": float(np.min(dists)) if dists else None,
        "violations_total": int(sum(m["violations"] for m in metrics)),
        "runs_with_violations": int(sum(m["violations"] > 0 for m in metrics)),
        "path_length_mean": float(np.mean([np.mean(m["path_length"]) for m in metrics])),
        "straight_line_length": float(np.mean([np.mean(m["straight_line_length"]) for m in metrics])),
        "admm_iterations_mean": float(np.mean([m["admm_iterations_mean"] or 0.0 for m in metrics])),
        "admm_iterations_max": int(max(m["admm_iterations_max"] or 0 for m in metrics)),
        "wall_time_s_mean": float(np.mean([m["wall_time_s"] for m in metrics])),
    }


def mean_residual_profile(rollout: Rollout, first_step: int = 0) -> np.ndarray:
    """Primal residual per ADMM iteration averaged over the run's steps from ``first_step`` on,
    shape (I,)."""
    res = rollout.primal_residuals[first_step:]
    with np.errstate(invalid="ignore"):
        return np.nanmean(res, axis=0) if res.size else np.zeros(0)


