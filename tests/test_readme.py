"""The README's two commands: the test command is what CI runs, the main command works."""

from __future__ import annotations

import json
import re
import shlex
from pathlib import Path

from torch_gpmpc.cli import main

ROOT = Path(__file__).resolve().parents[1]


def _readme_commands() -> list[str]:
    text = (ROOT / "README.md").read_text()
    return re.findall(r"```bash\n(.+?)\n```", text)[:2]


def test_ci_runs_the_readme_test_command():
    main_cmd, test_cmd = _readme_commands()
    ci = (ROOT / ".ci" / "run").read_text().splitlines()
    assert test_cmd in ci
    assert "pip install torch==2.13.0" in main_cmd and "pip install torch==2.13.0" in test_cmd


def test_readme_main_command_runs_a_short_paper_scenario(tmp_path):
    main_cmd, _ = _readme_commands()
    gpmpc_part = main_cmd.split("&&")[-1].strip()
    argv = shlex.split(gpmpc_part)
    assert argv[0].endswith("gpmpc") and argv[1] == "run"
    out = tmp_path / "paper"
    args = argv[1:]
    args[args.index("--out") + 1] = str(out)
    # Same command, cut short: 2 closed-loop steps, 3 ADMM iterations, small GP fit.
    code = main(args + ["--set", "max_steps=2", "--set", "admm_max_iter=3", "--set", "gp_iters=5"])
    assert code == 0
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["method"] == "gp-chance" and metrics["steps"] == 2
    assert (out / "rollout.npz").is_file()
    assert any((out / "tb").iterdir())
    assert sorted(p.name for p in (out / "figures").iterdir())


def _python_snippets(path: Path) -> list[str]:
    return re.findall(r"```python\n(.+?)\n```", path.read_text(), flags=re.S)


def _readme_python_snippets() -> list[str]:
    return _python_snippets(ROOT / "README.md")


def test_readme_python_snippets_run_as_written(tmp_path, monkeypatch, capsys):
    """Every ```python block of the README runs, in a fresh namespace, in an empty directory."""
    snippets = _readme_python_snippets()
    assert len(snippets) >= 2
    monkeypatch.chdir(tmp_path)
    for i, code in enumerate(snippets):
        exec(compile(code, f"README.md python snippet {i}", "exec"), {"__name__": f"readme_{i}"})
    out = capsys.readouterr().out
    assert "propagated" in out


def test_the_docs_python_snippets_run_as_written(tmp_path, monkeypatch, capsys):
    """Every ```python block of the docs' pages runs, in a fresh namespace, in an empty directory (the
    tutorials run when the docs build)."""
    monkeypatch.chdir(tmp_path)
    ran = 0
    for page in sorted((ROOT / "docs").rglob("*.md")):
        for i, code in enumerate(_python_snippets(page)):
            exec(compile(code, f"{page.relative_to(ROOT)} python snippet {i}", "exec"), {"__name__": f"docs_{i}"})
            ran += 1
    assert ran >= 3
