"""``gpmpc collect`` / ``gpmpc fit-gp`` end to end, TensorBoard events, the GP bench."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from torch_gpmpc.cli import main
from torch_gpmpc.data.transitions import Transitions
from torch_gpmpc.gp.model import ResidualGP
from torch_gpmpc.report.tensorboard import TBLogger, read_scalars


def _fails(argv, capsys) -> str:
    """Run the CLI expecting a user error: exit code 2 and exactly one line on stderr."""
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1, err
    assert "Traceback" not in err
    return err


@pytest.fixture(scope="module")
def collected(tmp_path_factory):
    out = tmp_path_factory.mktemp("collect") / "data.npz"
    assert main(["collect", "--out", str(out), "--agents", "2", "--samples", "40", "--seed", "3"]) == 0
    return out


def test_collect_writes_npz_and_csv(collected, tmp_path, capsys):
    assert main(["collect", "--out", str(tmp_path / "d.csv"), "--agents", "2", "--samples", "40",
                 "--seed", "3"]) == 0
    assert "80 transitions" in capsys.readouterr().out
    a, b = Transitions.load(collected), Transitions.load(tmp_path / "d.csv")
    assert torch.equal(a.x, b.x) and torch.equal(a.x_next, b.x_next) and torch.equal(a.agent, b.agent)
    with np.load(collected, allow_pickle=False) as f:
        assert set(f.files) == {"x", "u", "x_next", "agent"}
        assert f["x"].shape == (80, 2) and f["agent"].dtype.kind == "i"


def test_fit_gp_writes_model_events_figure(collected, tmp_path, capsys):
    model, logdir, fig = tmp_path / "gp.pt", tmp_path / "tb", tmp_path / "fig.png"
    code = main(["fit-gp", "--transitions", str(collected), "--out", str(model), "--logdir", str(logdir),
                 "--holdout", "0.25", "--agent", "1", "--iters", "5", "--figure", str(fig)])
    assert code == 0
    out = capsys.readouterr().out
    assert "NLL" in out and "lengthscale" in out and "held-out (10 rows, blocks split): RMSE" in out and "method: exact GP" in out and "coverage" in out
    gp = ResidualGP.load(model, expected_dim=2)
    assert gp.num_data == 30 and gp.gp_inputs == "state" and gp.residual_rows == "x0,x1"  # checked when a run loads it
    assert fig.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    scalars = read_scalars(logdir)
    assert [s for s, _ in scalars["gp/loss"]] == list(range(6))
    for tag in ("gp/lengthscale/d0_in0", "gp/lengthscale/d1_in1", "gp/noise/d0", "gp/outputscale/d1",
                "gp/holdout_rmse/d0"):
        assert tag in scalars, tag
    # the logged final hyperparameters are the saved model's (raw units)
    assert scalars["gp/noise/d1"][-1][1] == pytest.approx(float(gp.noise[1]), rel=1e-6)
    assert all(tag.startswith("gp/") for tag in scalars)


def test_fit_gp_report_sparse_model_and_run_with_it(collected, tmp_path, capsys):
    """--report holds the contract's keys (lists in the order of the residual rows); the sparse
    method is said in the summary, saved, and accepted by run --gp-model."""
    model, report, fig = tmp_path / "gp.pt", tmp_path / "r.json", tmp_path / "h.png"
    assert main(["fit-gp", "--transitions", str(collected), "--out", str(model), "--holdout", "0.25",
                 "--holdout-split", "random", "--report", str(report), "--gp-method", "sgpr", "--iters", "5",
                 "--holdout-figure", str(fig)]) == 0
    out = capsys.readouterr().out
    assert "method: sparse GP (SGPR" in out and "R^2" in out and "random split" in out
    data = json.loads(report.read_text())
    assert set(data) == {"n_train", "n_holdout", "residual", "holdout", "fit_seconds"}
    assert (data["n_train"], data["n_holdout"], data["residual"]) == (60, 20, [0, 1])
    assert set(data["holdout"]) == {"rmse", "r2", "coverage95"}
    assert all(len(v) == 2 for v in data["holdout"].values())
    assert 0.0 < data["fit_seconds"] < 60.0  # a 5-iteration fit of 60 points, timed (not a placeholder)
    assert fig.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert ResidualGP.load(model).method == "sgpr"
    run_out = tmp_path / "run"
    assert main(["run", "--gp-model", str(model), "--set", "max_steps=2", "--out", str(run_out), "--no-figures"]) == 0
    assert json.loads((run_out / "metrics.json").read_text())["steps"] == 2


def test_fit_gp_without_out_only_evaluates(collected, tmp_path, capsys):
    report = tmp_path / "r.json"
    assert main(["fit-gp", "--transitions", str(collected), "--holdout", "0.25", "--report", str(report),
                 "--iters", "3"]) == 0
    assert "the model was not saved" in capsys.readouterr().out
    assert sorted(p.name for p in tmp_path.iterdir()) == ["r.json"]


def test_fit_gp_state_input_and_adam(collected, tmp_path):
    model = tmp_path / "gp.pt"
    assert main(["fit-gp", "--transitions", str(collected), "--out", str(model), "--inputs", "state_input",
                 "--optimizer", "adam", "--iters", "3"]) == 0
    gp = ResidualGP.load(model)
    assert gp.input_dim == 4 and gp.gp_inputs == "state_input"


def test_collect_bad_input(tmp_path, capsys):
    err = _fails(["collect", "--out", str(tmp_path / "d.txt")], capsys)
    assert "unknown suffix '.txt'" in err
    err = _fails(["collect", "--out", str(tmp_path / "d.npz"), "--samples", "1"], capsys)
    assert "--samples must be >= 2" in err
    err = _fails(["collect", "--out", str(tmp_path / "d.npz"), "--dim", "4"], capsys)
    assert "--dim must be 2 or 3" in err
    assert list(tmp_path.iterdir()) == []


def test_fit_gp_bad_input(collected, tmp_path, capsys):
    out = tmp_path / "gp.pt"
    base = ["fit-gp", "--out", str(out)]
    assert "file not found" in _fails([*base, "--transitions", str(tmp_path / "none.npz")], capsys)
    bad = tmp_path / "bad.csv"
    bad.write_text("x0,x1,u0,u1,x_next0,x_next1\n1,2,3,4,5,6\n1,2,3,4,oops,6\n")
    assert "'oops' is not a number" in _fails([*base, "--transitions", str(bad)], capsys)
    assert "agent 9 not found" in _fails([*base, "--transitions", str(collected), "--agent", "9"], capsys)
    assert "--holdout must be in [0, 1)" in _fails([*base, "--transitions", str(collected), "--holdout", "1.5"],
                                                   capsys)
    err = _fails(["fit-gp", "--transitions", str(collected), "--out", str(tmp_path / "gp.json")], capsys)
    assert "must end in .pt" in err
    err = _fails([*base, "--transitions", str(collected), "--report", str(tmp_path / "r.json")], capsys)
    assert "need held-out rows: add --holdout 0.2" in err
    err = _fails([*base, "--transitions", str(collected), "--holdout", "0.2", "--report", str(tmp_path / "r.txt")],
                 capsys)
    assert "must end in .json" in err
    three_d = tmp_path / "d3.npz"
    assert main(["collect", "--out", str(three_d), "--dim", "3", "--samples", "5", "--agents", "1"]) == 0
    capsys.readouterr()
    err = _fails([*base, "--transitions", str(three_d), "--figure", str(tmp_path / "f.png")], capsys)
    assert "--figure needs 2D data" in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bad.csv", "d3.npz"]  # no model, no temp files


def test_tblogger_noop_and_nested_dicts(tmp_path):
    with TBLogger(None) as tb:
        assert not tb.enabled
        tb.scalar("gp/loss", 1.0, 0)
    with TBLogger(tmp_path / "tb") as tb:
        tb.scalars_from_dict("admm", {"primal_residual": 0.5, "per_edge": [1.0, 2.0], "name": "x"}, 3)
        tb.scalar("perf/solve_ms", float("nan"), 3)  # skipped
    scalars = read_scalars(tmp_path / "tb")
    assert scalars == {"admm/primal_residual": [(3, 0.5)], "admm/per_edge/0": [(3, 1.0)],
                       "admm/per_edge/1": [(3, 2.0)]}


def test_bench_gp_smoke(monkeypatch):
    import torch_gpmpc.bench.gp as bench_gp

    monkeypatch.setattr(bench_gp, "SIZES", (100,))
    result = bench_gp.run(quick=True, out=None)
    rows = {r["workload"]: r for r in result["table"]}
    row = rows["linearize 42 pts, N=100"]
    assert row["ours_ms"] > 0 and row["gpytorch_ms"] > 0 and row["max_abs_diff"] < 1e-10
    assert "fit N=100 (L-BFGS, 50 iters)" in rows


def test_fit_gp_warns_where_the_gp_explains_little(tmp_path, capsys):
    """Residuals that are noise alone (nothing the inputs see): the held-out R^2 is below LOW_R2 on both
    rows and fit-gp says so on stderr, naming the row and what to do, and still writes the model;
    without held-out rows it says how to get them."""
    from torch_gpmpc.cli.fit_gp import LOW_R2

    gen = torch.Generator().manual_seed(0)
    x = 4 * torch.rand(120, 2, generator=gen, dtype=torch.float64) - 2
    u = torch.rand(120, 2, generator=gen, dtype=torch.float64) - 0.5
    noise = 0.05 * torch.randn(120, 2, generator=gen, dtype=torch.float64)
    path = tmp_path / "noise.npz"
    Transitions(x, u, x + 0.1 * u + noise).save(path)
    report = tmp_path / "r.json"
    assert main(["fit-gp", "--transitions", str(path), "--out", str(tmp_path / "m.pt"), "--holdout", "0.3",
                 "--holdout-split", "random", "--iters", "10", "--report", str(report)]) == 0
    err = capsys.readouterr().err
    r2 = json.loads(report.read_text())["holdout"]["r2"]
    assert all(v < LOW_R2 for v in r2), r2
    for d in (0, 1):
        assert f"the GP explains little of residual row d{d} (state x{d}): hold-out R^2 {r2[d]:.3g}" in err
    assert (tmp_path / "m.pt").exists()
    assert main(["fit-gp", "--transitions", str(path), "--iters", "2"]) == 0
    assert "add --holdout 0.2 for its R^2 and coverage" in capsys.readouterr().err
