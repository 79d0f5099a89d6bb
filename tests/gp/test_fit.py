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


# ---------------------------------------------------------------------- starts of a fit
def _crowd_case():
    """The 100-agent crowd's noiseless recipe (a 20 m square, 100 points per agent) and its system."""
    cfg = Config(scenario="random", num_agents=100, circle_radius=10.0, comm_radius=2.5, noise_std=0.0)
    return cfg, make_system(cfg.dim, cfg.noise_std, cfg.wind_scale)


def _held_out_rmse(gp, system, box: float) -> torch.Tensor:
    """(R,) each output row's RMSE against the true residual at 500 fresh points of the square."""
    x = (2 * torch.rand(500, 2, dtype=torch.float64, generator=torch.Generator().manual_seed(7)) - 1) * box
    return (gp.predict(x)[0] - system.residual(x)).square().mean(0).sqrt()


def test_a_later_start_replaces_the_row_the_first_left_as_noise(monkeypatch):
    """Agent 64 of the crowd: from lengthscale 1 alone its second row ends where the residual is
    noise (held out against the true residual: an error like the residual's own spread); the fit
    from the starts has a far higher marginal likelihood there and learns the residual."""
    import torch_gpmpc.gp.fit as fit
    from torch_gpmpc.gp import fit_agent_gp

    cfg, system = _crowd_case()
    box = cfg.gp_fit_settings().box
    monkeypatch.setattr(fit, "LENGTHSCALE_STARTS", (1.0,))
    first = fit_agent_gp(cfg, system, 64)
    monkeypatch.undo()
    both = fit_agent_gp(cfg, system, 64)
    assert float(fit._row_losses(first)[1] - fit._row_losses(both)[1]) > 1.0  # nats per point
    first_error, error = _held_out_rmse(first, system, box), _held_out_rmse(both, system, box)
    assert float(first_error[1]) > 0.03 and float(error[1]) < 1e-3


def test_the_fit_keeps_each_row_of_the_start_that_wins_it_by_the_gain(monkeypatch):
    """The fit's rows against separate fits from each start (the same code with one start): each row
    has the hyperparameters, to the bit, of the start the rule picks, and a row no later start beats by
    RESTART_GAIN keeps the first start's."""
    import torch_gpmpc.gp.fit as fit
    from torch_gpmpc.gp import fit_agent_gp

    cfg, system = _crowd_case()
    alone = {}
    for start in fit.LENGTHSCALE_STARTS:
        monkeypatch.setattr(fit, "LENGTHSCALE_STARTS", (start,))
        for k in (3, 64):
            alone[start, k] = fit_agent_gp(cfg, system, k)
    monkeypatch.undo()
    for k in (3, 64):
        gp = fit_agent_gp(cfg, system, k)
        kept = [fit.LENGTHSCALE_STARTS[0]] * 2
        losses = fit._row_losses(alone[kept[0], k])
        for start in fit.LENGTHSCALE_STARTS[1:]:
            other = fit._row_losses(alone[start, k])
            better = (losses - other) > fit.RESTART_GAIN
            if not bool(better.any()):
                break
            kept = [start if b else s for b, s in zip(better.tolist(), kept)]
            losses = torch.where(better, other, losses)
        for row, start in enumerate(kept):
            for mine, theirs in zip(gp.model.parameters(), alone[start, k].model.parameters()):
                assert torch.equal(mine[row], theirs[row])
        torch.testing.assert_close(fit._row_losses(gp), losses, rtol=0, atol=0)


def test_a_fit_no_later_start_improves_is_the_first_starts_to_the_bit(monkeypatch):
    """The paper's data (noise 0.1): no row gains RESTART_GAIN from a shorter start, so the fit is the
    one from lengthscale 1 alone, bit for bit, and the callback sees its steps and the final loss once."""
    import torch_gpmpc.gp.fit as fit
    from torch_gpmpc.data.collect import collect_transitions
    from torch_gpmpc.dynamics.systems import NominalModel

    cfg = Config(method="gp")
    system = make_system(cfg.dim, cfg.noise_std, cfg.wind_scale)
    X, Y = collect_transitions(system, num_agents=1, samples=100, seed=1).residuals(NominalModel())
    steps = []
    gp = fit.fit_residual_gp(X, Y, iters=20, callback=lambda step, loss, hp: steps.append((step, loss)))
    monkeypatch.setattr(fit, "LENGTHSCALE_STARTS", (1.0,))
    alone = fit.fit_residual_gp(X, Y, iters=20)
    a, b = gp.model.state_dict(), alone.model.state_dict()
    assert all(torch.equal(a[key], b[key]) for key in a)
    assert [s for s, _ in steps] == list(range(21))
    assert steps[-1][1] == float(fit._row_losses(gp).sum())


def test_a_fit_of_no_steps_keeps_the_initial_hyperparameters():
    """``iters = 0`` asks for no optimization: no later start replaces the initial lengthscale 1."""
    from torch_gpmpc.gp.fit import fit_residual_gp

    g = torch.Generator().manual_seed(0)
    gp = fit_residual_gp(torch.randn(40, 2, generator=g, dtype=torch.float64),
                         0.01 * torch.randn(40, 2, generator=g, dtype=torch.float64), iters=0)
    lengthscale = gp.model.covar_module.base_kernel.lengthscale.detach()
    torch.testing.assert_close(lengthscale, torch.ones_like(lengthscale))
