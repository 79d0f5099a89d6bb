"""What the controller asks of an agent's residual model: the :class:`ResidualModel` protocol.

The controller never trains or inspects a GP; along each planned trajectory it calls
``linearize`` once per control step (paper eqs. 3, 4, 13) and reads ``noise`` for the
predictive variance of the chance margins. Anything with these four members works:
:class:`~torch_gpmpc.gp.model.ResidualGP` (the package's fitted SE-ARD GPs, exact or sparse),
:class:`~torch_gpmpc.gp.gpytorch_models.GPyTorchResidual` (a user's own GPyTorch exact models,
built by ``ResidualGP.from_gpytorch``), or a hand-written model (e.g. a constant variance).
A model may also offer ``shifted_gp()``, the fitted GP it plans with: then a team's models are
linearized in one batch (:mod:`~torch_gpmpc.gp.batch`); without it, one call per agent.

Shapes: n query points, Din GP inputs (the model's ``gp_inputs`` columns), R residual rows
(the model's ``residual`` indices, one GP each).
"""

from __future__ import annotations

from typing import Protocol, runtime_checkable

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
