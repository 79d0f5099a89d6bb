"""Figures of closed-loop runs (the paper's Figs. 2-6) and of ADMM behaviour.

All figures use matplotlib's Agg canvas directly (no display, no pyplot global
state, safe in worker processes) and are written atomically through
:func:`torch_gpmpc.fileio.atomic_path`. 3D runs are drawn in the x1-x2 plane.

Shapes use S = steps, K = agents, D = state dimension, T = horizon,
I = ADMM iterations, P = pairs (ordered as :func:`~torch_gpmpc.sim.metrics.pair_index`).
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.collections import EllipseCollection, LineCollection
from matplotlib.figure import Figure
from matplotlib.patches import Circle, Rectangle

from torch_gpmpc.config.obstacles import ObstacleField
from torch_gpmpc.errors import GpmpcError
from torch_gpmpc.fileio import atomic_path
from torch_gpmpc.sim.metrics import (body_radii_of, nearest_neighbour_distances, pair_distances, pair_index,
                                     path_lengths, run_setting, time_to_target)
from torch_gpmpc.sim.rollout import Rollout

logger = logging.getLogger(__name__)

_DPI = 110

#: Teams larger than this get no per-agent legend, and their distance figure the closest pair and
#: the median nearest neighbour per step instead of a line per pair (499 500 lines at K = 1000;
#: the tab10 colours repeat after 10 agents anyway).
MAX_LABELLED_AGENTS = 10
#: Distance figures with more pairs than this draw the pairs grey and label only the closest.
MAX_LABELLED_PAIRS = 10


def _color(k: int) -> str:
    """Colour of agent (or series) k, from matplotlib's tab10 cycle."""
    return f"C{k % 10}"


def _new_figure(ncols: int, nrows: int = 1, panel: tuple[float, float] = (4.0, 3.6)) -> tuple[Figure, np.ndarray]:
    """A Figure on an Agg canvas with an (nrows, ncols) array of axes."""
    fig = Figure(figsize=(panel[0] * ncols, panel[1] * nrows), layout="constrained")
    FigureCanvasAgg(fig)
    axes = fig.subplots(nrows, ncols, squeeze=False)
    return fig, axes


def _save(fig: Figure, path: str | Path) -> Path:
    """Write ``fig`` as PNG to ``path`` atomically; returns the path."""
    path = Path(path)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=_DPI)
    logger.debug("wrote %s", path)
    return path


# ---------------------------------------------------------------------------
# one run


def default_snapshot_steps(num_steps: int, count: int = 4) -> list[int]:
    """``count`` evenly spaced steps in 0..S including the last (fewer if S is small)."""
    return sorted({int(round(v)) for v in np.linspace(0, num_steps, count)})


def plot_trajectories(
    rollout: Rollout,
    path: str | Path,
    steps: Sequence[int] | None = None,
    reference_paths: Any = None,
) -> Path:
    """Snapshot panels of the agents' motion (the paper's Figs. 2-3).

    Per panel (one per step t): each agent's trajectory so far (solid), its current
    position (heavy dot) with a circle of its body radius (r_safe/2, or its ``radii`` entry), the plan made at t
    (dashed, small dot at its end), and the dashed straight line start -> target.
    The last panel says when the targets were reached.

    Args:
        rollout: the run; uses ``states`` (S+1, K, D), ``plans`` (S, K, T+1, D),
            ``targets`` (K, D) and ``config['r_safe']`` (and ``config['radii']``).
        path: PNG file to write.
        steps: steps t in 0..S to show (default: 4 evenly spaced, including S).
        reference_paths: optional reference, shape (K, R, D), drawn dotted.

    Returns:
        ``path``.
    """
    states = np.asarray(rollout.positions, dtype=np.float64)
    num_steps = states.shape[0] - 1
    steps = default_snapshot_steps(num_steps) if steps is None else [int(s) for s in steps]
    bad = [s for s in steps if not 0 <= s <= num_steps]
    if bad or not steps:
        raise GpmpcError(f"plot_trajectories: steps must be in 0..{num_steps}, got {list(steps)}")
    cfg = rollout.config or {}
    radii = body_radii_of(cfg, states.shape[1], run_setting(cfg, "r_safe"))
    ref = None if reference_paths is None else np.asarray(reference_paths, dtype=np.float64)
    fig, axes = _new_figure(len(steps))
    for n, (ax, t) in enumerate(zip(axes[0], steps)):
        _draw_snapshot(ax, rollout, states, t, radii, ref)
        title = f"t = {t}"
        if n == len(steps) - 1:
            ttt = time_to_target(states, rollout.targets, run_setting(cfg, "goal_tol"))
            title += f"\ntargets reached at t = {ttt}" if ttt is not None else "\ntargets not reached"
        ax.set_title(title, fontsize=10)
    if states.shape[1] <= MAX_LABELLED_AGENTS:
        axes[0][0].legend(loc="best", fontsize=7)
    _share_limits(axes[0], states, rollout.targets)
    return _save(fig, path)


