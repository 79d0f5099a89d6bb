"""Robustness: bad inputs, solver faults, property tests, interrupted runs.

* ``CLI_CASES``/``API_CASES``: one row per distinct bad input. Each must exit 2 (CLI)
  or raise :class:`GpmpcError` (API) with ONE line naming the problem and the fix, no
  traceback, and leave neither the output path nor a temporary ``.*.tmp*`` file behind.
* Solver faults: agent 1's local solve raises, returns NaN, or returns an infeasible
  answer on some ADMM iterations; the run continues with that agent's previous plan,
  the failures are counted in ``metrics.json`` and each kind is warned about once.
* Property tests (hypothesis): the local problem and the transitions loader.
* Interrupted runs: ``gpmpc run`` killed with SIGINT / SIGKILL leaves only complete files.
"""

from __future__ import annotations

import contextlib
import json
import dataclasses
import logging
import os
import pickle
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from torch_gpmpc.coordination.agent_step import LocalStep
from torch_gpmpc.cli import main
from torch_gpmpc.config import Config, load_config
from torch_gpmpc.data import Transitions, collect_transitions
from torch_gpmpc.errors import GpmpcError
from torch_gpmpc.gp import ResidualGP, fit_residual_gp
from torch_gpmpc.sim.metrics import compute_metrics
from torch_gpmpc.control.problem import FAILURE_KINDS, LocalProblemData
from torch_gpmpc.control.solvers import make_local_solver
from torch_gpmpc.sim.rollout import Rollout
from torch_gpmpc.sim.scenarios import Scenario, make_scenario
from torch_gpmpc.dynamics.systems import NominalModel, make_system

F64 = torch.float64


# =============================================================================== assets
class Assets:
    """Valid files the bad inputs are derived from (built once per module)."""

    def __init__(self, root: Path):
        g = torch.Generator().manual_seed(0)
        data = collect_transitions(make_system(2, 0.1), num_agents=2, samples=12, seed=1)
        self.npz = root / "valid.npz"
        self.csv = root / "valid.csv"
        data.save(self.npz)
        data.save(self.csv)
        x = torch.rand(15, 2, generator=g, dtype=F64) * 4 - 2
        self.gp2 = root / "gp2.pt"
        fit_residual_gp(x, 0.1 * torch.sin(x), iters=0).save(self.gp2)
        x3 = torch.rand(15, 3, generator=g, dtype=F64)
        self.gp3 = root / "gp3.pt"
        fit_residual_gp(x3, 0.1 * x3, iters=0).save(self.gp3)
        self.gp_state_input = root / "gp_si.pt"
        fit_residual_gp(torch.cat([x, x], 1), 0.1 * x, iters=0, gp_inputs="state_input").save(self.gp_state_input)


@pytest.fixture(scope="module")
def assets(tmp_path_factory) -> Assets:
    return Assets(tmp_path_factory.mktemp("assets"))


def arrays(n: int = 10, d: int = 2, du: int = 2, seed: int = 0) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    return {"x": rng.uniform(-2, 2, (n, d)), "u": rng.uniform(-1, 1, (n, du)), "x_next": rng.uniform(-2, 2, (n, d))}


def write_npz(tmp: Path, name: str = "t.npz", **arrs) -> Path:
    path = tmp / name
    with open(path, "wb") as fh:
        np.savez(fh, **arrs)
    return path


def with_value(value, name: str = "x", row: int = 3, col: int = 1, **kw) -> dict[str, np.ndarray]:
    a = arrays(**kw)
    a[name] = a[name].astype(np.float64)
    a[name][row, col] = value
    return a


def write(tmp: Path, name: str, content: str | bytes) -> Path:
    path = tmp / name
    path.write_bytes(content if isinstance(content, bytes) else content.encode())
    return path


CSV_HEAD = "x0,x1,u0,u1,x_next0,x_next1\n"
CSV_ROW = "0.1,0.2,0.3,0.4,0.5,0.6\n"
CSV_ROW2 = "1.1,1.2,1.3,1.4,1.5,1.6\n"


# argv builders: each returns (argv, output path that must not exist afterwards)
def fit(tmp: Path, transitions: Path, *extra: str):
    out = tmp / "gp.pt"
    return ["fit-gp", "--transitions", str(transitions), "--out", str(out), "--iters", "0", *extra], out


def collect(tmp: Path, *extra: str):
    out = tmp / "d.npz"
    return ["collect", "--out", str(out), "--samples", "5", *extra], out


#: keeps a wrongly accepted run short instead of hanging the suite
_RUN_GUARD = ["--no-figures", "--set", "max_steps=1", "--set", "admm_max_iter=1", "--set", "gp_iters=1"]


def run(tmp: Path, *extra: str):
    out = tmp / "run"
    # a method without GPs ignores gp_iters, and says so (one more stderr line)
    learns = not any(a == "--method" and b in ("nominal", "nonlinear") for a, b in zip(extra, extra[1:]))
    guard = _RUN_GUARD if learns else _RUN_GUARD[:-2]
    return ["run", "--out", str(out), *guard, *extra], out


def run_config(tmp: Path, name: str, text: str, *extra: str):
    return run(tmp, "--config", str(write(tmp, name, text)), *extra)


def run_scenario(tmp: Path, scenario: dict | str, *extra: str, name: str = "scen.json"):
    text = scenario if isinstance(scenario, str) else json.dumps(scenario)
    return run(tmp, "--method", "nominal", "--scenario", str(write(tmp, name, text)), *extra)


def run_model(tmp: Path, model: Path, *extra: str):
    return run(tmp, "--method", "gp", "--gp-model", str(model), *extra)


def valid_scenario(**changes) -> dict:
    return {"starts": [[4.0, 0.0], [-4.0, 0.0]], "targets": [[-4.0, 0.5], [4.0, -0.5]], **changes}


# -------------------------------------------------------------------- model files
class _OpenFile:
    """Unpickling this creates the file ``path`` (calls ``open(path, "w")``)."""

    def __init__(self, path: str):
        self.path = path

    def __reduce__(self):
        return (open, (self.path, "w"))


class _System:
    """Unpickling this runs a shell command that creates ``path``."""

    def __init__(self, path: str):
        self.path = path

    def __reduce__(self):
        return (os.system, (f"touch {self.path}",))


def _pwned(tmp: Path) -> Path:
    return tmp / "PWNED"


def malicious_torch_zip(tmp: Path) -> Path:
    path = tmp / "evil.pt"
    torch.save({"format": "torch_gpmpc.ResidualGP", "version": 1, "payload": _OpenFile(str(_pwned(tmp)))}, path)
    return path


def malicious_raw_pickle(tmp: Path) -> Path:
    return write(tmp, "evil_raw.pt", pickle.dumps({"x": _System(str(_pwned(tmp)))}, protocol=2))


def edited_model(tmp: Path, src: Path, edit, rehash: bool = True) -> Path:
    """A copy of a model file with ``edit`` applied to its payload (checksum updated if ``rehash``)."""
    from torch_gpmpc.gp.io import payload_checksum

    payload = torch.load(src, weights_only=True)
    edit(payload)
    if rehash:
        payload["checksum"] = payload_checksum(payload)
    path = tmp / "edited.pt"
    torch.save(payload, path)
    return path


def _nan_lengthscale(p):
    key = next(k for k in p["state_dict"] if k.endswith("raw_lengthscale"))
    p["state_dict"][key] = torch.full_like(p["state_dict"][key], float("nan"))


