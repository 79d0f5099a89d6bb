"""The sparse (SGPR) residual GP against independent answers: GPyTorch's own SGPR
(``InducingPointKernel``), the Nystrom term by direct solves, finite differences, a file
round trip, and a smooth field it must learn from thousands of rows."""

from __future__ import annotations

import math

import gpytorch
import pytest
import torch

from torch_gpmpc.data.transitions import Transitions
from torch_gpmpc.gp import ResidualGP, fit_residual_gp, holdout_metrics
from torch_gpmpc.gp import sparse
from torch_gpmpc.gp.fit import resolve_method

F64 = torch.float64


def _data(n: int, seed: int = 0, noise: float = 0.05) -> tuple[torch.Tensor, torch.Tensor]:
    """A smooth 2-output field of 3 inputs with Gaussian noise."""
    gen = torch.Generator().manual_seed(seed)
    x = torch.rand(n, 3, generator=gen, dtype=F64) * 4 - 2
    y = torch.stack([torch.sin(x[:, 0]) + 0.5 * x[:, 1], torch.cos(x[:, 1] * x[:, 2])], dim=1)
    return x, y + noise * torch.randn(n, 2, generator=gen, dtype=F64)


@pytest.fixture(scope="module")
def sgpr():
    x, y = _data(400)
    return fit_residual_gp(x, y, iters=15, method="sgpr", gp_inputs="x0,x1,x2", num_inducing=60)


class _GPyTorchSGPR(gpytorch.models.ExactGP):
    def __init__(self, x, y, likelihood, inducing):
        super().__init__(x, y, likelihood)
        self.mean_module = gpytorch.means.ZeroMean()
        self.base = gpytorch.kernels.ScaleKernel(gpytorch.kernels.RBFKernel(ard_num_dims=x.shape[-1]))
        self.covar_module = gpytorch.kernels.InducingPointKernel(self.base, inducing_points=inducing,
                                                                 likelihood=likelihood)

    def forward(self, x):
        return gpytorch.distributions.MultivariateNormal(self.mean_module(x), self.covar_module(x))


def test_sparse_mean_is_gpytorchs_sgpr_and_variance_adds_the_nystrom_term(sgpr):
    gp = sgpr
    assert gp.method == "sgpr" and gp.hyperparameters()["num_inducing"] == 60
    xq = _data(30, seed=5)[0]
    mean, var = gp.predict(xq)
    s = gp.standardization
    zq, zf, zu = s.inputs(xq), s.inputs(gp.train_inputs_raw), s.inputs(gp.inducing_points)
    ls = gp.model.covar_module.base_kernel.lengthscale.detach().reshape(2, -1)
    outputscale = gp.model.covar_module.outputscale.detach().reshape(2)
    noise = gp.likelihood.noise.detach().reshape(2)
    for d in range(2):
        likelihood = gpytorch.likelihoods.GaussianLikelihood()
        ys = s.outputs(gp.train_y_raw)[:, d]
        model = _GPyTorchSGPR(zf, ys, likelihood, zu.clone()).to(F64)
        model.base.base_kernel.lengthscale = ls[d]
        model.base.outputscale = outputscale[d]
        likelihood.noise = noise[d]
        model.eval()
        likelihood.eval()
        # without GPyTorch's FITC-like diagonal correction its SGPR is the Titsias posterior's mean
        with torch.no_grad(), gpytorch.settings.fast_pred_var(False), gpytorch.settings.max_cholesky_size(10**6), \
                gpytorch.settings.sgpr_diagonal_correction(False):
            post = model(zq)
            ref_mean = s.y_mean[d] + s.y_std[d] * post.mean
            # GPyTorch's SGPR variance is the DTC one; the Titsias posterior adds k_xx - k_xu K_uu^-1 k_ux
            kern = lambda a, b: outputscale[d] * torch.exp(-0.5 * torch.cdist(a / ls[d], b / ls[d]).square())  # noqa: E731
            K_uu = kern(zu, zu)
            k_ux = kern(zu, zq)
            nystrom = outputscale[d] - (k_ux * torch.linalg.solve(K_uu, k_ux)).sum(0)
            ref_var = s.y_std[d] ** 2 * (post.variance + nystrom)
        torch.testing.assert_close(mean[:, d], ref_mean, atol=1e-7, rtol=1e-6)
        torch.testing.assert_close(var[:, d], ref_var, atol=1e-8, rtol=1e-4)


