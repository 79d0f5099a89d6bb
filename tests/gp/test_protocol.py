"""Residual models as the controller sees them: the ResidualModel protocol, caches that follow
the hyperparameters, opt-in hyperparameter gradients, and a user's own GPyTorch models.

Independent answers: a GP rebuilt from scratch at the new hyperparameters, GPyTorch's own
predictive distribution, central finite differences (Jacobians and hyperparameter gradients).
"""

from __future__ import annotations

import gpytorch
import pytest
import torch

from tests.helpers import ConstantVarianceGP
from torch_gpmpc import GPyTorchResidual, ResidualGP, ResidualModel
from torch_gpmpc.errors import GpmpcError

F64 = torch.float64


def data(n=40, din=2, seed=0):
    g = torch.Generator().manual_seed(seed)
    x = 4 * torch.rand(n, din, generator=g, dtype=F64) - 2
    y = torch.stack([torch.sin(x[:, 1]), torch.cos(x[:, 0])], dim=1) + 0.01 * torch.randn(n, 2, generator=g,
                                                                                          dtype=F64)
    return x, y


QUERY = torch.tensor([[0.3, -0.2], [1.0, 0.5], [-1.2, 0.1]], dtype=F64)


def test_every_residual_model_follows_the_protocol():
    x, y = data()
    assert isinstance(ResidualGP(x, y), ResidualModel)
    assert isinstance(ConstantVarianceGP(0.1), ResidualModel)
    assert isinstance(ResidualGP.from_gpytorch(*user_models(x, y)), ResidualModel)


def test_changed_lengthscale_is_used_at_the_next_call():
    x, y = data()
    gp = ResidualGP(x, y)
    before = gp.linearize(QUERY)
    gp.model.covar_module.base_kernel.lengthscale = torch.tensor([[[0.3, 0.7]], [[0.5, 0.4]]], dtype=F64)
    after = gp.linearize(QUERY)
    fresh = ResidualGP(x, y)
    fresh.model.load_state_dict(gp.model.state_dict())
    for a, f, b in zip(after, fresh.linearize(QUERY), before):
        torch.testing.assert_close(a, f, rtol=1e-12, atol=1e-12)
        assert not torch.allclose(a, b)
    # an optimizer step changes the values in place: also seen
    raw = gp.model.covar_module.raw_outputscale
    with torch.no_grad():
        raw += 0.5
    torch.testing.assert_close(gp.predict(QUERY)[1], gp.gpytorch_predict(QUERY)[1], rtol=1e-9, atol=1e-12)


def test_hyperparameter_gradients_are_opt_in_and_match_finite_differences():
    x, y = data()
    gp = ResidualGP(x, y)
    gp.model.double(), gp.likelihood.double()  # float64 hyperparameters: finite differences of 1e-6
    raw = gp.model.covar_module.base_kernel.raw_lengthscale
    mean, jac, var = gp.linearize(QUERY)
    assert not mean.requires_grad  # off by default: the controller's hot path builds no graph
    gp.enable_hyperparameter_gradients()

    def objective():
        m, j, v = gp.linearize(QUERY)
        return m.sum() + 0.3 * j.sum() + 2.0 * v.sum() + gp.noise.sum()

    objective().backward()
    grad = raw.grad.clone()
    h = 1e-6
    for idx in [(0, 0, 0), (1, 0, 1)]:
        with torch.no_grad():
            raw[idx] += h
            up = float(objective())
            raw[idx] -= 2 * h
            down = float(objective())
            raw[idx] += h
        assert float(grad[idx]) == pytest.approx((up - down) / (2 * h), rel=1e-5)


class _Exact(gpytorch.models.ExactGP):
    def __init__(self, x, y, lik, kernel):
        super().__init__(x, y, lik)
        self.mean_module = gpytorch.means.ConstantMean()
        self.covar_module = gpytorch.kernels.ScaleKernel(kernel)

    def forward(self, x):
        return gpytorch.distributions.MultivariateNormal(self.mean_module(x), self.covar_module(x))


def user_models(x, y):
    liks = [gpytorch.likelihoods.GaussianLikelihood().double() for _ in range(y.shape[1])]
    kernels = [gpytorch.kernels.MaternKernel(nu=1.5, ard_num_dims=x.shape[1]),
               gpytorch.kernels.RBFKernel(ard_num_dims=x.shape[1])]
    models = [_Exact(x, y[:, r], liks[r], kernels[r]).double() for r in range(y.shape[1])]
    for m in models:
        m.eval()
    return models, liks


def test_user_gpytorch_models_predict_as_gpytorch_does_with_fd_jacobians():
    x, y = data()
    models, liks = user_models(x, y)
    gp = ResidualGP.from_gpytorch(models, liks)
    assert isinstance(gp, GPyTorchResidual) and (gp.input_dim, gp.output_dim) == (2, 2)
    mean, jac, var = gp.linearize(QUERY)
    for r, model in enumerate(models):
        with torch.no_grad():
            post = model(QUERY)
        torch.testing.assert_close(mean[:, r], post.mean, rtol=1e-12, atol=1e-12)
        torch.testing.assert_close(var[:, r], post.variance, rtol=1e-12, atol=1e-12)
    h = 1e-6
    for i in range(2):
        step = torch.zeros(2, dtype=F64)
        step[i] = h
        fd = (gp.linearize(QUERY + step)[0] - gp.linearize(QUERY - step)[0]) / (2 * h)
        torch.testing.assert_close(jac[:, :, i], fd, rtol=1e-6, atol=1e-8)
    noise = torch.stack([lik.noise.reshape(()) for lik in liks]).detach()
    torch.testing.assert_close(gp.noise, noise)


def test_user_models_follow_their_hyperparameters_and_give_opt_in_gradients():
    x, y = data()
    models, liks = user_models(x, y)
    gp = ResidualGP.from_gpytorch(models, liks)
    before = gp.linearize(QUERY)[0]
    kernel = models[1].covar_module.base_kernel
    kernel.lengthscale = torch.tensor([[0.4, 0.9]], dtype=F64)
    after = gp.linearize(QUERY)[0]
    assert torch.equal(after[:, 0], before[:, 0]) and not torch.allclose(after[:, 1], before[:, 1])
    gp.enable_hyperparameter_gradients()

    def objective():
        m, j, v = gp.linearize(QUERY)
        return m.sum() + 0.3 * j.sum() + 2.0 * v.sum()

    objective().backward()
    raw = kernel.raw_lengthscale
    grad = float(raw.grad[0, 1])
    h = 1e-6
    with torch.no_grad():
        raw[0, 1] += h
        up = float(objective())
        raw[0, 1] -= 2 * h
        down = float(objective())
        raw[0, 1] += h
    assert grad == pytest.approx((up - down) / (2 * h), rel=1e-5)


def test_from_gpytorch_refuses_what_it_cannot_serve():
    x, y = data()
    models, liks = user_models(x, y)
    with pytest.raises(GpmpcError, match="one model and one likelihood per residual row"):
        ResidualGP.from_gpytorch(models, liks[:1])
    with pytest.raises(GpmpcError, match="not a gpytorch.models.ExactGP"):
        ResidualGP.from_gpytorch([object(), models[1]], liks)
    with pytest.raises(GpmpcError, match=r"shape \(n, 2\)"):
        ResidualGP.from_gpytorch(models, liks).linearize(torch.zeros(3, 3, dtype=F64))