def _truncated(path: Path, tmp: Path, name: str, fraction: float = 0.5) -> Path:
    data = path.read_bytes()
    return write(tmp, name, data[: int(len(data) * fraction)])


def _flip_tensor_bytes(path: Path, tmp: Path) -> Path:
    """Flip one bit inside the stored training inputs (torch does not check zip CRCs)."""
    raw = torch.load(path, weights_only=True)["train_inputs"].numpy().tobytes()
    data = bytearray(path.read_bytes())
    at = bytes(data).index(raw) + 3
    data[at] ^= 0x01
    return write(tmp, "m.pt", bytes(data))


def _bitflipped(path: Path, tmp: Path, name: str) -> Path:
    data = bytearray(path.read_bytes())
    mid = len(data) // 3
    for i in range(mid, mid + 16):
        data[i] ^= 0xFF
    return write(tmp, name, bytes(data))


# ========================================================================= CLI table
# (id, builder(tmp, assets) -> (argv, out), expected substring of the error line)
CLI_CASES = [
    # ---- .npz transitions
    ("npz-not-a-zip", lambda t, a: fit(t, write(t, "t.npz", b"this is not an npz file")), "not a zip archive"),
    ("npz-zero-bytes", lambda t, a: fit(t, write(t, "t.npz", b"")), "not a zip archive"),
    ("npz-truncated", lambda t, a: fit(t, _truncated(a.npz, t, "t.npz")), "corrupt or truncated"),
    ("npz-bit-flipped", lambda t, a: fit(t, _bitflipped(a.npz, t, "t.npz")), "corrupt or truncated"),
    ("npz-missing-array-u", lambda t, a: fit(t, write_npz(t, x=arrays()["x"], x_next=arrays()["x_next"])),
     "missing array(s) 'u'"),
    ("npz-x-1d", lambda t, a: fit(t, write_npz(t, **{**arrays(), "x": np.zeros(10)})), "must be 2-D"),
    ("npz-x-3d", lambda t, a: fit(t, write_npz(t, **{**arrays(), "x": np.zeros((10, 2, 1))})), "must be 2-D"),
    ("npz-x-next-wrong-dim", lambda t, a: fit(t, write_npz(t, **{**arrays(), "x_next": np.zeros((10, 3))})),
     "shape mismatch"),
    ("npz-row-count-mismatch", lambda t, a: fit(t, write_npz(t, **{**arrays(), "u": np.zeros((9, 2))})),
     "shape mismatch"),
    ("npz-zero-columns", lambda t, a: fit(t, write_npz(t, x=np.zeros((10, 0)), u=np.zeros((10, 0)),
                                                      x_next=np.zeros((10, 0)))), "at least one column"),
    ("npz-nan", lambda t, a: fit(t, write_npz(t, **with_value(np.nan))), "non-finite"),
    ("npz-inf", lambda t, a: fit(t, write_npz(t, **with_value(-np.inf, name="x_next"))), "non-finite"),
    ("npz-extreme-value", lambda t, a: fit(t, write_npz(t, **with_value(3e9, name="u"))), "extreme value"),
    ("npz-empty", lambda t, a: fit(t, write_npz(t, **arrays(n=0))), "only 0 transition"),
    ("npz-one-sample", lambda t, a: fit(t, write_npz(t, **arrays(n=1))), "only 1 transition"),
    ("npz-all-duplicates", lambda t, a: fit(t, write_npz(t, **{k: np.repeat(v[:1], 6, 0) for k, v in arrays().items()})),
     "after dropping 5 exact duplicate"),
    ("npz-object-array", lambda t, a: fit(t, write_npz(t, **{**arrays(), "x": np.array([[1, "a"]] * 10, dtype=object)})),
     "pickled (object) array"),
    ("npz-string-dtype", lambda t, a: fit(t, write_npz(t, **{**arrays(), "x": np.full((10, 2), "1.0")})),
     "must be numeric"),
    ("npz-complex-dtype", lambda t, a: fit(t, write_npz(t, **{**arrays(), "u": np.ones((10, 2)) * 1j})),
     "must be numeric"),
    ("npz-agent-float", lambda t, a: fit(t, write_npz(t, **arrays(), agent=np.zeros(10))), "integer ids"),
    ("npz-agent-negative", lambda t, a: fit(t, write_npz(t, **arrays(), agent=-np.ones(10, dtype=int))),
     "negative id"),
    ("npz-input-dim-differs", lambda t, a: fit(t, write_npz(t, **arrays(du=3))), "input dimension Du=3"),
    ("npz-too-many-points-exact", lambda t, a: fit(t, write_npz(t, **arrays(n=5001)), "--gp-method", "exact"),
     "at most 5000"),
    # ---- .csv transitions
    ("csv-empty", lambda t, a: fit(t, write(t, "t.csv", "")), "is empty"),
    ("csv-header-only", lambda t, a: fit(t, write(t, "t.csv", CSV_HEAD)), "only 0 transition"),
    ("csv-bad-header", lambda t, a: fit(t, write(t, "t.csv", "a,b,c\n1,2,3\n4,5,6\n")), "bad header"),
    ("csv-columns-out-of-order", lambda t, a: fit(t, write(t, "t.csv", "u0,u1,x0,x1,x_next0,x_next1\n"
                                                           + CSV_ROW + CSV_ROW2)), "in this order"),
    ("csv-truncated-row", lambda t, a: fit(t, write(t, "t.csv", CSV_HEAD + CSV_ROW + CSV_ROW2 + "0.7,0.8,0.")),
     "fields but the header has 6"),
    ("csv-truncated-file", lambda t, a: fit(t, _truncated(a.csv, t, "t.csv", 0.47)), "fields but the header"),
    ("csv-not-a-number", lambda t, a: fit(t, write(t, "t.csv", CSV_HEAD + CSV_ROW + "1,2,3,4,oops,6\n")),
     "'oops' is not a number"),
    ("csv-nan", lambda t, a: fit(t, write(t, "t.csv", CSV_HEAD + CSV_ROW + "1,nan,3,4,5,6\n")), "non-finite"),
    ("csv-inf", lambda t, a: fit(t, write(t, "t.csv", CSV_HEAD + CSV_ROW + "1,2,3,4,5,-inf\n")), "non-finite"),
    ("csv-extreme-value", lambda t, a: fit(t, write(t, "t.csv", CSV_HEAD + CSV_ROW + "1e300,2,3,4,5,6\n")),
     "extreme value"),
    ("csv-binary-garbage", lambda t, a: fit(t, write(t, "t.csv", bytes(range(256)) * 4)), "not a UTF-8"),
    ("csv-one-sample", lambda t, a: fit(t, write(t, "t.csv", CSV_HEAD + CSV_ROW)), "only 1 transition"),
    ("csv-duplicated-rows", lambda t, a: fit(t, write(t, "t.csv", CSV_HEAD + CSV_ROW * 4)),
     "after dropping 3 exact duplicate"),
    ("csv-agent-not-integer", lambda t, a: fit(t, write(t, "t.csv", CSV_HEAD.strip() + ",agent\n"
                                                        + "0.1,0.2,0.3,0.4,0.5,0.6,0\n1,2,3,4,5,6,one\n")),
     "not an integer id"),
    ("transitions-unknown-suffix", lambda t, a: fit(t, write(t, "t.txt", CSV_HEAD + CSV_ROW)), "unknown suffix"),
    ("transitions-missing", lambda t, a: fit(t, t / "nope.npz"), "file not found"),
    ("transitions-is-a-directory", lambda t, a: fit(t, (t / "dir.npz").mkdir() or t / "dir.npz"), "file not found"),
    # ---- fit-gp arguments
    ("fit-gp-agent-absent", lambda t, a: fit(t, a.npz, "--agent", "9"), "agent 9 not found"),
    ("fit-gp-holdout-too-large", lambda t, a: fit(t, a.npz, "--holdout", "0.95"), "training rows"),
    ("fit-gp-holdout-out-of-range", lambda t, a: fit(t, a.npz, "--holdout", "1.5"), "--holdout must be in [0, 1)"),
    ("fit-gp-negative-iters", lambda t, a: fit(t, a.npz, "--iters", "-1"), "--iters must be >= 0"),
    ("fit-gp-out-not-pt", lambda t, a: (fit(t, a.npz)[0][:4] + [str(t / "gp.json")], t / "gp.json"),
     "must end in .pt"),
    ("fit-gp-figure-3d", lambda t, a: fit(t, write_npz(t, **arrays(d=3, du=3)), "--figure", str(t / "f.png")),
     "--figure needs 2D data"),
    # ---- collect arguments
    ("collect-zero-agents", lambda t, a: collect(t, "--agents", "0"), "--agents must be >= 1"),
    ("collect-one-sample", lambda t, a: (collect(t)[0] + ["--samples", "1"], collect(t)[1]), "--samples must be >= 2"),
    ("collect-huge-samples", lambda t, a: (collect(t)[0] + ["--samples", "100000000"], collect(t)[1]),
     "is more than 1000000"),
    ("collect-noise-nan", lambda t, a: collect(t, "--noise-std", "nan"), "--noise-std must be a finite"),
    ("collect-box-inf", lambda t, a: collect(t, "--box", "inf"), "--box must be a positive"),
    ("collect-u-max-zero", lambda t, a: collect(t, "--u-max", "0"), "--u-max must be a positive"),
    ("collect-dim-4", lambda t, a: collect(t, "--dim", "4"), "--dim must be 2 or 3"),
    ("collect-not-an-int", lambda t, a: collect(t, "--agents", "three"), "invalid int value: 'three'"),
    ("collect-bad-suffix", lambda t, a: (["collect", "--out", str(t / "d.json")], t / "d.json"), "unknown suffix"),
    ("collect-out-under-a-file", lambda t, a: (["collect", "--out", str(write(t, "f", "x") / "d.npz"), "--samples", "3"],
                                               t / "f" / "d.npz"), "is an existing file, not a directory"),
    # ---- config (file and --set)
    ("config-unknown-key-file", lambda t, a: run_config(t, "c.toml", "horizn = 5\n"), "did you mean 'horizon'"),
    ("config-unknown-key-set", lambda t, a: run(t, "--set", "rhoo=5"), "did you mean 'rho'"),
    ("config-unknown-key-unlike-any", lambda t, a: run(t, "--set", "nosuch=1"), "`gpmpc keys` lists them"),
    ("config-wrong-type-str", lambda t, a: run(t, "--set", "horizon=ten"), "expected int, got str"),
    ("config-wrong-type-float", lambda t, a: run_config(t, "c.toml", "horizon = 1.5\n"), "expected int, got float"),
    ("config-wrong-type-bool", lambda t, a: run(t, "--set", "horizon=true"), "expected int, got bool"),
    ("config-null-not-allowed", lambda t, a: run(t, "--set", "rho=null"), "expected float, got NoneType"),
    ("config-horizon-zero", lambda t, a: run(t, "--set", "horizon=0"), "'horizon': 0 is out of range"),
    ("config-horizon-negative", lambda t, a: run_config(t, "c.json", '{"horizon": -3}'), "'horizon': -3 is out"),
    ("config-horizon-huge", lambda t, a: run(t, "--set", "horizon=100000"), "[1, 1000]"),
    ("config-eps-one", lambda t, a: run(t, "--set", "eps=1"), "'eps': 1.0 is out of range; use a number in (0, 1)"),
    ("config-eps-zero", lambda t, a: run(t, "--set", "eps=0"), "'eps': 0.0 is out of range"),
    ("config-eps-above-one", lambda t, a: run_config(t, "c.toml", "eps = 1.5\n"), "'eps': 1.5 is out of range"),
    ("config-u-max-zero", lambda t, a: run(t, "--set", "u_max=0"), "'u_max': 0.0 is out of range"),
    ("config-u-max-negative", lambda t, a: run(t, "--set", "u_max=-1"), "'u_max': -1.0 is out of range"),
    ("config-r-safe-negative", lambda t, a: run(t, "--set", "r_safe=-0.1"), "'r_safe': -0.1 is out of range"),
    ("config-rho-nan", lambda t, a: run(t, "--set", "rho=NaN"), "'rho': nan is not finite"),
    ("config-inf-word", lambda t, a: run(t, "--set", "gp_online_max_input_change=inf"), "give a large finite one"),
    ("config-nan-word", lambda t, a: run(t, "--set", "rho=nan"), "numbers must be finite, give a number"),
    ("config-rho-zero", lambda t, a: run(t, "--set", "rho=0"), "'rho': 0.0 is out of range"),
    ("config-risk-split-one", lambda t, a: run(t, "--set", "risk_split=1"), "'risk_split'"),
    ("config-seed-negative", lambda t, a: run(t, "--seed", "-1"), "'seed': -1 is out of range"),
    ("config-dim-4", lambda t, a: run(t, "--set", "dim=4"), "'dim': 4 is out of range; use 2 or 3"),
    ("config-num-agents-paper", lambda t, a: run(t, "--set", "num_agents=5"), "paper scenario has 3 agents"),
    ("config-circle-radius-huge", lambda t, a: run(t, "--set", "circle_radius=1e7"), "(0, 10000]"),
    ("config-gp-samples-huge", lambda t, a: run(t, "--set", "gp_samples=1000000"), "'gp_samples'"),
    ("config-r-safe-exceeds-start-gap", lambda t, a: run(t, "--set", "r_safe=10"), "closer than r_safe = 10"),
    ("config-method-unknown", lambda t, a: run(t, "--method", "magic"), "'method': 'magic' is not one of"),
    ("config-gp-inputs-state-input", lambda t, a: run(t, "--method", "gp", "--set", "gp_inputs=state_input"),
     "'gp_inputs'"),
    ("config-set-without-equals", lambda t, a: run(t, "--set", "horizon"), "expected NAME=VALUE"),
    ("config-toml-syntax", lambda t, a: run_config(t, "c.toml", "horizon = = 5\n"), "cannot be parsed"),
    ("config-json-list", lambda t, a: run_config(t, "c.json", "[1, 2]"), "expected a table"),
    ("config-unknown-suffix", lambda t, a: run_config(t, "c.ini", "horizon=5"), "unknown suffix '.ini'"),
    ("config-missing-file", lambda t, a: run(t, "--config", str(t / "none.toml")), "does not exist"),
    ("config-threads-zero", lambda t, a: (["--threads", "0"] + run(t)[0], run(t)[1]), "--threads must be >= 1"),
    ("run-out-is-a-file", lambda t, a: (["run", "--out", str(write(t, "runfile", "x")), *_RUN_GUARD],
                                        t / "runfile" / "metrics.json"), "is an existing file"),
    ("distributed-agents-per-process-zero", lambda t, a: (["run", "--backend", "distributed", "--agents-per-process",
                                                           "0", "--out", str(t / "d")], t / "d"),
     "--agents-per-process (agents_per_process) must be >= 1"),
    ("distributed-timeout-zero", lambda t, a: (["run", "--backend", "distributed", "--timeout", "0", "--out",
                                                str(t / "d")], t / "d"), "--timeout must be > 0 seconds"),
    ("distributed-mission", lambda t, a: (["run", "--backend", "distributed", "--set", "risk_mode=mission",
                                           "--set", "risk_budget=0.05", "--out", str(t / "d")], t / "d"),
     "config key 'risk_mode': the mission budget runs in process only"),
    ("calibrate-budget-out-of-range", lambda t, a: (["calibrate", "--mission", "--budgets", "1.5", "--out",
                                                     str(t / "c")], t / "c"), "--budgets"),
    ("calibrate-negative-baseline-runs", lambda t, a: (["calibrate", "--mission", "--baseline-runs", "-1", "--out",
                                                        str(t / "c")], t / "c"), "--baseline-runs must be >= 0"),
    ("calibrate-budgets-without-mission", lambda t, a: (["calibrate", "--budgets", "0.01", "--out", str(t / "c")],
                                                        t / "c"), "add --mission"),
    ("tune-out-is-a-file", lambda t, a: (["tune", "--iters", "0", "--out", str(write(t, "tunefile", "x"))],
                                         t / "tunefile" / "tuned.json"), "is an existing file; give a directory"),
    ("bench-out-is-a-file", lambda t, a: (["bench", "--sections", "gp", "--quick", "--out",
                                           str(write(t, "benchfile", "x"))], t / "benchfile" / "bench.json"),
     "is an existing file; give a directory"),
    ("reproduce-out-is-a-file", lambda t, a: (["reproduce", "--runs", "1", "--out", str(write(t, "repfile", "x"))],
                                              t / "repfile" / "table.md"), "is an existing file; give a directory"),
    ("collect-out-is-a-directory", lambda t, a: (["collect", "--out", str(t)], t / "d.npz"),
     "is an existing directory; give a file path"),
    ("benchmark-unknown-scenario", lambda t, a: (["benchmark", "--scenario", "randum", "--quick", "--out",
                                                  str(t / "b")], t / "b"), "'randum' is not one of"),
    # ---- scenario files
    ("scenario-starts-too-close", lambda t, a: run_scenario(t, valid_scenario(starts=[[0, 0], [0.2, 0]])),
     "closer than r_safe"),
    ("scenario-duplicate-starts", lambda t, a: run_scenario(t, valid_scenario(starts=[[1, 1], [1, 1]])),
     "are 0 apart"),
    ("scenario-target-out-of-range", lambda t, a: run_scenario(t, valid_scenario(targets=[[1e5, 0], [4, 0]])),
     "exceeds 10000"),
    ("scenario-target-nan", lambda t, a: run_scenario(t, '{"starts": [[4, 0], [-4, 0]], "targets": [[NaN, 0], [4, 0]]}'),
     "not finite"),
    ("scenario-target-inf-toml", lambda t, a: run_scenario(t, "starts = [[4, 0], [-4, 0]]\ntargets = [[inf, 0], [4, 0]]\n",
                                                           name="s.toml"), "not finite"),
    ("scenario-count-mismatch", lambda t, a: run_scenario(t, valid_scenario(targets=[[1, 1]])), "one target per start"),
    ("scenario-ragged", lambda t, a: run_scenario(t, valid_scenario(starts=[[4, 0], [-4]])), "ragged"),
    ("scenario-wrong-dim", lambda t, a: run_scenario(t, valid_scenario(starts=[[4, 0, 0], [-4, 0, 0]],
                                                                       targets=[[-4, 0, 0], [4, 0, 0]])),
     "config has dim = 2"),
    ("scenario-unknown-key", lambda t, a: run_scenario(t, {"starts": [[4, 0], [-4, 0]], "target": [[0, 1], [1, 0]]}),
     "did you mean 'targets'"),
    ("scenario-missing-targets", lambda t, a: run_scenario(t, {"starts": [[4, 0], [-4, 0]]}), "missing key 'targets'"),
    ("scenario-empty-starts", lambda t, a: run_scenario(t, valid_scenario(starts=[])), "non-empty"),
    ("scenario-string-coordinate", lambda t, a: run_scenario(t, valid_scenario(starts=[["4", 0], [-4, 0]])),
     "give a number"),
    ("scenario-bool-coordinate", lambda t, a: run_scenario(t, valid_scenario(starts=[[True, 0], [-4, 0]])),
     "give a number"),
    ("scenario-ref-points-one", lambda t, a: run_scenario(t, valid_scenario(ref_points=1)), "'ref_points' is 1"),
    ("scenario-reference-unknown", lambda t, a: run_scenario(t, valid_scenario(reference="curve")), "'reference' is"),
    ("scenario-unparsable", lambda t, a: run_scenario(t, '{"starts": [[4, 0], '), "cannot be parsed"),
    ("scenario-not-a-table", lambda t, a: run_scenario(t, "[[4, 0]]"), "expected a table"),
    ("scenario-missing-file", lambda t, a: run(t, "--scenario", str(t / "none.json")), "does not exist"),
    ("scenario-unknown-suffix", lambda t, a: run_scenario(t, "x", name="s.yaml"), "use .json or .toml"),
    # ---- GP model files for `gpmpc run --gp-model`
    ("model-random-bytes", lambda t, a: run_model(t, write(t, "m.pt", os.urandom(512))), "cannot be read"),
    ("model-empty-file", lambda t, a: run_model(t, write(t, "m.pt", b"")), "the file is empty"),
    ("model-is-transitions", lambda t, a: run_model(t, write_npz(t, **arrays())), "gpmpc fit-gp --transitions t.npz"),
    ("model-truncated", lambda t, a: run_model(t, _truncated(a.gp2, t, "m.pt")), "cannot be read"),
    ("model-bit-flipped-header", lambda t, a: run_model(t, _bitflipped(a.gp2, t, "m.pt")), "corrupt"),
    ("model-bit-flipped-tensor", lambda t, a: run_model(t, _flip_tensor_bytes(a.gp2, t)), "checksum mismatch"),
    ("model-tampered-values", lambda t, a: run_model(t, edited_model(
        t, a.gp2, lambda p: p["train_y"].mul_(2.0), rehash=False)), "checksum mismatch"),
    ("model-wrong-dimension", lambda t, a: run_model(t, a.gp3), "D=3 residual dimensions but D=2 is required"),
    ("model-state-input-kind", lambda t, a: run_model(t, a.gp_state_input), "Din=4 inputs"),
    ("model-malicious-torch-zip", lambda t, a: run_model(t, malicious_torch_zip(t)), "refused to load"),
    ("model-malicious-raw-pickle", lambda t, a: run_model(t, malicious_raw_pickle(t)), "only files written by"),
    ("model-foreign-torch-file", lambda t, a: run_model(t, (torch.save({"w": torch.ones(3, dtype=torch.float64)}, t / "m.pt"), t / "m.pt")[1]),
     "not a torch_gpmpc ResidualGP file"),
    ("model-wrong-version", lambda t, a: run_model(t, edited_model(t, a.gp2, lambda p: p.update(version=99))),
     "unsupported version 99"),
    ("model-nan-hyperparameter", lambda t, a: run_model(t, edited_model(t, a.gp2, _nan_lengthscale)), "NaN/inf"),
    ("model-inconsistent-shapes", lambda t, a: run_model(t, edited_model(t, a.gp2, lambda p: p.update(x_mean=torch.zeros(5, dtype=torch.float64)))),
     "'x_mean' has shape (5,)"),
    ("model-missing-file", lambda t, a: run_model(t, t / "none.pt"), "file not found"),
    ("model-with-non-gp-method", lambda t, a: run(t, "--method", "nominal", "--gp-model", str(write(t, "m.pt", b"xx"))),
     "cannot be read"),
]


