"""Config: flat keys from files and --set, strict errors naming the nearest key."""

from __future__ import annotations

import json

import pytest

from torch_gpmpc.config import Config, load_config, parse_overrides
from torch_gpmpc.errors import GpmpcError


def test_defaults_are_the_paper_scenario():
    c = Config()
    assert (c.horizon, c.rho, c.r_safe, c.eps, c.u_max, c.alpha, c.goal_tol, c.max_steps) == (
        13, 20.0, 0.5, 0.1, 2.0, 1e-3, 0.1, 150)
    assert (c.num_agents, c.method, c.noise_std, c.risk_split) == (3, "gp-chance", 0.1, 0.5)


def test_file_then_overrides(tmp_path):
    f = tmp_path / "c.toml"
    f.write_text('rho = 5\nmethod = "nominal"\ncomm_radius = 3.0\n')
    c = load_config(f, parse_overrides(["rho=7.5", "admm_tol=1e-4"]))
    assert (c.rho, c.method, c.comm_radius, c.admm_tol) == (7.5, "nominal", 3.0, 1e-4)
    j = tmp_path / "c.json"
    j.write_text(json.dumps({"horizon": 5}))
    assert load_config(j).horizon == 5


@pytest.mark.parametrize(
    "data, fragment",
    [
        ({"rhoo": 1}, "did you mean 'rho'"),
        ({"horizn": 3}, "did you mean 'horizon'"),
        ({"horizon": 1.5}, "expected int"),
        ({"horizon": 0}, "'horizon'"),
        ({"eps": 1.5}, "(0, 1)"),
        ({"eps": 0}, "(0, 1)"),
        ({"u_max": -1}, "'u_max'"),
        ({"r_safe": -0.1}, "'r_safe'"),
        ({"method": "mpc"}, "gp-chance"),
        ({"rho": "big"}, "expected float"),
        ({"rho": float("nan")}, "not finite"),
        ({"num_agents": 5}, "scenario=circle"),
    ],
)
def test_bad_values_name_the_key_and_fix(data, fragment):
    with pytest.raises(GpmpcError, match=None) as exc:
        load_config(overrides=data)
    assert fragment in str(exc.value)


def test_bad_files(tmp_path):
    with pytest.raises(GpmpcError, match="does not exist"):
        load_config(tmp_path / "missing.toml")
    bad = tmp_path / "bad.toml"
    bad.write_text("rho = = 3")
    with pytest.raises(GpmpcError, match="cannot be parsed"):
        load_config(bad)
    with pytest.raises(GpmpcError, match="NAME=VALUE"):
        parse_overrides(["rho"])


def test_retired_gp_noise_in_margin_maps_onto_margin_variance():
    with pytest.warns(FutureWarning, match="margin_variance=predictive"):
        assert load_config(None, {"gp_noise_in_margin": True}).margin_variance == "predictive"
    with pytest.warns(FutureWarning, match="margin_variance=latent"):
        cfg = load_config(None, {"gp_noise_in_margin": False})
    assert cfg.margin_variance == "latent" and "gp_noise_in_margin" not in cfg.to_dict()
    assert Config().pair_margin == "sum" and Config().margin_variance == "predictive"
    with pytest.raises(GpmpcError, match="pair_margin"):
        Config(pair_margin="max")


def test_a_file_from_before_anderson_was_removed_loads_and_asking_for_it_is_refused():
    """A tuned.json or config file that holds ``admm_acceleration = off`` (and its memory) loads with a
    warning; ``anderson`` is refused with the reason, in files and from Python."""
    with pytest.warns(FutureWarning, match="admm_acceleration' is retired"):
        cfg = load_config(None, {"admm_acceleration": "off", "admm_anderson_memory": 5, "rho": 3.0})
    assert cfg.rho == 3.0 and "admm_acceleration" not in cfg.to_dict()
    with pytest.raises(GpmpcError, match="'admm_acceleration': Anderson acceleration was removed"):
        load_config(None, {"admm_acceleration": "anderson"})
    with pytest.raises(GpmpcError, match="'admm_anderson_memory': Anderson acceleration was removed"):
        Config(admm_anderson_memory=5)


def test_the_command_line_shows_a_retired_key_as_one_warning_line(tmp_path, capsys):
    """Python hides DeprecationWarning by default, so the user never saw this one: it is a
    FutureWarning, and ``gpmpc`` prints it as one line like its errors."""
    import warnings

    from torch_gpmpc.cli import main

    with warnings.catch_warnings():
        warnings.simplefilter("always")  # whatever the test session's filters say
        code = main(["run", "--set", "gp_noise_in_margin=true", "--no-figures", "--set", "max_steps=1",
                     "--set", "admm_max_iter=1", "--set", "gp_iters=1", "--out", str(tmp_path / "run")])
    assert code == 0
    assert ("gpmpc run: warning: config key 'gp_noise_in_margin' is deprecated; it means "
            "margin_variance=predictive") in capsys.readouterr().err.splitlines()