def _draw_snapshot(ax: Any, rollout: Rollout, states: np.ndarray, t: int, radii: np.ndarray,
                   ref: np.ndarray | None) -> None:
    """One panel of :func:`plot_trajectories` at step t (``radii`` (K,): the bodies drawn)."""
    targets = np.asarray(rollout.targets, dtype=np.float64)
    plans = np.asarray(rollout.plan_positions, dtype=np.float64)
    _draw_obstacles(ax, (rollout.config or {}).get("obstacles"))
    if states.shape[1] > MAX_LABELLED_AGENTS:
        _draw_team(ax, states, targets, plans[t] if t < plans.shape[0] else None, t, radii, ref)
        return
    for k in range(states.shape[1]):
        c = _color(k)
        start, goal = states[0, k], targets[k]
        ax.plot([start[0], goal[0]], [start[1], goal[1]], "--", color=c, lw=0.8, alpha=0.5)
        ax.plot(goal[0], goal[1], "x", color=c, ms=7)
        if ref is not None:
            ax.plot(ref[k, :, 0], ref[k, :, 1], ":", color=c, lw=0.8, alpha=0.6)
        ax.plot(states[: t + 1, k, 0], states[: t + 1, k, 1], "-", color=c, lw=1.5, label=f"agent {k}")
        if t < plans.shape[0]:
            plan = plans[t, k]
            ax.plot(plan[:, 0], plan[:, 1], "--", color=c, lw=1.2)
            ax.plot(plan[-1, 0], plan[-1, 1], "o", color=c, ms=3)
        pos = states[t, k]
        ax.plot(pos[0], pos[1], "o", color=c, ms=8)
        if radii[k] > 0:
            ax.add_patch(Circle((pos[0], pos[1]), radii[k], fill=False, color=c, lw=0.8))
    ax.set_aspect("equal", adjustable="box")
    ax.set_xlabel("x1")
    ax.set_ylabel("x2")
    ax.grid(True, lw=0.3)


def _draw_team(ax: Any, states: np.ndarray, targets: np.ndarray, plans: np.ndarray | None, t: int,
               radii: np.ndarray, ref: np.ndarray | None) -> None:
    """A large team's panel of :func:`plot_trajectories` at step t, the same marks as the per-agent
    loop of :func:`_draw_snapshot` drawn as one collection each (a line artist per agent and mark
    took about 40 s at K = 1000). Shapes: states (S+1, K, D), targets (K, D), plans (K, T+1, D),
    radii (K,), ref (K, R, D)."""
    colors = [_color(k) for k in range(states.shape[1])]
    pos = states[t, :, :2]

    def lines(segments: Any, **style: Any) -> None:
        ax.add_collection(LineCollection(list(segments), colors=colors, **style))

    lines(np.stack([states[0, :, :2], targets[:, :2]], axis=1), linestyles="--", linewidths=0.8, alpha=0.5)
    ax.scatter(targets[:, 0], targets[:, 1], marker="x", c=colors, s=20, linewidths=0.8)
    if ref is not None:
        lines(ref[:, :, :2], linestyles=":", linewidths=0.8, alpha=0.6)
    lines(states[: t + 1, :, :2].transpose(1, 0, 2), linewidths=1.0)
    if plans is not None:
        lines(plans[:, :, :2], linestyles="--", linewidths=0.8)
    ax.scatter(pos[:, 0], pos[:, 1], c=colors, s=9)
    ax.add_collection(EllipseCollection(2 * radii, 2 * radii, 0.0, units="xy", offsets=pos,
                                        offset_transform=ax.transData, facecolors="none", edgecolors=colors,
                                        linewidths=0.5))
    ax.set_aspect("equal", adjustable="box")
    ax.set_xlabel("x1")
    ax.set_ylabel("x2")
    ax.grid(True, lw=0.3)


