"""Transitions: file formats, validation errors, the paper's data recipe."""

from __future__ import annotations

import logging

import numpy as np
import pytest
import torch

from torch_gpmpc.data import Transitions, collect_transitions
from torch_gpmpc.errors import GpmpcError
from torch_gpmpc.gp import fit_from_transitions
from torch_gpmpc.dynamics.systems import NominalModel, make_system


@pytest.fixture(scope="module")
def data() -> Transitions:
    return collect_transitions(make_system(), num_agents=3, samples=20, seed=1)


def _arrays(n=5, d=2):
    rng = np.random.default_rng(0)
    return {"x": rng.normal(size=(n, d)), "u": rng.normal(size=(n, d)), "x_next": rng.normal(size=(n, d)),
            "agent": np.arange(n) % 2}


def _write_npz(path, **arrays):
    with open(path, "wb") as fh:
        np.savez(fh, **arrays)
    return path


def _csv(tmp_path, text, name="t.csv"):
    path = tmp_path / name
    path.write_text(text)
    return path


def _load_error(path) -> str:
    with pytest.raises(GpmpcError) as info:
        Transitions.load(path)
    return str(info.value)


# ---------------------------------------------------------------------- round trips
@pytest.mark.parametrize("suffix", [".npz", ".csv"])
def test_round_trip_is_exact(tmp_path, data, suffix):
    path = tmp_path / f"t{suffix}"
    data.save(path)
    back = Transitions.load(path)
    for name in ("x", "u", "x_next", "agent"):
        assert torch.equal(getattr(back, name), getattr(data, name)), name
    assert back.x.dtype == torch.float64 and back.agent.dtype == torch.int64


def test_round_trip_without_agent_column(tmp_path, data):
    plain = Transitions(data.x, data.u, data.x_next)
    plain.save(tmp_path / "t.csv")
    assert (tmp_path / "t.csv").read_text().splitlines()[0] == "x0,x1,u0,u1,x_next0,x_next1"
    back = Transitions.load(tmp_path / "t.csv")
    assert back.agent is None and torch.equal(back.x_next, plain.x_next)


def test_csv_and_npz_give_the_same_fit(tmp_path, data):
    data.save(tmp_path / "t.csv")
    data.save(tmp_path / "t.npz")
    hps = [fit_from_transitions(Transitions.load(tmp_path / f"t.{s}"), agent=0, iters=10).hyperparameters()
           for s in ("csv", "npz")]
    for key in ("lengthscale", "outputscale", "noise"):
        np.testing.assert_allclose(hps[0][key], hps[1][key], rtol=1e-6, atol=0)


# ---------------------------------------------------------------------- data recipe
def test_collect_follows_the_paper_recipe():
    system = make_system(noise_std=0.1)
    tr = collect_transitions(system, num_agents=2, samples=2000, seed=3, u_max=2.0, box=4.0)
    assert tr.x.shape == (4000, 2) and tr.u.shape == (4000, 2) and tr.agent_ids == [0, 1]
    assert bool((tr.x.abs() <= 4.0).all()) and bool((tr.u.norm(dim=1) < 2.0).all())
    # area-uniform in the disc: P(||u|| < r) = (r / u_max)^2
    for r in (0.5, 1.0, 1.5):
        frac = float((tr.u.norm(dim=1) < r).double().mean())
        assert abs(frac - (r / 2.0) ** 2) < 0.03, (r, frac)
    # states uniform in the box: mean 0, variance box^2 / 3
    assert abs(float(tr.x.var()) - 16.0 / 3.0) < 0.3
    # x' = x + 0.1 u + g(x) + w with w ~ N(0, 0.01 I): the leftover is the noise
    w = tr.x_next - (tr.x + 0.1 * tr.u + system.wind(tr.x))
    assert abs(float(w.mean())) < 0.01 and abs(float(w.std()) - 0.1) < 0.005


def test_collect_is_seeded():
    system = make_system()
    a = collect_transitions(system, 2, 10, seed=5)
    b = collect_transitions(system, 2, 10, seed=5)
    c = collect_transitions(system, 2, 10, seed=6)
    assert torch.equal(a.x_next, b.x_next) and not torch.equal(a.x, c.x)


def test_collect_rejects_bad_sizes():
    with pytest.raises(GpmpcError, match="samples"):
        collect_transitions(make_system(), 1, 1, seed=0)
    with pytest.raises(GpmpcError, match="u-max"):
        collect_transitions(make_system(), 1, 10, seed=0, u_max=0.0)


