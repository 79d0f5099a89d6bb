"""The online guard: a learner is planned with only while it predicts held-out transitions better."""

from __future__ import annotations

import copy

import pytest
import torch

from torch_gpmpc import ResidualGP
from torch_gpmpc.gp.guard import GUARD_MIN_ROWS, GUARD_WINDOW, GuardedOnlineGP, surely_positive
from torch_gpmpc.gp.offset import OffsetCorrected
from torch_gpmpc.gp.online import OnlineGP

F64 = torch.float64


def _fitted(seed=0):
    g = torch.Generator().manual_seed(seed)
    x = 4 * torch.rand(40, 1, generator=g, dtype=F64) - 2
    return ResidualGP(x, torch.sin(x) + 0.01 * torch.randn(40, 1, generator=g, dtype=F64))


def _points(n, seed):
    return 3 * torch.rand(n, 1, generator=torch.Generator().manual_seed(seed), dtype=F64) - 1.5


def test_an_update_that_worsens_held_out_points_is_refused():
    """The learner is fed rows whose residual is the truth plus a +-0.4 lag that no input sees; each
    new point is first judged on its true residual. The learner predicts those worse, so the agent
    keeps planning with the frozen fit, bit for bit, and the guard's scores are the squared errors
    written out."""
    guarded = GuardedOnlineGP(OnlineGP(_fitted(), budget=60))
    frozen_before = guarded.frozen.predict(_points(5, 9))[0]
    x = _points(20, 1)
    expected = []
    for i in range(20):
        row, truth = x[i:i + 1], torch.sin(x[i:i + 1])
        f = float((truth - guarded.frozen.predict(row)[0]).square().sum())
        lr = float((truth - guarded.learner.predict(row)[0]).square().sum())
        expected.append((f, lr))
        guarded.judge(row, truth)
        assert not guarded.adopted
        guarded.add(row, truth + (0.4 if i % 2 else -0.4))
    assert list(guarded.errors) == expected[-GUARD_WINDOW:]
    assert sum(e[1] for e in expected[-GUARD_WINDOW:]) > 2 * sum(e[0] for e in expected[-GUARD_WINDOW:])
    q = _points(7, 5)
    for a, b in zip(guarded.linearize(q), guarded.frozen.linearize(q)):
        assert torch.equal(a, b)
    torch.testing.assert_close(guarded.frozen.predict(_points(5, 9))[0], frozen_before, rtol=0, atol=0)
    assert guarded.gp.num_data == 60   # the learner kept learning while refused


def test_an_update_that_predicts_held_out_points_better_is_adopted_and_refused_again():
    """The residual moves up by 0.3: within a few judged rows the learner, which has learnt it, is
    surely better and plans; when the residual moves back, the frozen fit takes over."""
    guarded = GuardedOnlineGP(OnlineGP(_fitted(), budget=30))
    x = _points(60, 2)
    adopted = []
    for i in range(60):
        shift = 0.3 if i < 30 else 0.0
        row = x[i:i + 1]
        guarded.judge(row, torch.sin(row) + shift)
        guarded.add(row, torch.sin(row) + shift)
        adopted.append(guarded.adopted)
    assert adopted[:GUARD_MIN_ROWS - 1] == [False] * (GUARD_MIN_ROWS - 1)
    assert all(adopted[8:30])
    assert not any(adopted[30 + GUARD_WINDOW:])
    q = _points(4, 3)
    assert torch.equal(guarded.predict(q)[0], guarded.frozen.predict(q)[0])


def test_each_candidate_is_judged_less_its_own_offset_estimate():
    """The learner less :attr:`offset` (0.3 here), the fit less the fit's own estimate (still 0)."""
    guarded = GuardedOnlineGP(OnlineGP(_fitted(), budget=30))
    model = OffsetCorrected(guarded, drift=0.01)
    model.offset = torch.tensor([0.3], dtype=F64)
    row = _points(1, 4)
    fit_error = model.judge(row, torch.sin(row) + 0.3)
    f, lr = guarded.errors[-1]
    assert lr < 1e-3 and abs(f - 0.09) < 1e-3
    assert abs(float(fit_error[0, 0]) - 0.3) < 0.03


def test_the_learner_must_be_better_by_two_standard_errors():
    """Paired gains (frozen minus learner squared error): mean against 2 sample standard deviations
    over sqrt(n), written out."""
    assert surely_positive([0.3, 0.1, 0.2])          # mean 0.2 > 2 * 0.1 / sqrt(3) = 0.115
    assert not surely_positive([0.3, -0.1, 0.2])     # mean 0.133 < 2 * 0.208 / sqrt(3) = 0.240
    assert not surely_positive([1.0, -1.0, 1.0, -1.0])
    assert surely_positive([0.5, 0.5, 0.5])          # no spread: any positive mean