def _draw_obstacles(ax: Any, obstacles: Any) -> None:
    """The obstacles' footprints in the x1-x2 plane (grey), if the run has any."""
    if not obstacles:
        return
    for o in ObstacleField.parse(obstacles).obstacles:
        if o.kind == "box":
            ax.add_patch(Rectangle((o.lower[0], o.lower[1]), o.upper[0] - o.lower[0], o.upper[1] - o.lower[1],
                                   color="0.6", alpha=0.6, lw=0))
        else:
            ax.add_patch(Circle((o.center[0], o.center[1]), o.radius, color="0.6", alpha=0.6, lw=0))


def _share_limits(axes: Sequence[Any], states: np.ndarray, targets: Any) -> None:
    """Same x/y limits on every panel, covering all states and targets (with a margin)."""
    pts = np.concatenate([states.reshape(-1, states.shape[-1]), np.asarray(targets, dtype=np.float64)])
    pts = pts[np.all(np.isfinite(pts), axis=1)]
    if not len(pts):
        return
    lo, hi = pts[:, :2].min(axis=0), pts[:, :2].max(axis=0)
    pad = 0.1 * max(float((hi - lo).max()), 1.0)
    for ax in axes:
        ax.set_xlim(lo[0] - pad, hi[0] + pad)
        ax.set_ylim(lo[1] - pad, hi[1] + pad)


def plot_distances(rollout: Rollout, path: str | Path) -> Path:
    """Inter-agent distance over time, with r_safe dashed: one line per pair (beyond
    :data:`MAX_LABELLED_PAIRS` pairs grey, the closest pair coloured and labelled), or for a team
    of more than :data:`MAX_LABELLED_AGENTS` the closest pair and the agents' median distance to
    their nearest neighbour per step.

    Args:
        rollout: the run; uses ``states`` (S+1, K, D) and ``config['r_safe']``.
        path: PNG file to write.

    Returns:
        ``path``.
    """
    states = np.asarray(rollout.positions, dtype=np.float64)
    r_safe = run_setting(rollout.config or {}, "r_safe")
    fig, axes = _new_figure(1, panel=(6.0, 3.6))
    ax = axes[0, 0]
    steps = np.arange(states.shape[0])
    if states.shape[1] > MAX_LABELLED_AGENTS:
        nearest = nearest_neighbour_distances(states)  # (S+1, K)
        ax.plot(steps, nearest.min(axis=1), color="C3", lw=1.5, label="closest pair")
        ax.plot(steps, np.median(nearest, axis=1), color="C0", lw=1.2, label="median nearest neighbour")
    else:
        dists = pair_distances(states)  # (S+1, P)
        pairs = pair_index(states.shape[1])
        if len(pairs) <= MAX_LABELLED_PAIRS:
            for p, (i, j) in enumerate(pairs):
                ax.plot(steps, dists[:, p], color=_color(p), label=f"agents {i}-{j}")
        else:
            ax.plot(steps, dists, color="0.75", lw=0.6)
            closest = int(np.argmin(dists.min(axis=0)))
            i, j = pairs[closest]
            ax.plot(steps, dists[:, closest], color="C3", lw=1.5, label=f"closest pair (agents {i}-{j})")
        if dists.shape[1] == 0:
            ax.text(0.5, 0.5, "single agent: no pairs", ha="center", transform=ax.transAxes)
    ax.axhline(r_safe, color="k", ls="--", lw=1.0, label=f"r_safe = {r_safe:g}")
    ax.set_xlabel("step t")
    ax.set_ylabel("distance")
    ax.set_title(f"inter-agent distances ({rollout.method}, {states.shape[1]} agents)", fontsize=10)
    ax.grid(True, lw=0.3)
    ax.legend(fontsize=7)
    return _save(fig, path)


