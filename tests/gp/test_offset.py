"""The offset estimate (offset-free tracking) against closed forms and a plant with a known bias."""

from __future__ import annotations

import math

import pytest
import torch

from torch_gpmpc import Config, ResidualGP
from torch_gpmpc.coordination.controller import Controller
from torch_gpmpc.dynamics.plants import ModelPlant
from torch_gpmpc.dynamics.team import team_system_from_config
from torch_gpmpc.errors import GpmpcError
from torch_gpmpc.gp.fit import fit_agent_gps
from torch_gpmpc.gp.offset import OffsetCorrected, offset_corrected
from torch_gpmpc.gp.online import OnlineLearning
from torch_gpmpc.sim.closed_loop import ADMMPlanner, run_closed_loop, simulate
from torch_gpmpc.sim.metrics import compute_metrics
from torch_gpmpc.sim.scenarios import Scenario

F64 = torch.float64


def _gp(noise: float) -> ResidualGP:
    x = torch.linspace(-2, 2, 12, dtype=F64)[:, None]
    gp = ResidualGP(x, torch.cat([torch.sin(x), torch.cos(x)], 1))
    gp.likelihood.noise = torch.full((2, 1), noise, dtype=F64)  # standardized units
    return gp.refresh()


def test_the_gain_settles_at_the_random_walk_filters_closed_form():
    """A random walk of variance q per step seen through noise r: the Kalman gain settles at
    ``p / (p + r)`` with ``p = (q + sqrt(q^2 + 4 q r)) / 2`` (the scalar Riccati equation's root)."""
    model = OffsetCorrected(_gp(0.05), drift=0.01)
    for _ in range(400):
        model.observe(torch.zeros(2, dtype=F64))
    q, r = 0.01 ** 2, model.noise.detach()
    p = (q + torch.sqrt(q ** 2 + 4 * q * r)) / 2
    torch.testing.assert_close(model.variance, p * r / (p + r), rtol=1e-10, atol=0)


def test_the_offset_averages_noise_and_adds_its_variance_to_the_margins():
    """Noisy errors around a constant bias b: the estimate ends near b (within a few of its own
    standard deviations), and the model's mean and variance are the GP's plus the offset and P."""
    gp = _gp(0.2)
    model = OffsetCorrected(gp, drift=0.01)
    b = torch.tensor([1.0, -0.6], dtype=F64)
    gen = torch.Generator().manual_seed(0)
    z = torch.tensor([[0.4]], dtype=F64)
    for _ in range(2000):
        y = gp.predict(z)[0][0] + b + model.noise.sqrt() * torch.randn(2, generator=gen, dtype=F64)
        model.observe(y - model.predict(z)[0][0])
    assert torch.all((model.offset - b).abs() < 4 * model.variance.sqrt())
    assert torch.all((model.offset - b).abs() < b.abs() / 4)  # it moved: 4 sigma alone would not say so
    mean, var = model.predict(z)
    gp_mean, gp_var = gp.predict(z)
    torch.testing.assert_close(mean, gp_mean + model.offset, rtol=0, atol=1e-15)
    torch.testing.assert_close(var, gp_var + model.variance, rtol=0, atol=1e-15)
    lin_mean, lin_jac, lin_var = model.linearize(z)
    gp_lin = gp.linearize(z)
    torch.testing.assert_close(lin_jac, gp_lin[1], rtol=0, atol=0)
    torch.testing.assert_close(lin_var, gp_lin[2] + model.variance, rtol=0, atol=1e-15)


def test_errors_that_jump_from_step_to_step_move_the_estimate_little():
    """Errors of +-0.5 in turn (a vehicle's tracking lag, not a disturbance) on a GP whose noise is
    small: the errors' running mean square becomes the filter's noise, and the estimate stays near 0
    where the GP's noise alone would let it follow each error."""
    model = OffsetCorrected(_gp(1e-4), drift=0.01)
    swing = []
    for i in range(200):
        model.observe(torch.full((2,), 0.5 if i % 2 else -0.5, dtype=F64))
        swing.append(float(model.offset.abs().max()))
    assert max(swing[100:]) < 0.02
    assert torch.all(model.error_variance > 0.2)


def test_an_online_gp_and_the_offset_never_count_an_error_twice():
    """An online GP under the offset, one point flown again and again on a plant that is the GP plus a
    constant b: the GP learns the transition less the offset, the offset what the updated GP still
    misses, and their prediction ends on the truth (it overshot by ~40 % of b when the GP learned the
    raw residual)."""
    from torch_gpmpc.gp.online import OnlineGP

    gp = _gp(1e-3)
    model = OffsetCorrected(OnlineGP(gp, budget=40), drift=0.01)
    z = torch.tensor([[0.4]], dtype=F64)
    truth = gp.predict(z)[0][0] + torch.tensor([0.3, -0.2], dtype=F64)
    for _ in range(30):  # the offset first, with the GP frozen
        model.observe(truth - model.predict(z)[0][0])
    misses = []
    for _ in range(12):  # then online, as OnlineLearning.observe does it
        model.add(z, truth[None])
        model.observe(truth - model.predict(z)[0][0])
        misses.append(float((model.predict(z)[0][0] - truth).abs().max()))
    # measured: 0.053 falling to 0.005; learning the raw residual, 0.04 rising to 0.10, then 0.087
    assert misses[-1] < 0.01 and all(b <= a + 1e-12 for a, b in zip(misses, misses[1:]))


