"""The online guard: an agent plans with its online GP only while it predicts better than the frozen one.

An online GP learns every transition it is given; some of them mislead it (a quadrotor's attitude
lag, which no GP input sees; a regime it leaves again; rows that push the fit's own rows out of the
window). The guard keeps the GP as it was fitted (*frozen*) beside the one that learns and scores
both *prequentially*: each new transition is predicted by both before either learns from it, so
every score is on a point both models hold out. The agent plans with the learner only while, over
the last ``GUARD_WINDOW`` transitions, its squared one-step error is lower than the frozen model's by
more than two standard errors of the paired differences (from ``GUARD_MIN_ROWS`` transitions on);
otherwise with the frozen model.

Why a test and not the lower mean: in closed loop the model an agent plans with shapes the
transitions both are judged on. A learner that is only slightly better (within the noise of a
quadrotor's lag) makes plans whose transitions it then predicts slightly better again, and the team
drifts into a worse regime for both models. Measured on four Crazyflies in a 2 m/s wind that turns
at step 40 (RotorPy, seeds 0 / 1, without the model's smoothing, offset estimate and input filter;
the docs' RotorPy page): one-step error after the change 0.072 / 0.069 with the test, 0.166 / 0.196
with the lower mean, 0.20 / 0.19 with no guard, against 0.064 / 0.063 frozen.

What this gives: a learner that predicts the held-out transitions no better than the fit is planned
with only by chance, at a few percent of the steps (a simulation of equally good models: 6 % of the
windows of 3 transitions, 3 % of those of 10; ``tests/gp/test_guard.py``); one better by more than
their noise is adopted within a few transitions (after a wind change, where the frozen model's error
jumps). The learner keeps learning while refused, so it is adopted as soon as it is surely better. It
is not a guarantee on the closed loop: the runs with the learner and without it fly different
transitions.

Shapes: n query points, Din GP inputs, R residual rows.
"""

from __future__ import annotations

import copy
from collections import deque

import torch
from torch import Tensor

from torch_gpmpc.gp.protocol import PlanningGP, evaluates_as, planning_gp

#: transitions over which the two models' one-step errors are compared (about 1 s at 10 Hz)
GUARD_WINDOW = 10
#: transitions scored before the learner may be adopted
GUARD_MIN_ROWS = 3
#: standard errors by which the learner's mean gain must exceed 0
GUARD_SIGMAS = 2.0


def surely_positive(gains: list[float]) -> bool:
    """Whether the mean of ``gains`` (n,) exceeds ``GUARD_SIGMAS`` of its standard errors (a one-sided
    paired test: the learner's error is lower by more than chance explains)."""
    g = torch.tensor(gains, dtype=torch.float64)
    return bool(g.mean() > GUARD_SIGMAS * g.std() / len(gains) ** 0.5)


class GuardedOnlineGP:
    """An :class:`~torch_gpmpc.gp.online.OnlineGP` beside its frozen fit, planning with the learner only
    while it predicted the latest held-out transitions surely better (the
    :class:`~torch_gpmpc.gp.protocol.ResidualModel` protocol).

    Args:
        learner: the online GP (its ``gp`` is updated in place by :meth:`add`).
        frozen: the GP as fitted (never updated; default: a copy of the learner's GP at construction).
            Give the fit itself where the learner keeps only the latest rows of a larger fit.

    Attributes:
        frozen: the GP as fitted.
        adopted: whether the learner is the model planned with.
        errors: the last ``GUARD_WINDOW`` transitions' summed squared errors, (frozen, learner) pairs.

    Examples:
        >>> import torch
        >>> from torch_gpmpc import ResidualGP
        >>> from torch_gpmpc.gp.guard import GuardedOnlineGP
        >>> from torch_gpmpc.gp.online import OnlineGP
        >>> x = torch.linspace(-2, 2, 10, dtype=torch.float64)[:, None]
        >>> guarded = GuardedOnlineGP(OnlineGP(ResidualGP(x, torch.sin(x)), budget=20))
        >>> z = torch.tensor([[0.5]], dtype=torch.float64)
        >>> for _ in range(5):       # the residual moved up by 0.3: each row is judged, then learnt
        ...     row = torch.sin(z) + 0.3
        ...     _ = guarded.judge(z, row)
        ...     guarded.add(z, row)
        >>> guarded.adopted
        True
    """

    def __init__(self, learner, frozen=None) -> None:
        self.learner = learner
        self.frozen = copy.deepcopy(learner.gp) if frozen is None else frozen
        self.adopted = False
        self.errors: deque[tuple[float, float]] = deque(maxlen=GUARD_WINDOW)

    @property
    def gp(self):
        """The learner's GP (its rows and hyperparameters)."""
        return self.learner.gp

    @property
    def planning_model(self):
        """The model the agent plans with: the learner if adopted, else the frozen GP."""
        return self.learner if self.adopted else self.frozen

    # ------------------------------------------------------------------ the ResidualModel protocol
    @property
    def input_dim(self) -> int:
        """Din."""
        return self.frozen.input_dim

    @property
    def output_dim(self) -> int:
        """R."""
        return self.frozen.output_dim

    @property
    def noise(self) -> Tensor:
        """(R,) the planning model's observation-noise variances, raw units."""
        return self.planning_model.noise

    def linearize(self, x: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """The planning model's mean (n, R), Jacobian (n, R, Din) and latent variance (n, R) at ``x``
        (n, Din)."""
        return self.planning_model.linearize(x)

    def predict(self, x: Tensor, include_noise: bool = False) -> tuple[Tensor, Tensor]:
        """The planning model's mean and variance (n, R) at ``x`` (n, Din)."""
        return self.planning_model.predict(x, include_noise=include_noise)

    def planning_gp(self) -> PlanningGP | None:
        """The planning model's GP, for a team's batched evaluation (:mod:`~torch_gpmpc.gp.batch`)."""
        return planning_gp(self.planning_model) if evaluates_as(self, GuardedOnlineGP) else None

    # ------------------------------------------------------------------ judging and learning
    def judge(self, inputs: Tensor, y: Tensor, frozen_y: Tensor | None = None) -> Tensor:
        """Score both models on transitions neither has learnt, inputs (n, Din) and residuals (n, R)
        in raw units (``frozen_y``, (n, R): the frozen model's, where it differs, as with its own
        offset estimate), and choose the planning model. Call it before :meth:`add` of the same rows.
        Returns the frozen fit's errors ``frozen_y - mean`` (n, R) on these transitions."""
        with torch.no_grad():
            frozen_error = (y if frozen_y is None else frozen_y) - self.frozen.predict(inputs)[0]
            learner = (y - self.learner.predict(inputs)[0]).square().sum(-1)
        self.errors.extend(zip(frozen_error.square().sum(-1).tolist(), learner.tolist()))
        if len(self.errors) >= GUARD_MIN_ROWS:
            self.adopted = surely_positive([f - lr for f, lr in self.errors])
        return frozen_error

    def add(self, inputs: Tensor, y: Tensor) -> None:
        """Let the learner learn rows ``inputs`` (n, Din), residuals ``y`` (n, R)
        (:meth:`OnlineGP.add <torch_gpmpc.gp.online.OnlineGP.add>`)."""
        self.learner.add(inputs, y)

    def end_step(self) -> bool:
        """Count one control step of the learner (its scheduled refits). Returns whether it re-fitted."""
        return self.learner.end_step()