class _StderrLogs:
    """Route WARNING log records to (captured) stderr, as the console script does."""

    def __enter__(self):
        self.handler = logging.StreamHandler(sys.stderr)
        self.handler.setLevel(logging.WARNING)
        logging.getLogger().addHandler(self.handler)
        return self

    def __exit__(self, *exc):
        logging.getLogger().removeHandler(self.handler)


def _leftovers(tmp: Path) -> list[Path]:
    return [p for p in tmp.rglob(".*") if ".tmp" in p.name]


@pytest.mark.parametrize("build, expect", [pytest.param(b, e, id=i) for i, b, e in CLI_CASES])
def test_cli_rejects_bad_input(build, expect, assets, tmp_path, capsys):
    argv, out = build(tmp_path, assets)
    before = set(tmp_path.rglob("*"))
    capsys.readouterr()
    with _StderrLogs():
        try:
            code = main(argv)
        except SystemExit as exc:  # argparse usage errors exit (the console script's behaviour)
            code = exc.code
    captured = capsys.readouterr()
    lines = captured.err.strip().splitlines()
    assert code == 2, captured
    assert len(lines) == 1, captured.err
    assert lines[0].startswith("gpmpc"), lines[0]
    assert "Traceback" not in captured.err and "error:" in lines[0]
    assert expect in lines[0], lines[0]
    assert captured.out == ""
    assert not out.exists(), f"partial output {out}"
    assert set(tmp_path.rglob("*")) == before, "the failed command created files"
    assert _leftovers(tmp_path) == []
    assert not _pwned(tmp_path).exists()


