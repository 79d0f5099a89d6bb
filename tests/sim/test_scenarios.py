"""Scenarios: closed forms, the reference window, file validation, random placement."""

from __future__ import annotations

import json
import math

import pytest
import torch

from torch_gpmpc.config.schema import Config
from torch_gpmpc.errors import GpmpcError
from torch_gpmpc.sim.scenarios import Scenario, make_scenario

SQ3 = math.sqrt(3.0)


def test_paper_scenario_closed_form():
    sc = make_scenario(Config())
    assert sc.starts.dtype == torch.float64 and sc.starts.shape == (3, 2)
    expected = torch.tensor([[4.0, 0.0], [-2.0, 2.0 * SQ3], [-2.0, -2.0 * SQ3]], dtype=torch.float64)
    torch.testing.assert_close(sc.starts, expected)
    # agent 1: start (4 cos(2pi/3), 4 sin(2pi/3)), target its antipode
    torch.testing.assert_close(sc.starts[1], torch.tensor([4 * math.cos(2 * math.pi / 3),
                                                           4 * math.sin(2 * math.pi / 3)], dtype=torch.float64))
    torch.testing.assert_close(sc.targets, -expected)
    assert sc.reference_kind == "line" and sc.ref_points == 50 and sc.name == "paper"


def test_paper_scenario_3d_has_zero_third_coordinate():
    sc = make_scenario(Config(dim=3))
    assert sc.starts.shape == (3, 3)
    assert torch.all(sc.starts[:, 2] == 0) and torch.all(sc.targets[:, 2] == 0)
    torch.testing.assert_close(sc.starts[1, :2], torch.tensor([-2.0, 2.0 * SQ3], dtype=torch.float64))


def test_circle_scenario_any_k():
    sc = make_scenario(Config(scenario="circle", num_agents=4, circle_radius=2.0))
    expected = torch.tensor([[2.0, 0.0], [0.0, 2.0], [-2.0, 0.0], [0.0, -2.0]], dtype=torch.float64)
    torch.testing.assert_close(sc.starts, expected, atol=1e-12, rtol=0)
    torch.testing.assert_close(sc.targets, -expected, atol=1e-12, rtol=0)


def test_circle_too_crowded_names_pair():
    with pytest.raises(GpmpcError, match=r"starts of agents \d+ and \d+ are 0.2513 apart, closer than r_safe = 0.5"):
        make_scenario(Config(scenario="circle", num_agents=100, circle_radius=4.0))


def test_reference_window_line():
    sc = make_scenario(Config())
    start, target = sc.starts, sc.targets
    w0 = sc.reference_window(0, 13)
    assert w0.shape == (3, 14, 2) and w0.dtype == torch.float64
    torch.testing.assert_close(w0[:, 0], start)
    torch.testing.assert_close(w0[:, 1], start + (target - start) / 49)
    torch.testing.assert_close(w0[:, 13], start + (target - start) * 13 / 49)
    # agent 0 goes (4,0) -> (-4,0): x1 = 4 - 8 i / 49
    torch.testing.assert_close(w0[0, :, 0], torch.tensor([4 - 8 * i / 49 for i in range(14)], dtype=torch.float64))
    w = sc.reference_window(48, 4)  # indices 48..52
    torch.testing.assert_close(w[:, 0], start + (target - start) * 48 / 49)
    for i in range(1, 5):  # index 49 reaches the target, then hold
        torch.testing.assert_close(w[:, i], target)
    torch.testing.assert_close(sc.reference_window(200, 2), target[:, None].expand(3, 3, 2))


def test_reference_path():
    sc = make_scenario(Config(ref_points=5))
    path = sc.reference_path()
    assert path.shape == (3, 5, 2)
    torch.testing.assert_close(path[:, 0], sc.starts)
    torch.testing.assert_close(path[:, -1], sc.targets)
    torch.testing.assert_close(path[:, 2], (sc.starts + sc.targets) / 2)


def test_reference_target_kind():
    sc = make_scenario(Config(reference="target"))
    w = sc.reference_window(3, 13)
    assert w.shape == (3, 14, 2)
    torch.testing.assert_close(w, sc.targets[:, None].expand(3, 14, 2))
    assert sc.reference_path().shape == (3, 50, 2)


def test_scenario_dataclass_rejects_bad_shapes():
    with pytest.raises(ValueError, match="shape"):
        Scenario(torch.zeros(3, 2, dtype=torch.float64), torch.zeros(2, 2, dtype=torch.float64))


# ---------------------------------------------------------------------------
# files

GOOD = {"starts": [[0.0, 0.0], [2.0, 0.0]], "targets": [[2.0, 2.0], [0.0, 2.0]]}


