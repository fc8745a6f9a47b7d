"""End-to-end merge time per stage for three map sizes, and merge_batch throughput vs a loop.

Maps: the room scene of ``tests/test_pipeline.py``, copied here (robot 1 sees x < 3 m in the world frame,
robot 2 sees x >= 0.8 m in a frame yawed by pi/4) at three resolutions, so leaf counts grow
~4x per step. Each size is merged from a guess 0.1 rad / 0.1 m off: read both files, occupied
clouds, overlap, ICP, transform, fuse, write. The first call (compile) is timed apart from the
steady state (median of ``--repeats``).

Anchor (issue 7): the thesis pipeline in C++ on OctoMap 1.10 on this 2-core CPU takes 1.75 s /
7.7 s / 32.8 s end to end for 0.26M+0.31M / 1.05M+1.18M / 4.4M+4.7M leaves; use ``--res`` to
reach those sizes (memory and minutes grow accordingly).

``--campus RES`` adds an outdoor pair: the simulated campus (``sim.campus``, ~100 x 60 m,
16-beam lidar; ~1M leaves per map at 0.2 m), written to ``.bt`` and read back as a user's
maps would be, merged with each refinement from a guess off by 1 m / 0.08 rad (``multi``: 2 m
/ 1.7 rad), with the mean displacement of map 2's occupied voxels before and after.

``--guess-grid RES`` merges the simulated lab and office pairs (``make_two_robot_maps``, read
back from ``.bt``) with ``refine="multi"`` from 11 far guesses each: the truth turned by six
yaws (0.5-3 rad) + 0.36 m, and five with roll / pitch errors too (0.05-0.15 rad, + 0.5-2 m);
"right" = mean displacement of map 2's occupied voxels below 2 voxels.

    .venv/bin/python benchmarks/bench_merge.py                       # 0.1, 0.05, 0.025 m
    .venv/bin/python benchmarks/bench_merge.py --res 0.1 --batch 8    # batch throughput only
    .venv/bin/python benchmarks/bench_merge.py --no-sizes --batch 0 --campus 0.2
    .venv/bin/python benchmarks/bench_merge.py --no-sizes --batch 0 --guess-grid 0.05
"""

from __future__ import annotations

import argparse
import math
import platform
import statistics
import tempfile
import time
from pathlib import Path

import _host_memory
import jax
import numpy as np

from octomerge_jax.io import load, save
from octomerge_jax.pipeline import MergeConfig, merge, merge_batch, transform_from_xyz_rpy
from octomerge_jax.sim import make_two_robot_maps, small_room_map, small_room_voxels

STAGES = ("load", "occupied_points", "overlap", "icp", "transform", "fuse", "save")


# the small room of tests/test_pipeline.py (octomerge_jax.sim.small_room)
T_TRUE = transform_from_xyz_rpy(0.35, -0.25, 0.0, 0.0, 0.0, math.pi / 4)  # T_1_2: a pi/4 yaw


def make_pair(res):
    voxels = small_room_voxels(res)
    m1 = small_room_map((-1.0, 3.0), res, voxels=voxels)
    m2 = small_room_map((0.8, 9.0), res, T_TRUE, voxels=voxels)
    return m1, m2, T_TRUE


def guess(dyaw=0.1, dx=0.1):
    return transform_from_xyz_rpy(0.35 + dx, -0.25 - 0.05, 0.0, 0.0, 0.0, math.pi / 4 + dyaw)


def end_to_end(p1, p2, out, T_init, T_true):
    t0 = time.perf_counter()
    m1, m2 = load(p1), load(p2)
    t_load = time.perf_counter() - t0
    merged, rep = merge(m1, m2, T_init, T_1_2_true=T_true)
    t1 = time.perf_counter()
    save(merged, out)
    t = dict(rep.timings, load=t_load, save=time.perf_counter() - t1)
    t["end_to_end"] = time.perf_counter() - t0
    return t, rep


