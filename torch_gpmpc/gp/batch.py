"""A team's residual models evaluated at once: one batched posterior for every agent whose model is a
:class:`~torch_gpmpc.gp.model.ResidualGP` (possibly wrapped), instead of one call per agent.

The controller linearizes every agent's GP along its plan at every control step. Per agent that is a
few small tensor operations whose cost is mostly the call itself, so a team of 100 spent more time
calling its GPs than computing them. Here the models' prediction caches are stacked and the posterior
mean and Jacobian of all of them come from the same operations as one model's
(:mod:`~torch_gpmpc.gp.cache`), with a leading batch dimension; the variance is solved model by model
against each one's own factor. The results are the bits of the per-model calls.

A model joins a batch through ``planning_gp()`` (:class:`~torch_gpmpc.gp.protocol.PlanningGP`: the
fitted GP it plans with and the constant shifts a wrapper adds, such as an offset estimate); models
whose caches have the same shapes form one batch. Models without it (a user's own,
:class:`~torch_gpmpc.gp.gpytorch_models.GPyTorchResidual`, a subclass that predicts otherwise) are
called one by one.

Shapes: B models, n query points, Din GP inputs, R residual rows, N support points.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import torch
from torch import Tensor

from torch_gpmpc.errors import GpmpcError
from torch_gpmpc.gp.cache import (
    PredictionCache, StackedCaches, cross_covariances, explained_variance, latent_variance, mean_and_jacobian,
    posterior_mean, raw_mean,
)
from torch_gpmpc.gp.protocol import PlanningGP, planning_gp


def linearize_models(models: Sequence, x: Tensor, include_noise: bool = False) -> tuple[Tensor, Tensor, Tensor]:
    """Every model's ``linearize`` at its own points, at once (the same bits as one call per model).

    Args:
        models: B residual models (the :class:`~torch_gpmpc.gp.protocol.ResidualModel` protocol),
            all with R outputs.
        x: (B, n, Din) GP inputs, model b's at ``x[b]``.
        include_noise: add each model's observation-noise variance ``noise`` (R,) to its variance.

    Returns:
        ``(mean (B, n, R), jac (B, n, R, Din), var (B, n, R))``.

    Raises:
        GpmpcError: x not (B, n, Din) for the B models, or a model's results not (n, R), (n, R, Din),
            (n, R) with the team's R, or its noise not (R,).
    """
    if not isinstance(x, Tensor) or x.ndim != 3 or x.shape[0] != len(models):
        shape = tuple(x.shape) if isinstance(x, Tensor) else type(x).__name__
        raise GpmpcError(f"linearize_models: x must be (B, n, Din) with B = {len(models)}, one row of points per "
                         f"model, got {shape}")
    groups = _groups(models, x)
    if len(groups) == 1 and len(groups[0].indices) == len(models):  # the usual case: one batch
        return groups[0].linearize(x.to(torch.float64), include_noise)
    out: list = [None] * len(models)
    for group in groups:
        for j, parts in enumerate(zip(*group.linearize(x[list(group.indices)].to(torch.float64), include_noise))):
            out[group.indices[j]] = parts
    for b, model in enumerate(models):
        if out[b] is None:
            mean, jac, var = _checked(b, model, model.linearize(x[b]), x[b])
            out[b] = (mean, jac, var + _noise(b, model, var) if include_noise else var)
    rows = [parts[0].shape[-1] for parts in out]
    usual = max(set(rows), key=rows.count)
    for b, count in enumerate(rows):
        if count != usual:
            raise GpmpcError(f"the residual model of agent {b} has {count} outputs where most of the team's have "
                             f"{usual}: a team's models must share the residual rows")
    return tuple(torch.stack(parts) for parts in zip(*out))


def predict_models(models: Sequence, x: Sequence[Tensor], include_noise: bool = False) -> list[tuple[Tensor, Tensor]]:
    """Every model's ``predict`` at its own points, at once (the same bits as one call per model).

    Args:
        models: B residual models with ``predict``.
        x: B tensors of GP inputs, model b's (n_b, Din_b) (a mixed team's differ).
        include_noise: add each model's observation noise (the predictive variance).

    Returns:
        B pairs ``(mean (n_b, R_b), var (n_b, R_b))`` (a batch's are views of one stacked tensor).

    Raises:
        GpmpcError: not one tensor of points per model, or points of the wrong shape for a model.
    """
    if len(x) != len(models):
        raise GpmpcError(f"predict_models: got {len(x)} point sets for {len(models)} models; give one per model")
    out: list = [None] * len(models)
    for group in _groups(models, x):
        points = torch.stack([x[b] for b in group.indices]).to(torch.float64)
        for j, parts in enumerate(zip(*group.predict(points, include_noise))):
            out[group.indices[j]] = parts
    for b, model in enumerate(models):
        if out[b] is None:
            out[b] = model.predict(x[b], include_noise=include_noise)
    return out


@dataclass
class _Group:
    """Models whose caches and points have the same shapes and whose wrappers shift as many times:
    their indices in the team, views and caches."""

    indices: list[int]
    views: list[PlanningGP]
    caches: list[PredictionCache]

    def linearize(self, x: Tensor, include_noise: bool) -> tuple[Tensor, Tensor, Tensor]:
        """Mean (G, n, R), Jacobian (G, n, R, Din) and variance (G, n, R) at x (G, n, Din)."""
        stack = StackedCaches.stack(self.caches)
        s, k = cross_covariances(stack, x)
        mean, jac = mean_and_jacobian(stack, s, k)
        mean, var = self._shifted(mean, self._latent_variance(stack, k))
        if include_noise:  # after the shifts, as a caller adds a model's noise to its variance
            var = var + self._noise()
        return mean, jac, var

    def predict(self, x: Tensor, include_noise: bool) -> tuple[Tensor, Tensor]:
        """Mean and variance (G, n, R) at x (G, n, Din)."""
        stack = StackedCaches.stack(self.caches)
        _, k = cross_covariances(stack, x)
        var = self._latent_variance(stack, k)
        if include_noise:  # before the shifts, as ResidualGP.predict adds it
            var = var + self._noise()
        return self._shifted(raw_mean(stack, posterior_mean(stack, k)), var)

    def _noise(self) -> Tensor:
        """(G, 1, R) the models' observation-noise variances, raw units."""
        return torch.stack([c.noise_raw for c in self.caches])[:, None, :]

    def _latent_variance(self, stack: StackedCaches, k: Tensor) -> Tensor:
        """(G, n, R): each model's solves against its own factor, the rest on the stack."""
        explained, added = zip(*(explained_variance(c, k[j]) for j, c in enumerate(self.caches)))
        return latent_variance(stack, torch.stack(explained), None if added[0] is None else torch.stack(added))

    def _shifted(self, mean: Tensor, var: Tensor) -> tuple[Tensor, Tensor]:
        """Mean and variance (G, n, R) with the wrappers' shifts, in their order."""
        for i in range(len(self.views[0].mean_shifts)):
            mean = mean + torch.stack([v.mean_shifts[i] for v in self.views]).to(mean)[:, None, :]
        for i in range(len(self.views[0].var_shifts)):
            var = var + torch.stack([v.var_shifts[i] for v in self.views]).to(var)[:, None, :]
        return mean, var


def _groups(models: Sequence, x: Sequence[Tensor] | Tensor) -> list[_Group]:
    """The models that join a batch, grouped by the shapes of their caches and points and by their
    shifts. Checks the points as each model's own call would (once per group for a (B, n, Din) x)."""
    groups: dict[tuple, _Group] = {}
    for b, model in enumerate(models):
        view = planning_gp(model)
        if view is None:
            continue
        c: PredictionCache = view.gp.prediction_cache()
        points = x.shape[1:] if isinstance(x, Tensor) else view.gp.check_query(x[b]).shape
        key = (tuple(c.S.shape), c.chol_add is not None, tuple(points), len(view.mean_shifts), len(view.var_shifts))
        group = groups.get(key)
        if group is None:
            if isinstance(x, Tensor):
                view.gp.check_query(x[b])
            group = groups[key] = _Group([], [], [])
        group.indices.append(b)
        group.views.append(view)
        group.caches.append(c)
    return list(groups.values())


def _checked(b: int, model, result: tuple[Tensor, Tensor, Tensor], x: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Model b's own ``linearize`` result, checked against its protocol shapes (n, R), (n, R, Din), (n, R)."""
    n, din = x.shape
    rows = getattr(model, "output_dim", result[0].shape[-1])
    expected = {"mean": (n, rows), "Jacobian": (n, rows, din), "variance": (n, rows)}
    for (name, shape), part in zip(expected.items(), result):
        if tuple(part.shape) != shape:
            raise GpmpcError(f"the residual model of agent {b} returned a {name} of shape {tuple(part.shape)}, "
                             f"expected {shape} (the ResidualModel protocol's linearize)")
    return result


def _noise(b: int, model, like: Tensor) -> Tensor:
    """Model b's observation-noise variance ``noise`` as an (R,) tensor like ``like`` (n, R)."""
    noise = torch.as_tensor(model.noise, dtype=like.dtype, device=like.device).reshape(-1)
    if noise.shape[0] != like.shape[-1]:
        raise GpmpcError(f"the residual model of agent {b} has a noise of {noise.shape[0]} entries, expected "
                         f"R = {like.shape[-1]}, one per residual row")
    return noise
