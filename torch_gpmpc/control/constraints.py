"""The agent-local problem's own constraints: input bounds and soft state constraints.

Besides the dynamics and the collision rows, a local problem has

* **input bounds** (hard): a norm ``||U_tau|| <= u_max``, a box ``|U_tau,j| <= b_j``, or both;
* **state rows** (soft): ``n_l^T X_tau >= b_l`` for tau = 1..T, from the model's ``state_box``
  and ``state_rows`` and the scenario's workspace box on the positions, each with a slack
  ``s >= 0`` at the exact-penalty weight ``slack_penalty`` (``n^T x + s >= b``), like the
  collision rows; per-problem half-space rows (:attr:`LocalProblemData.halfspace_normals`)
  are the same family;
* **a state norm bound** (soft): ``||X_tau[idx]|| <= v`` stated smoothly as
  ``||X_tau[idx]||^2 <= v^2 + 2 v sigma_tau``, ``sigma >= 0`` (penalty ``slack_penalty
  sigma``): convex, equal to the hard bound whenever that is feasible and the penalty exceeds
  its multiplier, and ``sigma ~ ||x|| - v`` just outside it.

Soft state constraints keep every local problem feasible: a measured state outside the box
(wind, noise) gives a plan that steers back, with the slack reported, never a failed solve.
:class:`LocalConstraints` holds them as plain numbers; every solver states the same problem.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from torch_gpmpc.config.model_spec import ModelSpec
from torch_gpmpc.config.workspace import Workspace
from torch_gpmpc.errors import GpmpcError


@functools.lru_cache(maxsize=64)
def _row_tensors(normals: tuple, bounds: tuple, dim: int, dtype: torch.dtype, device) -> tuple[Tensor, Tensor]:
    """:meth:`LocalConstraints.rows` for its plain-number rows (cached by value)."""
    return (torch.tensor(normals, dtype=dtype, device=device).reshape(len(bounds), dim),
            torch.tensor(bounds, dtype=dtype, device=device))


@dataclass(frozen=True)
class LocalConstraints:
    """Input bounds and soft state constraints of agents with state dimension D, input dimension Du.

    Attributes:
        input_norm: ``||u|| <= input_norm`` or ``None``.
        input_box: ``|u_j| <= input_box[j]`` (length Du) or ``None``.
        row_normals: soft state rows ``n_l^T x >= b_l``, L rows of length D (L may be 0).
        row_bounds: their right-hand sides ``b_l`` (length L).
        norm_indices: state indices of the soft norm bound, or ``None``.
        norm_bound: ``v`` of ``||x[norm_indices]|| <= v``, or ``None``.

    Examples:
        >>> from torch_gpmpc import ModelSpec
        >>> from torch_gpmpc.config.workspace import Workspace
        >>> c = LocalConstraints.of(ModelSpec.double_integrator(dim=2), workspace=Workspace((-1.0, -2.0), (1.0, 2.0)))
        >>> c.num_rows, c.row_normals[0], c.row_bounds[:2]
        (4, (1.0, 0.0, 0.0, 0.0), (-1.0, -1.0))
    """

    input_norm: float | None
    input_box: tuple[float, ...] | None
    row_normals: tuple[tuple[float, ...], ...]
    row_bounds: tuple[float, ...]
    norm_indices: tuple[int, ...] | None = None
    norm_bound: float | None = None

    @classmethod
    def of(cls, spec: ModelSpec, u_max: float | None = None, workspace: Workspace | None = None
           ) -> "LocalConstraints":
        """The constraints of model ``spec`` (``u_max`` overrides its norm bound, if it has one) and
        an optional workspace box on its positions."""
        n = spec.state_dim
        norm = spec.input_norm if (u_max is None or spec.input_norm is None) else float(u_max)
        if norm is not None and not norm > 0:
            raise GpmpcError(f"input norm bound must be > 0, got {norm}")
        normals: list[tuple[float, ...]] = []
        bounds: list[float] = []

        def add_box(indices, lower, upper) -> None:
            for i, lo, hi in zip(indices, lower, upper):
                for sign, b in ((1.0, lo), (-1.0, hi)):  # x_i >= lo and -x_i >= -hi
                    if math.isfinite(b):
                        normals.append(tuple(sign if c == i else 0.0 for c in range(n)))
                        bounds.append(sign * b)

        if spec.state_box_indices is not None:
            add_box(spec.state_box_indices, spec.state_box_lower, spec.state_box_upper)
        if spec.state_rows_G is not None:
            for row, h in zip(spec.state_rows_G, spec.state_rows_h):  # G x <= h  <=>  -G x >= -h
                normals.append(tuple(-v for v in row))
                bounds.append(-h)
        if workspace is not None:
            workspace.check_dim(spec.position_dim)
            add_box(spec.position, workspace.lower, workspace.upper)
        return cls(norm, spec.input_box, tuple(normals), tuple(bounds), spec.state_bound_indices,
                   spec.state_bound_norm)

    @property
    def num_rows(self) -> int:
        """L, the number of constant soft state rows."""
        return len(self.row_bounds)

    def rows(self, dim: int, dtype: torch.dtype = torch.float64, device=None) -> tuple[Tensor, Tensor]:
        """The constant state rows as tensors: normals (L, D) and bounds (L,) (made once per dtype and
        device: every solve reads them; shared, so do not modify them in place)."""
        return _row_tensors(self.row_normals, self.row_bounds, dim, dtype, device)

    def input_violation(self, U: np.ndarray) -> np.ndarray:
        """How far inputs (B, T, Du) exceed the input bounds, per problem (B,) (NumPy: the
        acceptance check of a solve, which no gradient passes through)."""
        batch = U.shape[0]
        out = np.zeros(batch)
        if self.input_box is not None:
            box = np.asarray(self.input_box, dtype=U.dtype)
            out = np.maximum(out, np.clip(np.abs(U) - box, 0.0, None).reshape(batch, -1).max(1, initial=0.0))
        if self.input_norm is not None:
            excess = np.clip(np.linalg.norm(U, axis=-1) - self.input_norm, 0.0, None)
            out = np.maximum(out, excess.reshape(batch, -1).max(1, initial=0.0))
        return out

    @property
    def input_scale(self) -> float:
        """The largest input magnitude the bounds allow (the scale of input residuals)."""
        sizes = [v for v in (self.input_norm, max(self.input_box) if self.input_box else None) if v is not None]
        return max(sizes)

    def state_violation(self, X: Tensor, halfspace_normals: Tensor | None = None,
                        halfspace_bounds: Tensor | None = None) -> Tensor:
        """How far plans X (B, T+1, D) leave the soft state constraints at tau = 1..T, per step
        (B, T): the largest ``b - n^T x`` of the rows (constant and per-problem half-spaces
        (B, L', T, D), (B, L', T)) and ``||x[idx]|| - v``, clamped at 0 (differentiable)."""
        Xt = X[:, 1:]
        out = Xt.new_zeros(Xt.shape[:2])
        if not self.num_rows and self.norm_bound is None and (halfspace_normals is None
                                                              or not halfspace_normals.shape[1]):
            return out
        if self.num_rows:
            normals, bounds = self.rows(X.shape[-1], X.dtype, X.device)
            gap = bounds - Xt @ normals.T  # (B, T, L)
            out = torch.maximum(out, gap.amax(-1))
        if halfspace_normals is not None and halfspace_normals.shape[1]:
            gap = halfspace_bounds - (halfspace_normals * Xt[:, None]).sum(-1)  # (B, L', T)
            out = torch.maximum(out, gap.amax(1))
        if self.norm_bound is not None:
            norm = torch.linalg.vector_norm(Xt[..., list(self.norm_indices)], dim=-1)
            out = torch.maximum(out, norm - self.norm_bound)
        return out.clamp(min=0)