def bench_sizes(resolutions, repeats):

    print("\n## End to end per stage (seconds; first call includes compilation)\n")
    print("| res [m] | leaves m1+m2 | merged | call | " + " | ".join(STAGES) + " | end to end | eps_r | eps_t |")
    print("|---" * (len(STAGES) + 7) + "|")
    with tempfile.TemporaryDirectory() as d:
        for res in resolutions:
            m1, m2, T = make_pair(res)
            p1, p2, out = Path(d) / "a.ot", Path(d) / "b.ot", Path(d) / "m.bt"
            save(m1, p1)
            save(m2, p2)
            first, rep = end_to_end(p1, p2, out, guess(), T)
            steady = [end_to_end(p1, p2, out, guess(), T)[0] for _ in range(repeats)]
            med = {k: statistics.median(s[k] for s in steady) for k in steady[0]}
            for name, t in (("first", first), (f"median of {repeats}", med)):
                print(f"| {res:g} | {m1.num_leaves:,}+{m2.num_leaves:,} | {rep.counts['leaves_merged']:,} | {name} | "
                      + " | ".join(f"{t.get(k, 0.0):.2f}" for k in STAGES)
                      + f" | {t['end_to_end']:.2f} | {rep.epsilon_r:.3f} | {rep.epsilon_t:.3f} |", flush=True)


def bench_batch(res, n_pairs):

    m1, m2, T = make_pair(res)
    rng = np.random.default_rng(0)
    pairs = [(m1, m2, guess(float(rng.uniform(-0.1, 0.1)), float(rng.uniform(-0.1, 0.1))), T)
             for _ in range(n_pairs)]
    # warm up both paths (compilation) on the same shapes
    merge(*pairs[0][:3])
    merge_batch(pairs[:n_pairs])
    t0 = time.perf_counter()
    for p in pairs:
        merged, _ = merge(*p[:3])
        jax.block_until_ready(merged)
    t_loop = time.perf_counter() - t0
    t0 = time.perf_counter()
    res_b = merge_batch(pairs)
    jax.block_until_ready([r.merged for r in res_b])
    t_batch = time.perf_counter() - t0
    ok = sum(r.status == "ok" for r in res_b)
    print(f"\n## merge_batch vs a loop of merge ({n_pairs} pairs of {m1.num_leaves:,}+{m2.num_leaves:,} leaves at {res:g} m, steady state)\n")
    print("| method | seconds | pairs/s |\n|---|---|---|")
    print(f"| loop of merge() | {t_loop:.2f} | {n_pairs / t_loop:.2f} |")
    print(f"| merge_batch ({ok} ok) | {t_batch:.2f} | {n_pairs / t_batch:.2f} |")
    print(f"\nspeed-up {t_loop / t_batch:.2f}x")


def read_back_from_bt(*maps):
    """The maps written to ``.bt`` files and read back, as a user's maps arrive (maximum
    likelihood, pruned)."""
    with tempfile.TemporaryDirectory() as d:
        paths = [Path(d) / f"{i}.bt" for i in range(len(maps))]
        for m, path in zip(maps, paths):
            save(m, path)
        return tuple(load(path) for path in paths)


CAMPUS_RUNS = (("icp", 1.0, 0.08), ("icp+dense", 1.0, 0.08), ("dense", 1.0, 0.08), ("multi", 2.0, 1.7))


def bench_campus(res, repeats):
    t0 = time.perf_counter()
    m1, m2, T = make_two_robot_maps("campus", res, yaw_2_rad=0.9, offset_2=(40.0, 25.0, 0.3), max_range=30.0)
    t_sim = time.perf_counter() - t0
    m1, m2 = read_back_from_bt(m1, m2)
    print(f"\n## Outdoor campus at {res:g} m ({m1.num_leaves:,}+{m2.num_leaves:,} leaves from .bt, "
          f"simulated in {t_sim:.0f} s)\n")
    print("| refine | guess off (m, rad) | displacement before -> after [m] | eps_r | eps_t | report | "
          f"first s | median of {repeats} s |")
    print("|---|---|---|---|---|---|---|---|")
    for refine, dx, dyaw in CAMPUS_RUNS:
        g = T @ transform_from_xyz_rpy(dx, -0.6 * dx, 0.0, 0.0, 0.0, dyaw)
        times = []
        for _ in range(repeats + 1):
            t0 = time.perf_counter()
            merged, rep = merge(m1, m2, g, refine=refine, T_1_2_true=T)
            jax.block_until_ready(merged)
            times.append(time.perf_counter() - t0)
        status = rep.icp["status"] if rep.icp else "-"
        if rep.warnings:
            status += " (" + "; ".join(w.split(";")[0] for w in rep.warnings) + ")"
        print(f"| {refine} | {dx:g}, {dyaw:g} | {rep.displacement_init:.3f} -> {rep.displacement:.3f} | "
              f"{rep.epsilon_r:.4f} | {rep.epsilon_t:.3f} | {status} | {times[0]:.1f} | "
              f"{statistics.median(times[1:]):.1f} |", flush=True)


