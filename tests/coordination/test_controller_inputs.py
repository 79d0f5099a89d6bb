"""Bad input at the Python front door (Controller, ControllerSettings, ModelSpec) is refused with a
GpmpcError naming the field and the fix, before any solve."""

from __future__ import annotations

import warnings

import pytest
import torch

from tests.helpers import ConstantVarianceGP
from torch_gpmpc import Controller, ControllerSettings, GpmpcError, ModelSpec, NominalModel

F64 = torch.float64


def _swap(horizon: int = 5):
    x0 = torch.tensor([[-1.0, 0.05, 0.0, 0.0], [1.0, -0.05, 0.0, 0.0]], dtype=F64)
    return x0, x0.flip(0)[:, None].expand(2, horizon + 1, 4).clone()


@pytest.mark.parametrize("field", ["x", "xref"])
def test_a_non_finite_state_or_reference_is_refused_naming_the_agent(field):
    ctrl = Controller(ModelSpec.double_integrator(2), settings=ControllerSettings(method="nominal", horizon=5))
    x0, xref = _swap()
    if field == "x":
        x0[1, 2] = float("nan")
    else:
        xref[1, 3, 0] = float("inf")
    with pytest.raises(GpmpcError, match=f"{field} of agent 1 is not finite"):
        ctrl.step(x0, xref)
    assert ctrl.warm is None  # nothing was solved


def test_misspelt_controller_settings_name_the_nearest_key():
    with pytest.raises(GpmpcError, match="did you mean 'horizon'"):
        ControllerSettings(horizn=5)


def test_residual_models_of_the_wrong_size_are_refused_at_construction():
    model = ModelSpec.double_integrator(2)  # GPs read x0, x1 and learn rows 2, 3

    full_state = ConstantVarianceGP(0.01)
    full_state.input_dim = 4
    with pytest.raises(GpmpcError, match=r"reads 4 inputs.*gp_inputs = \['x0', 'x1'\]"):
        Controller(model, gps=[full_state] * 2, settings=ControllerSettings(horizon=5))
    one_row = ConstantVarianceGP(0.01)
    one_row.output_dim = 1
    with pytest.raises(GpmpcError, match=r"predicts 1 rows.*residual = \[2, 3\]"):
        Controller(model, gps=[one_row] * 2, settings=ControllerSettings(horizon=5))


def test_a_model_from_tensors_is_validated_as_a_table_without_a_torch_warning():
    A = torch.tensor([[1.0, 0.1], [0.0, 1.0]], dtype=F64)
    B = torch.tensor([[0.005], [0.1]], dtype=F64)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        table = ModelSpec.from_table({"A": A, "B": B, "position": [0], "residual": [1],
                                      "input_bound": {"box": torch.tensor([2.0])}})
        direct = ModelSpec(name="model", dt=0.1, A=A, B=B, position=(0,), residual=(1,), gp_inputs=("x0", "x1"),
                           input_box=(2.0,))
        NominalModel(direct).A()
    assert direct == table and direct.A == ((1.0, 0.1), (0.0, 1.0))
    with pytest.raises(GpmpcError, match="B has 1 rows"):
        ModelSpec(name="m", dt=0.1, A=A, B=B[:1], position=(0,), residual=(1,), gp_inputs=("x0", "x1"),
                  input_box=(2.0,))


def test_the_step_plans_on_one_torch_thread_and_restores_the_callers_count():
    """Controller.step plans as simulate does (torch on one thread inside), whatever the caller set."""
    seen = []
    ctrl = Controller(ModelSpec.double_integrator(2), settings=ControllerSettings(method="nominal", horizon=5))
    original = ctrl.admm.solve_step

    def spy(*args, **kwargs):
        seen.append(torch.get_num_threads())
        return original(*args, **kwargs)

    ctrl.admm.solve_step = spy
    before = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        ctrl.step(*_swap())
        assert seen == [1] and torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(before)


