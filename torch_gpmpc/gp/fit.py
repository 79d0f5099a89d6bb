"""Fitting residual GPs: the free function :func:`fit_residual_gp` (as botorch's
``fit_gpytorch_mll``), fits from logged transitions, and the one per-agent recipe the
closed loop and the distributed agents use (:func:`fit_agent_gps`, :func:`fit_agent_gp`).
"""

from __future__ import annotations

import contextlib
import logging
import math
from typing import Any, Callable

import gpytorch
import torch
from linear_operator.utils.errors import NanError, NotPSDError
from torch import Tensor

from torch_gpmpc.config.schema import Config
from torch_gpmpc.config.settings import GPFitSettings
from torch_gpmpc.errors import GpmpcError
from torch_gpmpc.gp.model import MAX_CHOLESKY_SIZE, ResidualGP, check_training_data
from torch_gpmpc.gp.normalization import Standardization
from torch_gpmpc.gp.sparse import EXACT_MAX_POINTS, HYPERPARAMETER_SUBSET, NUM_INDUCING, kmeans_centers
from torch_gpmpc.threads import torch_threads

log = logging.getLogger(__name__)

#: Most training points :func:`fit_residual_gp` accepts: an exact GP needs O(N^2)
#: memory and O(N^3) time per output dimension (5000 points: ~0.4 GB for D = 2).
MAX_TRAINING_POINTS = 5000
#: Most training points of a sparse fit (its factorization holds D x M x N numbers).
MAX_SPARSE_POINTS = 100_000
#: Fitting methods: ``auto`` is ``exact`` up to ``gp.sparse.EXACT_MAX_POINTS`` rows, else ``sgpr``.
GP_METHODS = ("auto", "exact", "sgpr")
#: Jitter levels (added to the kernel diagonal, standardized units) tried when a
#: Cholesky factorization fails; ``None`` is GPyTorch's default.
JITTERS = (None, 1e-6, 1e-4)

#: Initial lengthscales of a fit, in standard deviations of its (standardized) inputs, tried in turn
#: (:func:`_fit_from_starts`). From 1 alone, 50 of the 200 output rows of the 100-agent crowd's
#: noiseless GPs (100 points over a 20 m square, a residual that varies over about 0.65 standard
#: deviations) ended where the residual is noise, at a marginal likelihood up to 4.8 nats per point
#: below the optimum a start at 0.3 reaches (held out: RMSE up to 0.073, the residual's own spread,
#: against at most 0.001 from the starts).
LENGTHSCALE_STARTS = (1.0, 0.3, 0.1)
#: How much a later start must lower an output row's negative log marginal likelihood (nats per
#: training point) to replace that row's hyperparameters: less is one optimum reached twice, and the
#: first start's fit is kept to the bit.
RESTART_GAIN = 0.1

Callback = Callable[[int, float, dict], None]
#: Marginal-likelihood evaluations a fit remembers (the last line search's), so that L-BFGS's
#: evaluation of each step's start point, the point its previous line search ended on, is free.
RECENT_EVALUATIONS = 4


class _LBFGS(torch.optim.LBFGS):
    """``torch.optim.LBFGS`` whose constructor does not import ``torch._dynamo`` (1 s at a first fit).

    ``Optimizer.add_param_group`` is wrapped so that ``torch.compile`` does not trace it, and that
    wrapper imports ``torch._dynamo`` on its first call; a fit is never compiled, so its instances
    use the unwrapped method (``functools.wraps``' ``__wrapped__``; the wrapped one if a torch lacks it).
    """

    add_param_group = getattr(torch.optim.Optimizer.add_param_group, "__wrapped__",
                              torch.optim.Optimizer.add_param_group)


def _neg_mll(model: gpytorch.models.ExactGP, mll: gpytorch.mlls.ExactMarginalLogLikelihood) -> Tensor:
    """Negative exact marginal log likelihood per datum, summed over outputs (:func:`_row_neg_mll`)."""
    return _row_neg_mll(model, mll).sum()


