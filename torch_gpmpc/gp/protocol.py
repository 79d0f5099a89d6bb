"""What the controller asks of an agent's residual model: the :class:`ResidualModel` protocol.

The controller never trains or inspects a GP; along each planned trajectory it linearizes it once
per control step (paper eqs. 3, 4, 13) and reads ``noise`` for the predictive variance of the chance
margins. Anything with the four members of :class:`ResidualModel` works:
:class:`~torch_gpmpc.gp.model.ResidualGP` (the package's fitted SE-ARD GPs, exact or sparse),
:class:`~torch_gpmpc.gp.gpytorch_models.GPyTorchResidual` (a user's own GPyTorch exact models,
built by ``ResidualGP.from_gpytorch``), or a hand-written model (e.g. a constant variance).
A model may also offer ``planning_gp()``: the fitted GP it plans with (:class:`PlanningGP`). Then a
team's models are linearized in one batch (:mod:`~torch_gpmpc.gp.batch`) from that view, without
calling their ``linearize``, so the view must predict exactly as the model does; without it, one
``linearize`` call per agent.

Shapes: n query points, Din GP inputs (the model's ``gp_inputs`` columns), R residual rows
(the model's ``residual`` indices, one GP each).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Protocol, runtime_checkable

from torch import Tensor


@runtime_checkable
class ResidualModel(Protocol):
    """A residual model ``r(zeta) ~ N(mu(zeta), diag(var(zeta)))`` of R rows.

    Attributes:
        input_dim: Din, the GP input size.
        output_dim: R, the number of residual rows.
        noise: (R,) observation-noise variances (added to ``var`` for the predictive variance).

    Examples:
        >>> import torch
        >>> from torch_gpmpc.gp.protocol import ResidualModel
        >>> class Zero:                       # no residual, a constant variance
        ...     input_dim, output_dim = 2, 2
        ...     noise = torch.full((2,), 0.01, dtype=torch.float64)
        ...     def linearize(self, x):
        ...         n = x.shape[0]
        ...         return x.new_zeros(n, 2), x.new_zeros(n, 2, 2), x.new_full((n, 2), 0.04)
        >>> isinstance(Zero(), ResidualModel)
        True
    """

    @property
    def input_dim(self) -> int: ...

    @property
    def output_dim(self) -> int: ...

    @property
    def noise(self) -> Tensor: ...

    def linearize(self, x: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """Mean, mean Jacobian and latent variance at n points.

        Args:
            x: (n, Din) GP inputs, float64.

        Returns:
            ``(mean (n, R), jac (n, R, Din), var (n, R))``, differentiable w.r.t. ``x`` (and the
            hyperparameters where the model offers it).
        """
        ...


@dataclass(frozen=True)
class PlanningGP:
    """A fitted GP (``ResidualGP``) and the constant shifts a wrapper adds to its mean and to its
    variance, each (R,), applied in order (outermost wrapper last)."""

    gp: Any
    mean_shifts: tuple[Tensor, ...] = field(default_factory=tuple)
    var_shifts: tuple[Tensor, ...] = field(default_factory=tuple)

    def shifted(self, mean: Tensor, var: Tensor) -> "PlanningGP":
        """This view with one more shift of the mean and of the variance (each (R,)) on top."""
        return PlanningGP(self.gp, (*self.mean_shifts, mean), (*self.var_shifts, var))


def planning_gp(model) -> PlanningGP | None:
    """The :class:`PlanningGP` ``model`` plans with, or ``None`` if it offers none (then it is called
    on its own)."""
    view = getattr(model, "planning_gp", None)
    return view() if callable(view) else None


def evaluates_as(model, cls: type) -> bool:
    """Whether ``model`` predicts exactly as ``cls`` does: neither its class (a subclass of ``cls``)
    nor the instance replaces ``linearize`` or ``predict``. A model's ``planning_gp()`` offers its view
    only then, since the batch computes the view and never calls the model's own methods."""
    own = vars(model) if hasattr(model, "__dict__") else {}
    return all(getattr(type(model), name) is getattr(cls, name) and name not in own
               for name in ("linearize", "predict"))
