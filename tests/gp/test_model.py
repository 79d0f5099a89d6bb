"""ResidualGP against independent answers: the true wind, finite differences, a
closed form written from the paper's equations, GPyTorch's own predictions."""

from __future__ import annotations

import os
import pickle

import gpytorch
import numpy as np
import pytest
import torch

from torch_gpmpc.data import collect_transitions
from torch_gpmpc.errors import GpmpcError
from torch_gpmpc.gp import ResidualGP, fit_per_agent, fit_residual_gp, holdout_metrics
from torch_gpmpc.gp.cache import safe_cholesky
from torch_gpmpc.gp.io import FORMAT
from torch_gpmpc.dynamics.systems import NominalModel, make_system

SYSTEM = make_system(noise_std=0.1)
#: grid RMSE of the seed-0 fit measured at 0.0379 (10 seeds: 0.021-0.044); the bound
#: leaves margin for BLAS differences but is far below the wind amplitude 0.1.
RMSE_BOUND = 0.05


@pytest.fixture(scope="module")
def train():
    """The paper's data for one agent: N = 100, noise std 0.1, seed 0."""
    return collect_transitions(SYSTEM, num_agents=1, samples=100, seed=0).residuals(NominalModel())


@pytest.fixture(scope="module")
def gp(train) -> ResidualGP:
    """Fitted with the real defaults (L-BFGS, 50 iterations)."""
    return fit_residual_gp(*train)


@pytest.fixture(scope="module")
def grid() -> torch.Tensor:
    axis = torch.linspace(-4.0, 4.0, 20, dtype=torch.float64)
    return torch.stack(torch.meshgrid(axis, axis, indexing="ij"), dim=-1).reshape(-1, 2)


@pytest.fixture(scope="module")
def queries() -> torch.Tensor:
    gen = torch.Generator().manual_seed(7)
    return (torch.rand(15, 2, generator=gen, dtype=torch.float64) * 2 - 1) * 4.5  # also a little outside the data


# ---------------------------------------------------------------------- independent closed form
def paper_gp(gp: ResidualGP, X: torch.Tensor, Y: torch.Tensor, x: torch.Tensor):
    """Mean (eq. 3) and latent variance (eq. 4) written directly in raw units.

    The model standardizes y, i.e. its prior mean is the empirical mean m_d of Y_d;
    eq. 3 then applies to the centred targets: mu_d = m_d + k^T (K + s^2 I)^{-1} (Y_d - m_d).
    Uses only the model's raw hyperparameters and a dense solve (no Cholesky, no cache).
    """
    m = Y.mean(0)
    means, variances = [], []
    for d in range(Y.shape[1]):
        ell, sf2, sn2 = gp.lengthscales[d], gp.outputscales[d], gp.noise[d]

        def kappa(a, b, sf2=sf2, ell=ell):
            return sf2 * torch.exp(-0.5 * (((a[:, None, :] - b[None, :, :]) / ell) ** 2).sum(-1))

        A = kappa(X, X) + sn2 * torch.eye(X.shape[0], dtype=torch.float64)
        ks = kappa(x, X)
        means.append(m[d] + ks @ torch.linalg.solve(A, Y[:, d] - m[d]))
        variances.append(sf2 - (ks * torch.linalg.solve(A, ks.T).T).sum(-1))
    return torch.stack(means, 1), torch.stack(variances, 1)


def test_recovers_the_wind_on_a_grid(gp, grid):
    mean, _ = gp.predict(grid)
    rmse = float((mean - SYSTEM.wind(grid)).square().mean().sqrt())
    print(f"grid RMSE {rmse:.4f}")
    assert rmse < RMSE_BOUND


def test_predictive_intervals_cover_held_out_data(gp):
    test = collect_transitions(SYSTEM, num_agents=1, samples=500, seed=1000).residuals(NominalModel())
    cov = holdout_metrics(gp, *test)["coverage95_all"]
    print(f"95% coverage {cov:.3f}")
    assert 0.90 <= cov <= 0.99


def test_hyperparameters_are_sensible(gp):
    hp = gp.hyperparameters()
    # g_1 = 0.1 sin(x_2) ignores x_1, g_2 = 0.1 cos(x_1) ignores x_2 (ARD finds it)
    assert hp["lengthscale"][0][0] > 3 * hp["lengthscale"][0][1]
    assert hp["lengthscale"][1][1] > 3 * hp["lengthscale"][1][0]
    # the noise variance is near s^2 = 0.01
    assert all(0.005 < s2 < 0.02 for s2 in hp["noise"])
    assert gp.lengthscales.shape == (2, 2) and gp.outputscales.shape == (2,) and gp.noise.shape == (2,)


def test_mean_and_variance_match_the_paper_formulas(gp, train, queries):
    mean, var = gp.predict(queries)
    ref_mean, ref_var = paper_gp(gp, *train, queries)
    torch.testing.assert_close(mean, ref_mean, rtol=1e-9, atol=1e-12)
    torch.testing.assert_close(var, ref_var, rtol=1e-7, atol=1e-12)
    _, var_noisy = gp.predict(queries, include_noise=True)
    torch.testing.assert_close(var_noisy, var + gp.noise, rtol=0, atol=1e-15)