def test_sparse_linearize_matches_predict_and_finite_differences(sgpr):
    gp = sgpr
    x = _data(6, seed=7)[0]
    mean, var = gp.predict(x)
    m2, jac, v2 = gp.linearize(x)
    torch.testing.assert_close(m2, mean)
    torch.testing.assert_close(v2, var)
    h = 1e-6
    for i in range(3):
        e = torch.zeros(3, dtype=F64)
        e[i] = h
        fd = (gp.predict(x + e)[0] - gp.predict(x - e)[0]) / (2 * h)
        torch.testing.assert_close(jac[:, :, i], fd, atol=1e-6, rtol=1e-5)


def test_sparse_model_file_round_trip(sgpr, tmp_path):
    path = tmp_path / "sgpr.pt"
    sgpr.save(path)
    loaded = ResidualGP.load(path, expected_dim=2, expected_input_dim=3)
    assert loaded.method == "sgpr"
    x = _data(8, seed=9)[0]
    for a, b in zip(sgpr.linearize(x), loaded.linearize(x), strict=True):
        torch.testing.assert_close(a, b)
    payload = torch.load(path, weights_only=True)
    payload["inducing_points"] = payload["inducing_points"][:, :2]
    torch.save(payload, tmp_path / "bad.pt")
    from torch_gpmpc.errors import GpmpcError

    with pytest.raises(GpmpcError, match="inducing_points"):
        ResidualGP.load(tmp_path / "bad.pt")


def test_auto_method_switches_at_the_threshold():
    assert resolve_method("auto", sparse.EXACT_MAX_POINTS) == "exact"
    assert resolve_method("auto", sparse.EXACT_MAX_POINTS + 1) == "sgpr"
    assert resolve_method("exact", 10**6) == "exact"


def test_sparse_fit_learns_a_smooth_field_from_thousands_of_rows_with_calibrated_intervals():
    """A wind-tunnel-like residual: smooth and strong against the noise, 4000 rows (auto picks
    SGPR); held out by time blocks: R^2 >= 0.95 and 95 % coverage in [0.9, 0.99]."""
    x, y = _data(4000, seed=1, noise=0.05)
    data = Transitions(x=x, u=torch.zeros(4000, 3, dtype=F64), x_next=x)
    train, test = data.split(0.2, seed=0, mode="blocks")
    rows = lambda part: (part.x, y[(part.x[:, None, :] == x[None]).all(-1).nonzero()[:, 1]])  # noqa: E731
    gp = fit_residual_gp(*rows(train), iters=30, gp_inputs="x0,x1,x2")
    assert gp.method == "sgpr"
    m = holdout_metrics(gp, *rows(test))
    assert min(m["r2"]) >= 0.95, m
    assert all(0.9 <= c <= 0.99 for c in m["coverage95"]), m


def test_holdout_r2_is_one_minus_sse_over_sst():
    class Fixed:
        def predict(self, x, include_noise=False):
            return x.clone(), torch.ones_like(x)

    x = torch.tensor([[1.0], [2.0], [4.0]], dtype=F64)
    y = torch.tensor([[1.5], [2.0], [3.0]], dtype=F64)
    m = holdout_metrics(Fixed(), x, y)
    sse, sst = 0.25 + 0 + 1.0, ((y - y.mean()) ** 2).sum().item()
    assert m["r2"][0] == pytest.approx(1 - sse / sst)
    assert m["rmse"][0] == pytest.approx(math.sqrt(sse / 3))
