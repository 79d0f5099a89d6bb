"""``gpmpc bench`` section ``run``: the paper scenario end to end, and where its time goes.

Two measurements of the main job (paper scenario, proposed method ``gp-chance``, seed 0,
default config):

1. ``gpmpc run --out DIR/run`` as a child process, timed from outside: the wall time a
   user sees (imports, GP fitting, closed loop, rollout, figures, TensorBoard).
2. The same closed loop in this process with timers wrapped around its parts:
   GP fitting; the linearization (GP mean, Jacobian and variance; once per step with the
   default ``relinearize=false``, every iteration otherwise); per ADMM iteration the rest of
   the problem assembly (normals, margins, consensus slots), the local
   solve (split into canonicalization, the compiled kernels (the warm active-set solves and the
   cold interior point for what they leave) and the rest of the layer:
   acceptance check, outputs) and the consensus/dual update, for the iterations through the torch
   path (each step's first two and last, :meth:`~torch_gpmpc.coordination.admm.ADMM.iterate`); the
   compiled iterations between them (:mod:`~torch_gpmpc.coordination.steady`) split into their
   kernel calls and the rest (consensus terms, acceptance check, consensus and penalty updates);
   "ADMM other" is the rest of each step's ADMM (safety check, fallback, bookkeeping) and "loop
   other" the rest of each closed-loop step (graph, true system, recording, logging).

The closed loop needs no backward pass (gradients are only used by ``gpmpc tune``);
the ``local`` section times forward+backward.
"""

from __future__ import annotations

import contextlib
import os
import pkgutil
import subprocess
import sys
import time
from pathlib import Path

import torch

#: (module, attribute, label) of the functions timed inside the closed loop.
TIMED = (
    ("torch_gpmpc.gp.fit", "fit_agent_gps", "gp_fit"),
    ("torch_gpmpc.coordination.admm.ADMM", "solve_step", "admm_step"),
    ("torch_gpmpc.coordination.agent_step.LocalStep", "assemble", "assembly"),
    ("torch_gpmpc.coordination.agent_step", "linearize_plan", "linearize"),
    ("torch_gpmpc.coordination.agent_step.LocalStep", "solve", "solve"),
    ("torch_gpmpc.control.solvers.interior_point", "canonicalize", "canonicalize"),
    ("torch_gpmpc.control.solvers.ipm_kernel", "solve_polish_batch", "kernel"),
    ("torch_gpmpc.control.solvers.ipm_active", "solve_batch", "kernel_warm"),
    ("torch_gpmpc.coordination.admm", "copies_update", "consensus"),
    ("torch_gpmpc.coordination.admm", "plane_iteration", "consensus"),
    ("torch_gpmpc.coordination.steady.SteadyIterations", "iterate", "compiled"),
    ("torch_gpmpc.coordination.planes.PlaneIterations", "iterate", "compiled"),
)
#: Labels whose time inside a compiled iteration is booked as ``<label>@compiled``.
KERNEL_LABELS = ("kernel", "kernel_warm")


@contextlib.contextmanager
def _timers():
    """Wrap every :data:`TIMED` function with a timer; yields ``{label: [seconds, calls]}``."""
    totals: dict[str, list] = {label: [0.0, 0] for *_, label in TIMED}  # a label may time several functions
    totals.update({f"{label}@compiled": [0.0, 0] for label in KERNEL_LABELS})
    inside: list[str] = []  # the timed calls under way

    def wrap(fn, label):
        def timed(*args, **kwargs):
            key = f"{label}@compiled" if label in KERNEL_LABELS and "compiled" in inside else label
            inside.append(label)
            start = time.perf_counter()
            try:
                return fn(*args, **kwargs)
            finally:
                totals[key][0] += time.perf_counter() - start
                totals[key][1] += 1
                inside.pop()
        return timed

    saved = []

    for owner_path, attr, label in TIMED:
        owner = pkgutil.resolve_name(owner_path)
        original = owner.__dict__[attr] if isinstance(owner, type) else getattr(owner, attr)
        saved.append((owner, attr, original))
        setattr(owner, attr, wrap(original, label))
    try:
        yield totals
    finally:
        for owner, attr, original in reversed(saved):
            setattr(owner, attr, original)


def _command_wall(out: Path) -> float:
    """Seconds of ``gpmpc run --out out`` in a child process (the README's main job)."""
    start = time.perf_counter()
    subprocess.run([sys.executable, "-m", "torch_gpmpc.cli.entry", "run", "--out", str(out)], check=True,
                   stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env={**os.environ, "OMP_NUM_THREADS": "1"})
    return time.perf_counter() - start