def _row_neg_mll(model: gpytorch.models.ExactGP, mll: gpytorch.mlls.ExactMarginalLogLikelihood) -> Tensor:
    """Negative exact marginal log likelihood per datum of each output row, shape (D,).

    Retries with increasing Cholesky jitter; raises GpmpcError when all fail.
    """
    last: Exception | None = None
    for jitter in JITTERS:
        ctx = (gpytorch.settings.cholesky_jitter(float_value=jitter, double_value=jitter)
               if jitter is not None else contextlib.nullcontext())
        try:
            with ctx, gpytorch.settings.max_cholesky_size(MAX_CHOLESKY_SIZE):
                out = model(*model.train_inputs)
                return -mll(out, model.train_targets)
        except (NotPSDError, torch.linalg.LinAlgError) as exc:
            last = exc
            log.warning("GP fit: Cholesky failed (jitter %s), retrying with more jitter", jitter)
    raise GpmpcError(f"GP fit failed: kernel matrix not positive definite even with jitter "
                     f"{JITTERS[-1]:g} ({last}); check for duplicated or extreme training data")


def fit_residual_gp(inputs: Tensor, y: Tensor, optimizer: str = "lbfgs", iters: int = 50, seed: int = 0,
                    callback: Callback | None = None, lr: float | None = None,
                    gp_inputs: str = "state", method: str = "auto", num_inducing: int = NUM_INDUCING) -> ResidualGP:
    """Fit a :class:`ResidualGP` by maximizing the exact marginal log likelihood, from each of
    :data:`LENGTHSCALE_STARTS` while a shorter start still finds a higher optimum for some output row.

    Args:
        inputs: raw training inputs, shape (N, Din).
        y: raw residual targets, shape (N, D).
        optimizer: ``"lbfgs"`` (``torch.optim.LBFGS`` with strong-Wolfe line search,
            the paper's choice) or ``"adam"``.
        iters: number of optimizer steps (L-BFGS iterations or Adam steps).
        seed: seeds torch's RNG for the fit and the sparse model's subset and k-means.
        callback: called as ``callback(step, loss, hyperparameters)`` for steps
            ``0..iters`` with the loss (negative MLL per datum, standardized units,
            summed over outputs) and the raw-unit :meth:`ResidualGP.hyperparameters`
            at which it was evaluated: the first start's steps, then as step ``iters`` the
            model returned (a step into NaN ends a start early).
        lr: learning rate (default 1.0 for L-BFGS, 0.1 for Adam).
        gp_inputs: ``"state"`` or ``"state_input"`` (recorded in the model).
        method: ``exact``; ``sgpr`` (hyperparameters by exact marginal likelihood on a seeded
            subset of :data:`~torch_gpmpc.gp.sparse.HYPERPARAMETER_SUBSET` rows, then the SGPR
            posterior on all rows with :data:`~torch_gpmpc.gp.sparse.NUM_INDUCING` k-means
            inducing points: :mod:`~torch_gpmpc.gp.sparse`); ``auto``: ``exact`` up to
            :data:`~torch_gpmpc.gp.sparse.EXACT_MAX_POINTS` rows, else ``sgpr``.
        num_inducing: inducing points M of the sparse model.

    Returns:
        The fitted model in eval mode with its prediction cache built (``gp.method`` says which).

    Raises:
        GpmpcError: bad arguments, non-PD kernel matrices, or a diverged fit.

    An exact fit runs on :data:`FIT_THREADS` torch thread whatever the caller's count (the caller's is
    restored): its small matrices gain nothing from a second thread, and a loaded machine loses.
    """
    if optimizer not in ("lbfgs", "adam"):
        raise GpmpcError(f"optimizer must be 'lbfgs' or 'adam', got {optimizer!r}")
    if int(iters) < 0:
        raise GpmpcError(f"iters must be >= 0, got {iters}")
    inputs = torch.as_tensor(inputs, dtype=torch.float64)
    y = torch.as_tensor(y, dtype=torch.float64)
    num = int(inputs.shape[0]) if inputs.ndim else 0
    method = resolve_method(method, num)
    check_training_size(num, method)
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(int(seed))
        if method == "exact":
            with torch_threads(FIT_THREADS):  # at most 1000 points: threads only add hand-offs
                gp = _fit_from_starts(lambda: ResidualGP(inputs, y, gp_inputs=gp_inputs), optimizer, int(iters),
                                      callback, lr)
                return gp.refresh()
        return _fit_sparse(inputs, y, optimizer, int(iters), int(seed), callback, lr, gp_inputs, int(num_inducing))


