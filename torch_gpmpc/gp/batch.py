"""A team's residual models evaluated at once: one batched posterior for every agent whose model is a
:class:`~torch_gpmpc.gp.model.ResidualGP` (possibly wrapped), instead of one call per agent.

The controller linearizes every agent's GP along its plan at every control step. Per agent that is a
few small tensor operations whose cost is mostly the call itself, so a team of 100 spent more time
calling its GPs than computing them. Here the models' prediction caches are stacked and the posterior
mean and Jacobian of all of them come from the same operations as one model's
(:mod:`~torch_gpmpc.gp.cache`), with a leading batch dimension; the variance is solved model by model
against each one's own factor. The results are the bits of the per-model calls.

A model joins the batch through ``shifted_gp()``: the :class:`ShiftedGP` it plans with (a fitted GP and
the constant shifts a wrapper adds, such as an offset estimate). Models without it (a user's own,
:class:`~torch_gpmpc.gp.gpytorch_models.GPyTorchResidual`) are called one by one, as are models whose
caches differ in shape from the rest (grouped by shape).

Shapes: B models, n query points, Din GP inputs, R residual rows, N support points.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Sequence

import torch
from torch import Tensor

from torch_gpmpc.errors import GpmpcError
from torch_gpmpc.gp.cache import (
    PredictionCache, StackedMeans, cross_covariances, explained_variance, latent_variance, mean_and_jacobian,
    posterior_mean, raw_mean,
)


@dataclass(frozen=True)
class ShiftedGP:
    """A fitted GP (``ResidualGP``) and the constant shifts a wrapper adds to its mean and to its
    variance, each (R,), applied in order (outermost wrapper last)."""

    gp: Any
    mean_shifts: tuple[Tensor, ...] = field(default_factory=tuple)
    var_shifts: tuple[Tensor, ...] = field(default_factory=tuple)

    def shifted(self, mean: Tensor, var: Tensor) -> "ShiftedGP":
        """This view with one more shift of the mean and of the variance (each (R,)) on top."""
        return ShiftedGP(self.gp, (*self.mean_shifts, mean), (*self.var_shifts, var))


def shifted_gp(model) -> ShiftedGP | None:
    """The :class:`ShiftedGP` ``model`` plans with, or ``None`` if it cannot join a batch."""
    view = getattr(model, "shifted_gp", None)
    return view() if callable(view) else None


def linearize_models(models: Sequence, x: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Every model's ``linearize`` at its own points, at once (the same bits as one call per model).

    Args:
        models: B residual models (the :class:`~torch_gpmpc.gp.protocol.ResidualModel` protocol),
            all with R outputs.
        x: (B, n, Din) GP inputs, model b's at ``x[b]``.

    Returns:
        ``(mean (B, n, R), jac (B, n, R, Din), var (B, n, R))``.
    """
    groups = _groups(models, x)
    if len(groups) == 1 and len(groups[0].indices) == len(models):  # the usual case: one batch
        return groups[0].linearize(x.to(torch.float64))
    out: list = [None] * len(models)
    for group in groups:
        for j, parts in enumerate(zip(*group.linearize(x[list(group.indices)].to(torch.float64)))):
            out[group.indices[j]] = parts
    for b, model in enumerate(models):
        if out[b] is None:
            out[b] = _checked(b, model, model.linearize(x[b]), x[b])
    shapes = [tuple(tuple(part.shape) for part in parts) for parts in out]
    for b, shape in enumerate(shapes):
        if shape != shapes[0]:
            raise GpmpcError(f"the residual model of agent {b} has {shape[0][-1]} outputs, agent 0's has "
                             f"{shapes[0][0][-1]}: a team's models must share the residual rows")
    return tuple(torch.stack(parts) for parts in zip(*out))


def predict_models(models: Sequence, x: Sequence[Tensor], include_noise: bool = False) -> list[tuple[Tensor, Tensor]]:
    """Every model's ``predict`` at its own points, at once (the same bits as one call per model).

    Args:
        models: B residual models with ``predict``.
        x: B tensors of GP inputs, model b's (n_b, Din_b) (a mixed team's differ).
        include_noise: add each model's observation noise (the predictive variance).

    Returns:
        B pairs ``(mean (n_b, R_b), var (n_b, R_b))``.
    """
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
    views: list[ShiftedGP]
    caches: list[PredictionCache]

    def linearize(self, x: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """Mean (G, n, R), Jacobian (G, n, R, Din) and variance (G, n, R) at x (G, n, Din)."""
        stack = StackedMeans.stack(self.caches)
        s, k = cross_covariances(stack, x)
        mean, jac = mean_and_jacobian(stack, s, k)
        mean, var = self._shifted(mean, self._latent_variance(stack, k))
        return mean, jac, var

    def predict(self, x: Tensor, include_noise: bool) -> tuple[Tensor, Tensor]:
        """Mean and variance (G, n, R) at x (G, n, Din)."""
        stack = StackedMeans.stack(self.caches)
        _, k = cross_covariances(stack, x)
        var = self._latent_variance(stack, k)
        if include_noise:
            var = var + torch.stack([c.noise_raw for c in self.caches])[:, None, :]
        return self._shifted(raw_mean(stack, posterior_mean(stack, k)), var)

    def _latent_variance(self, stack: StackedMeans, k: Tensor) -> Tensor:
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
        view = shifted_gp(model)
        if view is None:
            continue
        c: PredictionCache = view.gp.prediction_cache()
        points = x[b].shape if isinstance(x, Tensor) else view.gp.check_query(x[b]).shape
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
    expected = ((n, rows), (n, rows, din), (n, rows))
    got = tuple(tuple(part.shape) for part in result)
    if got != expected:
        raise GpmpcError(f"the residual model of agent {b} returned mean, Jacobian and variance of shapes {got}, "
                         f"expected {expected} (the ResidualModel protocol)")
    return result
