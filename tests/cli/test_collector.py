"""The console script's garbage-collector settings (torch_gpmpc.cli.collector)."""

import gc

import pytest

from torch_gpmpc.cli import collector, main


@pytest.fixture
def owned(monkeypatch):
    """This process as the console script's; the permanent generation emptied afterwards."""
    monkeypatch.setattr(collector, "_process_owned", True)
    yield
    gc.unfreeze()
    gc.enable()


def test_setup_phase_collects_nothing_inside_and_freezes_what_it_built(owned):
    before = gc.get_freeze_count()
    with collector.setup_phase():
        assert not gc.isenabled()
        built = [object() for _ in range(100)]
    assert gc.isenabled()
    assert gc.get_freeze_count() >= before + len(built)


def test_setup_phase_that_collects_keeps_collecting_inside_and_freezes_after(owned):
    before = gc.get_freeze_count()
    with collector.setup_phase(collect=True):  # fitting GPs, flying excitation flights
        assert gc.isenabled()
        built = [object() for _ in range(100)]
    assert gc.isenabled()
    assert gc.get_freeze_count() >= before + len(built)


def test_setup_phase_re_enables_the_collector_when_the_setup_fails(owned):
    with pytest.raises(ValueError), collector.setup_phase():
        raise ValueError("bad config")
    assert gc.isenabled()


def test_setup_phase_keeps_a_disabled_collector_disabled(owned):
    gc.disable()
    with collector.setup_phase():
        pass
    assert not gc.isenabled()


def test_main_called_from_python_leaves_the_collector_alone(tmp_path):
    """Only the console script's own process tunes its collector: a program (or this test
    session) that calls main() keeps its collector enabled and its objects collectable."""
    assert not collector._process_owned
    frozen = gc.get_freeze_count()
    code = main(["run", "--set", "max_steps=1", "--set", "method=nominal", "--no-figures",
                 "--out", str(tmp_path / "run")])
    collector.skip_final_collection()
    assert code == 0
    assert gc.isenabled()
    assert gc.get_freeze_count() == frozen


def test_console_script_exits_with_the_commands_code_and_its_outputs_written(tmp_path):
    """The process the console script owns: a run's outputs are complete, a bad value exits 2."""
    import subprocess
    import sys

    def console(*argv):
        return subprocess.run([sys.executable, "-c", "import sys; from torch_gpmpc.cli.entry import "
                               "console_main; sys.argv[0] = 'gpmpc'; console_main()", *argv],
                              capture_output=True, text=True, timeout=300)

    ok = console("run", "--set", "max_steps=2", "--set", "method=nominal", "--no-figures",
                 "--out", str(tmp_path / "run"))
    assert ok.returncode == 0, ok.stderr
    assert (tmp_path / "run" / "metrics.json").is_file() and (tmp_path / "run" / "rollout.npz").is_file()
    bad = console("run", "--set", "num_agents=0", "--out", str(tmp_path / "bad"))
    assert bad.returncode == 2 and "num_agents" in bad.stderr
