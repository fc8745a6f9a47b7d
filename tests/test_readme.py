"""The README stays true: its library example runs and its CLI commands exist."""

import re
import subprocess
import sys
from pathlib import Path

import pytest

README = Path(__file__).resolve().parents[1] / "README.md"


def test_readme_cli_commands_exist():
    from octomerge_jax.cli import build_parser

    text = README.read_text()
    used = set(re.findall(r"^octomerge ([a-z-]+)", text, re.M))
    parser = build_parser()
    sub = next(a for a in parser._actions if a.dest == "command")
    assert used and used <= set(sub.choices), used - set(sub.choices)


@pytest.mark.slow
def test_readme_library_example_runs(tmp_path):
    code = re.findall(r"```python\n(.*?)```", README.read_text(), re.S)[0]
    out = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True)
    assert out.returncode == 0, out.stderr[-2000:]
    assert (tmp_path / "merged.bt").stat().st_size > 0 and (tmp_path / "report.json").exists()