def test_offset_drift_applies_to_the_gp_mean_methods_only():
    assert Config(disturbance_drift=0.01).offset_drift == 0.01
    with pytest.warns(UserWarning, match="disturbance_drift"):
        cfg = Config(method="nominal-chance", disturbance_drift=0.01)
    assert cfg.offset_drift == 0.0
    wrapped = offset_corrected([_gp(0.05)], 0.01)
    assert offset_corrected(wrapped, 0.01)[0] is wrapped[0]  # never wrapped twice


def test_bad_drift_and_bad_error_are_refused():
    with pytest.raises(GpmpcError, match="disturbance_drift"):
        OffsetCorrected(_gp(0.05), drift=0.0)
    with pytest.raises(GpmpcError, match="R = 2"):
        OffsetCorrected(_gp(0.05), drift=0.01).observe(torch.zeros(3, dtype=F64))
    gps = [_gp(0.05)]
    assert offset_corrected(gps, 0.0) is gps


class BiasedPlant(ModelPlant):
    """The model plant with a constant push ``bias`` (K, D) on top of its dynamics: a disturbance
    the residual GP never saw."""

    def __init__(self, system, bias: torch.Tensor) -> None:
        super().__init__(system)
        self.bias = bias

    def step(self, t, x, u, noise=None):
        self.true_states = super().step(t, x, u, noise) + self.bias
        return self.true_states


def _hold_at_goal(cfg: Config, bias: torch.Tensor) -> tuple[float, torch.Tensor, torch.Tensor]:
    """One agent flies to its goal on a biased plant; returns its final distance, its final offset
    estimate and its GP's mean at the goal."""
    scenario = Scenario(torch.tensor([[-1.0, 0.5]], dtype=F64), torch.tensor([[1.0, -0.5]], dtype=F64),
                        ref_points=20)
    system = team_system_from_config(cfg)
    gps = offset_corrected(fit_agent_gps(cfg, system, 1), cfg.offset_drift)
    planner = ADMMPlanner(Controller.for_run(cfg, system, gps))
    learning = OnlineLearning(gps, system.nominal, online=False)
    rollout = run_closed_loop(cfg, scenario, BiasedPlant(system, bias), planner, learning=learning)
    final = float(torch.linalg.vector_norm(torch.as_tensor(rollout.states[-1]) - scenario.targets[0]))
    gp = gps[0].model if isinstance(gps[0], OffsetCorrected) else gps[0]
    goal_mean = gp.predict(system.nominal.gp_input(system.nominal.states_at(scenario.targets), None))[0][0]
    offset = gps[0].offset if isinstance(gps[0], OffsetCorrected) else torch.zeros(2, dtype=F64)
    return final, offset, goal_mean


def test_a_known_constant_bias_is_estimated_and_the_agent_settles_on_its_goal():
    """A noiseless single integrator whose plant adds a constant b per step that nothing in its data
    shows. At rest on the goal the true residual there is ``g(goal) + b``, so the estimate must
    end at ``g(goal) + b - mu(goal)`` (the vortex and the GP's mean, both known here) and the agent
    on its goal (to 4e-4: the input cost still trades a little distance for a smaller holding
    input); without the estimate it holds ``b`` over its feedback gain away."""
    bias = torch.tensor([[0.09, -0.06]], dtype=F64)
    cfg = Config(scenario="circle", num_agents=1, noise_std=0.0, goal_tol=1e-6, max_steps=80, gp_samples=30,
                 gp_iters=10, disturbance_drift=0.01)
    final, offset, goal_mean = _hold_at_goal(cfg, bias)
    system = team_system_from_config(cfg)
    g_goal = system.residual(system.nominal.states_at(torch.tensor([[1.0, -0.5]], dtype=F64)))[0]
    torch.testing.assert_close(offset, g_goal + bias[0] - goal_mean, rtol=0, atol=1e-6)
    assert final < 1e-3
    without, _, _ = _hold_at_goal(cfg.replace(disturbance_drift=0.0), bias)
    assert without > 0.1 > 100 * final  # the default goal_tol: never home without it


def test_the_offset_estimate_learns_a_turned_wind():
    """The paper's agents, the vortex turned at step 5 (the online-GP case of test_plants.py): the
    offset estimate alone, with frozen GPs, predicts the transitions after the change better than
    the same GPs without it (measured: 0.141 against 0.218 m; the errors' own variance, which the
    filter takes as its noise when it exceeds the GP's, keeps the gain low while they are large)."""
    base = Config(max_steps=30, wind_change_step=5, wind_scale=0.3, noise_std=0.01, gp_iters=10,
                  disturbance_drift=0.01)
    with_offset = compute_metrics(simulate(base))["online_prediction_rmse_after_change"]
    without = compute_metrics(simulate(base.replace(disturbance_drift=0.0)))["online_prediction_rmse_after_change"]
    assert with_offset < 0.75 * without
    assert math.isfinite(with_offset)