def test_a_stated_cost_follows_in_place_changes_and_the_settings_terminal_rule():
    from torch_gpmpc import QuadraticCost

    model = ModelSpec.double_integrator(2)
    x0, xref = _swap()
    q = torch.tensor([1.0, 1.0, 0.1, 0.1], dtype=F64)
    ctrl = Controller(model, settings=ControllerSettings(method="nominal", horizon=5), cost=QuadraticCost(Q=q, R=0.01))
    first = ctrl.step(x0, xref).problem.cost_Q[0, 0, 0]
    q.mul_(10.0)  # the user edits the weight in place: the next step uses it
    ctrl.reset()
    assert float(ctrl.step(x0, xref).problem.cost_Q[0, 0, 0]) == pytest.approx(10.0 * float(first))
    stage = Controller(model, settings=ControllerSettings(method="nominal", horizon=5, terminal_cost="stage"),
                       cost=QuadraticCost(Q=q, R=0.01))
    problem = stage.step(x0, xref).problem
    torch.testing.assert_close(problem.cost_P, problem.cost_Q)  # P = Q, as the settings say


def test_gradients_to_a_cost_tensor_survive_repeated_probes():
    from torch_gpmpc import QuadraticCost

    q = torch.tensor([1.0, 1.0, 0.1, 0.1], dtype=F64, requires_grad=True)
    ctrl = Controller(ModelSpec.double_integrator(2), settings=ControllerSettings(method="nominal", horizon=5),
                      cost=QuadraticCost(Q=q, R=0.01))
    x0, xref = _swap()
    grads = []
    for _ in range(2):  # a second backward builds on a new graph
        (g,) = torch.autograd.grad(ctrl.differentiable_step(x0, xref, iterations=5).plans.pow(2).sum(), q)
        grads.append(g)
    torch.testing.assert_close(grads[0], grads[1])
    assert float(grads[0].abs().max()) > 0


NOMINAL = ControllerSettings(method="nominal", horizon=5)


@pytest.mark.parametrize("make, match", [
    (lambda m: Controller(m, settings=NOMINAL, cost={"Q": 1.0, "R": 1.0}), "cost must be a QuadraticCost or a list"),
    (lambda m: Controller(m, settings=ControllerSettings(method="nominal", cost={"Q": 1.0, "R": 1.0}),
                          cost=_cost(Q=1.0, R=1.0)), "given twice"),
    (lambda m: Controller(m, settings=NOMINAL, cost=_cost(Q="abc", R=1.0)), "QuadraticCost.Q must be a number"),
    (lambda m: Controller(m, settings=NOMINAL, cost=[_cost(Q=1.0, R=1.0), _cost(Q=[1.0, 1.0], R=1.0)]),
     r"the cost of agent 1: QuadraticCost.Q: a diagonal of 4 entries is needed \(the model has 4 states\)"),
])
def test_bad_costs_name_what_is_wrong(make, match):
    with pytest.raises(GpmpcError, match=match):
        make(ModelSpec.double_integrator(2))


def _cost(**kwargs):
    from torch_gpmpc import QuadraticCost

    return QuadraticCost(**kwargs)


def test_alpha_with_a_stated_cost_warns():
    with pytest.warns(UserWarning, match="'alpha' is ignored under cost=QuadraticCost"):
        Controller(ModelSpec.double_integrator(2), settings=ControllerSettings(method="nominal", alpha=0.5),
                   cost=_cost(Q=1.0, R=0.1))


def test_a_model_spec_of_plain_tuples_is_validated_too():
    with pytest.raises(GpmpcError, match="position index 5 is not a state index"):
        ModelSpec(name="x", dt=0.1, A=((1.0, 0.0), (0.0, 1.0)), B=((0.1, 0.0), (0.0, 0.1)), position=(0, 5),
                  residual=(1,), gp_inputs=("x0", "x1"), input_norm=2.0)