def test_jacobian_matches_autograd_of_the_paper_formula(gp, train, queries):
    x = queries.clone().requires_grad_(True)
    jac_ref = torch.autograd.functional.jacobian(lambda z: paper_gp(gp, *train, z)[0].sum(0), x)  # (D, n, Din)
    torch.testing.assert_close(gp.mean_jacobian(queries), jac_ref.permute(1, 0, 2), rtol=1e-8, atol=1e-12)


def test_jacobian_matches_central_differences(gp, queries):
    h = 1e-5
    cols = []
    for i in range(2):
        e = torch.zeros(2, dtype=torch.float64)
        e[i] = h
        cols.append((gp.predict(queries + e)[0] - gp.predict(queries - e)[0]) / (2 * h))
    fd = torch.stack(cols, dim=-1)  # (n, D, Din)
    torch.testing.assert_close(gp.mean_jacobian(queries), fd, rtol=1e-5, atol=1e-9)


def test_predict_matches_gpytorch_eval_mode(gp, train, queries):
    X, Y = train
    gp.model.eval()
    gp.likelihood.eval()
    z = ((queries - X.mean(0)) / X.std(0)).expand(2, -1, -1)
    with torch.no_grad():
        post = gp.model(z)
        noisy = gp.likelihood(post)
    mean_ref = Y.mean(0) + Y.std(0) * post.mean.T
    var_ref = Y.var(0) * post.variance.T
    mean, var = gp.predict(queries)
    torch.testing.assert_close(mean, mean_ref, rtol=1e-10, atol=1e-13)
    torch.testing.assert_close(var, var_ref, rtol=1e-8, atol=1e-13)
    torch.testing.assert_close(gp.predict(queries, include_noise=True)[1], Y.var(0) * noisy.variance.T,
                               rtol=1e-8, atol=1e-13)


def test_linearize_equals_predict_and_mean_jacobian(gp, queries):
    mean, jac, var = gp.linearize(queries)
    assert mean.shape == (15, 2) and jac.shape == (15, 2, 2) and var.shape == (15, 2)
    pm, pv = gp.predict(queries)
    assert torch.equal(mean, pm) and torch.equal(var, pv)
    torch.testing.assert_close(jac, gp.mean_jacobian(queries), rtol=0, atol=0)


def test_linearize_is_differentiable_in_x(gp, queries):
    x = queries[:3].clone().requires_grad_(True)
    mean, _, _ = gp.linearize(x)
    (grad,) = torch.autograd.grad(mean[:, 0].sum(), x)
    torch.testing.assert_close(grad, gp.mean_jacobian(queries[:3])[:, 0, :], rtol=1e-10, atol=1e-14)


def test_query_shape_is_checked(gp):
    with pytest.raises(GpmpcError, match=r"shape \(n, 2\)"):
        gp.predict(torch.zeros(3, 4, dtype=torch.float64))


# ---------------------------------------------------------------------- other fitting paths
def test_state_input_model_and_adam_with_callback():
    tr = collect_transitions(SYSTEM, num_agents=1, samples=40, seed=2)
    X, Y = tr.residuals(NominalModel(), gp_inputs="state_input")
    steps = []
    gp = fit_residual_gp(X, Y, optimizer="adam", iters=5, gp_inputs="state_input",
                         callback=lambda step, loss, hp: steps.append((step, loss, hp)))
    assert [s for s, _, _ in steps] == list(range(6))
    assert steps[-1][1] < steps[0][1]  # Adam decreased the loss
    assert np.array(steps[0][2]["lengthscale"]).shape == (2, 4)
    mean, jac, var = gp.linearize(X[:5])
    assert jac.shape == (5, 2, 4) and gp.gp_inputs == "state_input"
    h = 1e-5
    e = torch.zeros(4, dtype=torch.float64)
    e[3] = h
    fd = (gp.predict(X[:5] + e)[0] - gp.predict(X[:5] - e)[0]) / (2 * h)
    torch.testing.assert_close(jac[:, :, 3], fd, rtol=1e-5, atol=1e-9)


def test_one_gp_per_agent():
    tr = collect_transitions(SYSTEM, num_agents=2, samples=30, seed=4)
    gps = fit_per_agent(tr, iters=3)
    assert sorted(gps) == [0, 1] and gps[0] is not gps[1]
    assert torch.equal(gps[1].train_inputs_raw, tr.for_agent(1).x)


def test_cholesky_failure_is_a_clear_error():
    K = -torch.eye(3, dtype=torch.float64).expand(2, 3, 3)
    with pytest.raises(GpmpcError, match="not positive definite even with jitter"):
        safe_cholesky(K, torch.ones(2, dtype=torch.float64))


