"""``gpmpc bench`` section ``local``: time per agent-local MPC problem.

Paper size (D = 2, T = 13, M = 2 neighbours), realistic crossing instances, batch 3 (one
ADMM iteration of the paper scenario) and 64. Paths, all measured in the same run on the
same instances, forward and forward+backward (backward of ``X.sum() + Y.sum()`` with
respect to rho, z and bounds):

- ``fast``: the default, :class:`~torch_gpmpc.control.solvers.interior_point.InteriorPointMPC` (compiled interior
  point per problem, implicit-KKT backward, tol 1e-10);
- ``cvxpylayers-default``: the :class:`~torch_gpmpc.control.solvers.conic.CvxpyLayerMPC` CvxpyLayer called with
  no solver arguments, i.e. cvxpylayers' default solver (diffcp + SCS at SCS's default
  tolerances; plans ~1e-3 accurate) and diffcp's default backward;
- ``reference``: ``solver=reference``, the same default solver tightened to eps 1e-9;
- ``clarabel``: ``solver=clarabel`` (diffcp + Clarabel, tol 1e-12);
- ``cvxpy+clarabel``: the same DPP problem solved by plain cvxpy with Clarabel, one
  problem after another (forward only, not differentiable).

``speedup_vs_default`` = cvxpylayers-default time / path time (the issue's ratio: at
least 20x forward and 10x forward+backward for ``fast`` at batch 64);
``speedup_vs_reference`` = reference time / path time. ``checks`` compares the fast
path's plans and gradients with the reference and clarabel paths on the same instances.
Timings use one torch thread.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import Callable

import cvxpy as cp
import torch

from torch_gpmpc.control.solvers.interior_point import InteriorPointMPC
from torch_gpmpc.control.examples import crossing_instance
from torch_gpmpc.control.problem import LocalProblemData
from torch_gpmpc.control.solvers.conic import CvxpyLayerMPC
from torch_gpmpc.dynamics.systems import NominalModel

logger = logging.getLogger(__name__)

HORIZON, DIM, NEIGHBORS = 13, 2, 2
U_MAX, ALPHA, R_SAFE, RHO, EPS = 2.0, 1e-3, 0.5, 20.0, 0.1
#: Latent GP variance used for the chance margins of the synthetic instances.
SYNTHETIC_VAR = 0.01


def crossing_instances(batch: int, seed: int = 0) -> LocalProblemData:
    """``batch`` agents mid-way through the paper's crossing, each with 2 neighbours.

    Agent and neighbours start on a circle of radius 1.2 and head through the centre
    at 0.15 per step (references at 0.2); dynamics are the vortex wind linearized along
    these lines (``nonlinear``), margins use a constant variance ``SYNTHETIC_VAR`` and the
    paper's risk 0.05 per agent (:func:`~torch_gpmpc.control.examples.crossing_instance`).

    Returns:
        Problem data with B = ``batch``, shapes as in :class:`LocalProblemData`.
    """
    inst = crossing_instance(batch, NEIGHBORS, horizon=HORIZON, radius=1.2, speed=0.15, ref_speed=0.2, spread=0.3,
                             method="nonlinear", variance=SYNTHETIC_VAR, seed=seed)
    return inst.problem_data(rho=RHO, eps=EPS, r_safe=R_SAFE)


def _with_grad(data: LocalProblemData) -> LocalProblemData:
    """Copy of ``data`` whose rho, z and bounds require gradients."""
    fields = dict(vars(data))
    for name in ("rho", "z_own", "z_nbr", "bounds"):
        fields[name] = fields[name].clone().requires_grad_(True)
    return LocalProblemData(**fields)


#: Batch sizes: one ADMM iteration of the paper scenario, and a large batch.
BATCHES = (3, 64)
#: The issue-7 targets: ``fast`` at batch 64 against cvxpylayers' default path.
TARGETS = {"forward": 20.0, "forward+backward": 10.0}


def _solve_default(mpc: CvxpyLayerMPC, data: LocalProblemData) -> tuple[torch.Tensor, torch.Tensor]:
    """cvxpylayers' default path: the layer called with no solver arguments; returns (X, Y)."""
    outputs = mpc.layer(*mpc.layer_parameters(data))
    return outputs[0], torch.stack(list(outputs[2:2 + NEIGHBORS]), dim=1)


def _solve_layer(layer) -> Callable[[LocalProblemData], tuple[torch.Tensor, torch.Tensor]]:
    """A layer's ``(X, Y)`` as a function of the data."""
    def solve(data: LocalProblemData) -> tuple[torch.Tensor, torch.Tensor]:
        sol = layer(data)
        return sol.X, sol.Y

    return solve


def _time(solve, data: LocalProblemData, backward: bool, repeats: int) -> float:
    """Best-of-``repeats`` seconds per batch."""
    best = float("inf")
    for _ in range(repeats):
        inputs = _with_grad(data) if backward else data
        start = time.perf_counter()
        if backward:
            X, Y = solve(inputs)
            (X.sum() + Y.sum()).backward()
        else:
            with torch.no_grad():
                solve(inputs)
        best = min(best, time.perf_counter() - start)
    return best


