"""The tuner: gradient steps on rho and the risk split, checkpoints, and the record of a run."""

from __future__ import annotations

import logging
import math
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

import torch
from torch import Tensor

from torch_gpmpc.config.tune_settings import TuneSettings
from torch_gpmpc.errors import GpmpcError
from torch_gpmpc.tuning.objective import ObjectiveValue, PARTS, TuningObjective
from torch_gpmpc.tuning.parameters import TuningParameters

log = logging.getLogger(__name__)


# --------------------------------------------------------------------------- settings
# --------------------------------------------------------------------------- parameters


# --------------------------------------------------------------------------- instances


# --------------------------------------------------------------------------- unrolled ADMM


# --------------------------------------------------------------------------- objective


# --------------------------------------------------------------------------- optimizer
@dataclass
class TuneRecord:
    """One tuning iteration (values at the parameters *before* the step).

    Attributes:
        iteration: 0-based iteration index.
        loss: objective value.
        parts: unweighted objective parts.
        rho: penalty.
        split: per-edge split ``{"lo_hi": s}``.
        grad_norm: Euclidean norm of the gradient w.r.t. the tuned parameters.
    """

    iteration: int
    loss: float
    parts: dict[str, float]
    rho: float
    split: dict[str, float]
    grad_norm: float

    def to_dict(self) -> dict[str, Any]:
        """JSON-serializable dict."""
        return asdict(self)