def resolve_method(method: str, num_points: int) -> str:
    """``exact`` or ``sgpr`` for ``method`` (one of :data:`GP_METHODS`) and N training points."""
    if method not in GP_METHODS:
        raise GpmpcError(f"GP method must be one of {GP_METHODS}, got {method!r}")
    if method == "auto":
        return "exact" if num_points <= EXACT_MAX_POINTS else "sgpr"
    return method


def _fit_sparse(inputs: Tensor, y: Tensor, optimizer: str, iters: int, seed: int, callback: Callback | None,
                lr: float | None, gp_inputs: str, num_inducing: int) -> ResidualGP:
    """Hyperparameters on a seeded subset (exact marginal likelihood), then the SGPR posterior on
    all rows with k-means inducing points; the standardization is that of all rows."""
    inputs, y = check_training_data(inputs, y)
    scale = Standardization.from_data(inputs, y)
    gen = torch.Generator().manual_seed(seed)
    subset = torch.randperm(inputs.shape[0], generator=gen)[:HYPERPARAMETER_SUBSET]
    hyper = _fit_from_starts(lambda: ResidualGP(inputs[subset], y[subset], gp_inputs=gp_inputs, normalization=scale),
                             optimizer, iters, callback, lr)
    centres = kmeans_centers(scale.inputs(inputs), num_inducing, seed)
    gp = ResidualGP(inputs, y, gp_inputs=gp_inputs, normalization=scale,
                    inducing_points=centres * scale.x_std + scale.x_mean)
    gp.model.load_state_dict(hyper.model.state_dict())
    return gp.refresh()


def check_training_size(num_points: int, method: str = "exact") -> None:
    """Raise if ``num_points`` exceeds what ``method`` (``exact`` or ``sgpr``) fits.

    Raises:
        GpmpcError: naming the size, the limit and the fix.
    """
    if method == "exact" and num_points > MAX_TRAINING_POINTS:
        raise GpmpcError(f"GP training data: N={num_points} points is more than an exact GP fits in "
                         f"reasonable time and memory (at most {MAX_TRAINING_POINTS}); use --gp-method sgpr "
                         "(or auto), subsample the transitions or fit one agent's rows (fit-gp --agent K)")
    if num_points > MAX_SPARSE_POINTS:
        raise GpmpcError(f"GP training data: N={num_points} points is more than the sparse GP holds "
                         f"(at most {MAX_SPARSE_POINTS}); subsample the transitions")


