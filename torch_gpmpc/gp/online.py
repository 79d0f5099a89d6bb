"""Online residual GPs: each agent adds its own observed transitions to its GP while it flies.

An exact GP keeps the Cholesky factor of ``K + s^2 I`` over its rows (:mod:`~torch_gpmpc.gp.cache`).
A new row appends one row to the factor and a budget-full window first drops its oldest row (a
rank-one update of the rest, :mod:`~torch_gpmpc.gp.cholesky_update`): O(N^2) per row, no new
factorization and no refit. A sparse (SGPR) GP keeps its inducing points; a new row is a rank-one
update of the factor of ``Sigma^-1 = K_uu + s^-2 K_uf K_fu`` and of ``K_uf y`` (:mod:`~torch_gpmpc.gp.sparse`),
a dropped row a downdate: O(M^2) per row. Both give the posterior of a batch fit on the same rows
with the same hyperparameters (tests check 1e-9).

**Budget** (``gp_online_budget``): a sliding window of the most recent rows; the rows the GP was
fitted on count as the oldest and leave first. After a change (the wind turns), the window forgets
the old regime at one row per step.

**Hyperparameters** stay fixed between refits; with ``gp_online_refit_every = N`` they are
re-optimized (a few L-BFGS steps from their current values, :func:`~torch_gpmpc.gp.fit.refit_hyperparameters`)
on the window every N steps, which costs one O(N^3) fit on that step (timed in ``gpmpc bench``).
The standardization of inputs and outputs stays the one of the first fit.

Shapes: n rows, Din GP inputs, R residual rows (the GP's outputs), K agents, N window rows.
"""

from __future__ import annotations

import copy
import dataclasses
import time

import torch
from torch import Tensor

from torch_gpmpc.config.schema import Config
from torch_gpmpc.errors import GpmpcError
from torch_gpmpc.gp.batch import predict_models
from torch_gpmpc.gp.cache import PredictionCache, squared_distances
from torch_gpmpc.gp.cholesky_update import cholesky_append, cholesky_drop_first, cholesky_rank_one
from torch_gpmpc.gp.fit import refit_hyperparameters
from torch_gpmpc.gp.guard import GuardedOnlineGP
from torch_gpmpc.gp.model import ResidualGP, check_training_data
from torch_gpmpc.gp.offset import OffsetCorrected, offset_corrected
from torch_gpmpc.gp.protocol import PlanningGP, evaluates_as, planning_gp
from torch_gpmpc.gp.sparse import sparse_posterior

#: L-BFGS steps of a periodic hyperparameter refit.
REFIT_ITERS = 10


