"""``gpmpc bench`` section ``fast``: FastLocalMPC against the cvxpylayers paths (issue 7).

Paper size (D = 2, T = 13, M = 2 neighbours), the crossing instances of
:mod:`eval.bench_local`, batch 3 (one ADMM iteration of the paper scenario) and 64.
Paths, all measured in the same run on the same instances, forward and forward+backward
(backward of ``X.sum() + Y.sum()`` with respect to rho, z and bounds):

- ``fast``: :class:`~torch_gpmpc.fastmpc.FastLocalMPC` (batched interior point, tol 1e-10);
- ``cvxpylayers-default``: the :class:`~torch_gpmpc.mpc.LocalMPC` CvxpyLayer called with
  no solver arguments, i.e. cvxpylayers' default solver (diffcp + SCS, SCS defaults);
- ``cvxpylayers-clarabel``: ``LocalMPC(solver="clarabel")`` (diffcp + Clarabel).

``speedup_vs_default`` = cvxpylayers-default time / path time for the same batch and pass.
Timings use one torch thread (the benchmark machine is shared).
"""

from __future__ import annotations

import logging
import time
from pathlib import Path

import torch

from eval.bench_local import ALPHA, DIM, HORIZON, NEIGHBORS, U_MAX, crossing_instances
from torch_gpmpc.fastmpc import FastLocalMPC
from torch_gpmpc.mpc import LocalMPC, LocalProblemData
from torch_gpmpc.systems import NominalModel

logger = logging.getLogger(__name__)


def _with_grad(data: LocalProblemData) -> LocalProblemData:
    """Copy of ``data`` whose rho, z and bounds require gradients."""
    fields = dict(vars(data))
    for name in ("rho", "z_own", "z_nbr", "bounds"):
        fields[name] = fields[name].clone().requires_grad_(True)
    return LocalProblemData(**fields)


def _default_layer(mpc: LocalMPC):
    """Call ``mpc``'s CvxpyLayer with cvxpylayers' default solver arguments."""

    def solve(data: LocalProblemData):
        outputs = mpc.layer(*mpc.layer_parameters(data))
        return outputs[0], torch.stack(list(outputs[2:2 + NEIGHBORS]), dim=1)

    return solve


def _fast_layer(fast: FastLocalMPC):
    def solve(data: LocalProblemData):
        sol = fast(data)
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


def run(quick: bool = False, out: Path | str | None = None) -> dict:
    """Measure the paths; returns ``{"table": [...], ...}`` (JSON-ready).

    Args:
        quick: fewer repeats.
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
    fast = FastLocalMPC(HORIZON, DIM, NEIGHBORS, nominal, U_MAX, ALPHA)
    clarabel = LocalMPC(HORIZON, DIM, NEIGHBORS, nominal, U_MAX, ALPHA, solver="clarabel")
    paths = {
        "fast": (_fast_layer(fast), fast_repeats),
        "cvxpylayers-default": (_default_layer(clarabel), slow_repeats),
        "cvxpylayers-clarabel": (lambda d: (lambda s: (s.X, s.Y))(clarabel(d)), slow_repeats),
    }
    rows, checks = [], []
    for batch in (3, 64):
        data = crossing_instances(batch, seed=batch)
        with torch.no_grad():  # warm-up, and agreement of the fast plans with Clarabel's
            fast_sol, ref_sol = fast(data), clarabel(data)
        checks.append({"batch": batch, "fast_iterations": fast.last_iterations,
                       "fast_ok_fraction": float(fast_sol.ok.double().mean()),
                       "max_abs_dX_vs_clarabel": float((fast_sol.X - ref_sol.X).abs().max()),
                       "max_abs_dY_vs_clarabel": float((fast_sol.Y - ref_sol.Y).abs().max())})
        timings = {(name, backward): _time(solve, data, backward, repeats)
                   for name, (solve, repeats) in paths.items() for backward in (False, True)}
        for (name, backward), seconds in timings.items():
            rows.append({
                "workload": f"local T={HORIZON} D={DIM} M={NEIGHBORS}",
                "path": name,
                "batch": batch,
                "pass": "forward+backward" if backward else "forward",
                "ms_per_problem": 1e3 * seconds / batch,
                "speedup_vs_default": timings[("cvxpylayers-default", backward)] / seconds,
            })
            logger.info("fast bench %s", rows[-1])
    return {
        "table": rows,
        "checks": checks,
        "notes": (f"best of {fast_repeats} (fast) / {slow_repeats} (cvxpylayers) repeats, one torch thread; "
                  "cvxpylayers-default = diffcp + SCS with default settings"),
    }
