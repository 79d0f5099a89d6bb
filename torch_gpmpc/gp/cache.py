"""The prediction cache of a fitted :class:`~torch_gpmpc.gp.model.ResidualGP`, and the posterior
evaluated from it.

Like GPyTorch's exact prediction strategy, the fitted model keeps the Cholesky factor of
``K + s^2 I`` and ``alpha = (K + s^2 I)^{-1} y`` in one object, rebuilt by
``ResidualGP.refresh()`` whenever the hyperparameters change.

The posterior functions (:func:`cross_covariances`, :func:`posterior_mean`, :func:`mean_and_jacobian`,
:func:`raw_mean`, :func:`latent_variance`) take one model's cache or a stack of B caches
(:class:`StackedCaches`, every tensor with a leading batch dimension): one code for an agent's model
and for a whole team's (:mod:`~torch_gpmpc.gp.batch`), element for element the same operations, so
the two give the same bits. Only :func:`explained_variance`, the triangular solves, takes one cache:
torch's batched solve gives other bits.
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


@dataclass
class StackedCaches:
    """The fields of B same-shaped :class:`PredictionCache` s that the posterior functions read,
    stacked on a leading batch dimension (shapes as there, with B in front). The factors (``chol``)
    stay with each model: :func:`explained_variance` is solved model by model."""

    x_mean: Tensor  # (B, Din)
    x_std: Tensor  # (B, Din)
    ls: Tensor  # (B, D, 1, Din)
    x_scale: Tensor  # (B, D, 1, Din)
    S: Tensor  # (B, D, N, Din)
    S_cols: tuple[Tensor, ...]  # Din tensors (B, D, 1, N)
    outputscale: Tensor  # (B, D)
    alpha: Tensor  # (B, D, N)
    y_mean: Tensor  # (B, D)
    y_std: Tensor  # (B, D)

    @classmethod
    def stack(cls, caches: list[PredictionCache]) -> "StackedCaches":
        """Stack B caches of the same shapes."""
        def stacked(name: str) -> Tensor:
            return torch.stack([getattr(c, name) for c in caches])

        columns = tuple(torch.stack([c.S_cols[i] for c in caches]) for i in range(len(caches[0].S_cols)))
        return cls(stacked("x_mean"), stacked("x_std"), stacked("ls"), stacked("x_scale"), stacked("S"), columns,
                   stacked("outputscale"), stacked("alpha"), stacked("y_mean"), stacked("y_std"))


def cross_covariances(c: PredictionCache | StackedCaches, x: Tensor) -> tuple[Tensor, Tensor]:
    """Scaled query points s (..., D, n, Din) and cross-covariances k (..., D, n, N) of raw query
    points x (..., n, Din); ``...`` is empty for one cache and (B,) for a stack."""
    s = (((x - c.x_mean[..., None, :]) / c.x_std[..., None, :]))[..., None, :, :] / c.ls
    # squared distances column by column: exact differences, faster than cdist for small Din
    sq = (s[..., 0:1] - c.S_cols[0]).square_()
    for i in range(1, len(c.S_cols)):
        sq += (s[..., i:i + 1] - c.S_cols[i]).square_()
    k = c.outputscale[..., :, None, None] * torch.exp(-0.5 * sq)
    return s, k


def posterior_mean(c: PredictionCache | StackedCaches, k: Tensor) -> Tensor:
    """Standardized posterior mean (..., D, n) from cross-covariances k (..., D, n, N)."""
    return (k * c.alpha[..., :, None, :]).sum(-1)


def mean_and_jacobian(c: PredictionCache | StackedCaches, s: Tensor, k: Tensor) -> tuple[Tensor, Tensor]:
    """Raw-unit mean (..., n, D) and Jacobian (..., n, D, Din) from :func:`cross_covariances`."""
    W = k * c.alpha[..., :, None, :]  # (..., D, n, N)
    mean_std = W.sum(-1)  # (..., D, n)
    # eq. 13 in scaled coordinates: d mu_std / d s_i = sum_n W_n (S_ni - s_i);
    # chain rule through s = (x - x_mean) / (x_std * lengthscale), then y = y_mean + y_std mu_std
    jac = (W @ c.S - mean_std[..., None] * s) / c.x_scale * c.y_std[..., :, None, None]
    return raw_mean(c, mean_std), jac.transpose(-3, -2)


def raw_mean(c: PredictionCache | StackedCaches, mean_std: Tensor) -> Tensor:
    """Raw-unit mean (..., n, D) from the standardized one (..., D, n)."""
    return c.y_mean[..., None, :] + c.y_std[..., None, :] * mean_std.transpose(-1, -2)


def explained_variance(c: PredictionCache, k: Tensor) -> tuple[Tensor, Tensor | None]:
    """What ONE cache's data explain of the prior variance at cross-covariances k (D, n, N):
    ``||chol^-1 k||^2`` (D, n), and for a sparse GP the ``||chol_add^-1 k||^2`` (D, n) it adds back
    (``None`` for an exact GP). Solved against the model's own factor."""
    v = torch.linalg.solve_triangular(c.chol, k.mT, upper=False)
    if c.chol_add is None:
        return v.square().sum(-2), None
    return v.square().sum(-2), torch.linalg.solve_triangular(c.chol_add, k.mT, upper=False).square().sum(-2)


def latent_variance(c: PredictionCache | StackedCaches, explained: Tensor, added: Tensor | None) -> Tensor:
    """Raw-unit latent variance (..., n, D) from :func:`explained_variance` (each (..., D, n)):
    ``outputscale - ||chol^-1 k||^2 (+ ||chol_add^-1 k||^2 for a sparse GP)``."""
    var = c.outputscale[..., :, None] - explained
    if added is not None:  # sparse: + k Sigma k (gp.sparse)
        var = var + added
    return c.y_std[..., None, :] ** 2 * var.clamp_min(0.0).transpose(-1, -2)


def parameter_values(module: torch.nn.Module) -> Tensor:
    """A snapshot of a module's parameter values, flattened (a new tensor): what a prediction
    cache is keyed on, so that in-place optimizer steps and setter assignments are both seen."""
    return torch.cat([p.detach().reshape(-1) for p in _parameters(module, [])])


def _parameters(module: torch.nn.Module, found: list[Tensor]) -> list[Tensor]:
    """Every parameter of ``module`` and its submodules, read from their registries: what
    ``module.parameters()`` yields (with shared ones repeated), at half its cost, for the check that
    every prediction makes."""
    found.extend(p for p in module._parameters.values() if p is not None)
    for child in module._modules.values():
        if child is not None:
            _parameters(child, found)
    return found


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
