"""Held-out accuracy and calibration of a fitted residual GP."""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor

from torch_gpmpc.gp.model import ResidualGP

#: Standard-normal quantile of a two-sided 95 % interval.
Z95 = 1.959963984540054


def holdout_metrics(gp: ResidualGP, inputs: Tensor, y: Tensor) -> dict[str, Any]:
    """Held-out accuracy: RMSE and R^2 of the mean, coverage of 95% predictive intervals.

    Args:
        gp: a fitted model.
        inputs: held-out inputs, shape (m, Din).
        y: held-out residual targets, shape (m, D).

    Returns:
        ``{"rmse": [D floats], "r2": [D floats], "coverage95": [D floats], "coverage95_all": float,
        "num": m}`` where ``r2 = 1 - SSE / SST`` per output over the held-out rows (SST about
        their own mean; 0 for a constant held-out target) and coverage uses
        ``predict(include_noise=True)``.
    """
    with torch.no_grad():
        mean, var = gp.predict(inputs, include_noise=True)
        err = y - mean
        inside = (err.abs() <= Z95 * var.sqrt()).to(torch.float64)
        sst = (y - y.mean(0)).square().sum(0)
        r2 = torch.where(sst > 0, 1.0 - err.square().sum(0) / sst.clamp_min(1e-300), torch.zeros_like(sst))
    return {
        "rmse": err.square().mean(0).sqrt().tolist(),
        "r2": r2.tolist(),
        "coverage95": inside.mean(0).tolist(),
        "coverage95_all": float(inside.mean()),
        "num": int(y.shape[0]),
    }