def test_debug_flag_shows_the_traceback(assets, tmp_path):
    argv, _ = run(tmp_path, "--set", "horizon=0")
    with pytest.raises(GpmpcError, match="horizon"):
        main(["--debug", *argv])


def test_malicious_model_never_runs(tmp_path):
    """Unpickling these would create PWNED: refused, through the API too, and nothing is created."""
    for path in (malicious_torch_zip(tmp_path), malicious_raw_pickle(tmp_path)):
        with pytest.raises(GpmpcError, match="GP model file"):
            ResidualGP.load(path)
    assert not _pwned(tmp_path).exists()
    # the payloads are real: plain pickle would have created the file
    pickle.loads(pickle.dumps(_OpenFile(str(_pwned(tmp_path))))).close()
    assert _pwned(tmp_path).exists()


# ========================================================================= API table
def _gp_bad_query(a: Assets):
    ResidualGP.load(a.gp2).predict(torch.zeros(3, 5, dtype=F64))


API_CASES = [
    ("api-config-misspelt-keyword", lambda a: Config(admm_couplng="copies"),
     "unknown config key 'admm_couplng'; did you mean 'admm_coupling'?"),
    ("api-config-removed-keyword", lambda a: Config(admm_acceleration="anderson"),
     "config key 'admm_acceleration': Anderson acceleration was removed: it gained nothing in a crowd"),
    ("api-transitions-nan", lambda a: Transitions(*with_value(np.nan).values()), "non-finite"),
    ("api-transitions-shape", lambda a: Transitions(np.zeros((4, 2)), np.zeros((3, 2)), np.zeros((4, 2))),
     "shape mismatch"),
    ("api-transitions-save-suffix", lambda a: Transitions.load(a.npz).save(a.npz.with_suffix(".h5")), "unknown suffix"),
    ("api-split-fraction", lambda a: Transitions.load(a.npz).split(1.0), "holdout fraction"),
    ("api-for-agent-without-column", lambda a: Transitions(*arrays().values()).for_agent(0), "no 'agent' column"),
    ("api-check-dim", lambda a: Transitions.load(a.npz).check_dim(3), "does not match the model's D=3"),
    ("api-collect-one-sample", lambda a: collect_transitions(make_system(2, 0.1), samples=1), "samples must be >= 2"),
    ("api-fit-one-point", lambda a: fit_residual_gp(torch.zeros(1, 2, dtype=torch.float64), torch.zeros(1, 2, dtype=torch.float64)), "N >= 2"),
    ("api-fit-nan", lambda a: fit_residual_gp(torch.full((4, 2), float("nan"), dtype=torch.float64), torch.zeros(4, 2, dtype=torch.float64)), "NaN or inf"),
    ("api-fit-optimizer", lambda a: fit_residual_gp(torch.rand(4, 2, dtype=torch.float64), torch.rand(4, 2, dtype=torch.float64), optimizer="sgd"),
     "optimizer must be"),
    ("api-gp-query-shape", _gp_bad_query, "query points must have shape (n, 2)"),
    ("api-gp-load-expected-dim", lambda a: ResidualGP.load(a.gp2, expected_dim=3), "D=3 is required"),
    ("api-config-horizon", lambda a: Config(horizon=0), "'horizon': 0 is out of range"),
    ("api-config-type", lambda a: Config(eps="0.1"), "expected float, got str"),
    ("api-config-unknown", lambda a: load_config(overrides={"u_maxx": 1.0}), "did you mean 'u_max'"),
    ("api-config-replace", lambda a: Config().replace(r_safe=-1.0), "'r_safe'"),
    ("api-scenario-nan", lambda a: Scenario(torch.tensor([[float("nan"), 0.0]], dtype=torch.float64), torch.zeros(1, 2, dtype=torch.float64)), "finite"),
    ("api-scenario-shape", lambda a: Scenario(torch.zeros(2, 2, dtype=torch.float64), torch.zeros(3, 2, dtype=torch.float64)), "shape (K, D)"),
    ("api-scenario-random-crowded", lambda a: make_scenario(Config(scenario="random", num_agents=30,
                                                                   min_separation=3.0, circle_radius=2.0)),
     "could not place"),
    ("api-simulate-gp-dim", lambda a: __import__("torch_gpmpc.sim.closed_loop", fromlist=["simulate"]).simulate(
        Config(method="gp", max_steps=1), gps=[ResidualGP.load(a.gp3)]), "dimension 3/3"),
    ("api-local-problem-shape", lambda a: _small_layer()(
        _problem(torch.zeros(1, 2, dtype=F64), PT, PM)._replace_x0(torch.zeros(1, 3, dtype=F64))),
     "x0 must have shape"),
    ("api-rollout-corrupt", lambda a: Rollout.load(_bitflip_file(a)), "cannot be read"),
]


