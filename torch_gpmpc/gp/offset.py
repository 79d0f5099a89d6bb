"""Offset-free tracking: each agent estimates what its residual model misses, as a disturbance.

A residual GP that is wrong by ``b`` at an agent's goal (few training points there, a wind the
data never saw) makes the MPC hold the agent where its *model* says it stays: a steady offset of
``b`` over the controller's feedback gain, which can exceed ``goal_tol`` for good. Offset-free
MPC (Pannocchia and Rawlings 2003; Maeder, Borrelli and Morari 2009) adds a disturbance ``d`` to
the prediction model and estimates it from the measurements; at a steady state the estimate
matches the plant, so the tracked target is where the plant really stays.

Here ``d`` lives on the model's residual rows, the predictions use ``mu(zeta) + d_hat`` along the
whole horizon, and ``d_hat`` is the Kalman filter of a random walk (drift variance ``q`` per
step) measured through each transition's residual error::

    e = y - (mu(zeta) + d_hat)            the one-step prediction error (the innovation)
    r = max(s_gp^2, mean of recent e^2)   the measurement noise
    P <- P + q;  k = P / (P + r);  d_hat <- d_hat + k e;  P <- (1 - k) P

``s_gp^2`` is the residual model's learned noise; the errors' own running mean square (about 20
steps' memory, ``ERROR_MEMORY``) takes over where they are larger: innovation-based adaptive
estimation of the measurement noise (Mehra 1972), conservative here since the innovations' variance
also holds ``P``. Without it a vehicle whose one-step errors are mostly its tracking lag (a
quadrotor whose commands jump) chased that lag as a disturbance and flew worse than without an
estimate. Where the data are noiseless the gain is near 1 and the estimate follows the last
errors; under noise ``s`` it is ``~sqrt(q) / s`` and the estimate averages the noise away.
The chance margins add ``P`` to the residual's variance: the estimate's own uncertainty.

Shapes: n query points, Din GP inputs, R residual rows.
"""

from __future__ import annotations

import torch
from torch import Tensor

from torch_gpmpc.errors import GpmpcError
from torch_gpmpc.gp.protocol import PlanningGP, evaluates_as, planning_gp


#: the weight of the newest squared error in the measured error variance (about 20 steps' memory)
ERROR_MEMORY = 0.05


