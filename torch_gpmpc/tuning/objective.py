"""The tuning objective: residuals, planned cost and a distance penalty over instances and
closed-loop MPC steps, as one smooth function of rho and the risk split."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence
import torch
from torch import Tensor
from torch_gpmpc.coordination.admm import ADMM
from torch_gpmpc.errors import GpmpcError
from torch_gpmpc.coordination.graph import communication_graph
from torch_gpmpc.dynamics.systems import TrueSystem
from torch_gpmpc.tuning.instances import TuneInstance
from torch_gpmpc.tuning.parameters import ObjectiveWeights, TuningParameters
from torch_gpmpc.tuning.unroll import distance_penalty, unroll_admm


#: Names of the objective's parts, in logging order (TensorBoard ``tune/<name>``).
PARTS = ("primal", "dual", "cost", "distance_penalty")


@dataclass
class ObjectiveValue:
    """One evaluation of :class:`TuningObjective`.

    Attributes:
        loss: the weighted objective, 0-d tensor (differentiable).
        parts: unweighted parts ``primal``, ``dual``, ``cost``, ``distance_penalty``
            (0-d tensors, means over instances and MPC steps).
    """

    loss: Tensor
    parts: dict[str, Tensor]

    def floats(self) -> dict[str, float]:
        """``loss`` and the parts as floats."""
        return {"loss": float(self.loss.detach()), **{k: float(v.detach()) for k, v in self.parts.items()}}


class TuningObjective:
    """The tuning objective over a batch of instances (definition: module docstring).

    Args:
        admm: the ADMM (its config: horizon, eps, r_safe, alpha, method, ...).
        instances: training instances.
        weights: objective weights (default :class:`ObjectiveWeights`).
        admm_iters: unrolled ADMM iterations per MPC step (fixed count).
        mpc_steps: closed-loop MPC steps per instance (at most the instance's noise length).
        warmup_iters: gradient-free iterations before the unrolled ones.
        system: the true system stepped between MPC steps (required).

    Attributes:
        evaluations: number of objective evaluations so far.
    """

    def __init__(
        self,
        admm: ADMM,
        instances: Sequence[TuneInstance],
        weights: ObjectiveWeights | None = None,
        admm_iters: int = 6,
        mpc_steps: int = 1,
        warmup_iters: int = 0,
        system: TrueSystem | None = None,
    ) -> None:
        if not instances:
            raise GpmpcError("TuningObjective needs at least one instance")
        for inst in instances:
            if inst.noise.shape[0] < mpc_steps - 1:
                raise GpmpcError(f"instance {inst.name}: noise for {inst.noise.shape[0]} steps, "
                                 f"mpc_steps={mpc_steps} needs {mpc_steps - 1}")
        if system is None:
            raise GpmpcError("TuningObjective: pass the true system stepped between MPC steps (system=..., e.g. "
                             "team_system_from_config(cfg))")
        self.admm = admm
        self.cfg = admm.settings
        self.instances = list(instances)
        self.weights = weights or ObjectiveWeights()
        self.admm_iters = int(admm_iters)
        self.mpc_steps = int(mpc_steps)
        self.warmup_iters = int(warmup_iters)
        self.system = system
        self.evaluations = 0

    def __call__(self, params: TuningParameters | None = None, rho: Tensor | None = None,
                 split: Tensor | float | None = None) -> ObjectiveValue:
        """Evaluate at ``params`` (or at explicit ``rho`` (0-d) and ``split``).

        Gradients flow to whatever of ``rho``/``split`` requires them (use
        ``torch.no_grad()`` for a cheaper forward-only evaluation).
        """
        if params is not None:
            rho, split = params.rho(), params.split()
        rho = torch.as_tensor(self.cfg.rho if rho is None else rho, dtype=torch.float64)
        split = self.cfg.risk_split if split is None else split
        self.evaluations += 1
        w = self.weights
        sums = {name: rho.new_zeros(()) for name in PARTS}
        count = 0
        nominal = self.admm.nominal
        for inst in self.instances:
            x, warm = inst.x0, inst.warm
            for step in range(self.mpc_steps):
                graph = communication_graph(nominal.positions(x.detach()), self.cfg.comm_radius)
                xref = nominal.reference_states(inst.scenario.reference_window(inst.t0 + step, self.cfg.horizon))
                un = unroll_admm(self.admm, x, xref, graph, self.admm_iters, rho, split, warm=warm,
                                 warmup_iters=self.warmup_iters)
                sol = un.result.solution
                sums["primal"] = sums["primal"] + un.primal[-1]
                sums["dual"] = sums["dual"] + un.dual[-1]
                sums["cost"] = sums["cost"] + sol.cost.mean()
                sums["distance_penalty"] = sums["distance_penalty"] + distance_penalty(
                    nominal.positions(sol.X), self.cfg.r_safe, w.distance_width, self.cfg.radii)
                count += 1
                if step + 1 < self.mpc_steps:
                    u = nominal.project(un.result.inputs[:, 0])  # each agent onto its model's bounds
                    x = self.system.step(x, u, noise=inst.noise[step])
                    warm = un.result.state.shifted()
        parts = {k: v / count for k, v in sums.items()}
        loss = (w.primal * parts["primal"] + w.dual * parts["dual"] + w.cost * parts["cost"]
                + w.distance * parts["distance_penalty"])
        return ObjectiveValue(loss=loss, parts=parts)