def write(tmp_path, data, suffix=".json"):
    path = tmp_path / f"scen{suffix}"
    path.write_text(json.dumps(data) if suffix == ".json" else data)
    return str(path)


def test_file_json_overrides_config(tmp_path):
    path = write(tmp_path, {**GOOD, "reference": "target", "ref_points": 7})
    sc = make_scenario(Config(), path)
    assert sc.num_agents == 2 and sc.reference_kind == "target" and sc.ref_points == 7
    torch.testing.assert_close(sc.starts, torch.tensor(GOOD["starts"], dtype=torch.float64))
    assert sc.name == "scen"


def test_file_toml(tmp_path):
    text = 'starts = [[0, 0], [2, 0]]\ntargets = [[2, 2], [0, 2]]\nreference = "line"\n'
    sc = make_scenario(Config(reference="target"), write(tmp_path, text, ".toml"))
    assert sc.reference_kind == "line" and sc.starts.dtype == torch.float64
    torch.testing.assert_close(sc.targets, torch.tensor(GOOD["targets"], dtype=torch.float64))


def test_file_round_trip_via_to_dict(tmp_path):
    sc = make_scenario(Config())
    again = make_scenario(Config(), write(tmp_path, sc.to_dict()))
    torch.testing.assert_close(again.starts, sc.starts)
    assert again.name == "paper"


BAD_CASES = [
    ({"targets": GOOD["targets"]}, r"missing key 'starts'"),
    ({"starts": GOOD["starts"]}, r"missing key 'targets'"),
    ({**GOOD, "starts": [[0.0, "a"], [2.0, 0.0]]}, r"starts\[0\]\[1\] is 'a' \(str\); give a number"),
    ({**GOOD, "starts": [[0.0, True], [2.0, 0.0]]}, r"starts\[0\]\[1\] is True"),
    ({**GOOD, "starts": [[0.0, 0.0], [2.0]]}, r"'starts' is ragged \(row lengths 2, 1\)"),
    ({**GOOD, "starts": [0.0, 1.0]}, r"starts\[0\] must be a list"),
    ({**GOOD, "starts": []}, r"'starts' must be a non-empty K x D list"),
    ({**GOOD, "targets": [[2.0, 2.0]]}, r"'starts' has 2 agents but 'targets' has 1"),
    ({"starts": [[0, 0, 0], [2, 0, 0]], "targets": [[1, 1, 0], [0, 1, 0]]},
     r"3 coordinates but the config has dim = 2"),
    ({**GOOD, "starts": [[0.0, 0.0], [0.3, 0.0]]}, r"starts of agents 0 and 1 are 0.3 apart, closer than r_safe = 0.5"),
    ({**GOOD, "targets": [[2.0, 2e4], [0.0, 2.0]]}, r"targets\[0\]\[1\] = 20000 exceeds 10000"),
    ({**GOOD, "startz": 1}, r"unknown key 'startz'; did you mean 'starts'\?"),
    ({**GOOD, "referense": "line"}, r"unknown key 'referense'; did you mean 'reference'\?"),
    ({**GOOD, "reference": "spline"}, r"'reference' is 'spline'; use one of line, target"),
    ({**GOOD, "ref_points": 1}, r"'ref_points' is 1; give an integer >= 2"),
]


@pytest.mark.parametrize("data, message", BAD_CASES)
def test_bad_file_cases(tmp_path, data, message):
    with pytest.raises(GpmpcError, match=message):
        make_scenario(Config(), write(tmp_path, data))


def test_non_finite_json_and_toml(tmp_path):
    (tmp_path / "a.json").write_text('{"starts": [[0, NaN], [2, 0]], "targets": [[2, 2], [0, 2]]}')
    with pytest.raises(GpmpcError, match=r"starts\[0\]\[1\] is nan, not finite"):
        make_scenario(Config(), str(tmp_path / "a.json"))
    (tmp_path / "b.toml").write_text("starts = [[0, 0], [2, 0]]\ntargets = [[inf, 2], [0, 2]]\n")
    with pytest.raises(GpmpcError, match=r"targets\[0\]\[0\] is inf, not finite"):
        make_scenario(Config(), str(tmp_path / "b.toml"))


def test_file_level_errors(tmp_path):
    with pytest.raises(GpmpcError, match="does not exist"):
        make_scenario(Config(), str(tmp_path / "nope.json"))
    (tmp_path / "s.yaml").write_text("starts: []")
    with pytest.raises(GpmpcError, match="unknown suffix '.yaml'; use .json or .toml"):
        make_scenario(Config(), str(tmp_path / "s.yaml"))
    (tmp_path / "broken.json").write_text("{starts: ")
    with pytest.raises(GpmpcError, match="cannot be parsed"):
        make_scenario(Config(), str(tmp_path / "broken.json"))
    (tmp_path / "list.json").write_text("[1, 2]")
    with pytest.raises(GpmpcError, match="expected a table"):
        make_scenario(Config(), str(tmp_path / "list.json"))


