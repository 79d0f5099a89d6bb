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