def _fit_from_starts(new_gp: Callable[[], ResidualGP], optimizer: str, iters: int, callback: Callback | None,
                     lr: float | None) -> ResidualGP:
    """Fit a new GP (``new_gp()``) from each of :data:`LENGTHSCALE_STARTS` in turn, keeping per output
    row the start with the highest marginal likelihood where it beats the row kept so far by more
    than :data:`RESTART_GAIN`; the next start is tried only while the last one replaced some row.
    The starts are compared after ``iters`` steps each, converged or not (``iters = 0``: the first
    start's initial values alone). ``callback`` sees the first start's steps and, as step ``iters``,
    the fit returned."""
    gp = new_gp()
    gp.model.covar_module.base_kernel.lengthscale = LENGTHSCALE_STARTS[0]
    _optimize(gp, optimizer, iters, callback, lr)
    losses = _row_losses(gp)
    if not bool(torch.isfinite(losses).all()):  # the point the steps ended on (each step's start was finite)
        raise GpmpcError(f"GP fit diverged (loss {float(losses.sum())}) at step {iters}; try --optimizer lbfgs, "
                         "fewer --iters or check the data")
    for start in LENGTHSCALE_STARTS[1:] if iters > 0 else ():  # no steps: the initial values, as asked
        other = new_gp()
        other.model.covar_module.base_kernel.lengthscale = start
        try:
            _optimize(other, optimizer, iters, None, lr, nan_level=logging.DEBUG)
            other_losses = _row_losses(other)
        except (GpmpcError, NanError, NotPSDError, torch.linalg.LinAlgError) as exc:  # keep the fit in hand
            log.debug("GP fit: the start from lengthscale %g failed: %s", start, exc)
            break
        gain = losses - other_losses
        better = gain > RESTART_GAIN
        if not bool(better.any()):
            break
        _adopt_rows(gp, other, better)
        log.info("GP fit: output row(s) %s refitted from lengthscale %g (log marginal likelihood higher by %s "
                 "per point)", better.nonzero().flatten().tolist(), start,
                 ", ".join(f"{v:.3g}" for v in gain[better].tolist()))
        losses = torch.where(better, other_losses, losses)
    if callback is not None:
        callback(iters, float(losses.sum()), gp.hyperparameters())
    return gp


def _row_losses(gp: ResidualGP) -> Tensor:
    """(D,) each output row's negative log marginal likelihood per datum at the GP's hyperparameters."""
    gp.model.train()
    gp.likelihood.train()
    with torch.no_grad():
        return _row_neg_mll(gp.model, gpytorch.mlls.ExactMarginalLogLikelihood(gp.likelihood, gp.model))


def _adopt_rows(gp: ResidualGP, other: ResidualGP, rows: Tensor) -> None:
    """Copy ``other``'s hyperparameters of the output rows ``rows`` ((D,) bool) into ``gp`` (every
    parameter of the batch GP has the output row as its leading dimension)."""
    with torch.no_grad():
        for mine, theirs in zip(gp.model.parameters(), other.model.parameters()):
            mine[rows] = theirs[rows]


def _optimize(gp: ResidualGP, optimizer: str, iters: int, callback: Callback | None,
              lr: float | None, nan_level: int = logging.WARNING) -> None:
    """``iters`` optimizer steps on the exact marginal likelihood from the GP's hyperparameters,
    with ``callback(step, loss, hyperparameters)`` at each step's start point (steps
    ``0..iters-1``). A step into NaN ends the fit at the last finite point (logged at ``nan_level``)."""
    model = gp.model
    model.train()
    gp.likelihood.train()
    mll = gpytorch.mlls.ExactMarginalLogLikelihood(gp.likelihood, model)
    params = [p for p in model.parameters() if p.requires_grad]

    def new_optimizer() -> torch.optim.Optimizer:
        if optimizer == "lbfgs":
            return _LBFGS(params, lr=lr or 1.0, max_iter=1, line_search_fn="strong_wolfe")
        return torch.optim.Adam(params, lr=lr or 0.1)

    opt = new_optimizer()
    recent: list[tuple[list[Tensor], Tensor, list[Tensor | None]]] = []  # (point, loss, gradients)

    def closure() -> Tensor:
        # each L-BFGS step (one iteration) starts by evaluating its point, which the previous
        # step's line search has just evaluated: answer from the recent evaluations, bit for bit
        point = [p.detach().clone() for p in params]
        for seen, loss, grads in recent:
            if all(torch.equal(a, b) for a, b in zip(seen, point)):
                for p, g in zip(params, grads):
                    p.grad = None if g is None else g.clone()
                return loss
        for p in params:  # Optimizer.zero_grad() would import torch._dynamo (see _LBFGS)
            p.grad = None
        loss = _neg_mll(model, mll)
        loss.backward()
        recent.append((point, loss.detach(), [None if p.grad is None else p.grad.clone() for p in params]))
        del recent[:max(0, len(recent) - RECENT_EVALUATIONS)]
        return loss

    last_good = _copy_state(model)
    for step in range(iters):
        hp = gp.hyperparameters()
        try:
            loss = opt.step(closure)
        except (NanError, NotPSDError, torch.linalg.LinAlgError, GpmpcError) as exc:
            loss = torch.tensor(float("nan"))
            log.debug("GP fit step %d failed: %s", step, exc)
        if not (math.isfinite(float(loss.detach())) and _finite_state(model)):
            # an optimizer step into NaN (seen with noise-free data, where the noise runs to its
            # bound, and with rows whose signal the data cannot resolve, where the outputscale
            # runs to 0 or the lengthscales to infinity): keep the last finite hyperparameters
            model.load_state_dict(last_good)
            log.log(nan_level, "GP fit: step %d produced NaN; keeping the hyperparameters of step %d (%s)", step,
                    step - 1, _degenerate_rows(gp))
            return
        last_good = _copy_state(model)
        if optimizer == "lbfgs" and _line_search_stalled(opt, params[0]):
            # the strong-Wolfe search found no step along the quasi-Newton direction (seen on
            # smooth, low-noise data after a first long step): L-BFGS would repeat it forever,
            # so drop its curvature history and restart from steepest descent
            log.debug("GP fit: L-BFGS line search stalled at step %d; restarting its history", step)
            opt = new_optimizer()
        if callback is not None:
            callback(step, float(loss.detach()), hp)