def run(quick: bool = False, out: Path | str | None = None) -> dict:
    """Time the main job and break its closed loop down; returns the table (JSON-ready).

    Args:
        quick: 10 closed-loop steps and no child-process run (CI smoke).
        out: output directory of the bench (the child run writes to ``out/run``).
    """
    from torch_gpmpc.config.schema import Config
    from torch_gpmpc.coordination import kernels
    from torch_gpmpc.sim.closed_loop import simulate

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        kernels.warm_up()  # compile or load the kernels before timing (a one-off per installation)
        result: dict = {}
        if not quick and out is not None:
            result["gpmpc_run_wall_s"] = _command_wall(Path(out) / "run")
        cfg = Config(max_steps=10) if quick else Config()
        with _timers() as totals:
            start = time.perf_counter()
            rollout = simulate(cfg)
            total = time.perf_counter() - start
    finally:
        torch.set_num_threads(threads)
    seconds = {label: t for label, (t, _) in totals.items()}
    iterations = int(rollout.admm_iterations.sum())
    loop = total - seconds["gp_fit"]
    parts = {
        "linearize": seconds["linearize"],
        "assembly other": seconds["assembly"] - seconds["linearize"],
        "solve: canonicalize": seconds["canonicalize"],
        "solve: kernel (warm active set)": seconds["kernel_warm"],
        "solve: kernel (cold interior point)": seconds["kernel"],
        "solve: layer other": seconds["solve"] - seconds["canonicalize"] - seconds["kernel"] - seconds["kernel_warm"],
        "consensus": seconds["consensus"],
        "compiled iterations: kernel": seconds["kernel@compiled"] + seconds["kernel_warm@compiled"],
        "compiled iterations: other": seconds["compiled"] - seconds["kernel@compiled"] - seconds["kernel_warm@compiled"],
        "ADMM other": seconds["admm_step"] - seconds["assembly"] - seconds["solve"] - seconds["consensus"]
        - seconds["compiled"],
        "loop other": loop - seconds["admm_step"],
    }
    table = [{"workload": "gp-chance seed 0", "part": "GP fit (3 agents)", "total_s": seconds["gp_fit"],
              "ms_per_step": None, "ms_per_admm_iteration": None, "share_of_loop": None}]
    for name, value in parts.items():
        table.append({"workload": "gp-chance seed 0", "part": name, "total_s": value,
                      "ms_per_step": 1e3 * value / rollout.num_steps,
                      "ms_per_admm_iteration": 1e3 * value / iterations, "share_of_loop": value / loop})
    table.append({"workload": "gp-chance seed 0", "part": "closed loop", "total_s": loop,
                  "ms_per_step": 1e3 * loop / rollout.num_steps, "ms_per_admm_iteration": 1e3 * loop / iterations,
                  "share_of_loop": 1.0})
    result.update({"table": table, "steps": rollout.num_steps, "admm_iterations": iterations,
                   "calls": {label: count for label, (_, count) in totals.items()},
                   "notes": "in-process closed loop with timers; gpmpc_run_wall_s is the whole command"})
    result["models"] = _model_workloads(quick, 1e3 * loop / iterations)
    return result


def _model_workloads(quick: bool, paper_ms_per_iteration: float) -> list[dict]:
    """The closed loop with the double integrator (3D, four agents on a circle, noiseless): time
    per ADMM iteration against the paper workload's (the local problems have 6 states, 3 inputs)."""
    from torch_gpmpc.config.schema import Config
    from torch_gpmpc.dynamics.systems import system_from_config
    from torch_gpmpc.gp.fit import fit_agent_gps
    from torch_gpmpc.sim.closed_loop import simulate

    cfg = Config(model="double-integrator", dim=3, scenario="circle", num_agents=4, noise_std=0.0,
                 max_steps=10 if quick else 150)
    gps = fit_agent_gps(cfg, system_from_config(cfg), cfg.num_agents)
    start = time.perf_counter()
    rollout = simulate(cfg, gps=gps)
    wall = time.perf_counter() - start
    iterations = int(rollout.admm_iterations.sum())
    ms = 1e3 * wall / max(iterations, 1)
    return [{"workload": "double-integrator 3D, circle of 4, noiseless (closed loop)", "steps": rollout.num_steps,
             "admm_iterations_per_step": iterations / max(rollout.num_steps, 1), "wall_s": wall,
             "ms_per_admm_iteration": ms, "ratio_to_paper_per_iteration": ms / paper_ms_per_iteration}]
