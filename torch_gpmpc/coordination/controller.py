"""The cooperative controller: built once from a model, residual models and settings, then
stepped (the public API); and the one place a controller is built from a run configuration."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Sequence

import torch
from torch import Tensor

from torch_gpmpc.config.model_spec import ModelSpec
from torch_gpmpc.config.schema import Config
from torch_gpmpc.config.settings import ControllerSettings
from torch_gpmpc.config.team import team_spec
from torch_gpmpc.coordination.admm import ADMM
from torch_gpmpc.coordination.agent_step import LocalStep, as_nominal
from torch_gpmpc.coordination.graph import Graph, communication_graph
from torch_gpmpc.control.cost import QuadraticCost
from torch_gpmpc.control.solvers.ipm_threads import planning_threads
from torch_gpmpc.coordination.state import ADMMState, StepResult
from torch_gpmpc.coordination.team_step import TeamStep
from torch_gpmpc.dynamics.methods import Method
from torch_gpmpc.dynamics.systems import NominalModel, TrueSystem, VortexWind
from torch_gpmpc.dynamics.team import TeamNominal, TeamSystem
from torch_gpmpc.errors import GpmpcError


class Controller:
    """Cooperative GP-MPC for a team of K agents of one model: consensus ADMM over the
    neighbour graph, each agent solving its own chance-constrained local problem.

    Build it once, then call :meth:`step` at every control step: it warm-starts from the last
    step's plans (shifted by one step), as a receding-horizon controller does. Everything
    model-dependent (state and input sizes, input bound, ``uncertainty = auto``, the message
    size) comes from ``model``.

    Args:
        model: the agents' known linear model: a :class:`ModelSpec`
            (``ModelSpec.double_integrator(...)``, ``ModelSpec.load(path)``), a
            :class:`~torch_gpmpc.dynamics.systems.NominalModel`, or a model file path; or a list of
            them, one per agent (a mixed team: states and inputs lifted to the largest model's
            sizes, :mod:`~torch_gpmpc.config.team`).
        gps: one residual model per agent (the :class:`~torch_gpmpc.gp.protocol.ResidualModel`
            protocol: a :class:`~torch_gpmpc.gp.model.ResidualGP`, or user GPyTorch models wrapped
            by :meth:`ResidualGP.from_gpytorch`); needed by the ``gp*`` and ``*-chance`` methods.
        settings: the controller settings (default :class:`ControllerSettings`: the paper's).
        wind: the known wind, for the ``nonlinear`` baselines only.
        cost: the tracking cost (:class:`~torch_gpmpc.control.cost.QuadraticCost`), one for all agents or a
            list of K; ``None``: the settings' (Q = I but 0 on rows that hold the last input, R = alpha I, the LQR terminal weight). One model only.

    Attributes:
        agent_step: the per-agent step (:class:`~torch_gpmpc.coordination.agent_step.LocalStep`).
        admm: the consensus ADMM (:class:`~torch_gpmpc.coordination.admm.ADMM`).
        warm: the state the next :meth:`step` warm-starts from (``None``: cold start); save and
            restore it to evaluate a step twice from the same point.

    Examples:
        >>> import torch
        >>> from torch_gpmpc import Controller, ControllerSettings, ModelSpec
        >>> model = ModelSpec.double_integrator(dim=2, dt=0.1, u_max=2.0)
        >>> ctrl = Controller(model, settings=ControllerSettings(method="nominal", horizon=8))
        >>> x0 = torch.tensor([[-1.0, 0, 0, 0], [1.0, 0, 0, 0]], dtype=torch.float64)
        >>> xref = x0.flip(0)[:, None].expand(2, 9, 4)      # swap places
        >>> step = ctrl.step(x0, xref)
        >>> tuple(step.plans.shape), tuple(step.inputs.shape), ctrl.message_size, ctrl.uncertainty
        ((2, 9, 4), (2, 8, 2), 8, 'propagated')
    """

    def __init__(self, model: ModelSpec | NominalModel | str | Path | Sequence, gps: Sequence | None = None,
                 settings: ControllerSettings | None = None, wind: VortexWind | None = None,
                 cost: QuadraticCost | Sequence[QuadraticCost] | None = None) -> None:
        models = list(model) if isinstance(model, (list, tuple)) else [model]
        models = [ModelSpec.load(m) if isinstance(m, (str, Path)) else m for m in models]
        for m in models:
            if not isinstance(m, (ModelSpec, NominalModel)):
                raise GpmpcError(f"Controller: model must be a ModelSpec, a NominalModel or a model file path (or "
                                 f"a list of them, one per agent), got {type(m).__name__}")
        settings = settings or ControllerSettings()
        method = Method.parse(settings.method)
        if method.needs_gp and gps is None:
            raise GpmpcError(f"Controller: method {method.value!r} needs one residual model per agent (gps=[...]); "
                             "use settings.method='nominal' for none")
        gps = None if gps is None else list(gps)
        team = team_spec([as_nominal(m).spec for m in models]) if len(models) > 1 else None
        if team is not None and team.is_mixed:
            if cost is not None:
                raise GpmpcError("Controller: cost= takes one model's sizes; a mixed team uses the settings' cost "
                                 "(Q = I, R = alpha I) for now")
            self.agent_step = TeamStep(settings, team, method, wind, gps)
        else:
            check_residual_models(gps, as_nominal(models[0]).spec)
            self.agent_step = LocalStep(settings, as_nominal(models[0]), method, wind, gps, cost)
        self.admm = ADMM(self.agent_step)
        self.warm: ADMMState | None = None
        self._probes: dict[int, Controller] = {}  # differentiable_step's controllers, by iteration count

    @classmethod
    def for_run(cls, cfg: Config, system: TrueSystem | TeamSystem, gps: list | None = None,
                method: str | Method | None = None) -> "Controller":
        """The controller of a run configuration (what ``simulate``, ``gpmpc run`` and ``gpmpc tune``
        plan with): its per-agent step from :func:`make_agent_step` (the method decides what the agents
        know of ``system``: its wind, their GPs), the cost from the configuration's ``cost`` table."""
        return cls._of(make_agent_step(cfg, system, gps, method))

    @classmethod
    def _of(cls, agent_step: LocalStep | TeamStep) -> "Controller":
        """A controller around a built per-agent step."""
        ctrl = cls.__new__(cls)
        ctrl.agent_step, ctrl.admm, ctrl.warm, ctrl._probes = agent_step, ADMM(agent_step), None, {}
        return ctrl

    @property
    def settings(self) -> ControllerSettings:
        """The controller settings."""
        return self.agent_step.settings

    @property
    def model(self) -> NominalModel | TeamNominal:
        """The agents' known model (tensor form; a mixed team's models, one per agent)."""
        return self.agent_step.nominal

    @property
    def message_size(self) -> int:
        """Numbers one agent sends one neighbour per ADMM iteration (its copy of the pair's
        trajectories, ``2 (T+1) n``, plus T projected variances with the sum/joint margins)."""
        return self.agent_step.message_size

    @property
    def uncertainty(self) -> str:
        """The covariance model in use (``pointwise``, ``propagated`` or ``feedback``)."""
        return self.agent_step.uncertainty

    def reset(self) -> None:
        """Forget the warm start: the next step starts cold (every agent planning to stay)."""
        self.warm = None

    def graph(self, x: Tensor) -> Graph:
        """The communication graph of states ``x`` (K, n): pairs closer than ``comm_radius``."""
        return communication_graph(self.model.positions(x.detach()), self.settings.comm_radius)

    def step(self, x: Tensor, xref: Tensor, graph: Graph | None = None, rho: float | Tensor | None = None,
             risk_split: float | Tensor | None = None, safety_fallback: bool = True) -> StepResult:
        """Plan one control step for every agent.

        Args:
            x: (K, n) measured states.
            xref: (K, T+1, n) reference windows (``model.reference_states`` turns position
                paths (K, T+1, P) into state references).
            graph: the communication graph (default: by ``settings.comm_radius``).
            rho: ADMM penalty; a tensor with ``requires_grad`` gets gradients. Given, every edge
                starts the step at it; ``None``: edges keep the penalty residual balancing adapted
                at the last step (new edges start at ``settings.rho``).
            risk_split: scalar or (K, K) share of each pair's risk taken by its lower-indexed
                agent (default the settings'); a tensor gets gradients.
            safety_fallback: after an unconverged stop, re-plan the agents of unsafe or conflicting
                pairs against their neighbours (:meth:`ADMM.solve_step
                <torch_gpmpc.coordination.admm.ADMM.solve_step>`); those plans do not depend on
                ``rho``, so a gradient probe with a fixed iteration budget turns it off.

        Returns:
            The :class:`~torch_gpmpc.coordination.state.StepResult`: ``plans`` (K, T+1, n),
            ``inputs`` (K, T, m) (apply ``inputs[:, 0]``), ``iterations``, ``converged``,
            residual histories, failure counts. Gradients flow from ``plans``/``inputs`` to
            ``rho``, ``risk_split`` and, where enabled, the GP hyperparameters, within this step
            (the warm start carried to the next step is detached).
        """
        x = torch.as_tensor(x, dtype=torch.float64)
        xref = torch.as_tensor(xref, dtype=torch.float64)
        K, n, T = x.shape[0], self.model.dim, self.settings.horizon
        if x.dim() != 2 or x.shape[1] != n:
            raise GpmpcError(f"Controller.step: x must have shape (K, {n}), got {tuple(x.shape)}")
        if tuple(xref.shape) != (K, T + 1, n):
            raise GpmpcError(f"Controller.step: xref must have shape ({K}, {T + 1}, {n}) = (K, T+1, n), "
                             f"got {tuple(xref.shape)}")
        if self.agent_step.gps is not None and len(self.agent_step.gps) != K:
            raise GpmpcError(f"Controller.step: {K} agents but {len(self.agent_step.gps)} residual models")
        weights = getattr(self.agent_step, "cost_weights", None)
        if weights is not None and weights[0].shape[0] not in (1, K):
            raise GpmpcError(f"Controller.step: {weights[0].shape[0]} costs for {K} agents; give one QuadraticCost "
                             "for all agents or one per agent")
        refuse_non_finite(x, "x")
        refuse_non_finite(xref, "xref")
        graph = self.graph(x) if graph is None else graph
        warm = None if self.warm is None or self.warm.plans.shape[0] != K else self.warm.shifted()
        if warm is not None and rho is not None:
            warm = dataclasses.replace(warm, rho=None)  # the given rho starts every edge
        # torch on one thread, the compiled solver on the caller's count (as simulate plans): torch's
        # small-tensor ops only lose to thread hand-offs, most of all on a loaded machine
        with planning_threads():
            result = self.admm.solve_step(x, xref, graph, warm=warm, rho=rho, risk_split=risk_split,
                                          safety_fallback=safety_fallback)
        self.warm = result.state.detached()
        return result


    def differentiable_step(self, x: Tensor, xref: Tensor, iterations: int = 25, graph: Graph | None = None,
                            rho: float | Tensor | None = None, risk_split: float | Tensor | None = None) -> StepResult:
        """One step set up for gradients: exactly ``iterations`` ADMM iterations (no stopping test: a test
        met at rho but not at rho + h would make the map jump), no safety fallback (its re-planned plans
        do not depend on rho), cold local solves, from this controller's warm start, which it neither
        uses up nor advances: call it again to probe the same step.

        Args:
            x, xref, graph, rho, risk_split: as :meth:`step` (give ``rho`` / ``risk_split`` as tensors
                with ``requires_grad`` to get their gradients; a stated cost's tensors get theirs too).
                Under ``admm_coupling = copies`` rho weighs every consensus term; under ``planes`` it
                only sizes the offsets' moves, which are capped at a quarter of the pair's distance, so
                where no move is below its cap the plans do not depend on rho (no gradient to it).
            iterations: the fixed ADMM iteration count.

        Returns:
            The :class:`~torch_gpmpc.coordination.state.StepResult`; differentiate its ``plans`` or ``inputs``.

        Examples:
            >>> import torch
            >>> from torch_gpmpc import Controller, ControllerSettings, ModelSpec
            >>> settings = ControllerSettings(method="nominal", horizon=6, admm_coupling="copies")
            >>> ctrl = Controller(ModelSpec.double_integrator(2), settings=settings)
            >>> x0 = torch.tensor([[-1.0, 0.1, 0, 0], [1.0, -0.1, 0, 0]], dtype=torch.float64)
            >>> rho = torch.tensor(20.0, dtype=torch.float64, requires_grad=True)
            >>> step = ctrl.differentiable_step(x0, x0.flip(0)[:, None].expand(2, 7, 4), iterations=5, rho=rho)
            >>> step.iterations, step.inputs.pow(2).sum().backward(), rho.grad is not None
            (5, None, True)
        """
        if iterations < 1:
            raise GpmpcError(f"Controller.differentiable_step: iterations must be >= 1, got {iterations}")
        probe = self._probes.get(iterations)
        if probe is None:
            copies = {"admm_dual_tol": None, "admm_rel_tol": 0.0} if self.settings.admm_coupling == "copies" else {}
            settings = self.settings.replace(admm_tol=1e-300, admm_max_iter=int(iterations), solver_warm=False,
                                             **copies)  # the planes have no dual or relative tolerance
            probe = Controller._of(self.agent_step.with_settings(settings))
            self._probes[iterations] = probe
        probe.warm = self.warm
        return probe.step(x, xref, graph, rho=rho, risk_split=risk_split, safety_fallback=False)


def check_residual_models(gps: list | None, spec: ModelSpec) -> None:
    """Refuse residual models whose sizes do not fit the model: each reads ``len(spec.gp_inputs)`` inputs
    (the model's ``gp_inputs``) and predicts ``len(spec.residual)`` rows (its ``residual``)."""
    for k, gp in enumerate(gps or []):
        if gp is None:
            continue
        din, dout = int(gp.input_dim), int(gp.output_dim)
        if din != len(spec.gp_inputs):
            raise GpmpcError(
                f"Controller: the residual model of agent {k} reads {din} inputs, but model {spec.name!r} feeds its GPs "
                f"gp_inputs = {list(spec.gp_inputs)} ({len(spec.gp_inputs)}); train the GP on exactly those "
                f"columns, or set the model's gp_inputs to the {din} columns it was trained on")
        if dout != len(spec.residual):
            raise GpmpcError(
                f"Controller: the residual model of agent {k} predicts {dout} rows, but model {spec.name!r} learns "
                f"residual = {list(spec.residual)} ({len(spec.residual)}); give one GP output per residual row")


def refuse_non_finite(values: Tensor, name: str) -> None:
    """Raise :class:`GpmpcError` naming the first agent whose ``values`` (K, ...) hold a NaN or inf."""
    bad = ~torch.isfinite(values.detach()).reshape(values.shape[0], -1).all(dim=1)
    if bool(bad.any()):
        k = int(torch.nonzero(bad)[0])
        raise GpmpcError(f"Controller.step: {name} of agent {k} is not finite ({int(bad.sum())} agent(s) in all); "
                         f"pass measured states and references without NaN or inf")


def make_agent_step(cfg: Config, system: TrueSystem | TeamSystem, gps: list | None = None,
                    method: str | Method | None = None) -> LocalStep | TeamStep:
    """The per-agent step of ``method`` (default ``cfg.method``) for a run configuration.

    The method decides what the agents know: the ``nonlinear`` baselines get the true
    wind of ``system``, the ``gp`` and chance methods their residual GPs; the nominal
    model is ``system``'s (a mixed team's :class:`~torch_gpmpc.dynamics.team.TeamSystem` gives a
    :class:`~torch_gpmpc.coordination.team_step.TeamStep`, one local step per model).

    Args:
        cfg: run configuration.
        system: the true system (its nominal model and, for ``nonlinear``, its wind).
        gps: residual GPs indexed by agent id (ignored by methods that need none).
        method: overrides ``cfg.method``.
    """
    method = Method.parse(method or cfg.method)
    wind = system.wind if method.needs_wind else None
    gps = gps if method.needs_gp else None
    if isinstance(system, TeamSystem):
        return TeamStep(cfg, system.team, method, wind, gps)
    return LocalStep(cfg, system.nominal, method, wind, gps)


