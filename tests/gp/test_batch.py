"""A team's models evaluated at once (gp.batch) give the bits of one call per model, whatever wraps them."""

from __future__ import annotations

import pytest
import torch

from tests.helpers import ConstantVarianceGP
from torch_gpmpc import ResidualGP
from torch_gpmpc.errors import GpmpcError
from torch_gpmpc.gp.batch import linearize_models, predict_models
from torch_gpmpc.gp.fit import fit_residual_gp
from torch_gpmpc.gp.guard import GuardedOnlineGP
from torch_gpmpc.gp.offset import OffsetCorrected
from torch_gpmpc.gp.online import OnlineGP

F64 = torch.float64


def _field(n: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    """n noisy rows of a smooth 2-output field of 2 inputs."""
    gen = torch.Generator().manual_seed(seed)
    x = torch.rand(n, 2, generator=gen, dtype=F64) * 4 - 2
    y = torch.stack([torch.sin(x[:, 0]) * x[:, 1], torch.cos(x[:, 1])], 1)
    return x, y + 0.05 * torch.randn(n, 2, generator=gen, dtype=F64)


@pytest.fixture(scope="module")
def team() -> list:
    """Six agents' models of every kind the runs plan with: fitted exact GPs (two of 30 rows, one of
    40: two batches), a sparse GP, offset-corrected and guarded online models, and a user's model."""
    exact = [fit_residual_gp(*_field(30, seed), iters=10, gp_inputs="x0,x1") for seed in range(2)]
    bigger = fit_residual_gp(*_field(40, 2), iters=10, gp_inputs="x0,x1")
    sparse = fit_residual_gp(*_field(200, 3), iters=10, method="sgpr", num_inducing=20, gp_inputs="x0,x1")
    offset = OffsetCorrected(exact[1], drift=0.01)
    offset.offset = torch.tensor([0.03, -0.02], dtype=F64)
    offset.variance = torch.tensor([1e-4, 2e-4], dtype=F64)
    guarded = GuardedOnlineGP(OnlineGP(fit_residual_gp(*_field(30, 4), iters=10, gp_inputs="x0,x1"), budget=40))
    z = torch.tensor([[0.5, -0.5]], dtype=F64)
    for _ in range(5):  # the residual moved up by 0.5 there; the learner grows to 35 rows: its own batch
        guarded.judge(z, guarded.frozen.predict(z)[0] + 0.5)
        guarded.add(z, guarded.frozen.predict(z)[0] + 0.5)
    assert guarded.adopted
    return [exact[0], offset, bigger, sparse, OffsetCorrected(guarded, drift=0.01), ConstantVarianceGP(0.3)]


def _points(batch: int, n: int = 7) -> torch.Tensor:
    return torch.rand(batch, n, 2, generator=torch.Generator().manual_seed(9), dtype=F64) * 5 - 2.5


def test_linearize_models_is_each_models_linearize_bit_for_bit(team):
    x = _points(len(team))
    batched = linearize_models(team, x)
    for b, model in enumerate(team):
        for got, want in zip(batched, model.linearize(x[b])):
            assert torch.equal(got[b], want), f"model {b}"


def test_the_noise_is_added_as_a_caller_adds_it(team):
    x = _points(len(team))
    _, _, var = linearize_models(team, x, include_noise=True)
    for b, model in enumerate(team):
        assert torch.equal(var[b], model.linearize(x[b])[2] + model.noise), f"model {b}"


def test_predict_models_is_each_models_predict_bit_for_bit(team):
    x = list(_points(len(team), n=3))
    for include_noise in (False, True):
        batched = predict_models(team[:-1], x[:-1], include_noise=include_noise)
        for b, model in enumerate(team[:-1]):
            for got, want in zip(batched[b], model.predict(x[b], include_noise=include_noise)):
                assert torch.equal(got, want), f"model {b}, include_noise={include_noise}"


def test_a_whole_team_of_one_kind_is_one_batch_and_still_each_ones_bits():
    gps = [fit_residual_gp(*_field(25, seed), iters=5, gp_inputs="x0,x1") for seed in range(12)]
    x = _points(12, n=11)
    mean, jac, var = linearize_models(gps, x)
    for b, gp in enumerate(gps):
        for got, want in zip((mean[b], jac[b], var[b]), gp.linearize(x[b])):
            assert torch.equal(got, want)


def test_hyperparameter_gradients_take_each_models_own_path():
    gp = ResidualGP(*_field(20, 0), gp_inputs="x0,x1").enable_hyperparameter_gradients()
    x = _points(1)
    mean, _, var = linearize_models([gp], x)
    (mean.sum() + var.sum()).backward()
    assert gp.model.covar_module.raw_outputscale.grad is not None


def test_the_batch_is_differentiable_in_the_points_like_each_model():
    gps = [fit_residual_gp(*_field(25, seed), iters=5, gp_inputs="x0,x1") for seed in range(3)]
    x = _points(3).requires_grad_(True)
    mean, _, var = linearize_models(gps, x)
    (grad,) = torch.autograd.grad(mean.sum() + var.sum(), x)
    for b, gp in enumerate(gps):
        xb = x[b].detach().requires_grad_(True)
        m, _, v = gp.linearize(xb)
        torch.testing.assert_close(grad[b], torch.autograd.grad(m.sum() + v.sum(), xb)[0], rtol=1e-12, atol=1e-14)


def test_a_model_that_predicts_otherwise_is_asked_itself():
    """A subclass or an instance that replaces linearize is not batched from its GP: the batch would
    skip what it adds."""

    class Doubled(ResidualGP):
        def linearize(self, x):
            mean, jac, var = super().linearize(x)
            return mean, jac, 2 * var

    x, y = _field(20, 0)
    doubled, plain = Doubled(x, y, gp_inputs="x0,x1"), ResidualGP(x, y, gp_inputs="x0,x1")
    patched = OffsetCorrected(ResidualGP(x, y, gp_inputs="x0,x1"), drift=0.01)
    patched.linearize = lambda z: tuple(2 * part for part in OffsetCorrected.linearize(patched, z))
    points = _points(3)
    _, _, var = linearize_models([doubled, plain, patched], points)
    torch.testing.assert_close(var[0], 2 * plain.linearize(points[0])[2], rtol=0, atol=0)
    torch.testing.assert_close(var[2], patched.linearize(points[2])[2], rtol=0, atol=0)


def test_wrong_points_and_wrong_results_are_named():
    gp = fit_residual_gp(*_field(20, 0), iters=5, gp_inputs="x0,x1")
    with pytest.raises(GpmpcError, match=r"shape \(n, 2\)"):
        linearize_models([gp], torch.zeros(1, 4, 3, dtype=F64))
    with pytest.raises(GpmpcError, match=r"\(B, n, Din\) with B = 2"):
        linearize_models([gp, gp], torch.zeros(3, 4, 2, dtype=F64))
    with pytest.raises(GpmpcError, match="one per model"):
        predict_models([gp, gp], [torch.zeros(1, 2, dtype=F64)])

    class Wrong(ConstantVarianceGP):
        def linearize(self, x):
            mean, jac, var = super().linearize(x)
            return mean[:, :1], jac, var

    with pytest.raises(GpmpcError, match="agent 1 returned a mean"):
        linearize_models([gp, Wrong(0.1)], torch.zeros(2, 4, 2, dtype=F64))