def _degenerate_rows(gp: ResidualGP) -> str:
    """The output rows whose hyperparameters sit at a bound, which is where an L-BFGS line
    search steps into NaN, judged in the data's own units (the GP is fitted to standardized
    data): outputscale below 1e-6 of the row's variance (no signal the data resolve), noise
    within 2x of GPyTorch's 1e-4 floor (noise-free data), a lengthscale of 100 input standard
    deviations or more (an input the row does not vary with, e.g. the wind's x component with
    respect to x)."""
    var = gp.y_std ** 2
    scales, noises = (gp.outputscales / var).tolist(), (gp.noise.detach() / var).tolist()
    lengths = (gp.lengthscales / gp.x_std).tolist()
    notes = []
    for r, (ls, scale, noise) in enumerate(zip(lengths, scales, noises)):
        long = [i for i, v in enumerate(ls) if v >= 100.0]
        parts = (["outputscale ~ 0"] if scale < 1e-6 else []) + (["noise ~ 0"] if noise < 2e-4 else []) \
            + ([f"lengthscale >= 100 std on input(s) {long}"] if long else [])
        if parts:
            notes.append(f"output {r}: {', '.join(parts)}")
    return "; ".join(notes) if notes else "no hyperparameter at a bound"


def _line_search_stalled(opt: torch.optim.Optimizer, param: Tensor) -> bool:
    """Whether the last L-BFGS step's line search returned a zero step length."""
    t = opt.state.get(param, {}).get("t")
    return t is not None and float(t) == 0.0


def _copy_state(model: torch.nn.Module) -> dict:
    return {k: v.detach().clone() for k, v in model.state_dict().items()}


def _finite_state(model: torch.nn.Module) -> bool:
    return all(bool(torch.isfinite(p).all()) for p in model.parameters())


def fit_from_transitions(transitions, nominal=None, gp_inputs: str = "state", agent: int | None = None,
                         **fit_kwargs: Any) -> ResidualGP:
    """Fit a residual GP to logged transitions (paper eq. 2: ``y = x' - f(x, u)``).

    Args:
        transitions: a :class:`~torch_gpmpc.data.transitions.Transitions`.
        nominal: the known model f; default ``NominalModel(dim=D)`` (A = I, B = 0.1 I).
        gp_inputs: ``"state"`` (paper) or ``"state_input"``.
        agent: fit only this agent's rows (``None`` = all rows).
        **fit_kwargs: passed to :func:`fit_residual_gp` (optimizer, iters, seed, callback, lr).

    Returns:
        The fitted model.
    """
    from torch_gpmpc.dynamics.systems import NominalModel

    nominal = nominal if nominal is not None else NominalModel(transitions.state_dim)
    if agent is not None:
        transitions = transitions.for_agent(agent)
    X, Y = transitions.residuals(nominal, gp_inputs=gp_inputs)
    gp = fit_residual_gp(X, Y, gp_inputs=gp_inputs, **fit_kwargs)
    gp.residual_rows = residual_label(nominal.residual)  # named in its model file
    return gp