def plot_admm_residuals(rollout: Rollout, path: str | Path) -> Path:
    """ADMM primal and dual residual vs iteration, every step thin, the mean thick (log y), with each
    panel's stopping tolerance (the dual one ``admm_dual_tol``, or its default ``10 admm_tol``).

    The mean at iteration i is over the steps still iterating at i (NaN padding skipped), drawn only
    while at least a quarter of the steps (and 3) are: a mean of the few slowest steps says little.

    Args:
        rollout: the run; uses ``primal_residuals`` and ``dual_residuals`` (S, I),
            NaN-padded, and ``config['admm_tol']`` / ``config['admm_dual_tol']``.
        path: PNG file to write.

    Returns:
        ``path``.
    """
    cfg = rollout.config or {}
    fig, axes = _new_figure(2)
    primal_tol = cfg.get("admm_tol")
    dual_tol = cfg.get("admm_dual_tol")
    if dual_tol is None and primal_tol is not None and cfg.get("admm_stop", "primal-dual") == "primal-dual":
        dual_tol = 10.0 * float(primal_tol)  # the rule's default (penalty.py)
    panels = (
        ("primal residual max ||y - z||", rollout.primal_residuals, primal_tol),
        ("dual residual rho ||z - z_prev||", rollout.dual_residuals, dual_tol),
    )
    for ax, (label, res, tol) in zip(axes[0], panels):
        _draw_residuals(ax, np.asarray(res, dtype=np.float64), tol)
        ax.set_title(label, fontsize=10)
        ax.set_xlabel("ADMM iteration")
    axes[0, 0].set_ylabel("residual")
    return _save(fig, path)


def _draw_residuals(ax: Any, res: np.ndarray, tol: float | None) -> None:
    """Thin line per row of ``res`` (S, I), bold mean, optional tolerance line."""
    res = np.where(res > 0, res, np.nan)
    if res.ndim != 2 or not np.isfinite(res).any():
        ax.text(0.5, 0.5, "no residuals recorded", ha="center", transform=ax.transAxes)
        return
    its = np.arange(1, res.shape[1] + 1)
    segs = [np.column_stack([its, row])[np.isfinite(row)] for row in res]
    ax.add_collection(LineCollection([s for s in segs if len(s) > 1], colors="C0", linewidths=0.4, alpha=0.3))
    for s in segs:  # single-iteration steps still show up
        if len(s) == 1:
            ax.plot(s[0, 0], s[0, 1], ".", color="C0", ms=2, alpha=0.3)
    mean = _nanmean_rows(res)
    still = np.isfinite(res).sum(axis=0)
    mean[still < max(3, 0.25 * res.shape[0])] = np.nan  # a mean of the few slowest steps says little
    ax.plot(its, mean, color="C3", lw=2.0, label="mean over the steps still iterating")
    if tol is not None:
        ax.axhline(float(tol), color="k", ls="--", lw=1.0, label=f"absolute tolerance {float(tol):g}")
    ax.set_yscale("log")
    ax.autoscale_view()
    ax.grid(True, which="major", lw=0.4, alpha=0.6)
    ax.legend(fontsize=7)


def _nanmean_rows(values: np.ndarray) -> np.ndarray:
    """Mean over axis 0 ignoring NaN, NaN where a column has no finite value (no warning)."""
    finite = np.isfinite(values)
    count = finite.sum(axis=0)
    total = np.where(finite, values, 0.0).sum(axis=0)
    return np.divide(total, count, out=np.full(values.shape[1], np.nan), where=count > 0)


def plot_trajectories_3d(rollout: Rollout, path: str | Path) -> Path:
    """The agents' 3D paths (positions (S+1, K, 3)) with starts (o) and targets (x)."""
    pos = np.asarray(rollout.positions, dtype=np.float64)
    if pos.shape[-1] != 3:
        raise GpmpcError(f"plot_trajectories_3d needs 3D positions, got P = {pos.shape[-1]}")
    fig = Figure(figsize=(5.5, 5.0))
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(projection="3d")
    targets = np.asarray(rollout.targets, dtype=np.float64)
    if pos.shape[1] > MAX_LABELLED_AGENTS:
        _draw_team_3d(ax, pos, targets)
    else:
        for k in range(pos.shape[1]):
            c = _color(k)
            ax.plot(pos[:, k, 0], pos[:, k, 1], pos[:, k, 2], "-", color=c, lw=1.5, label=f"agent {k}")
            ax.scatter(*pos[0, k], color=c, marker="o")
            ax.scatter(*targets[k], color=c, marker="x")
        ax.legend(loc="upper left", fontsize=7)
    ax.set_xlabel("x")
    ax.set_ylabel("y")
    ax.set_zlabel("z")
    return _save(fig, path)


