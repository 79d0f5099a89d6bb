"""The prediction cache of a fitted :class:`~torch_gpmpc.gp.model.ResidualGP`.

Like GPyTorch's exact prediction strategy, the fitted model keeps the Cholesky factor of
``K + s^2 I`` and ``alpha = (K + s^2 I)^{-1} y`` in one object, rebuilt by
``ResidualGP.refresh()`` whenever the hyperparameters change.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import torch
from torch import Tensor

from torch_gpmpc.errors import GpmpcError

log = logging.getLogger(__name__)


@dataclass
class PredictionCache:
    """Everything ``ResidualGP.linearize`` needs (standardized units unless noted).

    Shapes: D outputs, N support points (the training points of an exact GP, the inducing
    points of a sparse one), Din inputs. The latent variance is
    ``outputscale - ||chol^-1 k||^2 (+ ||chol_add^-1 k||^2 for a sparse GP)``.
    """

    x_mean: Tensor  # (Din,) raw
    x_std: Tensor  # (Din,) raw
    ls: Tensor  # (D, 1, Din) standardized lengthscales
    x_scale: Tensor  # (D, 1, Din) raw: x_std * lengthscale
    S: Tensor  # (D, N, Din) training inputs / lengthscale (standardized)
    S_cols: tuple[Tensor, ...]  # Din contiguous columns of S, each (D, 1, N)
    outputscale: Tensor  # (D,)
    chol: Tensor  # (D, N, N) lower Cholesky factor of K + s^2 I
    alpha: Tensor  # (D, N) (K + s^2 I)^{-1} y
    y_mean: Tensor  # (D,) raw
    y_std: Tensor  # (D,) raw
    noise_raw: Tensor  # (D,) raw noise variance
    chol_add: Tensor | None = None  # (D, N, N) sparse GP: lower factor of Sigma^-1 (gp.sparse)


def parameter_values(module: torch.nn.Module) -> Tensor:
    """A snapshot of a module's parameter values, flattened (a new tensor): what a prediction
    cache is keyed on, so that in-place optimizer steps and setter assignments are both seen."""
    return torch.cat([p.detach().reshape(-1) for p in module.parameters()])


def squared_distances(a: Tensor, b: Tensor) -> Tensor:
    """Squared Euclidean distances, shape (..., n, m), computed without the mm trick."""
    return torch.cdist(a, b, compute_mode="donot_use_mm_for_euclid_dist").square()


def safe_cholesky(K: Tensor, outputscale: Tensor) -> Tensor:
    """Lower Cholesky factor of K (D, N, N), retrying with relative jitter."""
    eye = torch.eye(K.shape[-1], dtype=K.dtype)
    for jitter in (0.0, 1e-10, 1e-8, 1e-6, 1e-4):
        chol, info = torch.linalg.cholesky_ex(K + jitter * outputscale[:, None, None] * eye)
        if not bool(info.any()):
            if jitter:
                log.warning("GP cache: added jitter %.0e x outputscale to the kernel diagonal", jitter)
            return chol
    raise GpmpcError("GP kernel matrix is not positive definite even with jitter 1e-4; "
                     "check the training data for duplicated inputs or extreme scales")
