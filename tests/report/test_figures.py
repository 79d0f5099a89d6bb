"""Every plotting function writes a complete PNG atomically (no temp files left)."""

from __future__ import annotations

import numpy as np
import pytest

from torch_gpmpc.report import figures as plots
from torch_gpmpc.errors import GpmpcError
from torch_gpmpc.sim.metrics import pair_index
from tests.sim.test_metrics import HAND_STATES, HAND_TARGETS, make_rollout

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def assert_png(path):
    data = path.read_bytes()
    assert len(data) > 1000 and data[:8] == PNG_MAGIC


def assert_no_temp_files(directory):
    leftovers = [p.name for p in directory.iterdir() if ".tmp" in p.name or p.name.startswith(".")]
    assert leftovers == []


@pytest.fixture
def rollout():
    return make_rollout(HAND_STATES, HAND_TARGETS)


def test_plot_trajectories(tmp_path, rollout):
    out = plots.plot_trajectories(rollout, tmp_path / "traj.png")
    assert out == tmp_path / "traj.png"
    assert_png(out)
    ref = np.stack([np.linspace(HAND_STATES[0][k], HAND_TARGETS[k], 5) for k in range(2)])  # (K, R, D)
    assert_png(plots.plot_trajectories(rollout, tmp_path / "traj_ref.png", steps=[0, 2], reference_paths=ref))
    assert_no_temp_files(tmp_path)


def test_plot_trajectories_bad_steps_leave_nothing(tmp_path, rollout):
    with pytest.raises(GpmpcError, match=r"steps must be in 0..4"):
        plots.plot_trajectories(rollout, tmp_path / "t.png", steps=[9])
    assert list(tmp_path.iterdir()) == []


def test_default_snapshot_steps():
    assert plots.default_snapshot_steps(150) == [0, 50, 100, 150]
    assert plots.default_snapshot_steps(2) == [0, 1, 2]
    assert plots.default_snapshot_steps(0) == [0]


def test_save_run_figures(tmp_path, rollout):
    paths = plots.save_run_figures(rollout, tmp_path / "figures")
    assert [p.name for p in paths] == ["trajectories.png", "distances.png", "admm_residuals.png"]
    for p in paths:
        assert_png(p)
    assert_no_temp_files(tmp_path / "figures")


def test_single_agent_and_empty_residuals(tmp_path):
    r = make_rollout([[[0.0, 0.0]], [[3.0, 4.0]]], [[3.0, 4.0]])
    r.primal_residuals = np.full((1, 3), np.nan)
    for p in plots.save_run_figures(r, tmp_path):
        assert_png(p)
    assert_no_temp_files(tmp_path)


def _runs():
    short = make_rollout(HAND_STATES[:3], HAND_TARGETS)  # padded by holding its last value
    return {"gp-chance": [make_rollout(HAND_STATES, HAND_TARGETS), short],
            "nominal": [make_rollout(HAND_STATES, HAND_TARGETS)]}


def test_multi_run_figures(tmp_path):
    assert_png(plots.plot_distance_bands(_runs(), tmp_path / "bands.png", r_safe=0.5))
    assert_png(plots.plot_path_lengths(_runs(), tmp_path / "lengths.png"))
    sweep = {"gp": {1.0: np.geomspace(1, 1e-3, 20), 20.0: np.r_[np.geomspace(1, 1e-5, 10), [np.nan] * 10]},
             "nominal": {5.0: np.geomspace(2, 1e-2, 20)}}
    assert_png(plots.plot_admm_rho_sweep(sweep, tmp_path / "rho.png"))
    assert_no_temp_files(tmp_path)


def test_mixed_team_sizes_raise(tmp_path):
    runs = {"a": [make_rollout(HAND_STATES, HAND_TARGETS)], "b": [make_rollout([[[0.0, 0.0]]], [[0.0, 0.0]])]}
    with pytest.raises(GpmpcError, match="different numbers of agents"):
        plots.plot_distance_bands(runs, tmp_path / "x.png", r_safe=0.5)


def test_a_large_team_gets_summary_figures(tmp_path):
    """Past MAX_LABELLED_AGENTS the distance figure draws the closest pair and the median nearest
    neighbour per step (not a line per pair) and the snapshots draw collections: a 40-agent run
    writes every figure, and the nearest-neighbour distances match the pair distances."""
    from torch_gpmpc.sim.metrics import nearest_neighbour_distances, pair_distances

    rng = np.random.default_rng(0)
    k = 4 * plots.MAX_LABELLED_AGENTS
    states = np.cumsum(rng.normal(scale=0.1, size=(6, k, 2)), axis=0) + rng.uniform(-5, 5, size=(1, k, 2))
    nearest = nearest_neighbour_distances(states)
    np.testing.assert_allclose(nearest.min(axis=1), pair_distances(states).min(axis=1), rtol=0, atol=1e-12)
    assert nearest.shape == (6, k) and np.isfinite(nearest).all()
    for p in plots.save_run_figures(make_rollout(states, states[-1]), tmp_path):
        assert_png(p)
    assert_no_temp_files(tmp_path)


def test_a_team_with_many_pairs_draws_them_grey_without_a_warning(tmp_path, recwarn):
    """45 pairs (10 agents): one legend entry for the closest pair instead of 45, which collapsed
    the axes (matplotlib warned that the constrained layout was not applied)."""
    rng = np.random.default_rng(2)
    states = np.cumsum(rng.normal(scale=0.1, size=(5, plots.MAX_LABELLED_AGENTS, 2)), axis=0) * 10
    assert len(pair_index(plots.MAX_LABELLED_AGENTS)) > plots.MAX_LABELLED_PAIRS
    assert_png(plots.plot_distances(make_rollout(states, states[-1]), tmp_path / "d.png"))
    assert not [w for w in recwarn if "constrained_layout" in str(w.message)]


def test_a_large_3d_team_gets_its_paths_drawn(tmp_path):
    rng = np.random.default_rng(1)
    k = 2 * plots.MAX_LABELLED_AGENTS
    states = np.cumsum(rng.normal(scale=0.1, size=(5, k, 3)), axis=0)
    assert_png(plots.plot_trajectories_3d(make_rollout(states, states[-1]), tmp_path / "t3d.png"))
    assert_no_temp_files(tmp_path)