# ---------------------------------------------------------------------- selection
def test_residuals_for_agent_and_split(data):
    x, y = data.residuals(NominalModel())
    torch.testing.assert_close(y, data.x_next - data.x - 0.1 * data.u, rtol=0, atol=1e-14)
    assert torch.equal(x, data.x)
    xu, _ = data.residuals(NominalModel(), gp_inputs="state_input")
    assert xu.shape == (60, 4)
    one = data.for_agent(2)
    assert one.num_samples == 20 and bool((one.agent == 2).all())
    train, test = data.split(0.25, seed=0)
    assert (train.num_samples, test.num_samples) == (45, 15)
    rows = {tuple(r) for r in torch.cat([train.x, test.x]).tolist()}
    assert rows == {tuple(r) for r in data.x.tolist()}
    with pytest.raises(GpmpcError, match="agent 7 not found"):
        data.for_agent(7)
    with pytest.raises(GpmpcError, match=r"holdout fraction must be in \(0, 1\)"):
        data.split(1.0)
    with pytest.raises(GpmpcError, match="'state' or 'state_input'"):
        data.residuals(NominalModel(), gp_inputs="foo")


def test_block_split_holds_out_contiguous_time_blocks(data):
    """60 rows in 20 blocks of 3: a 0.2 holdout is 4 whole blocks, chosen by the seed; train and
    holdout partition the rows, and the result is reproducible."""
    index = torch.arange(60, dtype=torch.float64)[:, None].expand(60, 2)
    tagged = Transitions(x=index, u=data.u, x_next=data.x_next)
    train, test = tagged.split(0.2, seed=3, mode="blocks")
    held = test.x[:, 0].long().tolist()
    assert len(held) == 12 and held == sorted(held)
    starts = sorted({h // 3 for h in held})
    assert len(starts) == 4 and held == [3 * b + i for b in starts for i in range(3)]
    assert sorted(held + train.x[:, 0].long().tolist()) == list(range(60))
    again = tagged.split(0.2, seed=3, mode="blocks")[1]
    assert torch.equal(again.x, test.x)
    assert not torch.equal(tagged.split(0.2, seed=4, mode="blocks")[1].x, test.x)
    with pytest.raises(GpmpcError, match="holdout split must be one of"):
        tagged.split(0.2, mode="time")


# ---------------------------------------------------------------------- one error per problem
def test_missing_file(tmp_path):
    assert "file not found" in _load_error(tmp_path / "nope.npz")


def test_unknown_suffix(tmp_path):
    msg = _load_error(_csv(tmp_path, "x0\n", name="t.json"))
    assert "unknown suffix '.json'" in msg and ".npz or .csv" in msg


def test_npz_missing_array(tmp_path):
    a = _arrays()
    msg = _load_error(_write_npz(tmp_path / "t.npz", x=a["x"], u=a["u"]))
    assert "missing array(s) 'x_next'" in msg


def test_csv_missing_column(tmp_path):
    msg = _load_error(_csv(tmp_path, "x0,x1,u0,u1\n1,2,3,4\n5,6,7,8\n"))
    assert "bad header" in msg and "missing column(s) x_next0" in msg


@pytest.mark.parametrize("header", ["x0,x1,u0,u1,x_next1,x_next0", "x0,x1,u0,u1,x_next0,x_next1,foo",
                                    "a,b,c"])
def test_csv_bad_header(tmp_path, header):
    ncol = len(header.split(","))
    msg = _load_error(_csv(tmp_path, header + "\n" + ",".join(["1"] * ncol) + "\n"))
    assert "bad header" in msg and "expected columns" in msg


def test_csv_unparsable_cell(tmp_path):
    msg = _load_error(_csv(tmp_path, "x0,u0,x_next0\n1,2,3\n4,abc,6\n"))
    assert "line 3, column 'u0': 'abc' is not a number" in msg


def test_csv_truncated(tmp_path, data):
    data.save(tmp_path / "t.csv")
    text = (tmp_path / "t.csv").read_text()
    cut = text[: text.rfind(",", 0, len(text) - 30)]  # stop in the middle of the last line
    msg = _load_error(_csv(tmp_path, cut))
    assert "fields but the header has 7" in msg and "truncated" in msg


def test_csv_empty_and_binary(tmp_path):
    assert "is empty" in _load_error(_csv(tmp_path, ""))
    path = tmp_path / "b.csv"
    path.write_bytes(bytes(range(128, 256)))
    assert "not a UTF-8 text file" in _load_error(path)


def test_csv_agent_not_integer(tmp_path):
    msg = _load_error(_csv(tmp_path, "x0,u0,x_next0,agent\n1,2,3,0\n4,5,6,1.5\n"))
    assert "column 'agent': '1.5' is not an integer id" in msg


@pytest.mark.parametrize("garbage", ["random", "truncated"])
def test_npz_corrupt(tmp_path, garbage):
    path = tmp_path / "t.npz"
    if garbage == "random":
        path.write_bytes(np.random.default_rng(0).bytes(500))
    else:
        _write_npz(path, **_arrays(50))
        path.write_bytes(path.read_bytes()[:300])
    assert "cannot be read as .npz (corrupt or truncated?)" in _load_error(path)


def test_npz_object_array_refused(tmp_path):
    a = _arrays()
    path = _write_npz(tmp_path / "t.npz", x=a["x"], u=a["u"], x_next=np.array([{"a": 1}], dtype=object))
    assert "pickled (object) array" in _load_error(path)


def test_npz_wrong_dtype_and_rank(tmp_path):
    a = _arrays()
    msg = _load_error(_write_npz(tmp_path / "t.npz", x=a["x"], u=a["u"], x_next=np.array(["a"] * 5)))
    assert "'x_next' must be numeric" in msg
    msg = _load_error(_write_npz(tmp_path / "u.npz", x=a["x"][:, 0], u=a["u"], x_next=a["x_next"]))
    assert "'x' must be 2-D" in msg
    msg = _load_error(_write_npz(tmp_path / "v.npz", **{**a, "agent": a["agent"] + 0.5}))
    assert "'agent' must hold integer ids" in msg


def test_shape_mismatch_rows_and_columns(tmp_path):
    a = _arrays()
    msg = _load_error(_write_npz(tmp_path / "r.npz", **{**a, "u": a["u"][:4]}))
    assert "shape mismatch: 'x' has 5 rows but 'u' has 4" in msg
    msg = _load_error(_write_npz(tmp_path / "c.npz", **{**a, "x_next": np.zeros((5, 3))}))
    assert "shape mismatch: 'x' has D=2 columns but 'x_next' has 3" in msg


def test_non_finite(tmp_path):
    a = _arrays()
    a["x"][3, 1] = np.nan
    msg = _load_error(_write_npz(tmp_path / "t.npz", **a))
    assert "'x' has 1 non-finite value(s)" in msg and "row 3" in msg
    msg = _load_error(_csv(tmp_path, "x0,u0,x_next0\n1,2,inf\n4,5,6\n"))
    assert "'x_next' has 1 non-finite" in msg


def test_extreme_magnitude(tmp_path):
    a = _arrays()
    a["u"][2, 0] = 3e7
    msg = _load_error(_write_npz(tmp_path / "t.npz", **a))
    assert "'u' has extreme value 3e+07" in msg and "row 2" in msg


def test_too_few_samples(tmp_path):
    msg = _load_error(_csv(tmp_path, "x0,u0,x_next0\n1,2,3\n"))
    assert "only 1 transition(s); need at least 2" in msg


def test_duplicates_dropped_noise_kept(tmp_path, caplog):
    text = "x0,u0,x_next0\n1,2,3\n1,2,3\n1,2,3.5\n4,5,6\n"
    with caplog.at_level(logging.WARNING, logger="torch_gpmpc.data.transitions"):
        tr = Transitions.load(_csv(tmp_path, text))
    assert tr.x_next[:, 0].tolist() == [3.0, 3.5, 6.0]  # exact duplicate gone, noisy repeat kept
    assert "dropped 1 exact duplicate" in caplog.text


def test_duplicates_leaving_too_few(tmp_path):
    msg = _load_error(_csv(tmp_path, "x0,u0,x_next0\n1,2,3\n1,2,3\n"))
    assert "only 1 transition(s)" in msg


def test_dimension_mismatch_with_nominal(data):
    with pytest.raises(GpmpcError) as info:
        data.residuals(NominalModel(dim=3))
    assert "state dimension D=2" in str(info.value) and "model's D=3" in str(info.value)
    odd = Transitions(data.x, data.u[:, :1], data.x_next)
    with pytest.raises(GpmpcError, match="input dimension Du=1"):
        odd.residuals(NominalModel(dim=2))
    data.check_dim(2)  # matching dimensions pass silently
