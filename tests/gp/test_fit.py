"""Fitting that never crashes: the noise-free data of seed 1 (the noise variance runs to
its lower bound and an L-BFGS line search steps into NaN)."""

from __future__ import annotations

import torch

from torch_gpmpc.config import Config
from torch_gpmpc.dynamics.systems import make_system
from torch_gpmpc.gp import fit_agent_gps


def test_noise_free_seed_1_fits_with_finite_hyperparameters(caplog):
    cfg = Config(noise_std=0.0, seed=1, method="gp")
    system = make_system(cfg.dim, cfg.noise_std, cfg.wind_scale)
    gps = fit_agent_gps(cfg, system, 3)
    assert "produced NaN" in caplog.text  # the failure this guards against really happens here
    assert "noise ~ 0" in caplog.text  # and the warning names the hyperparameter at its bound
    x = torch.zeros(4, 2, dtype=torch.float64)
    for gp in gps:
        mean, var = gp.predict(x)
        assert bool(torch.isfinite(mean).all() and torch.isfinite(var).all())
        assert all(torch.isfinite(torch.as_tensor(v)).all() for v in gp.hyperparameters().values()
                   if not isinstance(v, str))
        # the fit still learns the wind: the residual at the origin is g(0) = [0, 0.1]
        torch.testing.assert_close(mean[0], torch.tensor([0.0, 0.1], dtype=torch.float64), atol=0.01, rtol=0)


def _fits(cfg: Config, monkeypatch, remembered: int) -> tuple[list[dict], int]:
    """The three agents' fitted state dicts and the marginal-likelihood evaluations they took."""
    import torch_gpmpc.gp.fit as fit

    calls = []
    evaluate = fit._neg_mll
    monkeypatch.setattr(fit, "_neg_mll", lambda model, mll: calls.append(1) or evaluate(model, mll))
    monkeypatch.setattr(fit, "RECENT_EVALUATIONS", remembered)
    gps = fit_agent_gps(cfg, make_system(cfg.dim, cfg.noise_std, cfg.wind_scale), 3)
    return [gp.model.state_dict() for gp in gps], len(calls)


def test_lbfgs_reuses_the_line_searchs_last_evaluation_bit_for_bit(monkeypatch):
    """Each L-BFGS step starts by evaluating the point its previous line search ended on; the fit
    answers it from memory: the same hyperparameters to the bit (through the NaN recovery of
    noise-free seed 1 as well) with about half the evaluations."""
    for cfg in (Config(method="gp"), Config(noise_std=0.0, seed=1, method="gp")):
        plain, plain_calls = _fits(cfg, monkeypatch, remembered=0)
        memo, memo_calls = _fits(cfg, monkeypatch, remembered=4)
        for a, b in zip(plain, memo):
            assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
        assert memo_calls < 0.6 * plain_calls


def test_a_runs_gp_fit_does_not_depend_on_torchs_thread_count():
    """Agent 42 of the 100-agent crowd's noiseless recipe is one whose fit differed on two torch
    threads (its predictions by 4e-12, and the crowd's closed loop with it); the recipe fits run on
    one thread and restore the caller's count."""
    from torch_gpmpc.gp import fit_agent_gp

    cfg = Config(scenario="random", num_agents=100, circle_radius=10.0, comm_radius=2.5, noise_std=0.0)
    system = make_system(cfg.dim, cfg.noise_std, cfg.wind_scale)
    x = torch.randn(50, 2, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    threads = torch.get_num_threads()
    means = []
    try:
        for count in (1, 2):
            torch.set_num_threads(count)
            gp = fit_agent_gp(cfg, system, 42)
            assert torch.get_num_threads() == count
            means.append(gp.predict(x)[0])
    finally:
        torch.set_num_threads(threads)
    assert torch.equal(means[0], means[1])


def test_a_model_file_names_the_residual_rows_it_learned_and_a_run_of_another_model_refuses_it(tmp_path):
    """A GP of a double integrator's velocity residuals (rows x2, x3) has the shape of the single
    integrator's (rows x0, x1): loading it there ran without a word. Files without the entry (older
    ones) still load."""
    import pytest

    from torch_gpmpc.errors import GpmpcError
    from torch_gpmpc.gp import ResidualGP, load_model_gp

    x = torch.randn(20, 2, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    gp = ResidualGP(x, 0.1 * torch.sin(x), gp_inputs="x0,x1")
    single, double = Config().model_spec(), Config(model="double-integrator").model_spec()
    gp.residual_rows = "x2,x3"
    gp.save(tmp_path / "di.pt")
    assert load_model_gp(str(tmp_path / "di.pt"), double).residual_rows == "x2,x3"
    with pytest.raises(GpmpcError, match="learned the residuals of state rows x2,x3 but the run's model has "
                                         "its residuals in rows x0,x1"):
        load_model_gp(str(tmp_path / "di.pt"), single)
    gp.residual_rows = None
    gp.save(tmp_path / "old.pt")
    assert load_model_gp(str(tmp_path / "old.pt"), single).residual_rows is None


def test_the_recipe_fits_record_their_models_residual_rows():
    cfg = Config(model="double-integrator", method="gp")
    from torch_gpmpc.dynamics.team import team_system_from_config
    from torch_gpmpc.gp import fit_agent_gp

    assert fit_agent_gp(cfg.replace(gp_iters=1), team_system_from_config(cfg), 0).residual_rows == "x2,x3"
