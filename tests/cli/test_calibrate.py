"""``gpmpc calibrate --mission`` end to end (a short form), and its interval against known values."""

from __future__ import annotations

import json

import pytest

from torch_gpmpc.cli import main
from torch_gpmpc.sim.calibration import clopper_pearson


def test_clopper_pearson_matches_tabulated_intervals():
    # scipy-independent references: 0/100 -> upper 1 - 0.025^(1/100); 5/100 -> [0.0164, 0.1128]
    assert clopper_pearson(0, 100) == pytest.approx((0.0, 1 - 0.025 ** (1 / 100)), rel=1e-9)
    low, high = clopper_pearson(5, 100)
    assert low == pytest.approx(0.01643, abs=1e-4) and high == pytest.approx(0.11283, abs=1e-4)
    assert clopper_pearson(3, 3)[1] == 1.0 and clopper_pearson(0, 0) == (0.0, 1.0)


def test_mission_calibration_writes_its_entry_beside_what_was_there(tmp_path, capsys):
    out = tmp_path / "cal"
    out.mkdir()
    (out / "calibration.json").write_text(json.dumps({"rows": [{"formulation": "sound", "eps": 0.1}]}))
    argv = ["calibrate", "--mission", "--runs", "2", "--baseline-runs", "1", "--workers", "1",
            "--set", "max_steps=3", "--out", str(out)]
    assert main(argv) == 0
    data = json.loads((out / "calibration.json").read_text())
    assert data["rows"] == [{"formulation": "sound", "eps": 0.1}]  # the pair-step rows stay
    mission = data["mission"]
    for key in ("runs", "runs_with_violation", "rate", "ci95", "risk_budget"):
        assert key in mission
    assert mission["runs"] == 2 and mission["risk_budget"] == 0.05 and len(mission["ci95"]) == 2
    assert [e["risk_mode"] for e in data["mission_rows"]] == ["mission", "pair_step"]
    assert (out / "mission.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"  # a PNG, not an empty file
    assert "| mission delta=0.05 | 2 |" in capsys.readouterr().out


def test_mission_calibration_refuses_a_method_without_margins(tmp_path, capsys):
    assert main(["calibrate", "--mission", "--runs", "1", "--set", "method=nominal", "--out", str(tmp_path)]) == 2
    assert "risk_mode" in capsys.readouterr().err