def _bitflip_file(a: Assets) -> Path:
    path = a.npz.parent / "rollout_bad.npz"
    path.write_bytes(b"PK\x03\x04" + b"\x00" * 64)
    return path


@pytest.mark.parametrize("call, expect", [pytest.param(c, e, id=i) for i, c, e in API_CASES])
def test_api_rejects_bad_input(call, expect, assets):
    with pytest.raises(GpmpcError) as info:
        call(assets)
    message = str(info.value)
    assert expect in message, message
    assert "\n" not in message


# ==================================================================== local problems
class _Data(LocalProblemData):
    def _replace_x0(self, x0):
        return _Data(**{**vars(self), "x0": x0})


def _problem(x0: torch.Tensor, T: int, M: int, **kw) -> _Data:
    """A local problem with identity dynamics, reference = x0, zero duals (overridable)."""
    B, D = x0.shape
    base = dict(
        x0=x0, xref=x0[:, None].expand(B, T + 1, D).clone(),
        dyn_A=torch.eye(D, dtype=F64).expand(B, T, D, D).clone(), dyn_c=torch.zeros(B, T, D, dtype=F64),
        normals=torch.zeros(B, M, T, D, dtype=F64), bounds=torch.zeros(B, M, T, dtype=F64),
        active=torch.ones(B, M, dtype=torch.bool), rho=torch.tensor(1.0, dtype=F64),
        z_own=torch.zeros(B, M, T + 1, D, dtype=F64), z_nbr=torch.zeros(B, M, T + 1, D, dtype=F64),
        lam_own=torch.zeros(B, M, T + 1, D, dtype=F64), lam_nbr=torch.zeros(B, M, T + 1, D, dtype=F64))
    base.update(kw)
    return _Data(**base)