# ---------------------------------------------------------------------------
# random


def _min_pair(x: torch.Tensor) -> float:
    i, j = torch.triu_indices(x.shape[0], x.shape[0], offset=1)
    return float((x[i] - x[j]).norm(dim=1).min())


def test_random_respects_separation_and_is_reproducible():
    cfg = Config(scenario="random", num_agents=8, min_separation=1.5, seed=3)
    a, b = make_scenario(cfg), make_scenario(cfg)
    torch.testing.assert_close(a.starts, b.starts)
    torch.testing.assert_close(a.targets, b.targets)
    assert a.starts.shape == (8, 2)
    assert _min_pair(a.starts) >= 1.5 and _min_pair(a.targets) >= 1.5
    assert a.starts.abs().max() <= 4.0 and a.targets.abs().max() <= 4.0
    c = make_scenario(cfg.replace(seed=4))
    assert not torch.equal(a.starts, c.starts)


def test_random_3d():
    sc = make_scenario(Config(scenario="random", num_agents=5, dim=3, seed=1))
    assert sc.starts.shape == (5, 3) and _min_pair(sc.starts) >= 1.0


def test_random_in_a_workspace_keeps_bodies_inside_and_is_unchanged_without_one():
    ws = {"min": [-2.0, -3.0, 0.0], "max": [2.0, 3.0, 2.5]}
    cfg = Config(scenario="random", num_agents=8, dim=3, seed=2, workspace=ws)
    sc = make_scenario(cfg)
    for pts in (sc.starts, sc.targets):
        assert bool((pts >= torch.tensor(ws["min"], dtype=torch.float64) + 0.25).all())
        assert bool((pts <= torch.tensor(ws["max"], dtype=torch.float64) - 0.25).all())
        assert _min_pair(pts) >= 1.0
    assert cfg.scenario_extent == 3.0 and cfg.gp_fit_settings().box == 3.0
    plain = make_scenario(Config(scenario="random", num_agents=5, dim=3, seed=1))
    assert float(plain.starts.abs().max()) > 2.0  # [-4, 4]^3 as before
    with pytest.raises(GpmpcError, match="no room"):
        make_scenario(Config(scenario="random", dim=2, workspace={"min": [0, 0], "max": [0.4, 3]}))


def test_random_impossible_separation_raises():
    cfg = Config(scenario="random", num_agents=20, min_separation=5.0, circle_radius=1.0)
    with pytest.raises(GpmpcError, match=r"could not place the start of agent \d+ at least 5 .*lower min_separation"):
        make_scenario(cfg)


def test_forest_lanes_cross_a_seeded_field_of_trees_with_passable_gaps():
    from torch_gpmpc.config.obstacles import FOREST_FILL, FOREST_GAP_EXTRA, FOREST_PACE, FOREST_TREE_RADIUS

    cfg = Config(scenario="forest", num_agents=10, num_obstacles=30, seed=3)
    sc = make_scenario(cfg)
    assert sc.num_agents == 10 and len(sc.obstacles) == 30
    torch.testing.assert_close(sc.starts[:, 1], sc.targets[:, 1])
    lane = max(cfg.min_separation, cfg.r_safe) + FOREST_GAP_EXTRA / 2  # 1.5: room to swerve beside a neighbour
    torch.testing.assert_close(sc.starts[:, 1], (torch.arange(10, dtype=torch.float64) - 4.5) * lane)
    # the band 2 (R - 1) x 2 H holds the 30 spacing discs at fill FOREST_FILL; H = 4.5 lane + 1
    spacing = 2 * FOREST_TREE_RADIUS + cfg.r_safe + FOREST_GAP_EXTRA
    H = 4.5 * lane + 1.0
    R = 30 * math.pi * (spacing / 2) ** 2 / FOREST_FILL / (4 * H) + 1.0
    assert cfg.scenario_extent == pytest.approx(R) and cfg.gp_fit_settings().box == pytest.approx(R)
    assert bool((sc.starts[:, 0] == -R).all()) and bool((sc.targets[:, 0] == R).all())
    centres = torch.tensor([o.center for o in sc.obstacles.obstacles], dtype=torch.float64)
    gaps = torch.pdist(centres) - 2 * FOREST_TREE_RADIUS
    assert float(gaps.min()) >= cfg.r_safe + FOREST_GAP_EXTRA - 1e-12
    assert float(centres[:, 0].abs().max()) <= R - 1.0 and float(centres[:, 1].abs().max()) <= H
    # the line asks at most FOREST_PACE of the input bound's speed (more points than ref_points = 50)
    speed = 2 * R / (sc.ref_points - 1) / cfg.dt
    assert sc.ref_points > cfg.ref_points and FOREST_PACE * cfg.u_max * 0.99 <= speed <= FOREST_PACE * cfg.u_max
    assert make_scenario(cfg.replace(ref_points=500)).ref_points == 500  # a slower line is kept
    again = make_scenario(cfg)
    assert again.obstacles == sc.obstacles and make_scenario(cfg.replace(seed=4)).obstacles != sc.obstacles
    in_3d = make_scenario(cfg.replace(dim=3, num_obstacles=10))
    assert {o.kind for o in in_3d.obstacles.obstacles} == {"cylinder"} and in_3d.starts.shape == (10, 3)