def _draw_team_3d(ax: Any, pos: np.ndarray, targets: np.ndarray) -> None:
    """A large team's 3D paths (pos (S+1, K, 3), targets (K, 3)), one collection per mark as in
    :func:`_draw_team`."""
    from mpl_toolkits.mplot3d.art3d import Line3DCollection

    colors = [_color(k) for k in range(pos.shape[1])]
    ax.add_collection3d(Line3DCollection(list(pos.transpose(1, 0, 2)), colors=colors, linewidths=1.0))
    ax.scatter(*pos[0].T, c=colors, marker="o", s=9)
    ax.scatter(*targets.T, c=colors, marker="x", s=20)
    ax.auto_scale_xyz(*[np.concatenate([pos[..., d].ravel(), targets[:, d]]) for d in range(3)])


def save_run_figures(rollout: Rollout, outdir: str | Path, reference_paths: Any = None) -> list[Path]:
    """Write ``trajectories.png``, ``distances.png`` and ``admm_residuals.png`` into ``outdir``
    (and ``trajectories_3d.png`` for 3D positions; ``trajectories.png`` shows the x-y plane; with GPs
    ``gp_prediction.png``, their one-step prediction over the run).

    Args:
        rollout: the run.
        outdir: directory (created if missing).
        reference_paths: optional reference, shape (K, R, D), for the trajectory figure.

    Returns:
        The written paths.
    """
    outdir = Path(outdir)
    written = [
        plot_trajectories(rollout, outdir / "trajectories.png", reference_paths=reference_paths),
        plot_distances(rollout, outdir / "distances.png"),
        plot_admm_residuals(rollout, outdir / "admm_residuals.png"),
    ]
    if np.asarray(rollout.positions).shape[-1] == 3:
        written.append(plot_trajectories_3d(rollout, outdir / "trajectories_3d.png"))
    if getattr(rollout, "prediction_error", None) is not None and rollout.num_steps > 0:
        from torch_gpmpc.report.gp_figures import plot_prediction_error

        written.append(plot_prediction_error({rollout.method: rollout}, outdir / "gp_prediction.png",
                                             (rollout.config or {}).get("wind_change_step")))
    return written


# ---------------------------------------------------------------------------
# several runs (gpmpc reproduce)


def _hold_pad(values: np.ndarray, length: int) -> np.ndarray:
    """Pad (N, ...) to (length, ...) by repeating the last row."""
    if values.shape[0] >= length:
        return values[:length]
    tail = np.repeat(values[-1:], length - values.shape[0], axis=0)
    return np.concatenate([values, tail], axis=0)


def _check_runs(runs: Mapping[str, Sequence[Rollout]]) -> int:
    """Every method has >= 1 run and all runs have the same K; returns K."""
    if not runs:
        raise GpmpcError("no runs to plot; give at least one method with one run")
    sizes = set()
    for method, rollouts in runs.items():
        if not rollouts:
            raise GpmpcError(f"method {method!r} has no runs to plot")
        sizes.update(np.asarray(r.states).shape[1] for r in rollouts)
    if len(sizes) != 1:
        raise GpmpcError(f"runs have different numbers of agents {sorted(sizes)}; plot one scenario at a time")
    return sizes.pop()


def plot_distance_bands(runs: Mapping[str, Sequence[Rollout]], path: str | Path, r_safe: float) -> Path:
    """Per method a panel: per pair the mean +- std of the distance over runs (paper Fig. 5).

    Shorter runs are padded by holding their last distance.

    Args:
        runs: method -> rollouts of the same scenario (same K).
        path: PNG file to write.
        r_safe: safety distance, drawn dashed.

    Returns:
        ``path``.
    """
    num_agents = _check_runs(runs)
    pairs = pair_index(num_agents)
    fig, axes = _new_figure(len(runs), panel=(3.6, 3.2))
    for ax, (method, rollouts) in zip(axes[0], runs.items()):
        dists = [pair_distances(r.positions) for r in rollouts]  # each (S_r+1, P)
        length = max(d.shape[0] for d in dists)
        stack = np.stack([_hold_pad(d, length) for d in dists])  # (N, L, P)
        mean, std = stack.mean(axis=0), stack.std(axis=0)
        t = np.arange(length)
        for p, (i, j) in enumerate(pairs):
            ax.plot(t, mean[:, p], color=_color(p), lw=1.2, label=f"agents {i}-{j}")
            ax.fill_between(t, mean[:, p] - std[:, p], mean[:, p] + std[:, p], color=_color(p), alpha=0.25)
        ax.axhline(r_safe, color="k", ls="--", lw=1.0, label=f"r_safe = {r_safe:g}")
        ax.set_title(f"{method} ({len(rollouts)} runs)", fontsize=10)
        ax.set_xlabel("step t")
        ax.grid(True, lw=0.3)
    axes[0, 0].set_ylabel("distance")
    axes[0, 0].legend(fontsize=7)
    return _save(fig, path)