class Tuner:
    """Gradient tuning of :class:`TuningParameters` on a :class:`TuningObjective`.

    Adam (with per-iteration learning-rate decay) or L-BFGS (strong-Wolfe line
    search, one ``step`` per iteration; its evaluations are counted by the objective).

    Args:
        objective: the objective.
        params: the parameters (optimized in place).
        settings: optimizer, lr, lr_decay, tune_rho, tune_split.
        edges: edges whose split is reported (default all pairs).
    """

    def __init__(self, objective: TuningObjective, params: TuningParameters,
                 settings: TuneSettings | None = None, edges: Sequence[Sequence[int]] | None = None) -> None:
        self.objective, self.params = objective, params
        self.settings = settings or TuneSettings()
        self.edges = [tuple(e) for e in edges] if edges is not None else None
        trainable = []
        if self.settings.tune_rho:
            trainable.append(params.log_rho)
        if self.settings.tune_split:
            trainable.append(params.theta)
        if not trainable:
            raise GpmpcError("nothing to tune: set tune.tune_rho=true or tune.tune_split=true")
        for p in (params.log_rho, params.theta):
            p.requires_grad_(any(p is q for q in trainable))
        self.trainable = trainable
        if self.settings.optimizer == "adam":
            self.optimizer: torch.optim.Optimizer = torch.optim.Adam(trainable, lr=self.settings.lr)
            self.scheduler = torch.optim.lr_scheduler.ExponentialLR(self.optimizer, gamma=self.settings.lr_decay)
        else:
            self.optimizer = torch.optim.LBFGS(trainable, lr=self.settings.lr, max_iter=1, history_size=10,
                                               line_search_fn="strong_wolfe")
            self.scheduler = None
        self.history: list[TuneRecord] = []

    @property
    def iteration(self) -> int:
        """Iterations done."""
        return len(self.history)

    def _evaluate(self) -> tuple[ObjectiveValue, float]:
        self.optimizer.zero_grad()
        value = self.objective(self.params)
        value.loss.backward()
        grads = [p.grad for p in self.trainable if p.grad is not None]
        gnorm = float(torch.sqrt(sum((g ** 2).sum() for g in grads))) if grads else 0.0
        return value, gnorm

    def step(self) -> TuneRecord:
        """One optimizer iteration; returns its record (also appended to ``history``)."""
        rho, split = float(self.params.rho().detach()), self.params.split_per_edge(self.edges)
        if self.settings.optimizer == "adam":
            value, gnorm = self._evaluate()
            self.optimizer.step()
            self.scheduler.step()
        else:
            first: dict[str, Any] = {}

            def closure() -> Tensor:
                value, gnorm = self._evaluate()
                first.setdefault("value", value)
                first.setdefault("gnorm", gnorm)
                return value.loss.detach()

            self.optimizer.step(closure)
            value, gnorm = first["value"], first["gnorm"]
        f = value.floats()
        record = TuneRecord(iteration=self.iteration, loss=f.pop("loss"), parts=f, rho=rho, split=split,
                            grad_norm=gnorm)
        self.history.append(record)
        if not math.isfinite(record.loss):
            raise GpmpcError(f"tuning objective is not finite at iteration {record.iteration} "
                             f"(rho={rho:.4g}); lower tune.lr")
        return record

    def run(self, iters: int, callback: Callable[[TuneRecord], None] | None = None) -> list[TuneRecord]:
        """Iterate until ``iters`` iterations are done in total (resumed ones count).

        Args:
            iters: total number of iterations.
            callback: called with each new record (after the step).
        """
        while self.iteration < iters:
            record = self.step()
            if callback is not None:
                callback(record)
        return self.history

    # ---------------------------------------------------------------- checkpoints
    def state_dict(self) -> dict[str, Any]:
        """Tensors (and plain containers of tensors/numbers) only: loads with ``weights_only=True``."""
        cols = ["loss", *PARTS, "rho", "grad_norm"]
        hist = torch.tensor([[r.loss, *[r.parts[p] for p in PARTS], r.rho, r.grad_norm] for r in self.history],
                            dtype=torch.float64).reshape(-1, len(cols))
        num = self.params.num_agents
        split_hist = torch.stack([_split_matrix(r.split, num) for r in self.history]) if self.history \
            else torch.zeros(0, num, num, dtype=torch.float64)
        return {
            "log_rho": self.params.log_rho.detach().clone(),
            "theta": self.params.theta.detach().clone(),
            "history": hist,
            "history_split": split_hist,
            "optimizer": self.optimizer.state_dict(),
            "scheduler": self.scheduler.state_dict() if self.scheduler is not None else {},
        }

    def load_state_dict(self, state: Mapping[str, Any]) -> None:
        """Restore parameters, optimizer state and history from :meth:`state_dict`.

        Raises:
            GpmpcError: the checkpoint belongs to a different number of agents or optimizer.
        """
        theta = state["theta"]
        if tuple(theta.shape) != tuple(self.params.theta.shape):
            raise GpmpcError(f"checkpoint has a split for {theta.shape[0]} agents, this run has "
                             f"{self.params.num_agents}; use another --out or drop --resume")
        try:
            self.optimizer.load_state_dict(state["optimizer"])
            if self.scheduler is not None and state.get("scheduler"):
                self.scheduler.load_state_dict(state["scheduler"])
        except (KeyError, ValueError) as exc:
            raise GpmpcError(f"checkpoint does not match this run's optimizer settings ({exc}); use the same "
                             "tune.optimizer/tune_rho/tune_split, another --out, or drop --resume") from exc
        with torch.no_grad():
            self.params.log_rho.copy_(state["log_rho"])
            self.params.theta.copy_(theta)
        edges = self.edges or [(i, j) for i in range(self.params.num_agents)
                               for j in range(i + 1, self.params.num_agents)]
        self.history = []
        for i, (row, split) in enumerate(zip(state["history"].tolist(), state["history_split"], strict=True)):
            parts = dict(zip(PARTS, row[1:1 + len(PARTS)], strict=True))
            self.history.append(TuneRecord(iteration=i, loss=row[0], parts=parts, rho=row[1 + len(PARTS)],
                                           split={f"{lo}_{hi}": float(split[lo, hi]) for lo, hi in edges},
                                           grad_norm=row[2 + len(PARTS)]))

    def save_checkpoint(self, path: str | Path) -> None:
        """Atomically ``torch.save`` :meth:`state_dict` to ``path``."""
        from torch_gpmpc.fileio import atomic_path

        with atomic_path(path) as tmp:
            torch.save(self.state_dict(), tmp)

    def load_checkpoint(self, path: str | Path) -> None:
        """Load a checkpoint written by :meth:`save_checkpoint` (``weights_only=True``).

        Raises:
            GpmpcError: missing or unreadable file, or a different number of agents.
        """
        path = Path(path)
        if not path.is_file():
            raise GpmpcError(f"no checkpoint at {str(path)!r}; run without --resume to start")
        try:
            state = torch.load(path, weights_only=True)
        except Exception as exc:  # noqa: BLE001 - any unreadable file is a user error
            raise GpmpcError(f"checkpoint {str(path)!r} cannot be read: {exc}") from exc
        self.load_state_dict(state)


def _split_matrix(split: Mapping[str, float], num_agents: int) -> Tensor:
    out = torch.full((num_agents, num_agents), 0.5, dtype=torch.float64)
    for key, value in split.items():
        lo, hi = (int(v) for v in key.split("_"))
        out[lo, hi] = value
    return out


# --------------------------------------------------------------------------- baselines, results


