"""Build and run the C++ peers on OctoMap 1.10 (``alg7_octomap.cpp``, ``alg8_octomap.cpp``): the
thesis's algorithms on the same maps, in the same run as ours. Needs ``g++`` and ``pip install
cmeel-octomap`` (the ``bench`` extra); without them the benchmarks quote the issue's anchors."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np

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


def write_leaves(fh, m) -> None:
    """One map in the peers' input layout: int64 n, float64 resolution, uint16 min-corner keys
    (n, 3), uint8 depths (n,), float32 log-odds (n,)."""
    lv = m.leaves()
    np.array([m.num_leaves], np.int64).tofile(fh)
    np.array([m.resolution], np.float64).tofile(fh)
    np.asarray(lv.keys, np.uint16).tofile(fh)
    np.asarray(lv.depths, np.uint8).tofile(fh)
    np.asarray(lv.log_odds, np.float32).tofile(fh)


def read_leaves(path):
    """A map a peer wrote in that layout: ``(keys (n, 3) uint16, depths (n,) int32, log-odds)``."""
    with open(path, "rb") as fh:
        n = int(np.fromfile(fh, np.int64, 1)[0])
        np.fromfile(fh, np.float64, 1)
        keys = np.fromfile(fh, np.uint16, 3 * n).reshape(n, 3)
        depths = np.fromfile(fh, np.uint8, n).astype(np.int32)
        log_odds = np.fromfile(fh, np.float32, n)
    return keys, depths, log_odds
