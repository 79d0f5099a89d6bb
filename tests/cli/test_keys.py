"""``gpmpc keys``: the config keys in the terminal, from the schema."""

from __future__ import annotations

import dataclasses

import pytest

from torch_gpmpc.cli.entry import main
from torch_gpmpc.config.reference import config_keys
from torch_gpmpc.config.schema import Config


def test_keys_are_every_config_field_with_its_default_and_rules():
    keys = {k.name: k for k in config_keys()}
    assert list(keys) == [f.name for f in dataclasses.fields(Config)]
    assert keys["admm_coupling"].allowed == "copies, planes" and keys["admm_coupling"].default == Config().admm_coupling
    assert "admm_coupling" in keys["rho_update"].applies  # ignored under the planes, with a warning
    assert keys["horizon"].meaning  # every key says what it means
    assert all(k.meaning for k in keys.values()), [k.name for k in keys.values() if not k.meaning]


def test_gpmpc_keys_prints_a_named_key_a_word_or_says_none_matches(capsys):
    assert main(["keys", "admm_coupling"]) == 0
    out = capsys.readouterr().out
    assert out.startswith("admm_coupling = 'planes'  (str)") and "allowed: copies, planes" in out
    assert out.count(" = ") == 1  # only the key named
    assert main(["keys", "admm"]) == 0
    assert capsys.readouterr().out.count("\n\n") >= 5
    assert main(["keys", "no-such-word"]) == 2
    assert "no config key mentions 'no-such-word'" in capsys.readouterr().err


@pytest.mark.parametrize("argv", [["keys", "--help"]])
def test_keys_help_says_what_word_filters(argv, capsys):
    with pytest.raises(SystemExit):
        main(argv)
    assert "WORD" in capsys.readouterr().out