def test_an_equally_good_learner_is_adopted_only_by_chance():
    """Paired squared errors of two equally good models (independent unit normal errors): the test
    adopts the learner on about 6 % of the windows of 3 transitions and 3 % of those of 10 (the figures
    the guard's docstring gives)."""
    g = torch.Generator().manual_seed(0)
    for n, low, high in ((3, 0.05, 0.07), (10, 0.025, 0.038)):
        errors = torch.randn(20000, n, 2, generator=g, dtype=F64).square()
        rate = sum(surely_positive(row.tolist()) for row in errors[..., 0] - errors[..., 1]) / 20000
        assert low < rate < high


def test_online_gps_keep_the_whole_fit_as_the_frozen_model():
    """A fit on more rows than the window: the learner keeps the latest rows, the frozen model all."""
    from torch_gpmpc.gp.online import online_gps

    fit = _fitted()
    guarded = online_gps([fit], budget=10, refit_every=0)[0]
    assert guarded.gp.num_data == 10 and guarded.frozen.num_data == fit.num_data == 40
    q = _points(6, 8)
    assert torch.equal(guarded.predict(q)[0], fit.predict(q)[0])


def test_learning_runs_with_unguarded_online_gps_too():
    from torch_gpmpc.config.model_spec import ModelSpec
    from torch_gpmpc.dynamics.systems import NominalModel
    from torch_gpmpc.gp.online import OnlineLearning

    nominal = NominalModel(ModelSpec.double_integrator(dim=1, dt=0.1, u_max=2.0))
    gp = ResidualGP(torch.zeros(5, 1, dtype=F64) + torch.arange(5.0, dtype=F64)[:, None], torch.zeros(5, 1, dtype=F64))
    learning = OnlineLearning([OffsetCorrected(OnlineGP(gp, budget=20), drift=0.01)], nominal, online=True)
    x = torch.tensor([[0.5, 0.1]], dtype=F64)
    learning.observe(x, torch.zeros(1, 1, dtype=F64), nominal(x, torch.zeros(1, 1, dtype=F64)))
    assert learning.gps[0].model.gp.num_data == 6


@pytest.mark.parametrize("refit_every", [0, 3])
def test_a_guarded_agent_plans_with_the_fit_and_its_own_estimate_or_the_learner_and_its_own(refit_every):
    """Replayed by hand on the same transitions: the fit in its own offset estimate (a frozen run's
    model) and the learner in its own (stepped from its error after learning and any refit). While
    the guard plans with the fit, the agent predicts and linearizes (one model's call and the team's
    batch, mean and variance) as the frozen run's model; once it adopts the learner, as the learner
    with its estimate. ``OnlineLearning.frozen_error`` is the frozen run's model's error throughout;
    unguarded online models keep no fit, so there is none."""
    from torch_gpmpc.config.model_spec import ModelSpec
    from torch_gpmpc.dynamics.systems import NominalModel
    from torch_gpmpc.gp.batch import linearize_models
    from torch_gpmpc.gp.online import OnlineLearning, online_gps

    nominal = NominalModel(ModelSpec.double_integrator(dim=1, dt=0.1, u_max=2.0))
    fit = _fitted()
    model = OffsetCorrected(online_gps([fit], budget=60, refit_every=refit_every)[0], drift=0.01)
    learning = OnlineLearning([model], nominal, online=True)
    frozen_run = OffsetCorrected(fit, drift=0.01)
    learner = OffsetCorrected(OnlineGP(copy.deepcopy(fit), budget=60, refit_every=refit_every), drift=0.01)
    x = torch.tensor([[0.5, 0.4]], dtype=F64)
    adopted = []
    for step in range(12):
        u = torch.tensor([[0.3 * (-1) ** step]], dtype=F64)
        # a push the fit never saw, that depends on the state
        x_next = nominal(x, u) + torch.tensor([[0.0, 0.5 * torch.sin(x[0, 1]).item() + 0.07]], dtype=F64)
        inputs, y = nominal.gp_targets(x, u, x_next)
        planned = learner if model.adopted else frozen_run
        torch.testing.assert_close(model.predict(inputs), planned.predict(inputs), rtol=0, atol=1e-12)
        want_mean, _, want_var = planned.linearize(inputs)
        got_mean, _, got_var = linearize_models([model], inputs[None])
        torch.testing.assert_close((got_mean[0], got_var[0]), (want_mean, want_var), rtol=0, atol=1e-12)
        expected = y - frozen_run.predict(inputs)[0]
        frozen_run.observe(expected[0])
        learner.add(inputs, y)
        learner.end_step()
        learner.observe((y - learner.predict(inputs)[0])[0])
        learning.observe(x, u, x_next)
        torch.testing.assert_close(learning.frozen_error, expected, rtol=0, atol=1e-12)
        adopted.append(model.adopted)
        x = x_next
    assert any(adopted) and not all(adopted)
    assert float((frozen_run.offset - learner.offset).abs().max()) > 1e-3  # two estimates, apart
    if refit_every:
        assert not torch.equal(learner.noise, frozen_run.noise)  # the refits moved the learner's noise

    unguarded = OnlineLearning([OnlineGP(_fitted(), budget=20)], nominal, online=True)
    unguarded.observe(x, u, x_next)
    assert unguarded.frozen_error is None
