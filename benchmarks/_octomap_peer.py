"""Build and run the C++ peers on OctoMap 1.10 (``alg7_octomap.cpp``, ``alg8_octomap.cpp``): the
thesis's algorithms on the same maps, in the same run as ours. Needs ``g++`` and ``pip install
cmeel-octomap`` (the ``bench`` extra); without them the benchmarks quote the issue's anchors."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent


def build(name: str) -> Path | None:
    """Compile ``benchmarks/<name>.cpp`` into ``benchmarks/_build/<name>`` (if the source is
    newer) against cmeel-octomap; ``None`` if g++, the package or the build fails."""
    src = HERE / f"{name}.cpp"
    gxx = shutil.which("g++")
    if not (src.exists() and gxx):
        return None
    try:
        import cmeel  # noqa: F401  (cmeel-octomap installs under cmeel.prefix)
    except ImportError:
        return None
    prefix = (Path(sys.prefix) / "lib" / f"python{sys.version_info.major}.{sys.version_info.minor}"
              / "site-packages" / "cmeel.prefix")
    if not (prefix / "include" / "octomap").exists():
        return None
    out_dir = HERE / "_build"
    out_dir.mkdir(exist_ok=True)
    exe = out_dir / name
    if not exe.exists() or exe.stat().st_mtime < src.stat().st_mtime:
        cmd = [gxx, "-O3", "-DNDEBUG", "-std=c++17", str(src), "-o", str(exe),
               f"-I{prefix / 'include'}", f"-L{prefix / 'lib'}", "-loctomap", "-loctomath",
               f"-Wl,-rpath,{prefix / 'lib'}"]
        r = subprocess.run(cmd, capture_output=True, text=True)
        if r.returncode != 0:
            print(f"C++ peer {name} build failed:\n" + r.stderr[-2000:], file=sys.stderr)
            return None
    return exe


def run(exe: Path, *args: str) -> dict | None:
    """Run a peer; its last stdout line is a JSON object (``None`` and stderr shown on failure)."""
    r = subprocess.run([str(exe), *map(str, args)], capture_output=True, text=True)
    if r.returncode != 0:
        print(f"C++ peer failed: {r.stderr[-1000:]}", file=sys.stderr)
        return None
    return json.loads(r.stdout.strip().splitlines()[-1])