class OnlineGP:
    """A fitted :class:`~torch_gpmpc.gp.model.ResidualGP` that learns from rows added during a run
    (the :class:`~torch_gpmpc.gp.protocol.ResidualModel` protocol, so the controller uses it as is).

    Args:
        gp: the fitted GP (exact or sparse); updated in place.
        budget: most rows kept (the window); a GP fitted on more keeps its most recent ``budget``.
        refit_every: re-optimize the hyperparameters every this many calls of :meth:`end_step`
            (0: never).

    Examples:
        >>> import torch
        >>> from torch_gpmpc import ResidualGP
        >>> from torch_gpmpc.gp.online import OnlineGP
        >>> x = torch.linspace(-2, 2, 10, dtype=torch.float64)[:, None]
        >>> online = OnlineGP(ResidualGP(x, torch.sin(x)), budget=10)
        >>> online.add(torch.tensor([[2.5]], dtype=torch.float64), torch.tensor([[0.6]], dtype=torch.float64))
        >>> online.gp.num_data, round(float(online.gp.train_inputs_raw[0, 0]), 3)   # the oldest row left
        (10, -1.556)
    """

    def __init__(self, gp: ResidualGP, budget: int, refit_every: int = 0) -> None:
        if int(budget) < 2:
            raise GpmpcError(f"gp_online_budget must be >= 2 rows, got {budget}")
        self.gp, self.budget, self.refit_every = gp, int(budget), int(refit_every)
        self.steps = 0
        if gp.num_data > self.budget:
            gp.set_rows(gp.train_inputs_raw[-self.budget:], gp.train_y_raw[-self.budget:])
        self._kuf_y = self._sparse_statistic() if gp.inducing_points is not None else None

    # ------------------------------------------------------------------ the ResidualModel protocol
    @property
    def input_dim(self) -> int:
        """Din."""
        return self.gp.input_dim

    @property
    def output_dim(self) -> int:
        """R."""
        return self.gp.output_dim

    @property
    def noise(self) -> Tensor:
        """(R,) observation-noise variances, raw units."""
        return self.gp.noise

    def linearize(self, x: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """Mean (n, R), Jacobian (n, R, Din) and latent variance (n, R) at ``x`` (n, Din), from the
        rows added so far."""
        return self.gp.linearize(x)

    def predict(self, x: Tensor, include_noise: bool = False) -> tuple[Tensor, Tensor]:
        """Mean and variance (n, R) at ``x`` (n, Din)."""
        return self.gp.predict(x, include_noise=include_noise)

    def planning_gp(self) -> PlanningGP | None:
        """Its GP, for a team's batched evaluation (:mod:`~torch_gpmpc.gp.batch`)."""
        return planning_gp(self.gp) if evaluates_as(self, OnlineGP) else None

    # ------------------------------------------------------------------ learning
    def add(self, inputs: Tensor, y: Tensor) -> None:
        """Add rows ``inputs`` (n, Din), residuals ``y`` (n, R) in raw units, one at a time (the
        window drops its oldest row when full)."""
        inputs, y = _check_rows(inputs, y, self.gp)
        with torch.no_grad():
            for i in range(inputs.shape[0]):
                if self.gp.inducing_points is None:
                    self._add_exact(inputs[i:i + 1], y[i:i + 1])
                else:
                    self._add_sparse(inputs[i:i + 1], y[i:i + 1])

    #: an unguarded online GP always plans with what it has learnt (:class:`~.guard.GuardedOnlineGP`
    #: chooses)
    adopted = True

    def judge(self, inputs: Tensor, y: Tensor, frozen_y: Tensor | None = None) -> None:
        """Nothing to choose between and no frozen fit kept (a
        :class:`~torch_gpmpc.gp.guard.GuardedOnlineGP` judges its learner against its fit here);
        ``inputs`` (n, Din), ``y`` and ``frozen_y`` (n, R). Returns ``None``."""

    @property
    def learner(self) -> "OnlineGP":
        """The model that learns: this one (a guarded model keeps it beside its fit)."""
        return self

    def end_step(self) -> bool:
        """Count one control step; re-fit the hyperparameters when ``refit_every`` steps have passed.
        Returns whether it re-fitted."""
        self.steps += 1
        if self.refit_every <= 0 or self.steps % self.refit_every:
            return False
        refit_hyperparameters(self.gp, REFIT_ITERS)
        if self._kuf_y is not None:
            self._kuf_y = self._sparse_statistic()
        return True

    def _scaled(self, c: PredictionCache, x: Tensor) -> Tensor:
        """Raw inputs (n, Din) over the lengthscales, (D, n, Din)."""
        return ((x - c.x_mean) / c.x_std) / c.ls

    def _noise_std_units(self) -> Tensor:
        # in the hyperparameters' own dtype: the batch factorization promotes it the same way
        return self.gp.likelihood.noise.reshape(self.output_dim).detach()

    def _standardized(self, y: Tensor) -> Tensor:
        """Raw residuals (n, R) -> (R, n) standardized."""
        return ((y - self.gp.y_mean) / self.gp.y_std).T

    def _add_exact(self, x: Tensor, y: Tensor) -> None:
        c = self.gp.prediction_cache()
        X, Y, S, chol = self.gp.train_inputs_raw, self.gp.train_y_raw, c.S, c.chol
        if X.shape[0] >= self.budget:
            X, Y, S, chol = X[1:], Y[1:], S[:, 1:], cholesky_drop_first(chol)
        s_new = self._scaled(c, x)  # (D, 1, Din)
        k = c.outputscale[:, None] * torch.exp(-0.5 * squared_distances(S, s_new)).squeeze(-1)
        chol = cholesky_append(chol, k, c.outputscale.to(k) + self._noise_std_units().to(k))
        S, X, Y = torch.cat([S, s_new], 1), torch.cat([X, x]), torch.cat([Y, y])
        alpha = torch.cholesky_solve(self._standardized(Y).unsqueeze(-1), chol).squeeze(-1)
        cols = tuple(S[:, None, :, i].contiguous() for i in range(S.shape[-1]))
        self.gp.set_rows(X, Y, dataclasses.replace(c, S=S, S_cols=cols, chol=chol, alpha=alpha))

    def _k_u(self, c: PredictionCache, x: Tensor) -> Tensor:
        """Inducing-point covariances of raw rows x (n, Din): (D, M, n)."""
        return c.outputscale[:, None, None] * torch.exp(-0.5 * squared_distances(c.S, self._scaled(c, x)))

    def _sparse_statistic(self) -> Tensor:
        """``K_uf y`` over the current rows, (D, M)."""
        c = self.gp.prediction_cache()
        return (self._k_u(c, self.gp.train_inputs_raw) @ self._standardized(self.gp.train_y_raw).unsqueeze(-1)).squeeze(-1)

    def _add_sparse(self, x: Tensor, y: Tensor) -> None:
        c = self.gp.prediction_cache()
        X, Y, chol, kuf_y = self.gp.train_inputs_raw, self.gp.train_y_raw, c.chol_add, self._kuf_y
        noise_sd = self._noise_std_units().sqrt().to(chol)[:, None]
        if X.shape[0] >= self.budget:
            k_old = self._k_u(c, X[:1]).squeeze(-1)
            chol = cholesky_rank_one(chol, k_old / noise_sd, -1.0)
            kuf_y = kuf_y - k_old * self._standardized(Y[:1])
            X, Y = X[1:], Y[1:]
        k_new = self._k_u(c, x).squeeze(-1)
        kuf_y = kuf_y + k_new * self._standardized(y)
        X, Y = torch.cat([X, x]), torch.cat([Y, y])
        if chol is None:  # the downdate lost definiteness: factor the window afresh
            S_f = self._scaled(c, X)
            chol = sparse_posterior(c.S, S_f, self._standardized(Y), c.outputscale, self._noise_std_units()).chol_sigma
        else:
            chol = cholesky_rank_one(chol, k_new / noise_sd, 1.0)
        alpha = torch.cholesky_solve(kuf_y.unsqueeze(-1), chol).squeeze(-1) / noise_sd.square()
        self._kuf_y = kuf_y
        self.gp.set_rows(X, Y, dataclasses.replace(c, chol_add=chol, alpha=alpha))


def _check_rows(inputs: Tensor, y: Tensor, gp: ResidualGP) -> tuple[Tensor, Tensor]:
    """New rows for ``gp``: checked like training data (one row is enough), in its dimensions."""
    inputs, y = check_training_data(inputs, y, min_rows=1)
    if inputs.shape[1] != gp.input_dim or y.shape[1] != gp.output_dim:
        raise GpmpcError(f"online GP rows must be (n, {gp.input_dim}) inputs and (n, {gp.output_dim}) residuals, "
                         f"got {tuple(inputs.shape)} and {tuple(y.shape)}")
    return inputs, y


class OnlineLearning:
    """Every agent's one-step prediction during a run, and with ``online`` its GP update.

    After each control step, agent k's GP predicts the residual of the transition it just made
    (``y = [x' - A x - B u]_residual`` at its GP input), before it learns from it: the error and the
    predictive variance (latent + noise) are what ``online_prediction_rmse`` and the coverage report.
    With ``online`` a :class:`~torch_gpmpc.gp.guard.GuardedOnlineGP` then judges its learner and its
    frozen fit on that transition (every transition, learnt or not) and learns it.

    Args:
        gps: one model per agent (the controller's objects: updated in place).
        nominal: the planning model (its residual rows and GP input columns; a mixed team's
            :class:`~torch_gpmpc.dynamics.team.TeamNominal`).
        online: add each agent's transitions to its own GP (:func:`online_gps`' guarded models, or
            :class:`OnlineGP` ones, either possibly offset-corrected).
        max_input_change: add a transition only if its input differs from the agent's previous one
            by at most this (Euclidean norm; ``None``: every transition). A vehicle that realizes its
            command with a lag (a quadrotor tilting first) makes transitions whose residual is mostly
            that lag while the command changes; the GP's inputs cannot see it, and learning it as a
            function of the state misleads the next plans.

    Attributes:
        update_seconds: wall time of the updates (and refits) of each step.
        skipped: transitions not added (input change above ``max_input_change``), per agent.
        adopted_share: per step, the share of agents planning with their learner (online only).
        frozen_error: the last step's errors of each agent's fit as it was before learning, on the
            same transitions, (K, R), with the offset estimate it would have made itself
            (:meth:`OffsetCorrected.judge <torch_gpmpc.gp.offset.OffsetCorrected.judge>`): learning
            against not learning on one flight (``None`` unless every model is guarded: ``online``
            with :func:`online_gps`' models).
    """

    def __init__(self, gps: list, nominal, online: bool, max_input_change: float | None = None) -> None:
        self.gps, self.nominal, self.online = gps, nominal, online
        self.max_input_change = max_input_change
        self.update_seconds: list[float] = []
        self.skipped = [0] * len(gps)
        self.adopted_share: list[float] = []
        self.frozen_error: Tensor | None = None
        self._u_prev: Tensor | None = None

    def observe(self, x: Tensor, u: Tensor, x_next: Tensor) -> tuple[Tensor, Tensor]:
        """One step of every agent: measured states x (K, D), inputs u (K, Du), next measured
        states (K, D). Returns prediction errors and predictive variances, each (K, R).

        An agent's :class:`~torch_gpmpc.gp.offset.OffsetCorrected` model then updates its offset
        estimate from its model's error on this transition: a frozen model's before, an online
        model's after the update (a guarded model's fit keeps its own estimate,
        :meth:`~torch_gpmpc.gp.offset.OffsetCorrected.judge`)."""
        inputs, y = self.nominal.gp_targets(x, u, x_next)
        if isinstance(inputs, Tensor):  # one model: (K, Din); a mixed team's: one (1, Din_k) per agent
            inputs = [inputs[k:k + 1] for k in range(inputs.shape[0])]
        errors, variances = [], []
        for k, (mean, var) in enumerate(predict_models(self.gps, inputs, include_noise=True)):
            errors.append(y[k] - mean[0])
            variances.append(var[0])
        start = time.perf_counter()
        if self.online:
            steady = self._steady_inputs(u)
            frozen = []
            for k, gp in enumerate(self.gps):
                # before it learns: a guarded model scores held-out rows
                frozen.append(gp.judge(inputs[k], y[k:k + 1]))
                if steady[k]:
                    gp.add(inputs[k], y[k:k + 1])
                else:
                    self.skipped[k] += 1
                gp.end_step()
            self.adopted_share.append(sum(gp.adopted for gp in self.gps) / len(self.gps))
            self.frozen_error = None if any(e is None for e in frozen) else torch.cat(frozen)
        corrected = [k for k, gp in enumerate(self.gps) if isinstance(gp, OffsetCorrected)]
        if self.online:  # the learners' estimates, from their errors after learning (the fits': in judge)
            means = predict_models([self.gps[k].learner for k in corrected], [inputs[k] for k in corrected])
            for k, (mean, _) in zip(corrected, means):
                self.gps[k].observe_learnt(y[k:k + 1], mean)
        else:
            for k in corrected:
                self.gps[k].observe(errors[k])
        self.update_seconds.append(time.perf_counter() - start if self.online else 0.0)
        return torch.stack(errors), torch.stack(variances)

    def _steady_inputs(self, u: Tensor) -> list[bool]:
        """Per agent, whether its input u (K, Du) changed by at most ``max_input_change`` since the
        last call (the first call: yes)."""
        prev, self._u_prev = self._u_prev, u.detach().clone()
        if self.max_input_change is None or prev is None:
            return [True] * u.shape[0]
        return ((u - prev).norm(dim=-1) <= self.max_input_change).tolist()


def online_gps(gps: list, budget: int, refit_every: int) -> list[GuardedOnlineGP]:
    """Each agent's own copy of its GP as a guarded :class:`OnlineGP` (a GP shared by several agents
    is copied, so each learns only its own transitions)."""
    # the guard's frozen model is the whole fit: the learner keeps only its latest ``budget`` rows
    return [GuardedOnlineGP(OnlineGP(copy.deepcopy(gp), budget, refit_every), frozen=copy.deepcopy(gp))
            for gp in gps]


def run_models(gps: list, cfg: Config) -> list:
    """Each agent's model as a run of ``cfg`` plans with it, in process and in an agent process alike:
    with ``gp_online`` its own guarded online copy (:func:`online_gps`), then its offset estimate
    where ``disturbance_drift`` > 0 (:func:`~torch_gpmpc.gp.offset.offset_corrected`)."""
    if cfg.gp_online:
        gps = online_gps(gps, cfg.gp_online_budget, cfg.gp_online_refit_every)
    return offset_corrected(gps, cfg.offset_drift)
