"""`gpmpc reproduce`: a 1-run, few-step version produces every file, and resumes from its cache."""

from __future__ import annotations

import csv

from torch_gpmpc.cli import main
from torch_gpmpc.config.schema import METHODS
from torch_gpmpc.report.tables import table_markdown
from torch_gpmpc.sim.experiments import SOUND_LABEL, summarize
from tests.sim.test_metrics import make_rollout

SHORT = ["--runs", "1", "--workers", "1", "--set", "max_steps=2", "--set", "admm_max_iter=2",
         "--set", "gp_iters=3", "--rho-values", "5,20", "--rho-start", "1", "--rho-steps", "1",
         "--rho-iterations", "2"]

FIGURES = ["fig1_gp_field.png", "fig2_trajectories_nominal.png", "fig3_trajectories_gp-chance.png",
           "fig4_admm_rho.png", "fig5_distances.png", "fig6_path_lengths.png"]


def test_short_reproduction_writes_every_file_and_resumes(tmp_path, capsys):
    out = tmp_path / "repro"
    assert main(["reproduce", "--out", str(out)] + SHORT) == 0
    for name in FIGURES:
        data = (out / "figures" / name).read_bytes()
        assert data[:8] == b"\x89PNG\r\n\x1a\n", name
    rows = list(csv.DictReader((out / "table.csv").read_text().splitlines()))
    assert [r["method"] for r in rows] == [*METHODS, SOUND_LABEL]  # the paper's six, then the sound one
    assert all(r["runs"] == "1" for r in rows)
    md = (out / "table.md").read_text()
    assert md.count("\n") == 3 + len(METHODS)
    cached = sorted(p.name for p in (out / "cache").iterdir())
    assert len(cached) == len(METHODS) * (1 + 2) + 1  # runs + two rho values each, and the sound run
    capsys.readouterr()
    assert main(["reproduce", "--out", str(out)] + SHORT) == 0
    assert f"{len(cached)} of {len(cached)} runs cached; computing 0" in capsys.readouterr().out


def test_summary_of_hand_made_runs():
    """Two runs with the same 3-4-5 states; run B's target for agent 0 is never reached."""
    states = [[[0, 0], [10, 0]], [[3, 0], [10, 0]], [[3, 4], [10, 0]]]
    run_a = make_rollout(states, [[3, 4], [10, 0]])
    run_b = make_rollout(states, [[100, 100], [10, 0]])
    row = summarize([run_a, run_b])
    assert row["runs"] == 2 and row["reached_fraction"] == 0.5
    assert (row["time_to_target_mean"], row["time_to_target_std"]) == (2.0, 0.0)
    assert row["min_distance_mean"] == 7.0 and row["min_distance_worst"] == 7.0  # |(3,0)-(10,0)|
    assert row["violations_total"] == 0 and row["runs_with_violations"] == 0  # r_safe = 4
    assert row["path_length_mean"] == 3.5  # agent 0 walks 3 + 4, agent 1 stays
    assert abs(row["straight_line_length"] - (2.5 + 100 * 2 ** 0.5 / 2) / 2) < 1e-12
    assert (row["admm_iterations_mean"], row["admm_iterations_max"]) == (2.0, 2)
    assert "| 2.0 ± 0.0 |" in table_markdown({"gp-chance": row})


def test_interrupted_reproduction_resumes_from_complete_files_only(tmp_path, capsys):
    """A run killed mid-way leaves some runs cached under their final names and perhaps a hidden,
    half-written temporary file (writes go to ``.NAME.*.tmp`` and are renamed). A rerun loads the
    complete files, ignores the fragment and computes exactly the missing runs."""
    from torch_gpmpc.sim.rollout import Rollout

    out = tmp_path / "repro"
    args = ["reproduce", "--out", str(out), "--methods", "nominal,nominal-chance"] + SHORT
    assert main(args) == 0
    cache = out / "cache"
    runs = sorted(p for p in cache.glob("*.npz") if not p.name.startswith("."))
    assert len(runs) == 7  # 2 methods x (1 run + 2 rho values) + the sound run
    lost = runs[1::2]
    fragment = cache / f".{lost[0].name}.x1y2.tmp.npz"
    fragment.write_bytes(lost[0].read_bytes()[:100])  # what a SIGKILL during the write leaves
    for path in lost:
        path.unlink()
    capsys.readouterr()
    assert main(args) == 0
    assert f"{7 - len(lost)} of 7 runs cached; computing {len(lost)}" in capsys.readouterr().out
    for path in runs:
        Rollout.load(path)  # every run is complete again
