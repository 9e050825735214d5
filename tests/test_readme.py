"""The README's two set-up commands stay true, and CI runs the test command verbatim."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _setup_commands() -> list[str]:
    text = (ROOT / "README.md").read_text()
    section = text.split("## Set up", 1)[1].split("\n## ", 1)[0]
    return re.findall(r"```bash\n(.+?)\n```", section, flags=re.S)


def test_readme_has_exactly_two_setup_commands() -> None:
    cmds = _setup_commands()
    assert len(cmds) == 2, cmds
    for cmd in cmds:
        assert "\n" not in cmd.strip(), "each set-up command is one line"
        assert cmd.startswith("pip install torch==2.13.0 && "), "CPU torch must be installed first"
    assert cmds[0].split("&&")[-1].strip() == "tridar-env demo"
    assert cmds[1].rstrip().endswith("pytest")


def test_ci_runs_readme_test_command_verbatim() -> None:
    ci = (ROOT / ".ci" / "run").read_text()
    assert _setup_commands()[1].strip() in ci.splitlines()
