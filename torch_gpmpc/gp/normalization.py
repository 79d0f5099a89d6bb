"""Standardization of a GP's inputs and outputs (as botorch's ``Standardize`` transform).

The GPs are fitted on standardized data; :class:`Standardization` holds the per-dimension
means and standard deviations that map raw units to standardized ones and back.
"""

from __future__ import annotations

from dataclasses import dataclass

from torch import Tensor


@dataclass(frozen=True)
class Standardization:
    """Per-dimension affine maps of inputs (Din,) and outputs (D,) to zero mean, unit variance.

    Attributes:
        x_mean, x_std: input means and standard deviations, shape (Din,).
        y_mean, y_std: output means and standard deviations, shape (D,).
    """

    x_mean: Tensor
    x_std: Tensor
    y_mean: Tensor
    y_std: Tensor

    @classmethod
    def from_data(cls, inputs: Tensor, y: Tensor) -> "Standardization":
        """Means and standard deviations of ``inputs`` (N, Din) and ``y`` (N, D); a constant
        dimension gets std 1 (nothing to scale)."""
        return cls(inputs.mean(0), _std(inputs), y.mean(0), _std(y))

    def inputs(self, x: Tensor) -> Tensor:
        """Raw inputs (..., Din) in standardized units."""
        return (x - self.x_mean) / self.x_std

    def outputs(self, y: Tensor) -> Tensor:
        """Raw outputs (..., D) in standardized units."""
        return (y - self.y_mean) / self.y_std


def _std(a: Tensor) -> Tensor:
    s = a.std(dim=0)
    return s.where(s > 1e-12 * (1.0 + a.abs().max(dim=0).values), s.new_ones(()))