def fit_per_agent(transitions, nominal=None, gp_inputs: str = "state", **fit_kwargs: Any) -> dict[int, ResidualGP]:
    """One GP per agent id in ``transitions`` (each agent learns its own residual).

    Returns:
        ``{agent_id: ResidualGP}``.
    """
    ids = transitions.agent_ids
    if not ids:
        raise GpmpcError(f"{transitions.source}: no 'agent' column, cannot fit one GP per agent")
    return {k: fit_from_transitions(transitions, nominal, gp_inputs, agent=k, **fit_kwargs) for k in ids}


def check_gp_inputs(cfg: Config) -> None:
    """The controller's GPs read the model's ``gp_inputs`` columns (the state, for the paper's
    model); the config key ``gp_inputs`` only matters to ``fit-gp`` without ``--model``.

    Raises:
        GpmpcError: ``gp_inputs`` is not ``state``.
    """
    if cfg.gp_inputs != "state":
        raise GpmpcError("config key 'gp_inputs': the controller's GPs read the model's gp_inputs columns; "
                         "use gp_inputs=state and give other columns in a model file (--set model=FILE)")


def load_model_gp(path: str, spec) -> ResidualGP:
    """A ``fit-gp`` model file checked against the run's model (its GP inputs and residual rows: a
    file that names the rows it learned must name the model's)."""
    gp = ResidualGP.load(path, expected_dim=len(spec.residual), expected_input_dim=len(spec.gp_inputs))
    rows = residual_label(spec.residual)
    if gp.residual_rows is not None and gp.residual_rows != rows:
        raise GpmpcError(f"GP model file {str(path)!r}: it learned the residuals of state rows {gp.residual_rows} "
                         f"but the run's model has its residuals in rows {rows}; fit a model file for this "
                         "model (gpmpc fit-gp --model ...)")
    return gp


#: Torch threads of a run's recipe fits: a run's GPs, like its plans, must not depend on ``--threads``.
#: Parallel reductions round differently (with two threads 3 of the noiseless 100-agent crowd's recipe
#: fits differed, predictions by up to 3e-11, and its closed loop after 25 steps by 0.6 m), and these
#: small fits gain nothing from a second thread.
FIT_THREADS = 1


def fit_agent_gp(settings: GPFitSettings | Config, system, k: int) -> ResidualGP:
    """Agent k's residual GP by the paper's data recipe, from agent k's data alone.

    The data set is :func:`~torch_gpmpc.data.collect.collect_transitions` with seed
    ``2 seed + 1`` (``samples`` transitions per agent, positions uniform in the box of
    half-width ``box``, inputs uniform in the model's input bound); the fit uses seed
    ``seed + k``. That recipe draws every agent's samples from one generator in agent order,
    so collecting ``k + 1`` agents and keeping row block k gives exactly agent k's rows of the
    whole team's data set: an agent in its own process replays the draws of agents ``0..k-1``
    and never sees their models.

    Args:
        settings: the fit settings (a run :class:`Config` is checked and converted with
            ``gp_fit_settings()``).
        system: the :class:`~torch_gpmpc.dynamics.systems.TrueSystem` that generates the data (a mixed
            team's :class:`~torch_gpmpc.dynamics.team.TeamSystem`: agent k's own model's system, as
            :func:`fit_agent_gps`).
        k: agent id.

    The fit runs on :data:`FIT_THREADS` torch thread whatever the caller's count.
    """
    if hasattr(system, "team"):
        system = system.systems[system.team.group_of[k]]
    flights = _flight_settings(settings)
    settings = _fit_settings(settings)
    with torch_threads(FIT_THREADS):
        if flights is not None:
            return _fit_rows(settings, system, _flight_data(settings, flights, system, range(k, k + 1)), k)
        return _fit_rows(settings, system, _recipe_data(settings, system, k + 1), k)


