"""The command line as a user meets it, process start to file written, in one run: import time,
``octomerge --help``, ``octomerge merge`` cold (empty compile cache) and warm for two map sizes,
``octomerge demo`` cold and warm, and the thesis pipeline in C++ on OctoMap 1.10 on the same
pairs (``alg7_octomap`` transform + prune, then ``alg8_octomap`` merge + prune + write; two
processes, their wall times added).

Pairs, written to ``.bt`` and read back by the command as a user's maps would be:
  room    the small room of ``tests/test_pipeline.py`` (``sim.small_room``) at 0.025 m, ~0.1M
          leaves per map; guess 0.05 m / 0.04 rad off.
  campus  the simulated campus (``sim.campus``, ~100 x 60 m, 16-beam lidar) at 0.2 m, 0.4-0.5M
          leaves per map as ``.bt`` (~1 min to simulate on an idle 2-core machine, kept in
          ``--data-dir``); guess 1 m / 0.08 rad off.
Each merge: ``octomerge merge IN1 IN2 OUT.bt --xyz .. --rpy .. --refine icp`` (and ``none``), and the
default command without a guess (``octomerge merge IN1 IN2 OUT.bt``: the guess-free search, the dense
step and the GICP polish). "cold" runs with an empty ``OCTOMERGE_CACHE_DIR``; "warm" is the median of
``--repeats`` runs after it (same cache).

    .venv/bin/python benchmarks/bench_cli.py                  # everything (C++ peer if cmeel-octomap)
    .venv/bin/python benchmarks/bench_cli.py --pairs room --no-demo
    .venv/bin/python benchmarks/bench_cli.py --in-process --pairs campus   # the stages in one process
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import _octomap_peer
import numpy as np

HERE = Path(__file__).resolve().parent
PY = sys.executable
GUESS = {"room": (0.05, -0.05, 0.0, 0.0, 0.0, -0.04), "campus": (1.0, -0.6, 0.0, 0.0, 0.0, 0.08)}


def timed(cmd, env=None, cwd=None, exits=(0,)) -> float:
    """Wall seconds of ``cmd`` (a fresh process); raises on an exit code not in ``exits``."""
    t0 = time.perf_counter()
    r = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=cwd)
    dt = time.perf_counter() - t0
    if r.returncode not in exits:
        raise RuntimeError(f"{' '.join(map(str, cmd))} failed ({r.returncode}):\n{r.stderr[-2000:]}")
    return dt


def median_of(n, cmd, env=None, exits=(0,)) -> float:
    return statistics.median(timed(cmd, env, exits=exits) for _ in range(n))


def make_pair(name: str, data: Path):
    """``(map1.bt, map2.bt, T_1_2 true)`` of pair ``name`` in ``data`` (simulated once)."""
    from octomerge_jax.io import save
    from octomerge_jax.pipeline import transform_from_xyz_rpy

    p1, p2, pt = data / f"{name}_1.bt", data / f"{name}_2.bt", data / f"{name}_T.npy"
    if not (p1.exists() and p2.exists() and pt.exists()):
        if name == "room":
            from octomerge_jax.sim import small_room_map, small_room_voxels

            T = np.asarray(transform_from_xyz_rpy(0.35, -0.25, 0.0, 0.0, 0.0, math.pi / 4))
            v = small_room_voxels(0.025)
            m1, m2 = small_room_map((-1.0, 3.0), 0.025, voxels=v), small_room_map((0.8, 9.0), 0.025, T, voxels=v)
        else:
            from octomerge_jax.sim import make_two_robot_maps

            m1, m2, T = make_two_robot_maps("campus", 0.2, yaw_2_rad=0.9, offset_2=(40.0, 25.0, 0.3),
                                            max_range=30.0)
        save(m1, p1)
        save(m2, p2)
        np.save(pt, np.asarray(T, np.float64))
    return p1, p2, np.load(pt)


def guess_args(name, T):
    from octomerge_jax.pipeline import transform_from_xyz_rpy

    G = T @ np.asarray(transform_from_xyz_rpy(*GUESS[name]))
    yaw = math.atan2(G[1, 0], G[0, 0])
    pitch = -math.asin(max(-1.0, min(1.0, G[2, 0])))
    roll = math.atan2(G[2, 1], G[2, 2])
    return ["--xyz", *map(str, G[:3, 3]), "--rpy", str(roll), str(pitch), str(yaw)]


def cpp_pipeline(p1, p2, T, work: Path):
    """The thesis pipeline on OctoMap (transform map 2, merge into map 1, prune, write): wall
    seconds of the two peer processes, or ``None`` without g++ / cmeel-octomap."""
    alg7, alg8 = _octomap_peer.build("alg7_octomap"), _octomap_peer.build("alg8_octomap")
    if alg7 is None or alg8 is None:
        return None
    write_peer_inputs(p1, p2, T, work)
    runs = []
    for _ in range(3):
        runs.append(timed([alg7, work / "t.bin"]) + timed([alg8, work / "m.bin", "1", work / "merged.bin"]))
    return statistics.median(runs)


def write_peer_inputs(p1, p2, T, work: Path) -> None:
    """The C++ peers' inputs: ``t.bin`` (map 2's leaves and ``T`` for Alg. 7) and ``m.bin``
    (map 1's leaves, map 2 transformed by ``T`` and the clamping bounds for Alg. 8)."""
    from octomerge_jax.io import load
    from octomerge_jax.map import OccupancyParams
    from octomerge_jax.resample import transform_map

    m1, m2 = load(p1), load(p2)
    m2t = transform_map(m2, T)
    P = OccupancyParams()
    with open(work / "t.bin", "wb") as fh:
        _octomap_peer.write_leaves(fh, m2)
        np.asarray(T, np.float64).tofile(fh)
    with open(work / "m.bin", "wb") as fh:
        _octomap_peer.write_leaves(fh, m1)
        _octomap_peer.write_leaves(fh, m2t)
        np.array([P.clamp_min_log_odds, P.clamp_max_log_odds], np.float32).tofile(fh)


def in_process(p1, p2, T, name: str, work: Path, repeats: int = 3):
    """The stages in one process on one pair: ``merge(..., refine="none")`` from the
    guess in this process once compiled (median of ``repeats`` after a first call), against
    the C++ stages' own clocks (Alg. 7's transform + prune, Alg. 8's merge + prune; no process
    start, read or write). Returns ``(ours s, C++ s or None)``."""
    import jax

    from octomerge_jax import merge
    from octomerge_jax.io import load
    from octomerge_jax.pipeline import transform_from_xyz_rpy

    m1, m2 = load(p1), load(p2)
    G = T @ np.asarray(transform_from_xyz_rpy(*GUESS[name]))
    runs = []
    for _ in range(repeats + 1):
        t0 = time.perf_counter()
        out, _ = merge(m1, m2, G, refine="none")
        jax.block_until_ready(out.code)
        runs.append(time.perf_counter() - t0)
    ours = statistics.median(runs[1:])
    alg7, alg8 = _octomap_peer.build("alg7_octomap"), _octomap_peer.build("alg8_octomap")
    if alg7 is None or alg8 is None:
        return ours, None
    write_peer_inputs(p1, p2, G, work)
    r7 = json.loads(subprocess.run([alg7, work / "t.bin"], capture_output=True, text=True, check=True).stdout
                    .strip().splitlines()[-1])
    r8 = json.loads(subprocess.run([alg8, work / "m.bin", "3", work / "merged.bin"], capture_output=True, text=True,
                                   check=True).stdout.strip().splitlines()[-1])
    return ours, r7["seconds"] + r8["merge_s"] + r8["prune_s"]


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--pairs", nargs="+", default=["room", "campus"], choices=sorted(GUESS))
    ap.add_argument("--repeats", type=int, default=2, help="warm runs (median)")
    ap.add_argument("--no-demo", action="store_true")
    ap.add_argument("--data-dir", type=Path, default=HERE / "_build" / "cli_data")
    ap.add_argument("--in-process", action="store_true",
                    help="only the in-process table: merge(refine='none') once compiled against the C++ stages")
    a = ap.parse_args()
    a.data_dir.mkdir(parents=True, exist_ok=True)
    if a.in_process:
        work = Path(tempfile.mkdtemp(prefix="bench_cli_"))
        try:
            print("| pair | ours: merge(refine='none'), in process, once compiled [s] | "
                  "C++ Alg. 7 transform + prune + Alg. 8 merge + prune [s] | C++ / ours |")
            print("|---|---|---|---|")
            for name in a.pairs:
                p1, p2, T = make_pair(name, a.data_dir)
                ours, cpp = in_process(p1, p2, T, name, work)
                ratio = f"{cpp / ours:.1f}x" if cpp else "-"
                print(f"| {name} | {ours:.3f} | {cpp if cpp is None else round(cpp, 3)} | {ratio} |", flush=True)
        finally:
            shutil.rmtree(work, ignore_errors=True)
        return
    work = Path(tempfile.mkdtemp(prefix="bench_cli_"))
    cli = [PY, "-m", "octomerge_jax"]
    rows = []
    try:
        rows.append(("`import octomerge_jax`", median_of(5, [PY, "-c", "import octomerge_jax"]), None, ""))
        rows.append(("`import jax` (for scale)", median_of(3, [PY, "-c", "import jax.numpy"]), None, ""))
        rows.append(("`octomerge --help`", median_of(5, cli + ["--help"]), None, ""))
        for name in a.pairs:
            p1, p2, T = make_pair(name, a.data_dir)
            from octomerge_jax.io import load

            leaves = "+".join(f"{load(p).num_leaves:,}" for p in (p1, p2))
            env = {**os.environ, "OCTOMERGE_CACHE_DIR": str(work / f"xla_{name}")}
            cmd = cli + ["merge", p1, p2, work / f"{name}.bt", "--refine", "icp", "--force", "-q",
                         *guess_args(name, T)]
            cold = timed(cmd, env)
            warm = median_of(a.repeats, cmd, env)
            cmd_none = [c if c != "icp" else "none" for c in cmd]
            warm_none = median_of(a.repeats, cmd_none, env)
            # the default command: no guess (guess-free search, dense step, GICP polish); exit 7 is
            # "ambiguous" (the room is nearly symmetric), written with --force
            env_default = {**os.environ, "OCTOMERGE_CACHE_DIR": str(work / f"xla_{name}_default")}
            cmd_default = cli + ["merge", p1, p2, work / f"{name}_default.bt", "--force", "-q"]
            cold_default = timed(cmd_default, env_default, exits=(0, 7))
            warm_default = median_of(a.repeats, cmd_default, env_default, exits=(0, 7))
            cpp = cpp_pipeline(p1, p2, T, work)
            rows.append((f"merge {name} icp, cold ({leaves} leaves)", cold, cpp, ""))
            rows.append((f"merge {name} icp, warm", warm, cpp, ""))
            rows.append((f"merge {name} none, warm", warm_none, cpp, ""))
            rows.append((f"merge {name} without a guess (default), cold", cold_default, cpp, ""))
            rows.append((f"merge {name} without a guess (default), warm", warm_default, cpp, ""))
            if cpp is not None:
                rows.append((f"C++ pipeline {name} (alg7 + alg8)", cpp, cpp, ""))
        if not a.no_demo:
            env = {**os.environ, "OCTOMERGE_CACHE_DIR": str(work / "xla_demo")}
            cmd = cli + ["demo", "--out-dir", work / "demo", "--no-figures"]
            rows.append(("demo (--no-figures), cold", timed(cmd, env), None, ""))
            rows.append(("demo (--no-figures), warm", median_of(a.repeats, cmd, env), None, ""))
    finally:
        shutil.rmtree(work, ignore_errors=True)
    import jax

    print(f"\n{platform.node()} | {os.cpu_count()} CPUs | Python {platform.python_version()} | "
          f"JAX {jax.__version__} | {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())} | "
          f"load average {os.getloadavg()[0]:.1f}\n")
    print("| what (process start to exit) | s | / C++ pipeline |")
    print("|---|---|---|")
    for what, s, cpp, _ in rows:
        ratio = f"{s / cpp:.2f}x" if cpp else "-"
        print(f"| {what} | {s:.2f} | {ratio} |")
    print(json.dumps({w: round(s, 3) for w, s, _, _ in rows}))


if __name__ == "__main__":
    main()