GUESS_GRID = ([(yaw, 0.0, 0.0, (0.3, 0.2, 0.0)) for yaw in (0.5, 1.7, -2.6, 3.0, -1.0, 2.2)]
              + [(0.5, 0.1, -0.08, (0.5, 0.3, 0.0)), (1.7, -0.1, 0.05, (1.0, -0.5, 0.2)),
                 (-2.6, 0.05, 0.1, (1.5, 1.0, 0.0)), (0.0, 0.15, 0.0, (2.0, 0.0, 0.0)),
                 (2.8, 0.0, -0.12, (0.5, -1.5, 0.3))])  # (yaw, roll, pitch [rad], offset [m])


def bench_guess_grid(res, hypotheses):
    cfg = MergeConfig().replace(registration={"refine": "multi", "hypotheses": hypotheses})
    print(f"\n## refine='multi', hypotheses={hypotheses!r}, from far guesses (lab / office at {res:g} m, from .bt)\n")
    print("| scene | yaw, roll, pitch [rad] | offset [m] | displacement before -> after [m] | right | s |")
    print("|---|---|---|---|---|---|")
    right = total = 0
    for scene in ("lab", "office"):
        m1, m2, T = make_two_robot_maps(scene, res)
        m1, m2 = read_back_from_bt(m1, m2)
        for yaw, roll, pitch, off in GUESS_GRID:
            g = transform_from_xyz_rpy(*off, roll, pitch, yaw) @ T
            t0 = time.perf_counter()
            _, rep = merge(m1, m2, g, T_1_2_true=T, config=cfg)
            ok = rep.displacement < 2 * res
            right, total = right + ok, total + 1
            print(f"| {scene} | {yaw:g}, {roll:g}, {pitch:g} | {off[0]:g}, {off[1]:g}, {off[2]:g} | "
                  f"{rep.displacement_init:.3f} -> {rep.displacement:.3f} | {'yes' if ok else 'no'} | "
                  f"{time.perf_counter() - t0:.1f} |", flush=True)
    print(f"\nright: {right} of {total} (each scene's first row includes compilation)")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--res", type=float, nargs="+", default=[0.1, 0.05, 0.025])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--batch", type=int, default=8, help="pairs for the batch benchmark (0: skip)")
    ap.add_argument("--no-sizes", action="store_true")
    ap.add_argument("--campus", type=float, nargs="*", default=[], metavar="RES",
                    help="outdoor campus pairs at these resolutions [m] (e.g. 0.2; ~1 min to simulate each)")
    ap.add_argument("--guess-grid", type=float, nargs="*", default=[], metavar="RES",
                    help="refine='multi' from 22 far guesses on the lab / office pairs at these resolutions [m]")
    ap.add_argument("--hypotheses", default="both", choices=("both", "correlation", "yaw_grid"),
                    help="registration.hypotheses for --guess-grid")
    _host_memory.add_flag(ap)
    a = ap.parse_args(argv)
    reuse = _host_memory.apply(a)
    print(f"# bench_merge: {platform.machine()} x{__import__('os').cpu_count()}, "
          f"{jax.devices()[0].platform}, JAX {jax.__version__}, "
          f"host memory reuse {reuse}")
    if not a.no_sizes:
        bench_sizes(a.res, a.repeats)
    if a.batch:
        bench_batch(max(a.res), a.batch)
    for res in a.campus:
        bench_campus(res, a.repeats)
    for res in a.guess_grid:
        bench_guess_grid(res, a.hypotheses)


if __name__ == "__main__":
    main()
