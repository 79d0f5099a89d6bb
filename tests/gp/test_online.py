"""Online GP updates against batch posteriors on the same rows and hyperparameters."""

from __future__ import annotations

import pytest
import torch

from torch_gpmpc import ResidualGP
from torch_gpmpc.gp.cholesky_update import cholesky_append, cholesky_drop_first, cholesky_rank_one
from torch_gpmpc.gp.fit import fit_residual_gp
from torch_gpmpc.gp.online import OnlineGP, OnlineLearning, online_gps

F64 = torch.float64


def _data(n, seed, shift=0.0):
    g = torch.Generator().manual_seed(seed)
    x = 4 * torch.rand(n, 3, generator=g, dtype=F64) - 2
    y = torch.stack([torch.sin(x[:, 0]) + shift, x[:, 1] * x[:, 2]], 1) + 0.05 * torch.randn(n, 2, generator=g, dtype=F64)
    return x, y


def _spd(n, seed):
    g = torch.Generator().manual_seed(seed)
    a = torch.randn(2, n, n, generator=g, dtype=F64)
    return a @ a.mT + n * torch.eye(n, dtype=F64)


def test_rank_one_update_and_downdate_match_a_new_factorization():
    K = _spd(6, 0)
    v = torch.randn(2, 6, generator=torch.Generator().manual_seed(1), dtype=F64)
    L = torch.linalg.cholesky(K)
    up = cholesky_rank_one(L, v, 1.0)
    torch.testing.assert_close(up, torch.linalg.cholesky(K + v[..., None] * v[:, None]), rtol=0, atol=1e-12)
    torch.testing.assert_close(cholesky_rank_one(up, v, -1.0), L, rtol=0, atol=1e-12)
    assert cholesky_rank_one(L, 100 * v, -1.0) is None  # not positive definite any more


def test_append_and_drop_first_match_a_new_factorization():
    K = _spd(7, 2)
    L = torch.linalg.cholesky(K[:, :6, :6])
    torch.testing.assert_close(cholesky_append(L, K[:, :6, 6], K[:, 6, 6]), torch.linalg.cholesky(K),
                               rtol=0, atol=1e-12)
    torch.testing.assert_close(cholesky_drop_first(torch.linalg.cholesky(K)), torch.linalg.cholesky(K[:, 1:, 1:]),
                               rtol=0, atol=1e-12)


def _batch_twin(gp, rows_x, rows_y, inducing=None):
    """A GP on exactly these rows with gp's standardization and hyperparameters, factored afresh."""
    twin = ResidualGP(rows_x, rows_y, gp_inputs=gp.gp_inputs, normalization=gp.standardization,
                      inducing_points=inducing)
    twin.model.load_state_dict(gp.model.state_dict())
    return twin.refresh()


@pytest.mark.parametrize("sparse", [False, True])
def test_online_rows_equal_a_refit_on_the_same_window(sparse):
    """Rank-one updates (exact) and the SGPR statistic updates equal the batch posterior of the
    window, to 1e-9, through the window's sliding (rows leave oldest first)."""
    x0, y0 = _data(30, 0)
    inducing = x0[:12].clone() if sparse else None
    gp = fit_residual_gp(x0, y0, iters=5, gp_inputs="x0,x1,x2")
    if sparse:
        gp = _batch_twin(gp, x0, y0, inducing)
    online = OnlineGP(gp, budget=35)
    x1, y1 = _data(15, 1, shift=0.5)
    for i in range(15):
        online.add(x1[i:i + 1], y1[i:i + 1])
    window_x, window_y = torch.cat([x0, x1])[-35:], torch.cat([y0, y1])[-35:]
    assert torch.equal(online.gp.train_inputs_raw, window_x)
    twin = _batch_twin(online.gp, window_x, window_y, inducing)
    q = _data(20, 7)[0]
    for a, b in zip(online.linearize(q), twin.linearize(q)):
        torch.testing.assert_close(a, b, rtol=0, atol=1e-9)


def test_sparse_update_equals_the_batch_sgpr_posterior_of_all_rows():
    x0, y0 = _data(40, 3)
    inducing = x0[:10].clone()
    gp = _batch_twin(fit_residual_gp(x0, y0, iters=5, gp_inputs="x0,x1,x2"), x0, y0, inducing)
    online = OnlineGP(gp, budget=1000)
    x1, y1 = _data(25, 4)
    online.add(x1, y1)
    twin = _batch_twin(online.gp, torch.cat([x0, x1]), torch.cat([y0, y1]), inducing)
    q = _data(10, 5)[0]
    torch.testing.assert_close(online.predict(q)[0], twin.predict(q)[0], rtol=0, atol=1e-9)
    torch.testing.assert_close(online.predict(q)[1], twin.predict(q)[1], rtol=0, atol=1e-9)