def _time_plain_cvxpy(mpc: CvxpyLayerMPC, data: LocalProblemData, repeats: int) -> float:
    """Best-of-``repeats`` seconds to solve the batch with plain cvxpy + Clarabel in a loop."""
    values = [p.detach().numpy() for p in mpc.layer_parameters(data)]
    best = float("inf")
    for _ in range(repeats):
        start = time.perf_counter()
        for b in range(data.x0.shape[0]):
            for param, value in zip(mpc.cvxpy_parameters, values):
                param.value = value[b]
            mpc.problem.solve(solver=cp.CLARABEL)
        best = min(best, time.perf_counter() - start)
    return best


def _plans_and_grads(solve, data: LocalProblemData) -> tuple[torch.Tensor, list[torch.Tensor]]:
    """Plans ``[X | Y]`` flattened per problem, and the gradients of ``X.sum() + Y.sum()``
    with respect to rho, z_own, z_nbr and bounds."""
    inputs = _with_grad(data)
    X, Y = solve(inputs)
    (X.sum() + Y.sum()).backward()
    plans = torch.cat([X.detach().flatten(1), Y.detach().flatten(1)], dim=1)
    return plans, [inputs.rho.grad, inputs.z_own.grad, inputs.z_nbr.grad, inputs.bounds.grad]


def _compare(fast, other) -> dict:
    """Largest plan difference and largest relative gradient difference (per input)."""
    (p_fast, g_fast), (p_other, g_other) = fast, other
    rel = max(float((a - b).norm() / b.norm().clamp_min(1e-12)) for a, b in zip(g_fast, g_other))
    return {"max_abs_plan_diff": float((p_fast - p_other).abs().max()), "max_rel_grad_diff": rel}


def run(quick: bool = False, out: Path | str | None = None) -> dict:
    """Measure the paths; returns ``{"table": [...], "checks": [...], "targets": {...}}`` (JSON-ready).

    Args:
        quick: fewer repeats, and the slow ``reference`` path only at batch 3.
        out: output directory (unused: the caller writes ``bench.json``).
    """
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        return _run(quick)
    finally:
        torch.set_num_threads(threads)


def _run(quick: bool) -> dict:
    fast_repeats, slow_repeats = (3, 1) if quick else (10, 2)
    nominal = NominalModel(DIM)
    fast = InteriorPointMPC(HORIZON, DIM, NEIGHBORS, nominal, U_MAX, ALPHA)
    layers = {name: CvxpyLayerMPC(HORIZON, DIM, NEIGHBORS, nominal, U_MAX, ALPHA, solver=name)
              for name in ("clarabel", "reference")}
    rows, checks = [], []
    for batch in BATCHES:
        data = crossing_instances(batch, seed=batch)
        paths = {
            "fast": (_solve_layer(fast), fast_repeats),
            "cvxpylayers-default": (lambda d: _solve_default(layers["clarabel"], d), slow_repeats),
            "clarabel": (_solve_layer(layers["clarabel"]), slow_repeats),
        }
        if not quick or batch <= 3:
            paths["reference"] = (_solve_layer(layers["reference"]), 1)
        # warm-up (first calls pay one-off costs) and the accuracy checks on the same instances
        answers = {name: _plans_and_grads(paths[name][0], data) for name in ("fast", "clarabel", "reference")
                   if name in paths}
        check = {"batch": batch, "fast_ok_fraction": float(fast(data).ok.double().mean()),
                 "fast_vs_clarabel": _compare(answers["fast"], answers["clarabel"])}
        if "reference" in answers:
            check["fast_vs_reference"] = _compare(answers["fast"], answers["reference"])
        checks.append(check)
        timings = {(name, backward): _time(solve, data, backward, repeats)
                   for name, (solve, repeats) in paths.items() for backward in (False, True)}
        timings[("cvxpy+clarabel", False)] = _time_plain_cvxpy(layers["clarabel"], data, slow_repeats)
        for (name, backward), seconds in sorted(timings.items(), key=lambda kv: kv[0][1]):
            reference = timings.get(("reference", backward))
            rows.append({
                "workload": f"local T={HORIZON} D={DIM} M={NEIGHBORS}",
                "path": name,
                "batch": batch,
                "pass": "forward+backward" if backward else "forward",
                "ms_per_problem": 1e3 * seconds / batch,
                "speedup_vs_default": timings[("cvxpylayers-default", backward)] / seconds,
                "speedup_vs_reference": None if reference is None else reference / seconds,
            })
            logger.info("local bench %s", rows[-1])
    return {"table": rows, "checks": checks, "targets": _targets(rows),
            "notes": f"best of {fast_repeats} (fast) / {slow_repeats} (cvxpylayers) repeats, one torch thread; "
                     "cvxpylayers-default = diffcp + SCS with default settings; reference = the same at eps 1e-9"}


def _targets(rows: list[dict]) -> dict:
    """Each target with the measured ratio (at the largest batch) and whether it is met."""
    batch = max(BATCHES)
    result = {}
    for pass_name, target in TARGETS.items():
        row = next(r for r in rows if r["path"] == "fast" and r["batch"] == batch and r["pass"] == pass_name)
        result[f"fast_batch{batch}_{pass_name}"] = {"speedup_vs_default": row["speedup_vs_default"],
                                                    "target": target, "met": row["speedup_vs_default"] >= target}
    return result
