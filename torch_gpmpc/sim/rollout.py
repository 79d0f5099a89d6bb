"""The record of one closed-loop run, and its ``rollout.npz`` file.

Shapes use S = steps taken, K = agents, D = state dimension, Du = input dimension,
P = position dimension (P = D for the paper's single integrator), T = horizon,
I = the iteration budget (``ControllerSettings.iteration_cap``).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

import numpy as np

from torch_gpmpc.errors import GpmpcError
from torch_gpmpc.fileio import atomic_path


@dataclass
class Rollout:
    """Everything a closed-loop run produced.

    Attributes:
        states: true states, shape (S+1, K, D); ``states[0]`` are the starts.
        inputs: applied inputs, shape (S, K, Du).
        plans: planned state trajectories at each step, shape (S, K, T+1, D).
        targets: final target positions, shape (K, P).
        adjacency: communication graph used at each step, bool, shape (S, K, K).
        admm_iterations: ADMM iterations at each step, int, shape (S,).
        converged: whether ADMM met its tolerance at each step, bool, shape (S,).
        primal_residuals: largest per-edge ||y - z|| per iteration, shape (S, I), NaN-padded.
        dual_residuals: rho ||z - z_prev|| per iteration, shape (S, I), NaN-padded.
        slack_max: largest collision slack of the final ADMM iterate per step, shape (S,).
        infeasible_solves: local solves with active slack or failed status per step, int, shape (S,).
        state_slack_max: how far the applied plans leave the soft state constraints per step, shape
            (S,) (0 inside; ``None`` in rollouts written before it was recorded).
        solve_time: seconds spent in local solves per step, shape (S,).
        chance_margin: largest chance margin Phi^-1(1-eps_k) sigma~ used per step, shape (S,).
        wall_time_s: total wall-clock time of the run, seconds.
        method: controller method name.
        seed: run seed.
        config: the run's configuration as a flat dict.
        messages_per_iteration: numbers each agent sends per ADMM iteration, shape (S, K).
        failed_solves: local solves that failed (solver exception, non-finite or inaccurate
            answer; the agent's previous plan was used instead) per step, int, shape (S,);
            ``None`` in files written before it existed.
        failed_solves_by_kind: the same split by kind, int, shape (S, 3), columns in the
            order of :data:`torch_gpmpc.control.problem.FAILURE_KINDS` (exception, non-finite, inaccurate).
        fallback: the safety fallback re-planned some agent at this step, bool, shape (S,).
        unsafe_plan: some pair's applied plans were closer at tau = 1 than their rows require,
            bool, shape (S,).
        pair_separation: the applied plans' distance at tau = 1 per pair, shape (S, K (K-1) / 2)
            (pairs in the order of :func:`~torch_gpmpc.sim.metrics.pair_index`; NaN for pairs not
            in contact).
        pair_required: the separation the pair's collision rows required at tau = 1 (``r_safe``
            plus the pair margin), shape (S, K (K-1) / 2), NaN for pairs not in contact.
        pair_risk: the bound on each pair's probability of colliding at the next sample, from the
            applied plans and the agents' variances at tau = 1, shape (S, K (K-1) / 2), NaN for pairs not
            in contact or methods without margins (``None`` in older files).
        obstacle_risk: each agent's summed bound on hitting an obstacle of its rows at the next
            sample, shape (S, K), NaN for methods without margins (``None`` without obstacles and
            in older files; the last four are ``None`` in files written before they existed).
        position: the state indices of the position (P of them); ``None``: every state.
        input_memory: the state rows that hold the last applied input in every agent's model
            (:attr:`~torch_gpmpc.config.model_spec.ModelSpec.input_memory`); ``None``: none.
        prediction_error: each agent's one-step GP prediction error of the residual it observed, shape
            (S, K, R) (``None`` without GPs; :class:`~torch_gpmpc.gp.online.OnlineLearning`).
        prediction_var: the GP's predictive variance (latent + noise) of the same, shape (S, K, R).
        frozen_prediction_error: with ``gp_online``, each agent's GP as fitted (with the offset
            estimate it would have made itself) on the same transitions, shape (S, K, R): the same
            flight judged without the learning (``None`` for frozen GPs, distributed runs and older
            files).
        gp_update_time: seconds of the online GP updates per step, shape (S,) (0 for a frozen GP).
        step_time: wall-clock seconds of each control step's planning (graph, reference and
            ADMM with its local solves and safety checks; not the plant; for the distributed
            backend the coordinator's wait for the agents' step, messages included), shape (S,)
            (``None`` in files written before it was recorded).

    Examples:
        >>> from torch_gpmpc import Config, compute_metrics, simulate
        >>> rollout = simulate(Config(method="nominal", max_steps=2))
        >>> rollout.states.shape, compute_metrics(rollout)["steps"]
        ((3, 3, 2), 2)
    """

    states: np.ndarray
    inputs: np.ndarray
    plans: np.ndarray
    targets: np.ndarray
    adjacency: np.ndarray
    admm_iterations: np.ndarray
    converged: np.ndarray
    primal_residuals: np.ndarray
    dual_residuals: np.ndarray
    slack_max: np.ndarray
    infeasible_solves: np.ndarray
    solve_time: np.ndarray
    chance_margin: np.ndarray
    wall_time_s: float
    method: str
    seed: int
    config: dict[str, Any] = field(default_factory=dict)
    messages_per_iteration: np.ndarray | None = None
    failed_solves: np.ndarray | None = None
    failed_solves_by_kind: np.ndarray | None = None
    fallback: np.ndarray | None = None
    unsafe_plan: np.ndarray | None = None
    pair_separation: np.ndarray | None = None
    pair_required: np.ndarray | None = None
    position: list[int] | None = None
    input_memory: list[int] | None = None
    state_slack_max: np.ndarray | None = None
    pair_risk: np.ndarray | None = None
    obstacle_risk: np.ndarray | None = None
    prediction_error: np.ndarray | None = None
    prediction_var: np.ndarray | None = None
    frozen_prediction_error: np.ndarray | None = None
    gp_update_time: np.ndarray | None = None
    step_time: np.ndarray | None = None

    @property
    def num_steps(self) -> int:
        """S, the number of control steps taken."""
        return int(self.inputs.shape[0])

    @property
    def num_agents(self) -> int:
        """K."""
        return int(self.states.shape[1])

    @property
    def positions(self) -> np.ndarray:
        """Positions of the true states, shape (S+1, K, P)."""
        states = np.asarray(self.states)
        return states if self.position is None else states[..., self.position]

    @property
    def plan_positions(self) -> np.ndarray:
        """Positions of the plans, shape (S, K, T+1, P)."""
        plans = np.asarray(self.plans)
        return plans if self.position is None else plans[..., self.position]

    def save(self, path: str | Path) -> None:
        """Write ``rollout.npz`` atomically (arrays only; config and names as JSON text)."""
        arrays = {
            name: np.asarray(getattr(self, name))
            for name in (
                "states", "inputs", "plans", "targets", "adjacency", "admm_iterations",
                "converged", "primal_residuals", "dual_residuals", "slack_max",
                "infeasible_solves", "solve_time", "chance_margin",
            )
        }
        for name in ("messages_per_iteration", "failed_solves", "failed_solves_by_kind", "fallback",
                     "unsafe_plan", "pair_separation", "pair_required", "state_slack_max", "pair_risk",
                     "obstacle_risk", "prediction_error", "prediction_var", "frozen_prediction_error", "gp_update_time",
                     "step_time"):
            if getattr(self, name) is not None:
                arrays[name] = np.asarray(getattr(self, name))
        meta = {"method": self.method, "seed": self.seed, "wall_time_s": self.wall_time_s,
                "config": self.config, "position": self.position, "input_memory": self.input_memory}
        arrays["meta_json"] = np.array(json.dumps(meta))
        with atomic_path(path) as tmp:
            with open(tmp, "wb") as fh:
                np.savez_compressed(fh, **arrays)

    @classmethod
    def load(cls, path: str | Path) -> "Rollout":
        """Read a ``rollout.npz`` written by :meth:`save` (no pickle is ever loaded)."""
        try:
            # opened here: np.load leaks its own handle when the archive is corrupt
            with open(path, "rb") as handle, np.load(handle, allow_pickle=False) as data:
                arrays = {k: data[k] for k in data.files}
            meta = json.loads(str(arrays.pop("meta_json")))
            # arrays a later version added are skipped, so its files still load here
            known = {f.name for f in fields(cls)}
            arrays = {name: value for name, value in arrays.items() if name in known}
            return cls(**arrays, method=meta["method"], seed=meta["seed"],
                       wall_time_s=meta["wall_time_s"], config=meta["config"], position=meta.get("position"),
                       input_memory=meta.get("input_memory"))
        except Exception as exc:  # noqa: BLE001 - BadZipFile, KeyError, TypeError, ... on a damaged file
            first = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
            raise GpmpcError(f"rollout file {str(path)!r} cannot be read (corrupt, truncated or not "
                             f"written by gpmpc run): {first}") from exc