def test_a_fit_larger_than_the_budget_keeps_its_latest_rows_and_refits_on_schedule():
    x0, y0 = _data(30, 0)
    online = OnlineGP(fit_residual_gp(x0, y0, iters=3, gp_inputs="x0,x1,x2"), budget=20, refit_every=2)
    assert torch.equal(online.gp.train_inputs_raw, x0[-20:])
    before = online.gp.hyperparameters()["lengthscale"]
    x1, y1 = _data(4, 1, shift=2.0)
    refits = []
    for i in range(4):
        online.add(x1[i:i + 1], y1[i:i + 1])
        refits.append(online.end_step())
    assert refits == [False, True, False, True]
    assert online.gp.hyperparameters()["lengthscale"] != before


def test_learning_reduces_the_prediction_error_after_a_shift():
    """A residual that jumps by 0.5: the frozen GP keeps its error, the online one learns it."""
    from torch_gpmpc.config.model_spec import ModelSpec
    from torch_gpmpc.dynamics.systems import NominalModel

    nominal = NominalModel(ModelSpec.double_integrator(dim=2, dt=0.1, u_max=2.0))   # GP inputs: positions
    g = torch.Generator().manual_seed(0)
    x = torch.randn(40, 4, generator=g, dtype=F64)
    u = torch.zeros(40, 2, dtype=F64)
    shifted = nominal(x, u).clone()
    shifted[:, 2:] += 0.5
    # at the initial hyperparameters (lengthscale 1): a fit to this pure noise is free to pick any
    # lengthscale, and a short one would not carry the shift to the next, unseen point
    base = ResidualGP(nominal.gp_input(x, u), 0.01 * torch.randn(40, 2, generator=g, dtype=F64),
                      gp_inputs=",".join(nominal.spec.gp_inputs))
    frozen = OnlineLearning([base], nominal, online=False)
    online = OnlineLearning(online_gps([base], budget=30, refit_every=0), nominal, online=True)
    err_f = [frozen.observe(x[i:i + 1], u[i:i + 1], shifted[i:i + 1])[0] for i in range(40)]
    err_o = [online.observe(x[i:i + 1], u[i:i + 1], shifted[i:i + 1])[0] for i in range(40)]
    late_f = torch.cat(err_f[-10:]).abs().mean()
    late_o = torch.cat(err_o[-10:]).abs().mean()
    assert late_f > 0.45 and late_o < 0.1
    assert base.num_data == 40   # the frozen GP was not touched by the online copy


def test_transitions_with_a_large_input_change_are_not_added():
    """max_input_change: a row is added only if the agent's input moved by at most that since its
    previous step (the first step always); the skipped rows are counted per agent."""
    from torch_gpmpc.config.model_spec import ModelSpec
    from torch_gpmpc.dynamics.systems import NominalModel

    nominal = NominalModel(ModelSpec.double_integrator(dim=2, dt=0.1, u_max=2.0))
    g = torch.Generator().manual_seed(1)
    x = torch.randn(2, 6, 4, generator=g, dtype=F64)     # (agents, steps, state)
    base = fit_residual_gp(torch.randn(20, 2, generator=g, dtype=F64), 0.01 * torch.randn(20, 2, generator=g, dtype=F64),
                           iters=2, gp_inputs=",".join(nominal.spec.gp_inputs))
    learning = OnlineLearning(online_gps([base, base], budget=50, refit_every=0), nominal, online=True,
                              max_input_change=0.15)
    # agent 0 holds its input; agent 1 changes it by 0.1 then 0.3 then 0.0 then 0.2
    u = torch.tensor([[[0.5, 0.5], [0.5, 0.5], [0.5, 0.5], [0.5, 0.5], [0.5, 0.5]],
                      [[0.0, 0.0], [0.1, 0.0], [0.4, 0.0], [0.4, 0.0], [0.4, 0.2]]], dtype=F64)
    for t in range(5):
        learning.observe(x[:, t], u[:, t], x[:, t + 1])
    assert learning.skipped == [0, 2]
    assert [gp.gp.num_data for gp in learning.gps] == [25, 23]