class OffsetCorrected:
    """A residual model plus an estimated constant disturbance (the
    :class:`~torch_gpmpc.gp.protocol.ResidualModel` protocol, so the controller uses it as is).

    Args:
        model: the agent's residual model (a :class:`~torch_gpmpc.gp.model.ResidualGP`, an
            :class:`~torch_gpmpc.gp.online.OnlineGP`, any ``ResidualModel`` with ``predict``).
        drift: the disturbance's random-walk standard deviation per step, raw units (> 0).

    Attributes:
        offset: (R,) the disturbance estimate ``d_hat`` (starts at 0).
        variance: (R,) its variance ``P`` (starts at ``drift**2``).
        error_variance: (R,) the errors' running mean square (starts at the model's noise).

    Examples:
        >>> import torch
        >>> from torch_gpmpc import OffsetCorrected, ResidualGP
        >>> x = torch.linspace(-2, 2, 10, dtype=torch.float64)[:, None]
        >>> gp = ResidualGP(x, torch.sin(x))
        >>> model = OffsetCorrected(gp, drift=0.1)
        >>> z = torch.tensor([[0.3]], dtype=torch.float64)
        >>> truth, _ = gp.predict(z)          # the plant's residual: the GP's mean plus a constant 0.05
        >>> for _ in range(50):
        ...     predicted, _ = model.predict(z)
        ...     model.observe((truth + 0.05 - predicted).squeeze(0))
        >>> round(float(model.offset[0]), 3)
        0.05
    """

    def __init__(self, model, drift: float) -> None:
        if not drift > 0:
            raise GpmpcError(f"disturbance_drift must be > 0 to estimate an offset, got {drift}")
        self.model, self.drift = model, float(drift)
        noise = torch.as_tensor(model.noise, dtype=torch.float64).detach().reshape(-1)
        self.offset = torch.zeros_like(noise)
        self.variance = torch.full_like(noise, self.drift ** 2)
        self.error_variance = noise.clone()
        # beside a guarded online model: the fit's own estimate, from the fit's errors (judge)
        self._fit_filter = (self.offset.clone(), self.variance.clone(), self.error_variance.clone())

    @property
    def input_dim(self) -> int:
        """Din, the number of GP inputs."""
        return self.model.input_dim

    @property
    def output_dim(self) -> int:
        """R, the number of residual rows."""
        return self.model.output_dim

    @property
    def noise(self) -> Tensor:
        """(R,) the model's observation-noise variances, raw units."""
        return self.model.noise

    def linearize(self, x: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """The model's mean plus the offset (n, R), its Jacobian (n, R, Din) and its latent
        variance plus the estimate's (n, R), at ``x`` (n, Din)."""
        mean, jac, var = self.model.linearize(x)
        offset, variance = self.estimate
        return mean + offset.to(mean), jac, var + variance.to(var)

    def predict(self, x: Tensor, include_noise: bool = False) -> tuple[Tensor, Tensor]:
        """Mean and variance (n, R) at ``x`` (n, Din), offset included."""
        mean, var = self.model.predict(x, include_noise=include_noise)
        offset, variance = self.estimate
        return mean + offset.to(mean), var + variance.to(var)

    def planning_gp(self) -> PlanningGP | None:
        """The wrapped model's GP with the offset on its mean and the estimate's variance on its
        variance, for a team's batched evaluation (:mod:`~torch_gpmpc.gp.batch`)."""
        view = planning_gp(self.model) if evaluates_as(self, OffsetCorrected) else None
        return None if view is None else view.shifted(*self.estimate)

    @property
    def estimate(self) -> tuple[Tensor, Tensor]:
        """The offset and its variance, each (R,), of the model planned with: while a guarded online
        model plans with its fit, the fit's own estimate; otherwise :attr:`offset` and
        :attr:`variance` (the only estimate of a frozen model; an online model's)."""
        if getattr(self.model, "adopted", True):
            return self.offset, self.variance
        return self._fit_filter[0], self._fit_filter[1]

    def observe(self, error: Tensor) -> None:
        """One Kalman step of :attr:`offset` from a transition's one-step prediction error ``error``
        (R,): the measured residual minus the model's mean plus :attr:`offset` at that transition's
        GP input. Beside a guarded online model this is the learner's estimate (its error after
        learning, :meth:`observe_learnt`); the fit's moves in :meth:`judge`."""
        # a filter state, never part of a gradient: detached, or every later step would differentiate
        # through the whole history
        error = torch.as_tensor(error, dtype=self.offset.dtype).detach().reshape(-1)
        if error.shape != self.offset.shape:
            raise GpmpcError(f"offset error has {error.shape[0]} entries, expected R = {self.offset.shape[0]}")
        self.offset, self.variance, self.error_variance = self._kalman_step(
            (self.offset, self.variance, self.error_variance), error, self.learner.noise)

    def _kalman_step(self, state: tuple[Tensor, Tensor, Tensor], error: Tensor,
                     noise: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """The filter ``state`` (offset, variance, error variance; each (R,)) after one error (R,),
        with the observation-noise variances ``noise`` (R,) of the model it corrects."""
        offset, variance, error_variance = state
        prior = variance + self.drift ** 2
        error_variance = (1 - ERROR_MEMORY) * error_variance + ERROR_MEMORY * error ** 2
        model_noise = torch.as_tensor(noise, dtype=prior.dtype).detach().reshape(-1)
        gain = prior / (prior + torch.maximum(model_noise, error_variance))
        return offset + gain * error, (1 - gain) * prior, error_variance

    # the learning of an online model passes through
    def add(self, inputs: Tensor, y: Tensor) -> None:
        """Add rows ``inputs`` (n, Din), residuals ``y`` (n, R) to the wrapped online model
        (:meth:`OnlineGP.add <torch_gpmpc.gp.online.OnlineGP.add>`), less the offset: the model learns
        what the offset does not explain, so the two never count the same error twice."""
        self.model.add(inputs, y - self.offset.to(y))

    def judge(self, inputs: Tensor, y: Tensor) -> Tensor | None:
        """Let the wrapped online model judge rows ``inputs`` (n, Din), residuals ``y`` (n, R)
        (:meth:`GuardedOnlineGP.judge <torch_gpmpc.gp.guard.GuardedOnlineGP.judge>`), each candidate
        with its own estimate: the learner less :attr:`offset`, the fit less the fit's estimate,
        which then takes a Kalman step from the fit's error, as in a run without learning. (One
        estimate for both would be unfair to one of them: an estimate moved by the learner's errors
        stops following a change the learner has absorbed; one moved by the fit's would count that
        change twice in the learner.)

        Returns the fit's errors with its own estimate (n, R), ``None`` without a fit kept."""
        errors = []
        for i in range(inputs.shape[0]):  # one transition at a time, as the estimates step
            row = y[i:i + 1]
            fit_error = self.model.judge(inputs[i:i + 1], row - self.offset.to(row),
                                         row - self._fit_filter[0].to(row))
            if fit_error is None:
                return None
            errors.append(fit_error)
            self._fit_filter = self._kalman_step(self._fit_filter, fit_error[0].detach().to(self.offset.dtype),
                                                 self.model.frozen.noise)
        return torch.cat(errors)

    @property
    def learner(self):
        """The wrapped model whose estimate :attr:`offset` is: a guarded model's learner, else the
        model itself (a guarded model's fit has its own estimate, :meth:`judge`)."""
        return getattr(self.model, "learner", self.model)

    def observe_learnt(self, y: Tensor, learner_mean: Tensor) -> None:
        """After the wrapped online model has learnt rows with residuals ``y`` (n, R): one Kalman
        step of :attr:`offset` per row from :attr:`learner`'s mean there after learning,
        ``learner_mean`` (n, R) (its error is near noise level where it learnt the row, so the
        learner and its estimate never count an error twice)."""
        for i in range(y.shape[0]):
            self.observe(y[i] - (learner_mean[i] + self.offset.to(learner_mean)))

    @property
    def adopted(self) -> bool:
        """Whether the wrapped online model plans with what it has learnt."""
        return self.model.adopted

    def end_step(self) -> bool:
        """Count a step of the wrapped online model
        (:meth:`OnlineGP.end_step <torch_gpmpc.gp.online.OnlineGP.end_step>`)."""
        return self.model.end_step()


def offset_corrected(gps: list, drift: float) -> list:
    """Each agent's model wrapped in its own :class:`OffsetCorrected` (``drift > 0``), or ``gps``
    unchanged (``drift == 0``: no offset estimate). One model shared by several agents gets one
    wrapper per agent: every agent estimates its own offset. A model already wrapped stays as it is."""
    if drift == 0:
        return gps
    return [gp if isinstance(gp, OffsetCorrected) else OffsetCorrected(gp, drift) for gp in gps]
