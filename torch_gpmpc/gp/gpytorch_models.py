"""A user's own GPyTorch models as an agent's residual model (:class:`GPyTorchResidual`).

One exact GP per residual row, any mean and kernel: predictions go through GPyTorch's own
predictive machinery (its prediction strategy caches the factorization), the mean Jacobian
through autograd (an exact GP's posterior mean at one point depends on that point only, so
the gradient of the summed mean is every point's Jacobian row).
"""

from __future__ import annotations

from typing import Sequence

import gpytorch
import torch
from torch import Tensor

from torch_gpmpc.errors import GpmpcError
from torch_gpmpc.gp.cache import parameter_values


class GPyTorchResidual(torch.nn.Module):
    """R user-built GPyTorch exact GPs, one per residual row, behind the
    :class:`~torch_gpmpc.gp.protocol.ResidualModel` protocol.

    The models are used as they are (trained by the user, in raw units). Their prediction
    caches are dropped whenever a hyperparameter changes, so a changed lengthscale is used at
    the next call. Gradients to the hyperparameters are opt-in
    (:meth:`enable_hyperparameter_gradients`); gradients to the query points always flow.

    Args:
        models: R ``gpytorch.models.ExactGP`` models, each with a single output and training
            inputs of shape (N_r, Din) (the same Din for all).
        likelihoods: R ``GaussianLikelihood`` (their ``noise`` is the predictive noise).

    Examples:
        >>> import gpytorch, torch
        >>> from torch_gpmpc import ResidualGP
        >>> class Exact(gpytorch.models.ExactGP):
        ...     def __init__(self, x, y, lik):
        ...         super().__init__(x, y, lik)
        ...         self.mean_module = gpytorch.means.ConstantMean()
        ...         self.covar_module = gpytorch.kernels.ScaleKernel(gpytorch.kernels.MaternKernel(nu=2.5))
        ...     def forward(self, x):
        ...         return gpytorch.distributions.MultivariateNormal(self.mean_module(x), self.covar_module(x))
        >>> x = torch.linspace(-2, 2, 20, dtype=torch.float64)[:, None]
        >>> liks = [gpytorch.likelihoods.GaussianLikelihood().double() for _ in range(2)]
        >>> models = [Exact(x, f(x[:, 0]), lik).double() for f, lik in zip((torch.sin, torch.cos), liks)]
        >>> gp = ResidualGP.from_gpytorch(models, liks)
        >>> mean, jac, var = gp.linearize(torch.zeros(3, 1, dtype=torch.float64))
        >>> tuple(mean.shape), tuple(jac.shape), tuple(var.shape)
        ((3, 2), (3, 2, 1), (3, 2))
    """

    def __init__(self, models: Sequence[gpytorch.models.ExactGP],
                 likelihoods: Sequence[gpytorch.likelihoods.GaussianLikelihood]) -> None:
        super().__init__()
        models, likelihoods = list(models), list(likelihoods)
        if not models or len(models) != len(likelihoods):
            raise GpmpcError(f"from_gpytorch: give one model and one likelihood per residual row "
                             f"(got {len(models)} models and {len(likelihoods)} likelihoods)")
        dims = set()
        for r, (model, lik) in enumerate(zip(models, likelihoods)):
            if not isinstance(model, gpytorch.models.ExactGP):
                raise GpmpcError(f"from_gpytorch: model {r} is a {type(model).__name__}, not a "
                                 "gpytorch.models.ExactGP")
            if not isinstance(lik, gpytorch.likelihoods.GaussianLikelihood):
                raise GpmpcError(f"from_gpytorch: likelihood {r} is a {type(lik).__name__}, not a "
                                 "gpytorch.likelihoods.GaussianLikelihood")
            inputs = model.train_inputs[0] if model.train_inputs else None
            if inputs is None or inputs.dim() != 2:
                raise GpmpcError(f"from_gpytorch: model {r} needs training inputs of shape (N, Din) "
                                 "(one output per model; batch models are not supported)")
            dims.add(int(inputs.shape[-1]))
        if len(dims) != 1:
            raise GpmpcError(f"from_gpytorch: the models read different input sizes {sorted(dims)}")
        self.models = torch.nn.ModuleList(models)
        self.likelihoods = torch.nn.ModuleList(likelihoods)
        self._input_dim = dims.pop()
        self._keys: list[Tensor | None] = [None] * len(models)
        #: whether predictions carry gradients to the hyperparameters
        self.hyperparameter_gradients = False

    @property
    def input_dim(self) -> int:
        """Din."""
        return self._input_dim

    @property
    def output_dim(self) -> int:
        """R, one model per residual row."""
        return len(self.models)

    @property
    def noise(self) -> Tensor:
        """(R,) the likelihoods' noise variances (float64)."""
        noise = torch.cat([lik.noise.reshape(-1)[:1] for lik in self.likelihoods]).to(torch.float64)
        return noise if self.hyperparameter_gradients else noise.detach()

    def enable_hyperparameter_gradients(self, enabled: bool = True) -> "GPyTorchResidual":
        """Opt in (or out) of gradients from :meth:`linearize` to every model's hyperparameters."""
        self.hyperparameter_gradients = bool(enabled)
        return self

    def linearize(self, x: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """Posterior mean, its Jacobian and the latent variance at ``x``.

        Args:
            x: (n, Din) query points.

        Returns:
            ``(mean (n, R), jac (n, R, Din), var (n, R))`` in float64.
        """
        if not isinstance(x, Tensor) or x.dim() != 2 or x.shape[1] != self.input_dim:
            shape = tuple(x.shape) if isinstance(x, Tensor) else type(x).__name__
            raise GpmpcError(f"GP query points must have shape (n, {self.input_dim}), got {shape}")
        means, jacs, variances = [], [], []
        for r in range(self.output_dim):
            mean, jac, var = self._row(r, x)
            means.append(mean)
            jacs.append(jac)
            variances.append(var)
        return torch.stack(means, -1), torch.stack(jacs, 1), torch.stack(variances, -1)

    def _row(self, r: int, x: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """Row r: mean (n,), Jacobian (n, Din), variance (n,)."""
        model, lik = self.models[r], self.likelihoods[r]
        model.eval()
        lik.eval()
        hyper = self.hyperparameter_gradients and torch.is_grad_enabled()
        key = parameter_values(model)
        if hyper or self._keys[r] is None or not torch.equal(self._keys[r], key):
            model.prediction_strategy = None  # GPyTorch rebuilds it from the current hyperparameters
            self._keys[r] = key
        dtype = model.train_inputs[0].dtype
        graph = torch.is_grad_enabled() and (x.requires_grad or hyper)
        with torch.enable_grad(), gpytorch.settings.detach_test_caches(not hyper):
            xq = x.to(dtype) if x.requires_grad else x.detach().to(dtype).requires_grad_(True)
            post = model(xq)
            mean = post.mean
            if mean.shape != (x.shape[0],):
                raise GpmpcError(f"from_gpytorch: model {r} returned a mean of shape {tuple(mean.shape)}, "
                                 f"expected ({x.shape[0]},): one output per model")
            (jac,) = torch.autograd.grad(mean.sum(), xq, create_graph=graph)
            var = post.variance
        if hyper:  # the prediction cache now holds this call's graph: never reuse it
            model.prediction_strategy = None
            self._keys[r] = None
        out = (mean, jac, var) if graph else (mean.detach(), jac.detach(), var.detach())
        return tuple(t.to(torch.float64) for t in out)
