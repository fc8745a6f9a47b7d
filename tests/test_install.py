"""What a newcomer does without make: ``pip install .`` in a fresh virtual environment, then
``octomerge demo``. Slow (it installs JAX and the package's dependencies from the package
index or pip's cache): run with ``pytest -m slow tests/test_install.py``."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.slow
def test_pip_install_then_demo_in_a_fresh_venv(tmp_path):
    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True)
    pip = [str(venv / "bin" / "python"), "-m", "pip", "install", "-q"]
    # a copy of the package, so the build leaves nothing in the checkout
    subprocess.run(["cp", "-r", str(ROOT / "octomerge_jax"), str(ROOT / "pyproject.toml"),
                    str(ROOT / "README.md"), str(tmp_path)], check=True)
    src = tmp_path
    subprocess.run(pip + [str(src)], check=True, timeout=1800)
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV")}
    env["OCTOMERGE_CACHE_DIR"] = str(tmp_path / "xla")
    out = subprocess.run([str(venv / "bin" / "octomerge"), "demo", "--out-dir", str(tmp_path / "demo")],
                         capture_output=True, text=True, env=env, cwd=tmp_path, timeout=1800)
    assert out.returncode == 0, out.stderr[-2000:]
    for name in ("map1.bt", "map2.bt", "merged.bt", "report.json", "overlap_before_after.png",
                 "merged_map.png"):
        assert (tmp_path / "demo" / name).stat().st_size > 0, name