def plot_path_lengths(runs: Mapping[str, Sequence[Rollout]], path: str | Path) -> Path:
    """Grouped bars of the mean path length per agent and method (paper Fig. 6).

    Groups are agents, bars within a group are methods (error bar: std over runs);
    the dashed segment over each group is that agent's mean straight-line length
    ||target - start||.

    Args:
        runs: method -> rollouts of the same scenario (same K).
        path: PNG file to write.

    Returns:
        ``path``.
    """
    num_agents = _check_runs(runs)
    methods = list(runs)
    width = 0.8 / len(methods)
    fig, axes = _new_figure(1, panel=(max(5.0, 1.6 * num_agents + 2.0), 3.6))
    ax = axes[0, 0]
    agents = np.arange(num_agents)
    straight = []
    for m, method in enumerate(methods):
        lengths = np.stack([path_lengths(r.positions) for r in runs[method]])  # (N, K)
        offset = (m - (len(methods) - 1) / 2) * width
        ax.bar(agents + offset, lengths.mean(axis=0), width, yerr=lengths.std(axis=0),
               color=_color(m), label=method, capsize=2)
        straight += [np.linalg.norm(np.asarray(r.targets) - np.asarray(r.positions)[0], axis=-1) for r in runs[method]]
    line = np.mean(straight, axis=0)  # (K,)
    for k in agents:
        ax.hlines(line[k], k - 0.45, k + 0.45, colors="k", linestyles="--", lw=1.2, zorder=3,
                  label="straight line" if k == 0 else None)
    ax.set_xticks(agents, [f"agent {k}" for k in agents])
    ax.set_ylabel("path length")
    ax.set_ylim(0, 1.25 * ax.get_ylim()[1])  # room for the legend above the bars
    ax.grid(True, axis="y", lw=0.3)
    ax.legend(fontsize=7, ncols=min(len(methods) + 1, 4), loc="upper center")
    return _save(fig, path)


def plot_admm_rho_sweep(results: Mapping[str, Mapping[float, Any]], path: str | Path) -> Path:
    """Mean primal residual vs ADMM iteration for several rho, one panel per method (paper Fig. 4).

    Args:
        results: method -> {rho: mean primal residual per iteration, shape (I,)}
            (NaN or non-positive entries are skipped).
        path: PNG file to write.

    Returns:
        ``path``.
    """
    if not results:
        raise GpmpcError("plot_admm_rho_sweep: no results to plot")
    fig, axes = _new_figure(len(results), panel=(3.6, 3.2))
    for ax, (method, by_rho) in zip(axes[0], results.items()):
        for n, (rho, curve) in enumerate(sorted(by_rho.items())):
            y = np.asarray(curve, dtype=np.float64).reshape(-1)
            y = np.where(y > 0, y, np.nan)
            ax.plot(np.arange(1, y.size + 1), y, color=_color(n), label=f"rho = {rho:g}")
        ax.set_yscale("log")
        ax.set_title(method, fontsize=10)
        ax.set_xlabel("ADMM iteration")
        ax.grid(True, which="both", lw=0.3)
        ax.legend(fontsize=7)
    axes[0, 0].set_ylabel("mean primal residual")
    return _save(fig, path)