def test_fit_rejects_bad_arguments(train):
    with pytest.raises(GpmpcError, match="optimizer must be"):
        fit_residual_gp(*train, optimizer="sgd")
    with pytest.raises(GpmpcError, match="same N"):
        fit_residual_gp(train[0][:10], train[1][:9])
    with pytest.raises(GpmpcError, match="NaN or inf"):
        fit_residual_gp(train[0] * float("nan"), train[1])


# ---------------------------------------------------------------------- files
def test_save_load_round_trip_is_identical(gp, tmp_path, queries):
    gp.save(tmp_path / "m.pt")
    back = ResidualGP.load(tmp_path / "m.pt", expected_dim=2)
    for a, b in zip(gp.linearize(queries), back.linearize(queries), strict=True):
        assert torch.equal(a, b)
    assert back.hyperparameters() == gp.hyperparameters()
    assert [p.name for p in tmp_path.iterdir()] == ["m.pt"]  # no temporary left behind


def test_wrong_dimension_is_refused(gp, tmp_path):
    gp.save(tmp_path / "m.pt")
    with pytest.raises(GpmpcError, match="predicts D=2 residual dimensions but D=3 is required"):
        ResidualGP.load(tmp_path / "m.pt", expected_dim=3)
    with pytest.raises(GpmpcError, match="Din=2 inputs"):
        ResidualGP.load(tmp_path / "m.pt", expected_input_dim=4)


class _Touch:
    """A pickle payload that would run a shell command when unpickled."""

    def __init__(self, target):
        self.target = str(target)

    def __reduce__(self):
        return (os.system, (f"touch {self.target}",))


class _OpenForWriting:
    """A pickle payload that would create a file when unpickled."""

    def __init__(self, target):
        self.target = str(target)

    def __reduce__(self):
        return (open, (self.target, "w"))


def test_malicious_pickles_are_refused(tmp_path):
    target = tmp_path / "pwned"
    files = {"torch_zip_system": tmp_path / "a.pt", "raw_pickle_open": tmp_path / "b.pt",
             "torch_zip_open": tmp_path / "c.pt", "raw_pickle4_system": tmp_path / "d.pt"}
    torch.save({"format": FORMAT, "version": 1, "payload": _Touch(target)}, files["torch_zip_system"])
    files["raw_pickle_open"].write_bytes(pickle.dumps(_OpenForWriting(target), protocol=2))
    torch.save([_OpenForWriting(target)], files["torch_zip_open"])
    files["raw_pickle4_system"].write_bytes(pickle.dumps(_Touch(target), protocol=4))
    for name, path in files.items():
        with pytest.raises(GpmpcError) as info:
            ResidualGP.load(path)
        # protocol-4 framing is already unreadable for the safe unpickler ("cannot be read")
        expected = "cannot be read" if "pickle4" in name else "refused to load"
        assert expected in str(info.value), name
        assert not target.exists(), name
    # the payload is live: an unsafe load does run it (proves the test is not vacuous)
    torch.load(files["torch_zip_system"], weights_only=False)
    assert target.exists()


@pytest.mark.parametrize("kind", ["random", "truncated", "empty"])
def test_corrupt_files_are_refused(gp, tmp_path, kind):
    path = tmp_path / "m.pt"
    if kind == "random":
        path.write_bytes(np.random.default_rng(0).bytes(4096))
    elif kind == "truncated":
        gp.save(path)
        path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    else:
        path.write_bytes(b"")
    with pytest.raises(GpmpcError, match="cannot be read"):
        ResidualGP.load(path)


def test_wrong_format_and_tampered_content(gp, tmp_path):
    path = tmp_path / "m.pt"
    torch.save({"weights": torch.zeros(3, dtype=torch.float64)}, path)
    with pytest.raises(GpmpcError, match="not a torch_gpmpc ResidualGP file"):
        ResidualGP.load(path)
    gp.save(path)
    good = torch.load(path, weights_only=True)
    key = "covar_module.base_kernel.raw_lengthscale"
    bad = {**good, "state_dict": {**good["state_dict"], key: good["state_dict"][key] * float("nan")}}
    torch.save(bad, path)
    with pytest.raises(GpmpcError, match="NaN/inf"):
        ResidualGP.load(path)
    bad = {**good, "state_dict": {k: v for k, v in good["state_dict"].items() if k != key}}
    torch.save(bad, path)
    with pytest.raises(GpmpcError, match="expected hyperparameters"):
        ResidualGP.load(path)
    bad = {**good, "y_std": torch.ones(3, dtype=torch.float64)}
    torch.save(bad, path)
    with pytest.raises(GpmpcError, match="'y_std' has shape"):
        ResidualGP.load(path)
    with pytest.raises(GpmpcError, match="file not found"):
        ResidualGP.load(tmp_path / "missing.pt")


def test_gpytorch_settings_untouched():
    """Fitting must not leave global GPyTorch settings changed."""
    assert gpytorch.settings.cholesky_jitter.value(torch.float64) == 1e-8
