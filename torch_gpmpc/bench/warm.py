"""``gpmpc bench`` section ``local``, table ``warm_start``: the fast solver's warm active-set solves
(:mod:`~torch_gpmpc.control.solvers.ipm_active`, ``solver_warm = true``, the default) against its
cold interior point (``solver_warm = false``) on the local problems ADMM makes, in its order.

Per workload, one closed loop runs cold with every local solve recorded (the layer and its
:class:`~torch_gpmpc.control.problem.LocalProblemData`); the recorded calls are then replayed, in
order, through a cold and a warm copy of each layer (one thread, no gradient, as in the closed
loop), each warm call from the previous call's ``solver_point`` as ADMM passes it. Reported: ms per local problem of each, their ratio, the share of problems the warm path
solved (the rest it handed to the cold interior point), and the largest difference between the
two paths' plans and inputs (the bar: 1e-6). Then the same closed loop runs warm, and its planning
time and ADMM iterations are set beside the cold run's.
"""

from __future__ import annotations

import contextlib
import logging
import time

import torch

from torch_gpmpc.config.schema import Config
from torch_gpmpc.control.solvers import ipm_kernel
from torch_gpmpc.control.solvers.interior_point import InteriorPointMPC
from torch_gpmpc.coordination.agent_step import LocalStep
from torch_gpmpc.sim.closed_loop import simulate
from torch_gpmpc.threads import torch_threads

logger = logging.getLogger(__name__)

#: The README's quadrotor demo model (examples/quadrotor/quadrotor.toml): a 3D double integrator
#: with an input norm bound and a speed limit.
QUADROTOR = {
    "name": "quadrotor-like (bench)", "dt": 0.1,
    "A": [[1, 0, 0, 0.1, 0, 0], [0, 1, 0, 0, 0.1, 0], [0, 0, 1, 0, 0, 0.1],
          [0, 0, 0, 1, 0, 0], [0, 0, 0, 0, 1, 0], [0, 0, 0, 0, 0, 1]],
    "B": [[0.005, 0, 0], [0, 0.005, 0], [0, 0, 0.005], [0.1, 0, 0], [0, 0.1, 0], [0, 0, 0.1]],
    "position": [0, 1, 2], "residual": [3, 4, 5], "gp_inputs": ["x0", "x1"],
    "input_bound": {"norm": 2.0}, "state_bound": {"indices": [3, 4, 5], "norm": 1.5},
}

#: name -> (config, steps in quick mode); every run's other keys at their defaults.
WORKLOADS = {
    "paper (3 single integrators)": (Config(max_steps=60), 15),
    "circle of 6 double integrators": (Config(model="double-integrator", scenario="circle", num_agents=6,
                                              max_steps=60), 15),
    "quadrotor demo (4, speed limit)": (Config(model=QUADROTOR, scenario="circle", num_agents=4, noise_std=0.03,
                                               max_steps=40), 10),
}


@contextlib.contextmanager
def recording():
    """Record every local solve of the closed loops run inside: yields the list of ``(layer, data)``."""
    calls: list = []
    original = LocalStep.solve

    def solve(self, layer, data, guess=None):
        calls.append((layer, data))
        return original(self, layer, data, guess)

    LocalStep.solve = solve
    try:
        yield calls
    finally:
        LocalStep.solve = original


def replay(calls: list, warm_start: bool) -> tuple[float, list, int, int]:
    """The recorded calls through fresh copies of their layers: ``(seconds, solutions, problems
    solved warm, problems)``."""
    copies: dict[int, InteriorPointMPC] = {}
    points: dict[int, object] = {}
    seconds, solutions, warm, total = 0.0, [], 0, 0
    with torch.no_grad():
        for layer, data in calls:
            copy = copies.setdefault(id(layer), layer.with_warm_start(warm_start))
            start = time.perf_counter()
            solutions.append(copy(data, guess=points.get(id(layer))))
            seconds += time.perf_counter() - start
            points[id(layer)] = solutions[-1].solver_point
            warm += copy.last_warm_rows
            total += data.x0.shape[0]
    return seconds, solutions, warm, total


def measure(name: str, cfg: Config) -> dict:
    """One workload's row (see the module docstring)."""
    with recording() as calls:
        cold_run = simulate(cfg.replace(solver_warm=False))
    calls = [(layer, data) for layer, data in calls if isinstance(layer, InteriorPointMPC)]
    cold_s, cold, _, problems = replay(calls, False)
    warm_s, warm, solved_warm, _ = replay(calls, True)
    warm_run = simulate(cfg.replace(solver_warm=True))
    diff = max(max(float((a.X - b.X).abs().max()), float((a.U - b.U).abs().max())) for a, b in zip(cold, warm))
    row = {
        "workload": name, "steps": cold_run.num_steps, "local_problems": problems,
        "ms_per_problem_cold": 1e3 * cold_s / problems, "ms_per_problem_warm": 1e3 * warm_s / problems,
        "speedup": cold_s / warm_s, "warm_fraction": solved_warm / problems,
        "max_abs_plan_diff": diff,
        "same_acceptance": all(bool(torch.equal(a.ok, b.ok)) for a, b in zip(cold, warm)),
        "closed_loop_planning_s_cold": float(cold_run.step_time.sum()),
        "closed_loop_planning_s_warm": float(warm_run.step_time.sum()),
        "admm_iterations_cold": int(cold_run.admm_iterations.sum()),
        "admm_iterations_warm": int(warm_run.admm_iterations.sum()),
    }
    logger.info("warm start %s", row)
    return row


def run_warm_start(quick: bool = False) -> list[dict]:
    """Every workload of :data:`WORKLOADS` (``quick``: fewer steps), on one thread."""
    with torch_threads(1):
        ipm_kernel.warm_up()  # compile or load both kernels before anything is timed
        return [measure(name, cfg.replace(max_steps=steps) if quick else cfg)
                for name, (cfg, steps) in WORKLOADS.items()]
