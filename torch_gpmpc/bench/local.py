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

``fast`` is timed cold (``warm_start=False``): each timing solves the same problems again, which
a warm start would answer from their own solutions. ``warm_start`` times the warm path where it
applies, on the sequences of problems ADMM makes (:mod:`~torch_gpmpc.bench.warm`).

``families``: every constraint family of the local problem (input norm, input box, both, state
box, state norm, state rows, workspace, half-spaces, all at once) on a 3D double integrator,
``fast`` against cvxpylayers' default solver on the same problems (:func:`run_families`).

``speedup_vs_default`` = cvxpylayers-default time / path time (the issue's ratio: at
least 20x forward and 10x forward+backward for ``fast`` at batch 64);
``speedup_vs_reference`` = reference time / path time. ``checks`` compares the fast
path's plans and gradients with the reference and clarabel paths on the same instances.
Timings use one torch thread.
"""

from __future__ import annotations

import logging
import os
import time
from pathlib import Path
from typing import Callable

import cvxpy as cp
import torch

from torch_gpmpc.bench.warm import run_warm_start
from torch_gpmpc.control.solvers.interior_point import InteriorPointMPC
from torch_gpmpc.control.examples import crossing_instance
from torch_gpmpc.control.problem import LocalProblemData
from torch_gpmpc.control.solvers.conic import CvxpyLayerMPC
from torch_gpmpc.dynamics.systems import NominalModel
from torch_gpmpc.threads import torch_threads

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
    with torch_threads(1):
        result = _run(quick)
    result["families"] = run_families(quick)
    result["threads"] = run_threads(quick)
    result["warm_start"] = run_warm_start(quick)
    return result


def _run(quick: bool) -> dict:
    fast_repeats, slow_repeats = (3, 1) if quick else (10, 2)
    nominal = NominalModel(DIM)
    fast = InteriorPointMPC(HORIZON, DIM, NEIGHBORS, nominal, U_MAX, ALPHA, warm_start=False)
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


# ------------------------------------------------------------------ constraint families
#: The constraint families of the local problem, timed one by one (and all together) on a 3D
#: double integrator (the random-transition benchmark's body): fast vs cvxpylayers' default.
FAMILIES = ("input-norm", "input-box", "input-norm-and-box", "state-box", "state-norm", "state-rows",
            "workspace", "halfspaces", "all")
#: Timed beside the families but outside their target: every family at once under a ceiling no
#: climb can stop below, so every problem must open its state slack (an infeasible start's
#: exact-penalty path, which takes several times the Newton steps).
STRESS_FAMILIES = ("all-ceiling-out-of-reach",)
FAMILY_TARGET = 20.0
_HALFSPACES = 2
#: Height of the half-space ceiling: where a climb of 0.4-0.6 m/s can stop under the vertical
#: acceleration bound of 1.25 (a feasible problem), and where none can.
_CEILING, _CEILING_OUT_OF_REACH = 0.25, 0.05


def family_problem(family: str, batch: int, seed: int = 0):
    """``(nominal, constraints, data)``: B 3D double integrators crossing the origin past two
    neighbours, climbing from height 0 (references at speed 1.2 across, 0.4-0.6 up), with the
    family's bounds set where they bind, every start inside them and every problem feasible
    (acceleration box, speed 1.1, per-axis speed 0.9, a workspace with a ceiling at 0.3, a face
    across the path and a ceiling at 0.25, which every climb can stop below: no state slack opens,
    ``checks`` records ``state_slack_max``). ``all`` is every family at once;
    ``all-ceiling-out-of-reach`` is ``all`` with the ceiling at 0.05, infeasible for every problem
    (:data:`STRESS_FAMILIES`)."""
    from torch_gpmpc.config.model_spec import double_integrator, parse_model
    from torch_gpmpc.config.workspace import Workspace
    from torch_gpmpc.control.constraints import LocalConstraints

    T, n = HORIZON, 6
    g = torch.Generator().manual_seed(seed)
    table = double_integrator(3, 0.1, 2.0).to_table()
    fams = FAMILIES[1:-1] if family in ("all",) + STRESS_FAMILIES else (family,)
    if "input-box" in fams or "input-norm-and-box" in fams:
        table["input_bound"] = {"box": [1.5, 1.5, 1.25]}
        if "input-norm-and-box" in fams:
            table["input_bound"]["norm"] = 2.0
    if "state-box" in fams:
        table["state_box"] = {"indices": [3, 4, 5], "lower": [-0.9, -0.9, -0.5], "upper": [0.9, 0.9, 0.5]}
    if "state-norm" in fams:
        table["state_bound"] = {"indices": [3, 4, 5], "norm": 1.1}
    if "state-rows" in fams:
        table["state_rows"] = {"G": [[0.0, 0.0, 0.0, 1.0, 1.0, 0.0]], "h": [1.2]}
    spec = parse_model(table, f"bench-{family}")
    workspace = Workspace((-1.25, -1.25, -0.3), (1.25, 1.25, 0.3)) if "workspace" in fams else None
    nominal = NominalModel(spec)
    angle = 2 * torch.pi * torch.rand(batch, generator=g, dtype=torch.float64)
    climb = 0.4 + 0.2 * torch.rand(batch, generator=g, dtype=torch.float64)
    heading = torch.stack([torch.cos(angle), torch.sin(angle), climb], 1)
    start = -1.2 * heading * torch.tensor([1.0, 1.0, 0.0], dtype=torch.float64)  # at height 0, climbing
    steps = torch.arange(T + 1, dtype=torch.float64)[None, :, None] * 0.1
    path = start[:, None] + 1.2 * steps * heading[:, None]
    xref = torch.cat([path, 1.2 * heading[:, None].expand(batch, T + 1, 3)], -1)
    x0 = torch.cat([start, heading], -1)
    dyn_A = nominal.A()[None, None].expand(batch, T, n, n).clone() \
        + 0.005 * torch.randn(batch, T, n, n, generator=g, dtype=torch.float64)
    dyn_c = 0.002 * torch.randn(batch, T, n, generator=g, dtype=torch.float64)
    normals = torch.zeros(batch, NEIGHBORS, T, n, dtype=torch.float64)
    z_nbr = torch.zeros(batch, NEIGHBORS, T + 1, n, dtype=torch.float64)
    for j in range(NEIGHBORS):
        side = torch.stack([-heading[:, 1], heading[:, 0], torch.zeros(batch, dtype=torch.float64)], 1) * (2 * j - 1)
        z_nbr[:, j, :, :3] = path + 0.3 * side[:, None]
        normals[:, j, :, :3] = -side[:, None]
    z_own = xref[:, None].expand(batch, NEIGHBORS, T + 1, n).clone()
    half_n = torch.zeros(batch, _HALFSPACES, T, n, dtype=torch.float64)
    half_b = -torch.ones(batch, _HALFSPACES, T, dtype=torch.float64)
    if "halfspaces" in fams:  # a face across the path (stay before it) and a ceiling at 0.15
        half_n[:, 0, :, :2] = -heading[:, None, :2]
        half_b[:, 0] = -0.2
        half_n[:, 1, :, 2] = -1.0
        half_b[:, 1] = -(_CEILING_OUT_OF_REACH if family in STRESS_FAMILIES else _CEILING)
    data = LocalProblemData(
        x0=x0, xref=xref, dyn_A=dyn_A, dyn_c=dyn_c, normals=normals,
        bounds=torch.full((batch, NEIGHBORS, T), 0.4, dtype=torch.float64),
        active=torch.ones(batch, NEIGHBORS, dtype=torch.bool), rho=torch.tensor(RHO, dtype=torch.float64),
        z_own=z_own, z_nbr=z_nbr, lam_own=torch.zeros_like(z_own), lam_nbr=torch.zeros_like(z_own),
        halfspace_normals=half_n, halfspace_bounds=half_b)
    return nominal, LocalConstraints.of(spec, workspace=workspace), data


def run_families(quick: bool = False) -> dict:
    """Each constraint family: ms per problem of ``fast`` (on one thread, and on every core) and of
    cvxpylayers' default solver (diffcp + SCS, default settings: its batch already runs on a
    thread per core) on the same problems, batch 3 and 64, forward and forward+backward; ``met``
    (``met_all_cores``) when every ratio of one thread (every core) is >= :data:`FAMILY_TARGET`.
    The rows of :data:`STRESS_FAMILIES` (``in_target`` false) are timed alike and left out of it."""
    threads, cores = torch.get_num_threads(), available_cores()
    torch.set_num_threads(1)
    try:
        rows, checks = [], []
        for family in FAMILIES + STRESS_FAMILIES:
            nominal, constraints, _ = family_problem(family, 1)
            args = (HORIZON, 6, NEIGHBORS, nominal, None, ALPHA)
            fast = InteriorPointMPC(*args, constraints=constraints, num_halfspaces=_HALFSPACES, warm_start=False)
            layer = CvxpyLayerMPC(*args, solver="clarabel", constraints=constraints, num_halfspaces=_HALFSPACES)
            default = lambda d, layer=layer: _solve_default(layer, d)  # noqa: E731
            for batch in BATCHES:
                data = family_problem(family, batch, seed=batch)[2]
                sol = fast(data)
                ref = layer(data)
                checks.append({"family": family, "batch": batch, "fast_ok_fraction": float(sol.ok.double().mean()),
                               "max_abs_plan_diff_vs_clarabel": float((sol.X - ref.X).abs().max()),
                               "state_slack_max": float(sol.state_slack.max())})
                for backward in (False, True):
                    t_fast, t_cores, t_default = _interleaved_times(fast, default, data, backward, cores, quick)
                    rows.append({"family": family, "batch": batch, "in_target": family in FAMILIES,
                                 "pass": "forward+backward" if backward else "forward",
                                 "fast_ms_per_problem": 1e3 * t_fast / batch,
                                 "default_ms_per_problem": 1e3 * t_default / batch,
                                 "speedup_vs_default": t_default / t_fast,
                                 "fast_all_cores_ms_per_problem": 1e3 * t_cores / batch,
                                 "speedup_all_cores_vs_default": t_default / t_cores})
                    logger.info("local families %s", rows[-1])
        worst = min(r["speedup_vs_default"] for r in rows if r["in_target"])
        worst_cores = min(r["speedup_all_cores_vs_default"] for r in rows if r["in_target"])
        return {"table": rows, "checks": checks, "cores": cores,
                "target": {"speedup_vs_default_min": worst, "target": FAMILY_TARGET, "met": worst >= FAMILY_TARGET,
                           "speedup_all_cores_vs_default_min": worst_cores,
                           "met_all_cores": worst_cores >= FAMILY_TARGET},
                "notes": "3D double integrator, T = 13, M = 2; best over interleaved rounds (each: fast best of "
                         "2-3 on one thread and on every core, the solver splitting batches of 8 or more, then "
                         "cvxpylayers default once: diffcp + SCS, whose batch runs on a thread pool of every "
                         "core), 2 rounds quick, 3 full"}
    finally:
        torch.set_num_threads(threads)


def _interleaved_times(fast, default, data: LocalProblemData, backward: bool, cores: int,
                       quick: bool) -> tuple[float, float, float]:
    """Best seconds per batch of ``fast`` on one thread, ``fast`` on ``cores`` threads and ``default``,
    each the best over rounds that time all three in turn: a slow spell of the machine (this
    project's 2 cores are shared) then costs every path alike instead of whichever ran through it."""
    best = [float("inf")] * 3
    for _ in range(2 if quick else 3):
        best[0] = min(best[0], _time(_solve_layer(fast), data, backward, 2 if quick else 3))
        torch.set_num_threads(cores)
        best[1] = min(best[1], _time(_solve_layer(fast), data, backward, 2 if quick else 3))
        torch.set_num_threads(1)
        best[2] = min(best[2], _time(default, data, backward, 1))
    return best[0], best[1], best[2]


# ------------------------------------------------------------------ threads
#: Batches of the threads comparison: a 64-problem batch and a 100-agent team's.
THREAD_BATCHES = (64, 100)


def available_cores() -> int:
    """Cores this process may run on."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


def run_threads(quick: bool = False) -> dict:
    """``fast`` on one thread and on every core (:mod:`~torch_gpmpc.control.solvers.ipm_threads`),
    same problems (the ``all`` family and the 2D crossing), forward and forward+backward; the
    plans must be the same bits."""
    threads, cores = torch.get_num_threads(), available_cores()
    nominal, constraints, _ = family_problem("all", 1)
    layers = {"all": InteriorPointMPC(HORIZON, 6, NEIGHBORS, nominal, None, ALPHA, constraints=constraints,
                                      num_halfspaces=_HALFSPACES, warm_start=False),
              "crossing": InteriorPointMPC(HORIZON, DIM, NEIGHBORS, NominalModel(DIM), U_MAX, ALPHA, warm_start=False)}
    rows = []
    try:
        for name, layer in layers.items():
            for batch in THREAD_BATCHES[:1] if quick else THREAD_BATCHES:
                data = family_problem("all", batch, seed=batch)[2] if name == "all" else \
                    crossing_instances(batch, seed=batch)
                plans = {}
                for n in sorted({1, cores}):
                    torch.set_num_threads(n)
                    with torch.no_grad():
                        plans[n] = layer(data).X
                for backward in (False, True):
                    seconds = {}
                    for n in sorted({1, cores}):
                        torch.set_num_threads(n)
                        seconds[n] = _time(_solve_layer(layer), data, backward, 2 if quick else 5)
                    rows.append({"workload": f"fast, {name}", "batch": batch,
                                 "pass": "forward+backward" if backward else "forward", "threads": cores,
                                 "ms_per_problem_1_thread": 1e3 * seconds[1] / batch,
                                 "ms_per_problem": 1e3 * seconds[cores] / batch,
                                 "speedup_vs_one_thread": seconds[1] / seconds[cores],
                                 "same_plans": bool(torch.equal(plans[1], plans[cores]))})
                    logger.info("local threads %s", rows[-1])
    finally:
        torch.set_num_threads(threads)
    return {"table": rows, "cores": cores}
