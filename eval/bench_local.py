"""``gpmpc bench`` section ``local``: time per agent-local MPC problem (design.md section 6).

Paper size (D = 2, T = 13, M = 2 neighbours), realistic crossing instances, batch 1, 3
and 32 (8 with ``quick``). Paths, all measured in the same run on the same instances:

- ``clarabel``: our default, :class:`~torch_gpmpc.mpc.LocalMPC` (cvxpylayers + diffcp
  with Clarabel), forward and forward+backward;
- ``reference``: the same layer with cvxpylayers' default solver (diffcp + SCS);
- ``reference-scs-default-eps``: the same, at SCS's default tolerances 1e-4 (faster,
  plans only accurate to ~1e-3);
- ``cvxpy+clarabel``: the same DPP problem solved by plain cvxpy with Clarabel, one
  problem after another (forward only, not differentiable).

``speedup_vs_reference`` = reference time / path time for the same batch and pass.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path

import cvxpy as cp
import torch

from torch_gpmpc.linearize import linearize_plan
from torch_gpmpc.mpc import LocalMPC, LocalProblemData, collision_rows
from torch_gpmpc.risk import chance_margins, collision_normals, pair_risks, state_covariances
from torch_gpmpc.systems import NominalModel, VortexWind

logger = logging.getLogger(__name__)

HORIZON, DIM, NEIGHBORS = 13, 2, 2
U_MAX, ALPHA, R_SAFE, RHO, EPS = 2.0, 1e-3, 0.5, 20.0, 0.1
#: Latent GP variance used for the chance margins of the synthetic instances.
SYNTHETIC_VAR = 0.01


def crossing_instances(batch: int, seed: int = 0) -> LocalProblemData:
    """``batch`` agents mid-way through the paper's crossing, each with 2 neighbours.

    Agent and neighbours start on a circle of radius 1.2 and head through the centre
    at 0.15 per step (references at 0.2); linearization points are these straight
    lines, dynamics are the vortex wind linearized along them (``nonlinear``), margins
    use a constant variance ``SYNTHETIC_VAR`` and the paper's risk 0.05 per agent.
    Consensus variables are the straight lines plus 0.02 noise, multipliers 0.1 noise.

    Returns:
        Problem data with B = ``batch``, shapes as in :class:`LocalProblemData`.
    """
    g = torch.Generator().manual_seed(seed)
    T, D, M = HORIZON, DIM, NEIGHBORS
    steps = torch.arange(T + 1, dtype=torch.float64)[:, None]

    def lines(angle: torch.Tensor, speed: float) -> torch.Tensor:
        start = 1.2 * torch.stack([torch.cos(angle), torch.sin(angle)], -1)
        return start[..., None, :] - speed * steps * start[..., None, :] / 1.2

    angle = 2 * torch.pi * torch.rand(batch, generator=g, dtype=torch.float64)
    nbr_angle = angle[:, None] + 2 * torch.pi * torch.arange(1, M + 1) / (M + 1) \
        + 0.3 * torch.rand(batch, M, generator=g, dtype=torch.float64)
    xbar, xbar_nbr = lines(angle, 0.15), lines(nbr_angle, 0.15)
    lin = linearize_plan("nonlinear", xbar, NominalModel(DIM), VortexWind())
    sigma = state_covariances("pointwise", torch.full_like(xbar, SYNTHETIC_VAR), lin.dyn_A)
    normals = collision_normals(xbar, xbar_nbr)
    eps_low, _ = pair_risks(EPS, 0.5)
    margins = chance_margins(normals, sigma, eps_low * torch.ones(batch, M))
    active = torch.ones(batch, M, dtype=torch.bool)
    rows, bounds = collision_rows(normals, margins, R_SAFE, active)

    def noise(*shape: int) -> torch.Tensor:
        return torch.randn(*shape, generator=g, dtype=torch.float64)

    return LocalProblemData(
        x0=xbar[:, 0].clone(), xref=lines(angle, 0.2), dyn_A=lin.dyn_A, dyn_c=lin.dyn_c,
        normals=rows, bounds=bounds, active=active, rho=torch.tensor(RHO),
        z_own=xbar[:, None].expand(batch, M, T + 1, D) + 0.02 * noise(batch, M, T + 1, D),
        z_nbr=xbar_nbr + 0.02 * noise(batch, M, T + 1, D),
        lam_own=0.1 * noise(batch, M, T + 1, D), lam_nbr=0.1 * noise(batch, M, T + 1, D),
    )


def _with_grad(data: LocalProblemData) -> LocalProblemData:
    """Copy of ``data`` whose rho, z and bounds require gradients."""
    fields = dict(vars(data))
    for name in ("rho", "z_own", "z_nbr", "bounds"):
        fields[name] = fields[name].clone().requires_grad_(True)
    return LocalProblemData(**fields)


#: SCS's own default tolerances (the ``reference`` path uses 1e-9 for accurate plans).
SCS_DEFAULT_EPS = {"eps_abs": 1e-4, "eps_rel": 1e-4}


def _time_layer(mpc: LocalMPC, data: LocalProblemData, backward: bool, repeats: int,
                solver_args: dict | None = None) -> tuple[float, float]:
    """Best-of-``repeats`` seconds per batch and the fraction of ok solves."""
    best, ok = float("inf"), 1.0
    for _ in range(repeats):
        inputs = _with_grad(data) if backward else data
        start = time.perf_counter()
        if backward:
            sol = mpc(inputs, solver_args=solver_args)
            (sol.X.sum() + sol.Y.sum()).backward()
        else:
            with torch.no_grad():
                sol = mpc(inputs, solver_args=solver_args)
        best = min(best, time.perf_counter() - start)
        ok = min(ok, float(sol.ok.double().mean()))
    return best, ok


def _time_plain_cvxpy(mpc: LocalMPC, data: LocalProblemData, repeats: int) -> float:
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


def run(quick: bool = False, out: Path | str | None = None) -> dict:
    """Measure the local-problem paths; returns ``{"table": [...], ...}`` (JSON-ready).

    Args:
        quick: fewer repeats and batch 8 instead of 32.
        out: output directory (unused: the caller writes ``bench.json``).
    """
    batches = (1, 3, 8 if quick else 32)
    repeats = 2 if quick else 5
    nominal = NominalModel(DIM)
    layers = {name: LocalMPC(HORIZON, DIM, NEIGHBORS, nominal, U_MAX, ALPHA, solver=name)
              for name in ("clarabel", "reference")}
    rows = []
    for batch in batches:
        data = crossing_instances(batch, seed=batch)
        layers["clarabel"](data)  # warm-up (first call pays one-off costs)
        timings = {}
        for path, mpc in layers.items():
            for backward in (False, True):
                seconds, ok = _time_layer(mpc, data, backward, repeats)
                timings[(path, backward)] = (seconds, ok)
            if path == "reference":
                for backward in (False, True):
                    timings[("reference-scs-default-eps", backward)] = _time_layer(
                        mpc, data, backward, repeats, SCS_DEFAULT_EPS)
        timings[("cvxpy+clarabel", False)] = (_time_plain_cvxpy(layers["clarabel"], data, repeats), 1.0)
        for (path, backward), (seconds, ok) in sorted(timings.items(), key=lambda kv: kv[0][1]):
            reference = timings[("reference", backward)][0]
            rows.append({
                "workload": f"local T={HORIZON} D={DIM} M={NEIGHBORS}",
                "path": path,
                "batch": batch,
                "pass": "forward+backward" if backward else "forward",
                "ms_per_problem": 1e3 * seconds / batch,
                "speedup_vs_reference": reference / seconds,
                "ok_fraction": ok,
            })
            logger.info("local bench %s", rows[-1])
    return {
        "table": rows,
        "notes": "best of %d repeats; reference = cvxpylayers default solver (diffcp + SCS, eps 1e-9); "
                 "cvxpy+clarabel solves the same DPP problem one by one, forward only" % repeats,
    }