def plot_calibration(rows: Sequence[Mapping[str, Any]], path: str | Path) -> Path:
    """Reliability diagram: empirical violation rate of active rows against the promised eps.

    Args:
        rows: ``calibration.json`` rows (``formulation, eps, rate, rate_low, rate_high, active``).
        path: PNG file to write.

    Returns:
        ``path``.
    """
    if not rows:
        raise GpmpcError("plot_calibration: no rows to plot")
    fig, axes = _new_figure(1, panel=(4.4, 4.0))
    ax = axes[0, 0]
    eps_max = max(float(r["eps"]) for r in rows)
    ax.plot([0, 1.1 * eps_max], [0, 1.1 * eps_max], "k--", lw=1, label="rate = eps")
    for n, name in enumerate(dict.fromkeys(r["formulation"] for r in rows)):
        mine = sorted((r for r in rows if r["formulation"] == name and r["rate"] is not None), key=lambda r: r["eps"])
        if not mine:
            continue
        eps = np.array([r["eps"] for r in mine])
        rate = np.array([r["rate"] for r in mine])
        err = np.clip([[r["rate"] - r["rate_low"] for r in mine], [r["rate_high"] - r["rate"] for r in mine]], 0, None)
        ax.errorbar(eps * (1 + 0.03 * (n - 0.5)), rate, yerr=err, fmt="o-", color=_color(n), capsize=3,
                    label=f"{name} ({sum(r['active'] for r in mine)} active rows)")
    ax.set_xlabel("promised risk per pair eps")
    ax.set_ylabel("empirical violation rate of active rows")
    ax.set_title("chance-constraint calibration (95 % Wilson intervals)", fontsize=9)
    ax.grid(True, lw=0.3)
    ax.legend(fontsize=7)
    return _save(fig, path)


def plot_mission_calibration(entries: Sequence[Mapping[str, Any]], path: str | Path) -> Path:
    """The fraction of whole runs with any violation (95 % Clopper-Pearson intervals) per
    risk setting, against each mission budget delta; and each setting's mean arrival.

    Args:
        entries: ``calibration.json``'s ``mission_rows`` (``risk_mode``, ``risk_budget`` or ``eps``,
            ``rate``, ``ci95``, ``runs``, ``arrival_mean``).
        path: PNG file to write.

    Returns:
        ``path``.
    """
    if not entries:
        raise GpmpcError("plot_mission_calibration: no entries to plot")
    fig, axes = _new_figure(2, panel=(4.2, 3.8))
    ax, ax_arr = axes[0, 0], axes[0, 1]
    labels = [f"mission\ndelta={e['risk_budget']:g}" if e["risk_mode"] == "mission" else f"pair_step\neps={e['eps']:g}"
              for e in entries]
    x = np.arange(len(entries))
    for i, e in enumerate(entries):
        rate = e["rate"] or 0.0
        low, high = e["ci95"]
        ax.errorbar([i], [rate], yerr=[[rate - low], [high - rate]], fmt="o", color=_color(i), capsize=4,
                    label=f"{labels[i].replace(chr(10), ' ')}: {e['runs_with_violation']}/{e['runs']} runs")
        if e["risk_mode"] == "mission":
            ax.plot([i - 0.3, i + 0.3], [e["risk_budget"]] * 2, "k--", lw=1)
        if e.get("arrival_mean") is not None:
            ax_arr.bar([i], [e["arrival_mean"]], color=_color(i))
    for a in (ax, ax_arr):
        a.set_xticks(x)
        a.set_xticklabels(labels, fontsize=7)
        a.grid(True, lw=0.3, axis="y")
    ax.set_ylabel("runs with any violation (fraction)")
    ax.set_title("mission risk: Monte Carlo (dashed: delta)", fontsize=9)
    ax.legend(fontsize=6)
    ax_arr.set_ylabel("last agent's arrival step (mean)")
    ax_arr.set_title("cost of the promise", fontsize=9)
    return _save(fig, path)


def plot_benchmark(summary: Sequence[Mapping[str, Any]], path: str | Path) -> Path:
    """``gpmpc benchmark``'s figure: success rate and compute per agent-step against team size,
    one line per scenario (rows of :func:`~torch_gpmpc.sim.benchmark.summary_rows`)."""
    fig, axes = _new_figure(2)
    by_scenario: dict[str, list] = {}
    for row in summary:
        by_scenario.setdefault(row["scenario"], []).append(row)
    for n, (name, rows) in enumerate(by_scenario.items()):
        rows = sorted(rows, key=lambda r: r["agents"])
        k = [r["agents"] for r in rows]
        axes[0][0].plot(k, [100 * r["success_rate"] for r in rows], "o-", color=_color(n), label=name)
        axes[0][1].plot(k, [np.nan if r["compute_ms_per_agent_step"] is None else r["compute_ms_per_agent_step"]
                            for r in rows], "o-", color=_color(n), label=name)
    axes[0][0].set_ylabel("success (%)")
    axes[0][0].set_ylim(-5, 105)
    axes[0][1].set_ylabel("compute per agent-step (ms)")
    for ax in axes[0]:
        ax.set_xlabel("agents")
        ax.grid(True, lw=0.3)
        ax.legend(fontsize=7)
    return _save(fig, path)