PT, PD, PM = 4, 2, 1
U_MAX = 2.0


def _residuals(data: LocalProblemData, sol) -> dict[str, float]:
    """Constraint violations of a returned solution (independent of CvxpyLayerMPC's own check)."""
    B = NominalModel(PD).B(dtype=F64)
    X, U, Y, s = sol.X, sol.U, sol.Y, sol.slack
    pred = (data.dyn_A @ X[:, :-1, :, None]).squeeze(-1) + U @ B.T + data.dyn_c
    gap = (data.normals * (X[:, None, 1:] - Y[:, :, 1:])).sum(-1)
    return {
        "x0": float((X[:, 0] - data.x0).abs().max()),
        "dynamics": float((X[:, 1:] - pred).abs().max()),
        "input": float((U.norm(dim=-1) - U_MAX).clamp(min=0).max()),
        "slack_sign": float((-s).clamp(min=0).max()),
        "collision": float((data.bounds - gap - s).clamp(min=0).max()),
    }


unit = st.floats(-1, 1, allow_nan=False, allow_infinity=False)


@st.composite
def local_instances(draw, pinned: bool):
    """Random local problems; ``pinned``: the neighbour copy is held on the agent by a huge rho."""
    def tensor(shape, lo, hi):
        flat = draw(st.lists(st.floats(lo, hi, allow_nan=False), min_size=int(np.prod(shape)),
                             max_size=int(np.prod(shape))))
        return torch.tensor(flat, dtype=F64).reshape(shape)

    x0 = tensor((1, PD), -2, 2)
    angle = draw(st.floats(0, 2 * np.pi))
    normal = torch.tensor([np.cos(angle), np.sin(angle)], dtype=F64)
    normals = normal.expand(1, PM, PT, PD).clone()
    dyn_A = torch.eye(PD, dtype=F64) + tensor((1, PT, PD, PD), -0.01, 0.01)
    dyn_c = tensor((1, PT, PD), -0.02, 0.02)
    xref = x0[:, None] + tensor((1, PT + 1, PD), -3, 3)
    bound = draw(st.floats(0.5, 1.5)) if pinned else draw(st.floats(0.0, 1.0))
    bounds = torch.full((1, PM, PT), bound, dtype=F64)
    if pinned:
        # neighbour copy pinned on the agent's start: X can move <= 0.2 + drift per step, the
        # copy ~slack_penalty / rho = 1e-3: the first collision row cannot hold without slack
        rho = torch.tensor(1e7, dtype=F64)
        z_nbr = x0[:, None, None].expand(1, PM, PT + 1, PD).clone()
        z_own = z_nbr.clone()
    else:
        rho = torch.tensor(draw(st.floats(0.1, 100.0)), dtype=F64)
        z_own = x0[:, None, None] + tensor((1, PM, PT + 1, PD), -1, 1)
        z_nbr = x0[:, None, None] + tensor((1, PM, PT + 1, PD), -3, 3)
    return _problem(x0, PT, PM, xref=xref, dyn_A=dyn_A, dyn_c=dyn_c, normals=normals, bounds=bounds,
                    rho=rho, z_own=z_own, z_nbr=z_nbr)


def _small_layer():
    return make_local_solver(PT, PD, PM, NominalModel(PD), U_MAX, 1e-3, 1e4, "clarabel")


@pytest.fixture(scope="module")
def small_layer():
    return _small_layer()


