"""Point-cloud insertion: octomerge_jax vs OctoMap C++ (pyoctomap ``insertPointCloud``).

Kinect-like scans (640 x 480 rays over 57 x 43 deg, ranges 3-5 m, so ~300k points each) from
10 poses along a path, resolution 0.05 m, inserted into one map. Prints a table: first call
(compile + run) apart from steady state (median of --repeats full runs, block_until_ready),
points per second, and the ratio to OctoMap in the same run.

  .venv/bin/python benchmarks/bench_insert.py [--scans 10] [--width 640 --height 480] [--repeats 3]
"""

from __future__ import annotations

import argparse
import statistics
import time

import jax
import numpy as np

from octomerge_jax import insert
from octomerge_jax.map import empty
from octomerge_jax.sim import DepthCamera, pose_from_xyz_rpy


def make_scans(n_scans: int, width: int, height: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    dirs = DepthCamera(width=width, height=height).ray_directions()
    clouds, origins = [], []
    for i in range(n_scans):
        T = pose_from_xyz_rpy(0.15 * i, 0.05 * i, 0.5, 0.0, 0.0, 0.12 * i)
        ranges = rng.uniform(3.0, 5.0, len(dirs))
        pts = dirs * ranges[:, None]
        clouds.append((pts @ T[:3, :3].T + T[:3, 3]).astype(np.float32))
        origins.append(T[:3, 3].astype(np.float32))
    return clouds, np.array(origins)


def run_ours_sequential(clouds, origins, res):
    plan = insert.CapacityPlan()
    for c, o in zip(clouds, origins):
        plan.reserve(c, o, res)
    m = empty(res)
    for c, o in zip(clouds, origins):
        m = insert.insert_point_cloud(m, c, o, plan=plan)
    jax.block_until_ready(m.log_odds)
    return m


def run_ours_batched(clouds, origins, res):
    m = insert.insert_point_clouds(empty(res), clouds, origins, batch_size=len(clouds))
    jax.block_until_ready(m.log_odds)
    return m


def run_octomap(clouds, origins, res):
    import pyoctomap

    t = pyoctomap.OcTree(res)
    for c, o in zip(clouds, origins):
        t.insertPointCloud(c.astype(np.float64), o.astype(np.float64))
    return t


def timed(fn, repeats):
    t0 = time.perf_counter()
    out = fn()
    first = time.perf_counter() - t0
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return first, statistics.median(times), out


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scans", type=int, default=10)
    ap.add_argument("--width", type=int, default=640)
    ap.add_argument("--height", type=int, default=480)
    ap.add_argument("--res", type=float, default=0.05)
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    clouds, origins = make_scans(args.scans, args.width, args.height)
    n_pts = sum(len(c) for c in clouds)
    rows = []
    _, oct_s, tree = timed(lambda: run_octomap(clouds, origins, args.res), args.repeats)
    rows.append(("OctoMap C++ (pyoctomap insertPointCloud)", float("nan"), oct_s))
    first, steady, m = timed(lambda: run_ours_sequential(clouds, origins, args.res), args.repeats)
    rows.append(("octomerge_jax insert_point_cloud (per scan)", first - steady, steady))
    first_b, steady_b, mb = timed(lambda: run_ours_batched(clouds, origins, args.res), args.repeats)
    rows.append((f"octomerge_jax insert_point_clouds (batch {args.scans})", first_b - steady_b, steady_b))
    # breakdown of one steady run: ray keys + dedupe vs applying the updates
    plan = insert.CapacityPlan()
    for c, o in zip(clouds, origins):
        plan.reserve(c, o, args.res)
    t0 = time.perf_counter()
    for c, o in zip(clouds, origins):
        jax.block_until_ready(insert.compute_update(c, o, args.res, plan=plan).words)
    t_keys = time.perf_counter() - t0

    print(f"{args.scans} scans x {len(clouds[0])} points ({args.width}x{args.height}, ranges 3-5 m), "
          f"res {args.res} m, {jax.device_count()} {jax.devices()[0].platform} device(s)")
    print(f"{'method':48s} {'compile s':>10s} {'steady s':>9s} {'Mpts/s':>8s} {'vs OctoMap':>10s}")
    for name, comp, s in rows:
        print(f"{name:48s} {comp:10.2f} {s:9.2f} {n_pts / s / 1e6:8.3f} {oct_s / s:9.2f}x")
    print(f"  of which ray keys + dedupe (compute_update, all scans): {t_keys:.2f} s")
    print(f"leaves: ours {m.num_leaves} (batched {mb.num_leaves}), OctoMap {tree.getNumLeafNodes()}")


if __name__ == "__main__":
    main()