def test_forest_gap_widens_every_gap_and_lengthens_the_band():
    from torch_gpmpc.config.obstacles import FOREST_FILL, FOREST_TREE_RADIUS

    base = Config(scenario="forest", num_agents=10, num_obstacles=30, seed=3)
    wide = base.replace(forest_gap=1.5)
    sc = make_scenario(wide)
    centres = torch.tensor([o.center for o in sc.obstacles.obstacles], dtype=torch.float64)
    assert len(sc.obstacles) == 30
    assert float((torch.pdist(centres) - 2 * FOREST_TREE_RADIUS).min()) >= wide.r_safe + 1.5 - 1e-12
    # spacing 2 x 0.25 + 0.5 + 1.5 = 2.5; lanes 1.0 + 0.75 apart, H = 4.5 x 1.75 + 1
    H = 4.5 * 1.75 + 1.0
    R = 30 * math.pi * (2.5 / 2) ** 2 / FOREST_FILL / (4 * H) + 1.0
    assert wide.scenario_extent == pytest.approx(R) and R > base.scenario_extent
    assert bool((sc.starts[:, 0] == -R).all()) and float(centres[:, 0].abs().max()) <= R - 1.0
    assert make_scenario(base.replace(forest_gap=1.0)).obstacles == make_scenario(base).obstacles  # the default
    with pytest.raises(GpmpcError, match="forest_gap"):
        Config(forest_gap=-0.1)


def test_file_obstacles_reach_the_run_config(tmp_path):
    from torch_gpmpc.sim.scenarios import with_scenario_world

    path = tmp_path / "obstacles.json"
    obstacles = [{"center": [0.0, 0.5], "radius": 0.5}, {"min": [1.0, -2.0], "max": [2.0, -1.0]}]
    path.write_text(json.dumps({"starts": [[-3, 0]], "targets": [[3, 0]], "obstacles": obstacles}))
    sc = make_scenario(Config(), path)
    assert [o.kind for o in sc.obstacles.obstacles] == ["sphere", "box"]
    cfg = with_scenario_world(Config(), sc)
    assert cfg.obstacles == sc.obstacles and cfg.to_dict()["obstacles"] == obstacles
    assert make_scenario(Config(), _write(tmp_path, sc.to_dict())).obstacles == sc.obstacles
    path.write_text(json.dumps({"starts": [[-3, 0]], "targets": [[3, 0]],
                                "obstacles": [{"center": [0.0, 0.5], "radius": 0.5, "z": [0, 1]}]}))
    with pytest.raises(GpmpcError, match=r"obstacles\[0\].*only with 3D"):
        make_scenario(Config(), path)


def _write(tmp_path, table):
    path = tmp_path / "round_trip.json"
    path.write_text(json.dumps(table))
    return path


def test_the_example_scenario_file_loads_and_flies(tmp_path):
    """examples/scenarios/square_swap.toml (the Scenario files guide's example): its world reaches the
    run (obstacle, workspace, radii), and two noiseless steps keep every pair and the pillar."""
    from pathlib import Path

    from torch_gpmpc.sim.closed_loop import simulate
    from torch_gpmpc.sim.metrics import compute_metrics
    from torch_gpmpc.sim.scenarios import load_scenario_file

    path = Path(__file__).resolve().parents[2] / "examples" / "scenarios" / "square_swap.toml"
    cfg = Config(noise_std=0.0, max_steps=2, gp_samples=30, gp_iters=5)
    scenario = load_scenario_file(path, cfg)
    assert scenario.num_agents == 4 and scenario.radii == (0.25, 0.25, 0.3, 0.3)
    assert scenario.obstacles is not None and scenario.workspace is not None
    metrics = compute_metrics(simulate(cfg, scenario=scenario))
    assert metrics["violations"] == 0 and metrics["obstacle_violations"] == 0
