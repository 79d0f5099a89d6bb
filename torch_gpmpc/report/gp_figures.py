"""Figure of a learned residual field (the paper's Fig. 1): true wind vs GP mean.

Uses matplotlib's object API with the Agg canvas (no pyplot, no global backend
state) and writes the PNG atomically.
"""

from __future__ import annotations

from pathlib import Path
from typing import Callable

import torch
from torch import Tensor

from torch_gpmpc.errors import GpmpcError
from torch_gpmpc.fileio import atomic_path


def plot_gp_field(gp, wind: Callable[[Tensor], Tensor], inputs: Tensor, path: str | Path,
                  box: float | None = None, grid: int = 20, title: str | None = None) -> None:
    """Quiver plot of the true wind g and the learned GP mean over a 2D box.

    The background shows the GP's latent standard deviation
    ``sqrt(var_1 + var_2)`` (the norm of the per-dimension stds).

    Args:
        gp: a fitted :class:`~torch_gpmpc.gp.model.ResidualGP` with state inputs, D = 2.
        wind: the true residual, ``(n, 2) -> (n, 2)``.
        inputs: training inputs, shape (N, 2) (plotted as points).
        path: PNG file to write.
        box: half-width of the plotted square (default: covers the training inputs).
        grid: arrows per axis.
        title: optional figure title.

    Raises:
        GpmpcError: if the model is not a 2D state-input model.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    if gp.input_dim != 2 or gp.output_dim != 2:
        raise GpmpcError(f"--figure needs a 2D model with state inputs (Din = D = 2), got "
                         f"Din={gp.input_dim}, D={gp.output_dim}; drop --figure")
    inputs = torch.as_tensor(inputs, dtype=torch.float64)
    half = float(box) if box is not None else float(inputs.abs().max()) * 1.02
    axis = torch.linspace(-half, half, grid)
    X1, X2 = torch.meshgrid(axis, axis, indexing="xy")
    pts = torch.stack([X1.reshape(-1), X2.reshape(-1)], dim=1)
    with torch.no_grad():
        mean, var = gp.predict(pts)
        true = wind(pts)
        fine = torch.linspace(-half, half, 4 * grid)
        F1, F2 = torch.meshgrid(fine, fine, indexing="xy")
        _, fvar = gp.predict(torch.stack([F1.reshape(-1), F2.reshape(-1)], dim=1))
    std = fvar.sum(1).sqrt().reshape(F1.shape)

    fig = Figure(figsize=(6.4, 6.0))
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)
    cs = ax.contourf(F1.numpy(), F2.numpy(), std.numpy(), levels=20, cmap="Greys", alpha=0.6)
    fig.colorbar(cs, ax=ax, label="GP std  sqrt(var_1 + var_2)")
    scale = float(max(true.norm(dim=1).max(), mean.norm(dim=1).max())) * grid / 1.5
    ax.quiver(pts[:, 0].numpy(), pts[:, 1].numpy(), true[:, 0].numpy(), true[:, 1].numpy(),
              color="tab:blue", scale=scale, width=0.004, label="true wind g(x)")
    ax.quiver(pts[:, 0].numpy(), pts[:, 1].numpy(), mean[:, 0].numpy(), mean[:, 1].numpy(),
              color="tab:red", scale=scale, width=0.003, alpha=0.85, label="GP mean mu(x)")
    ax.scatter(inputs[:, 0].numpy(), inputs[:, 1].numpy(), s=8, c="k", marker="o", label="training states")
    ax.set_xlim(-half, half)
    ax.set_ylim(-half, half)
    ax.set_aspect("equal")
    ax.set_xlabel("x_1")
    ax.set_ylabel("x_2")
    rmse = float((mean - true).square().mean().sqrt())
    ax.set_title(title or f"Residual GP vs true wind (N={gp.num_data}, grid RMSE {rmse:.3f})")
    ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.1), ncol=3, fontsize=8, frameon=False)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=120)


def plot_holdout_residuals(gp, inputs: Tensor, y: Tensor, residual: list[int], path: str | Path,
                           max_points: int = 600) -> None:
    """Held-out residuals over time: measured, predicted mean and its 95 % predictive band
    (noise included), one panel per residual dimension.

    Args:
        gp: a fitted :class:`~torch_gpmpc.gp.model.ResidualGP`.
        inputs: held-out GP inputs in log order, shape (m, Din).
        y: the measured residuals, shape (m, D).
        residual: the model's residual state indices (panel titles), length D.
        path: PNG file to write.
        max_points: plot the first this many held-out rows (a readable stretch of the log).
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    inputs, y = inputs[:max_points], y[:max_points]
    with torch.no_grad():
        mean, var = gp.predict(inputs, include_noise=True)
    half = 1.959963984540054 * var.sqrt()
    t = range(y.shape[0])
    fig = Figure(figsize=(8, 2.2 * y.shape[1]))
    FigureCanvasAgg(fig)
    for d in range(y.shape[1]):
        ax = fig.add_subplot(y.shape[1], 1, d + 1)
        ax.fill_between(t, (mean[:, d] - half[:, d]).numpy(), (mean[:, d] + half[:, d]).numpy(), color="C0",
                        alpha=0.25, linewidth=0, label="95 % predictive band")
        ax.plot(t, y[:, d].numpy(), color="k", linewidth=0.8, label="measured")
        ax.plot(t, mean[:, d].numpy(), color="C0", linewidth=1.0, label="GP mean")
        inside = float(((y[:, d] - mean[:, d]).abs() <= half[:, d]).double().mean())
        ax.set_ylabel(f"x{residual[d]} residual")
        ax.set_title(f"x{residual[d]}: {100 * inside:.0f} % of these rows inside the band", fontsize=9)
        if d == 0:
            ax.legend(fontsize=8, loc="upper right")
    fig.axes[-1].set_xlabel("held-out row (log order)")
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=110)