@settings(max_examples=20, deadline=None, database=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(data=local_instances(pinned=False))
def test_property_local_problem_feasible_instances_hold_constraints(small_layer, data):
    sol = small_layer(data)
    assert sol.ok.all() and (sol.failure == 0).all()
    res = _residuals(data, sol)
    assert max(res.values()) < 1e-6, res
    # the neighbour copy is free (rho <= 100): no slack is worth its 1e4 penalty
    assert not sol.slack_active.any(), sol.slack.max()


@settings(max_examples=15, deadline=None, database=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(data=local_instances(pinned=True))
def test_property_local_problem_infeasible_instances_report_slack(small_layer, data):
    sol = small_layer(data)
    assert sol.ok.all()  # softened, not failed
    assert sol.slack_active.all() and float(sol.slack[:, :, 0].min()) > 1e-3
    res = _residuals(data, sol)
    assert res["collision"] < 1e-5 and res["dynamics"] < 1e-6 and res["input"] < 1e-6, res


# ============================================================= transitions property tests
finite = st.floats(-1e5, 1e5, allow_nan=False, allow_infinity=False, width=64)


@st.composite
def transition_arrays(draw):
    n = draw(st.integers(2, 12))
    d = draw(st.integers(1, 3))
    du = draw(st.integers(1, 3))
    flat = draw(st.lists(finite, min_size=n * (2 * d + du), max_size=n * (2 * d + du)))
    table = np.array(flat, dtype=np.float64).reshape(n, 2 * d + du)
    table[:, 0] = np.arange(n)  # distinct rows: no de-duplication in the round trip
    agent = np.array(draw(st.lists(st.integers(0, 3), min_size=n, max_size=n))) if draw(st.booleans()) else None
    return table[:, :d], table[:, d:d + du], table[:, d + du:], agent


@settings(max_examples=25, deadline=None, database=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(arrs=transition_arrays(), suffix=st.sampled_from([".npz", ".csv"]))
def test_property_transitions_round_trip(tmp_path, arrs, suffix):
    x, u, x_next, agent = arrs
    path = tmp_path / f"rt{suffix}"
    Transitions(x, u, x_next, agent).save(path)
    back = Transitions.load(path)
    np.testing.assert_array_equal(back.x.numpy(), x)
    np.testing.assert_array_equal(back.u.numpy(), u)
    np.testing.assert_array_equal(back.x_next.numpy(), x_next)
    assert (back.agent is None) == (agent is None)
    if agent is not None:
        np.testing.assert_array_equal(back.agent.numpy(), agent)
    assert _leftovers(tmp_path) == []


@st.composite
def corruptions(draw):
    kind = draw(st.sampled_from(["truncate", "flip", "insert", "delete", "replace-cell"]))
    pos = draw(st.floats(0, 1))
    size = draw(st.integers(1, 64))
    blob = draw(st.binary(min_size=1, max_size=64))
    return kind, pos, size, blob


def _corrupt(data: bytes, kind: str, pos: float, size: int, blob: bytes) -> bytes:
    i = int(pos * (len(data) - 1))
    if kind == "truncate":
        return data[:i]
    if kind == "flip":
        out = bytearray(data)
        for j in range(i, min(i + size, len(out))):
            out[j] ^= blob[(j - i) % len(blob)] | 1
        return bytes(out)
    if kind == "insert":
        return data[:i] + blob + data[i:]
    if kind == "delete":
        return data[:i] + data[i + size:]
    return data[:i] + blob + data[i + len(blob):]


@pytest.fixture(scope="module")
def clean_files(tmp_path_factory):
    root = tmp_path_factory.mktemp("clean")
    rng = np.random.default_rng(5)
    t = Transitions(rng.normal(size=(8, 2)), rng.normal(size=(8, 2)), rng.normal(size=(8, 2)),
                    np.arange(8) % 2)
    files = {}
    for suffix in (".npz", ".csv"):
        files[suffix] = root / f"clean{suffix}"
        t.save(files[suffix])
    return {k: v.read_bytes() for k, v in files.items()}


@settings(max_examples=60, deadline=None, database=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(c=corruptions(), suffix=st.sampled_from([".npz", ".csv"]))
def test_property_corrupt_transitions_raise_only_gpmpc_error(tmp_path, clean_files, c, suffix):
    path = tmp_path / f"corrupt{suffix}"
    path.write_bytes(_corrupt(clean_files[suffix], *c))
    try:
        t = Transitions.load(path)
    except GpmpcError as exc:
        assert "\n" not in str(exc) and str(path) in str(exc)
    else:  # a benign corruption (e.g. a changed digit): what loads is valid
        assert t.num_samples >= 2 and bool(torch.isfinite(t.x).all())


@settings(max_examples=30, deadline=None, database=None)
@given(n=st.integers(0, 4), d=st.integers(0, 3), bad=st.sampled_from([np.nan, np.inf, -np.inf, 1e7, None]),
       shift=st.integers(-1, 1))
def test_property_transitions_constructor_rejects_with_gpmpc_error(n, d, bad, shift):
    rng = np.random.default_rng(n + 10 * d)
    x = rng.normal(size=(n, d))
    x_next = rng.normal(size=(max(n + shift, 0), d))
    u = rng.normal(size=(n, max(d, 1)))
    if bad is not None and n and d:
        x[0, 0] = bad
    try:
        Transitions(x, u, x_next)
    except GpmpcError:
        pass
    else:
        assert n >= 2 and d >= 1 and shift == 0 and bad is None


# ====================================================================== solver faults
class FaultyLayer(torch.nn.Module):
    """Wraps a CvxpyLayer; corrupts agent ``k``'s problem on the calls in ``when``.

    Modes: ``exception`` (the solver raises for that problem), ``nan`` (its rows come
    back NaN), ``inaccurate`` (its inputs are perturbed: dynamics no longer hold).
    """

    def __init__(self, real, mode: str, k: int, when: set[int]):
        super().__init__()
        self.real, self.mode, self.k, self.when = real, mode, k, when
        self.batched_calls = 0
        self.injected = 0
        self._single = None  # index of the next one-by-one retry

    def forward(self, *params, solver_args=None):
        batch = params[0].shape[0]
        if batch > 1:
            self.batched_calls += 1
            self._single = None
            if self.batched_calls in self.when:
                if self.mode == "exception":
                    self._single = 0
                    raise RuntimeError("injected solver failure")
                out = [o.clone() for o in self.real(*params, solver_args=solver_args)]
                self.injected += 1
                if self.mode == "nan":
                    out[0][self.k] = float("nan")
                else:
                    out[1][self.k] += 0.5  # U: X no longer follows the dynamics
                return tuple(out)
            return self.real(*params, solver_args=solver_args)
        if self._single is not None:  # one-by-one retry after a batched exception
            b, self._single = self._single, self._single + 1
            if b == self.k:
                self.injected += 1
                raise RuntimeError("injected solver failure")
        return self.real(*params, solver_args=solver_args)


@contextlib.contextmanager
def patched_solver(local_mpc, mode: str, k: int, when: set[int]):
    """Temporarily wrap ``local_mpc.layer`` (a controller's own solver) in a :class:`FaultyLayer`.

    (``monkeypatch.setattr`` cannot restore an ``nn.Module`` child: it lives in ``_modules``.)
    """
    real = local_mpc.layer
    faulty = FaultyLayer(real, mode, k, when)
    local_mpc.layer = faulty
    try:
        yield faulty
    finally:
        local_mpc.layer = real


# the injector wraps the cvxpylayers layer (and its one-by-one retry); the fast path has its own test
FAULT_CFG = dict(horizon=4, max_steps=6, admm_max_iter=4, method="nominal", noise_std=0.0, solver="clarabel",
                 terminal_cost="stage")  # the injector wraps the default-cost layer


@pytest.mark.parametrize("mode, kind", [("exception", "exception"), ("nan", "non-finite"),
                                        ("inaccurate", "inaccurate")])
def test_solver_faults_fall_back_count_and_warn_once(mode, kind, caplog, tmp_path, monkeypatch):
    from torch_gpmpc.sim.closed_loop import simulate

    import torch_gpmpc.coordination.agent_step as agent_step

    cfg = Config(**FAULT_CFG)
    real, made = agent_step.make_local_solver, []

    def faulty_factory(*args, **kwargs):  # the controller's own solver, its layer wrapped
        solver = real(*args, **kwargs)
        solver.layer = FaultyLayer(solver.layer, mode, 1, {1, 2, 4, 6, 7})
        made.append(solver.layer)
        return solver

    monkeypatch.setattr(agent_step, "make_local_solver", faulty_factory)
    with caplog.at_level(logging.WARNING):
        rollout = simulate(cfg)
    assert len(made) == 1  # one solver: 3 agents, 2 neighbours each
    faulty = made[0]
    assert rollout.num_steps == cfg.max_steps  # the run went on
    n = faulty.injected
    assert n >= 3, n
    m = compute_metrics(rollout)
    assert m["failed_local_solves"] == n and int(rollout.failed_solves.sum()) == n
    assert m["failed_local_solves_by_kind"] == {k: (n if k == kind else 0) for k in FAILURE_KINDS}
    assert rollout.failed_solves_by_kind.shape == (cfg.max_steps, 3)
    assert m["infeasible_local_solves"] >= n
    assert np.isfinite(rollout.states).all() and np.isfinite(rollout.inputs).all()
    warnings = [r for r in caplog.records if r.levelno >= logging.WARNING]
    assert len(warnings) == 1, [r.getMessage() for r in warnings]
    assert f"local MPC solve failed ({kind}" in warnings[0].getMessage()
    # contract keys stay; the new ones round-trip through the files
    out = tmp_path / "rollout.npz"
    rollout.save(out)
    back = Rollout.load(out)
    assert compute_metrics(back)["failed_local_solves"] == n


def test_failed_agent_keeps_its_previous_shifted_plan():
    """The first ADMM iteration of step 2 fails for agent 1: it uses step 1's plan shifted."""
    from torch_gpmpc.coordination.admm import ADMM
    from torch_gpmpc.coordination.graph import communication_graph

    cfg = Config(**{**FAULT_CFG, "admm_max_iter": 1})
    scen = make_scenario(cfg)
    admm = ADMM(LocalStep(cfg, cfg.model_spec()))
    x0 = scen.starts
    graph = communication_graph(x0, cfg.comm_radius)
    first = admm.solve_step(x0, scen.reference_window(0, cfg.horizon), graph)
    warm = first.state.shifted()
    x1 = first.plans[:, 1]
    with patched_solver(admm.agent_step.solver(graph.num_slots), "nan", k=1, when={1}):
        second = admm.solve_step(x1, scen.reference_window(1, cfg.horizon), graph, warm=warm)
    assert second.failed_solves == 1 and second.failed_by_kind["non-finite"] == 1
    torch.testing.assert_close(second.plans[1], warm.plans[1])
    torch.testing.assert_close(second.inputs[1], warm.inputs[1])
    assert torch.isfinite(second.plans).all()


def test_layer_exception_escaping_the_layer_fails_all_agents_not_the_run(monkeypatch, caplog):
    """A fault outside the solver call (the whole layer raises): every agent falls back."""
    import torch_gpmpc.coordination.agent_step as admm_mod
    from torch_gpmpc.sim.closed_loop import simulate

    real = admm_mod.make_local_solver
    calls = {"n": 0}

    def flaky_factory(*args, **kwargs):
        layer = real(*args, **kwargs)

        def call(data):
            calls["n"] += 1
            if calls["n"] == 2:
                raise RuntimeError("layer exploded")
            return layer(data)
        return call

    monkeypatch.setattr(admm_mod, "make_local_solver", flaky_factory)
    with caplog.at_level(logging.WARNING):
        rollout = simulate(Config(**{**FAULT_CFG, "max_steps": 2}))
    m = compute_metrics(rollout)
    assert m["failed_local_solves_by_kind"]["exception"] == 3
    assert "layer exploded" in caplog.text


def test_interrupt_wrapped_by_c_code_stops_the_run_instead_of_falling_back(monkeypatch):
    """Ctrl-C that arrives while compiled code calls back into Python comes out as
    ``SystemError(...) from KeyboardInterrupt`` (seen with numba); it must stop the run."""
    import torch_gpmpc.coordination.agent_step as admm_mod
    from torch_gpmpc.sim.closed_loop import simulate

    def interrupted_factory(*args, **kwargs):
        def call(data):
            try:
                raise KeyboardInterrupt
            except KeyboardInterrupt as interrupt:
                raise SystemError("returned a result with an exception set") from interrupt
        return call

    monkeypatch.setattr(admm_mod, "make_local_solver", interrupted_factory)
    with pytest.raises(KeyboardInterrupt):
        simulate(Config(**{**FAULT_CFG, "max_steps": 2}))


# ===================================================================== interrupted runs
def _check_output_dir(out: Path) -> None:
    """Every file in ``out`` is complete: metrics.json parses, rollout.npz loads, no temp files."""
    if (out / "metrics.json").exists():
        json.loads((out / "metrics.json").read_text())
    if (out / "rollout.npz").exists():
        Rollout.load(out / "rollout.npz")
    for png in (out / "figures").glob("*.png") if (out / "figures").exists() else ():
        assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    if (out / "tb").exists():
        from torch_gpmpc.report.tensorboard import read_scalars

        read_scalars(out / "tb")  # events are append-only records; a short file still reads


def _start_run(out: Path) -> subprocess.Popen:
    # A runner started in the background (nohup, `cmd &`) passes SIGINT on as *ignored*, and
    # Python then installs no KeyboardInterrupt handler; give the child the default handler
    # so the test does not depend on how its runner was launched.
    code = ("import signal, sys; signal.signal(signal.SIGINT, signal.default_int_handler); "
            "from torch_gpmpc.cli import main; sys.exit(main(sys.argv[1:]))")
    return subprocess.Popen(
        [sys.executable, "-c", code, "run", "--method", "nominal", "--out", str(out), "--no-figures",
         "--set", "max_steps=150", "--set", "horizon=13", "--set", "admm_coupling=copies"],  # long enough to kill
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, env={**os.environ, "PYTHONUNBUFFERED": "1"})


def _wait_until_running(proc: subprocess.Popen, out: Path, timeout: float = 60.0) -> None:
    deadline = time.time() + timeout
    while not (out / "tb").exists():  # created just before the closed loop starts
        assert proc.poll() is None, proc.communicate()
        assert time.time() < deadline, "run did not start"
        time.sleep(0.1)
    time.sleep(1.0)  # a few closed-loop steps


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGKILL], ids=["sigint", "sigkill"])
def test_killed_run_leaves_no_corrupt_output(tmp_path, sig):
    out = tmp_path / "run"
    proc = _start_run(out)
    try:
        _wait_until_running(proc, out)
        proc.send_signal(sig)
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    if sig == signal.SIGINT:
        assert proc.returncode == 130, err
        assert "interrupted" in err.decode().strip().splitlines()[-1]
        assert not (out / "metrics.json").exists() and not (out / "rollout.npz").exists()
    else:
        assert proc.returncode == -signal.SIGKILL
    _check_output_dir(out)
    assert _leftovers(out) == []


def test_interrupt_while_writing_leaves_no_partial_file(tmp_path, monkeypatch, capsys):
    """Ctrl-C in the middle of writing rollout.npz: the final name never appears half-written."""
    real = np.savez_compressed

    def interrupted(fh, **arrays):
        fh.write(b"PK\x03\x04partial")
        raise KeyboardInterrupt

    monkeypatch.setattr(np, "savez_compressed", interrupted)
    out = tmp_path / "run"
    code = main(["run", "--method", "nominal", "--out", str(out), "--no-figures", "--set", "max_steps=1",
                 "--set", "admm_max_iter=1", "--set", "horizon=4"])
    assert code == 130 and "interrupted" in capsys.readouterr().err
    assert not (out / "rollout.npz").exists() and not (out / "metrics.json").exists()
    assert _leftovers(out) == []
    monkeypatch.setattr(np, "savez_compressed", real)


def test_fast_solver_rejects_bad_problem_and_run_falls_back(monkeypatch, caplog):
    """The default fast path: agent 1's problem data turns non-finite on some calls. The
    solver flags that row (never raises), ADMM falls back, counts it and warns once."""
    from torch_gpmpc.control.solvers.interior_point import InteriorPointMPC
    from torch_gpmpc.sim.closed_loop import simulate

    real_forward = InteriorPointMPC.forward
    calls = {"n": 0, "injected": 0}

    def corrupting_forward(self, data, guess=None):
        calls["n"] += 1
        if calls["n"] in {2, 3, 5}:
            xref = data.xref.clone()
            xref[1] = float("nan")
            data = dataclasses.replace(data, xref=xref)
            calls["injected"] += 1
        return real_forward(self, data, guess)

    monkeypatch.setattr(InteriorPointMPC, "forward", corrupting_forward)
    cfg = Config(**{**FAULT_CFG, "solver": "fast"})
    with caplog.at_level(logging.WARNING):
        rollout = simulate(cfg)
    assert rollout.num_steps == cfg.max_steps
    m = compute_metrics(rollout)
    assert calls["injected"] == 3
    assert m["failed_local_solves"] == 3
    assert m["failed_local_solves_by_kind"]["non-finite"] == 3
    assert np.isfinite(rollout.states).all()
    warnings = [r for r in caplog.records if r.levelno >= logging.WARNING]
    assert len(warnings) == 1 and "non-finite" in warnings[0].getMessage()