def fit_agent_gps(settings: GPFitSettings | Config, system, agents: int) -> list[ResidualGP]:
    """Every agent's residual GP (:func:`fit_agent_gp` for ``k = 0..agents-1``, one data draw).

    A mixed team's system (:class:`~torch_gpmpc.dynamics.team.TeamSystem`): agent k's GP learns
    from row block k of the recipe's data drawn with its own model's system. On one torch thread, as
    :func:`fit_agent_gp`."""
    with torch_threads(FIT_THREADS):
        if hasattr(system, "team"):
            return _fit_team_gps(_fit_settings(settings), system, agents)
        flights = _flight_settings(settings)
        settings = _fit_settings(settings)
        data = _recipe_data(settings, system, agents) if flights is None \
            else _flight_data(settings, flights, system, range(agents))
        return [_fit_rows(settings, system, data, k) for k in range(agents)]


def _fit_team_gps(settings: GPFitSettings, system, agents: int) -> list[ResidualGP]:
    gps: list[ResidualGP | None] = [None] * agents
    for g, group_system in enumerate(system.systems):
        data = _recipe_data(settings, group_system, agents)
        for k in system.team.members(g):
            gps[k] = _fit_rows(settings, group_system, data, k)
    return gps


def _flight_settings(settings: GPFitSettings | Config):
    """With ``plant = rotorpy`` the GPs learn from excitation flights of the run's vehicles in its wind
    (seed ``2 seed + 1``, like the model plant's data), else ``None``."""
    if not isinstance(settings, Config) or settings.plant != "rotorpy":
        return None
    from torch_gpmpc.dynamics.rotorpy_plant import PlantSettings

    return PlantSettings.from_config(settings, seed=2 * settings.seed + 1)


def _flight_data(settings: GPFitSettings, flights, system, agents: range):
    from torch_gpmpc.data.flights import collect_flights

    return collect_flights(system.nominal, flights, samples=settings.samples, box=settings.box, agents=agents)


def _fit_settings(settings: GPFitSettings | Config) -> GPFitSettings:
    if isinstance(settings, Config):
        check_gp_inputs(settings)
        return settings.gp_fit_settings()
    return settings


def _recipe_data(settings: GPFitSettings, system, agents: int):
    from torch_gpmpc.data.collect import collect_transitions

    return collect_transitions(system, num_agents=agents, samples=settings.samples,
                               seed=2 * settings.seed + 1, box=settings.box)


def _fit_rows(settings: GPFitSettings, system, data, k: int) -> ResidualGP:
    inputs, y = data.for_agent(k).residuals(system.nominal)
    gp = fit_residual_gp(inputs, y, optimizer=settings.optimizer, iters=settings.iters, seed=settings.seed + k,
                         gp_inputs=gp_input_label(system.nominal))
    gp.residual_rows = residual_label(system.nominal.residual)
    return gp


def residual_label(rows) -> str:
    """The model file's name for the state rows a GP learns the residuals of: ``"x2,x3"``."""
    return ",".join(f"x{int(i)}" for i in rows)


def gp_input_label(nominal) -> str:
    """The model file's name for a GP's inputs: ``state`` for the paper's model, else the columns."""
    cols = list(nominal.spec.gp_inputs)
    return "state" if cols == [f"x{i}" for i in range(nominal.dim)] else ",".join(cols)


def refit_hyperparameters(gp: ResidualGP, iters: int = 10, optimizer: str = "lbfgs") -> ResidualGP:
    """Re-optimize a fitted GP's hyperparameters on its current rows, from their current values
    (an online GP's periodic refit); the standardization stays. Returns ``gp`` with its cache rebuilt.

    A sparse GP's hyperparameters are re-fitted on its rows by exact marginal likelihood, as at its fit.
    """
    _optimize(gp, optimizer, int(iters), None, None)
    return gp.refresh()