def plot_prediction_error(runs, path: str | Path, change_step: int | None = None, window: int = 10) -> Path:
    """The GPs' one-step prediction during runs (learning curves): per step, the RMS prediction error
    over agents and residual rows (solid) and the RMS predictive standard deviation (dotted); below,
    the share of rows within 1.96 predictive standard deviations over a sliding ``window`` of steps.

    Args:
        runs: label -> :class:`~torch_gpmpc.sim.rollout.Rollout` with ``prediction_error`` (S, K, R).
        path: PNG file to write.
        change_step: draws the wind change there.

    Raises:
        GpmpcError: a run without GP predictions.
    """
    import numpy as np
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(7.0, 5.2))
    FigureCanvasAgg(fig)
    ax_err, ax_cov = fig.subplots(2, 1, sharex=True)
    lowest = 1.0
    for i, (label, rollout) in enumerate(runs.items()):
        if getattr(rollout, "prediction_error", None) is None:
            raise GpmpcError(f"run {label!r} has no GP predictions (a method without GPs?)")
        err, var = np.asarray(rollout.prediction_error), np.asarray(rollout.prediction_var)
        steps = np.arange(err.shape[0])
        color = f"C{i}"
        ax_err.plot(steps, np.sqrt((err ** 2).mean(axis=(1, 2))), "-", color=color, lw=1.2, label=f"{label}: error")
        ax_err.plot(steps, np.sqrt(var.mean(axis=(1, 2))), ":", color=color, lw=1.2, label=f"{label}: predicted std")
        inside = (np.abs(err) <= 1.96 * np.sqrt(var)).mean(axis=(1, 2))
        w = max(1, min(window, len(steps)))  # a run shorter than the window: one point
        share = np.convolve(inside, np.ones(w) / w, mode="valid")
        lowest = min(lowest, float(np.nanmin(share)) if share.size else 1.0)
        ax_cov.plot(steps[w - 1:], share, "-", color=color, label=label)
    for ax in (ax_err, ax_cov):
        if change_step is not None:
            ax.axvline(change_step, color="k", lw=0.8, ls="--")
    ax_cov.axhline(0.95, color="grey", lw=0.8, ls="--", label="nominal 95 %")
    ax_err.set_title("The GPs' one-step residual prediction during the run", fontsize=10)
    ax_err.set_ylabel("one-step residual, RMS")
    ax_cov.set_ylabel(f"share inside the 95 % band\n({window}-step window)")
    ax_cov.set_xlabel("control step")
    ax_cov.set_ylim(max(0.0, min(0.9, lowest) - 0.05), 1.01)  # the band's share, not a 0-1 axis
    ax_err.legend(fontsize=7)
    ax_cov.legend(fontsize=7, loc="lower right")
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=110)
    return path
