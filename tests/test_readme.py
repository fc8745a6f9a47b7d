"""The README stays true: its first example runs, its names and CLI commands exist, its links resolve."""

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

import octomerge_jax as om

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
BENCHMARKS = ROOT / "benchmarks" / "README.md"


def _python_blocks() -> list[str]:
    return re.findall(r"```python\n(.*?)```", README.read_text(), re.S)


def _run(code: str, cwd: Path) -> subprocess.CompletedProcess:
    paths = [str(ROOT)] + [p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep) if p]
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(paths))
    return subprocess.run([sys.executable, "-c", code], cwd=cwd, env=env, capture_output=True, text=True,
                          timeout=600)


def test_readme_example_runs(tmp_path):
    """The first screen's example (built-in room, ICP from a wrong guess) runs and writes its map."""
    out = _run(_python_blocks()[0], tmp_path)
    assert out.returncode == 0, out.stderr[-2000:]
    assert (tmp_path / "merged.bt").stat().st_size > 0
    eps = re.search(r"eps_r ([0-9.]+) -> ([0-9.]+), displacement ([0-9.]+) -> ([0-9.]+) m", out.stdout)
    assert eps, out.stdout
    eps_r_init, eps_r, disp_init, disp = map(float, eps.groups())
    assert eps_r < eps_r_init and disp < disp_init


@pytest.mark.slow
def test_readme_library_example_runs(tmp_path):
    """The Library section's example (simulated lab) runs after the first one, whose imports it uses."""
    first, library = _python_blocks()[:2]
    out = _run(first + "\n" + library, tmp_path)
    assert out.returncode == 0, out.stderr[-2000:]
    assert (tmp_path / "report.json").exists() and (tmp_path / "lab.ot").stat().st_size > 0


@pytest.mark.slow
def test_readme_many_robots_example_places_every_map(tmp_path):
    """The Many robots example (guess-free office team) places all four maps and writes its poses."""
    first = _python_blocks()[0]
    team = next(b for b in _python_blocks() if "team_maps" in b)
    out = _run(first + "\n" + team + "\nassert all(t is not None for t in report.transforms), report.summary()\n",
               tmp_path)
    assert out.returncode == 0, out.stderr[-2000:]
    assert len((tmp_path / "poses.tum").read_text().splitlines()) == 4


def test_readme_names_exist():
    used = set(re.findall(r"\bom\.([A-Za-z_]\w*)", "".join(_python_blocks())))
    assert used and not {n for n in used if not hasattr(om, n)}


def test_readme_cli_commands_exist():
    from octomerge_jax.cli import build_parser

    text = README.read_text()
    used = set(re.findall(r"^octomerge ([a-z-]+)", text, re.M))
    parser = build_parser()
    sub = next(a for a in parser._actions if a.dest == "command")
    assert used and used <= set(sub.choices), used - set(sub.choices)


def test_readme_environment_variables_exist():
    source = "".join(p.read_text() for p in (ROOT / "octomerge_jax").rglob("*.py"))
    for name in set(re.findall(r"\bOCTOMERGE_[A-Z_]+", README.read_text())):
        assert name in source, name


def _slug(heading: str) -> str:
    """GitHub's anchor of a Markdown heading."""
    return re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-")


def test_readme_benchmark_links_resolve():
    anchors = {_slug(h) for h in re.findall(r"^#+ (.*)$", BENCHMARKS.read_text(), re.M)}
    links = re.findall(r"\(benchmarks/README\.md#([\w-]+)\)", README.read_text())
    assert links and set(links) <= anchors, set(links) - anchors


def test_benchmark_commands_name_existing_scripts():
    scripts = set(re.findall(r"benchmarks/(\w+\.py)", BENCHMARKS.read_text()))
    assert scripts and all((ROOT / "benchmarks" / s).exists() for s in scripts), scripts


def test_design_sections_named_in_the_code_exist():
    """Code that points to ``docs/design.md``, "Heading" names a section that is there."""
    headings = set(re.findall(r"^#+ (.*)$", (ROOT / "docs" / "design.md").read_text(), re.M))
    named = set()
    for path in (ROOT / "octomerge_jax").rglob("*.py"):
        for refs in re.findall(r'design\.md`*,\s*((?:"[^"]+"(?:\s*(?:,|and)\s*)?)+)', path.read_text()):
            named |= set(re.findall(r'"([^"]+)"', refs))
    assert named and named <= headings, named - headings
