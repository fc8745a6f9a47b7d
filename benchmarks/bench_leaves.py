"""Benchmark: ``transform_map`` and ``octomerge merge`` cost in proportion to leaves, not volume.

Part 1, coarse leaves: a map of free leaves at every depth 1-12 (a few hundred bytes as ``.bt``)
merged with itself by ``octomerge merge --refine none`` (identity: every leaf carried over) and
with a yaw of 0.3 rad (the leaves' faces leave the lattice, so the exact output has billions of
finest leaves: the memory budget must refuse it with a one-line error). Each command runs in a
fresh process: wall time, exit status, peak RSS (``getrusage`` of the child), the error line.

Part 2, outdoor maps: the simulated ``campus`` scanned by a 16-beam lidar with long-range rays,
inserted at 0.2 m and pruned (large free leaves), the first 1/8, 1/4, 1/2 and all scans; each
map transformed by a yaw plus a translation in a fresh subprocess: source leaves, output leaves,
coarsest leaf depth, first call and steady
time, peak RSS. With ``--baseline DIR`` (a checkout of the package before this change) the same
maps run there too, under ``--baseline-budget`` of address space.

Usage: ``.venv/bin/python benchmarks/bench_leaves.py [--fractions 0.125,0.25,0.5,1]
[--baseline DIR] [--skip-cli]``
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
RES = 0.2
YAW = 0.3  # rad
SHIFT = (1.3, -0.7, 0.2)  # m


# ----------------------------------------------------------------------------- maps


def coarse_leaves_map(resolution: float = 0.1, top: int = 1):
    """Free leaves at every depth ``top``-12, nested towards the origin: at each depth 6 of the 8
    children of the node above are free leaves (two free values alternating, so they do not
    prune), one is unknown and one is split further."""
    from octomerge_jax import map as mp
    from octomerge_jax import morton

    keys, depths, vals = [], [], []
    free = (float(mp.logit(0.1192)), float(mp.logit(0.3)))
    for d in range(top, 13):
        size = 1 << (16 - d)
        node = ((morton.KEY_OFFSET - 1) >> (17 - d)) << (17 - d)
        split = ((morton.KEY_OFFSET - 1) >> (16 - d)) << (16 - d)
        for c in range(8):
            child = np.array([node + ((c >> a) & 1) * size for a in range(3)])
            if np.all(child == split) or c == 3:
                continue
            keys.append(child)
            depths.append(d)
            vals.append(free[(c + d) % 2])
    codes = morton.keys_to_codes(np.array(keys, np.uint64))
    return mp.from_leaves(codes, np.array(depths), np.array(vals, np.float32), resolution)


def outdoor_map(step: int = 8, seed: int = 0):
    """The campus (robot 1's path, every ``step``-th pose) scanned by a 16-beam lidar with 80 m
    rays, inserted at ``RES`` (OctoMap ``insertPointCloud``), then taken as a long-observed
    site: maximum likelihood (occupied voxels at the upper clamp), and every voxel of the
    scanned box farther than one voxel from an occupied one free at the lower clamp (one pass
    of a 16-beam lidar leaves gaps between its beams; many passes close them), pruned.
    Returns the map (large free leaves between the buildings)."""
    from octomerge_jax import map as mp
    from octomerge_jax import morton, sim, tree

    sc = sim.make_scene("campus", seed)
    lidar = sim.SpinningLidar(max_range=80.0)
    poses = sim.poses_along_path(sc.paths[0], sc.spacing or 2.0, sc.sensor_height,
                                 sc.targets[0], sc.closed[0])[::step]
    m = sim.build_map(sim.scan(lidar, sc.triangles, poses, seed=seed), poses, RES, 80.0)
    lv = m.leaves()
    keys = morton.codes_to_keys(lv.codes).astype(np.int64)
    k0 = keys.min(axis=0)
    ext = (keys + (1 << (16 - lv.depths.astype(np.int64)))[:, None]).max(axis=0) - k0
    occ = np.zeros(tuple(ext), bool)
    for d in np.unique(lv.depths):
        sel = (lv.depths == d) & (lv.log_odds > 0)
        s = 1 << (16 - int(d))
        g = np.stack(np.meshgrid(*[np.arange(s)] * 3, indexing="ij"), -1).reshape(-1, 3)
        k = (keys[sel, None, :] + g[None] - k0).reshape(-1, 3)
        occ[k[:, 0], k[:, 1], k[:, 2]] = True
    near = occ.copy()
    for a in range(3):  # dilate by one voxel (6-neighbourhood), axis by axis
        lo_, hi_ = [slice(None)] * 3, [slice(None)] * 3
        lo_[a], hi_[a] = slice(1, None), slice(None, -1)
        near[tuple(lo_)] |= occ[tuple(hi_)]
        near[tuple(hi_)] |= occ[tuple(lo_)]
    fk, ok = np.argwhere(~near) + k0, np.argwhere(occ) + k0
    codes = morton.keys_to_codes(np.concatenate([fk, ok]).astype(np.uint64))
    values = np.concatenate([np.full(len(fk), mp.logit(0.1192), np.float32),
                             np.full(len(ok), mp.logit(0.971), np.float32)])
    return tree.prune(mp.from_leaves(codes, np.full(codes.size, 16), values, RES))


def crop(m, fraction: float):
    """The leaves of ``m`` whose centres lie in the first ``fraction`` of its x extent."""
    from octomerge_jax import map as mp

    lv = m.leaves()
    x = lv.centers[:, 0]
    cut = x.min() + fraction * (x.max() - x.min()) + 1e-9
    keep = x <= cut
    return mp.from_leaves(lv.codes[keep], lv.depths[keep], lv.log_odds[keep], m.resolution)


def yaw_T():
    c, s = np.cos(YAW), np.sin(YAW)
    T = np.eye(4)
    T[:3, :3] = [[c, -s, 0], [s, c, 0], [0, 0, 1]]
    T[:3, 3] = SHIFT
    return T


# ----------------------------------------------------------------------------- children


def child_transform(path: str, repeats: int) -> dict:
    import jax

    from octomerge_jax import io, resample

    m = io.load(path)
    T = yaw_T()
    t0 = time.perf_counter()
    out = resample.transform_map(m, T)
    jax.block_until_ready(out.code)
    first = time.perf_counter() - t0
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = resample.transform_map(m, T)
        jax.block_until_ready(out.code)
        times.append(time.perf_counter() - t0)
    row = dict(src_leaves=m.num_leaves, out_leaves=out.num_leaves,
               min_depth=int(np.asarray(m.depth)[:m.num_leaves].min()), first_s=first,
               steady_s=float(np.median(times)))
    return row


def run_child(args: list[str], pythonpath: Path, limit_bytes: int | None = None,
              env_extra: dict | None = None, timeout_s: float = 1800):
    """Run ``python args`` as a child: ``(last JSON line or None, wall s, peak RSS MB, rc,
    stderr lines)``; ``limit_bytes``: its address space (``ulimit -v``). Needs GNU time."""
    env = dict(os.environ, PYTHONPATH=str(pythonpath), OCTOMERGE_CACHE_DIR="off",
               **(env_extra or {}))
    # GNU time reports the peak RSS of the exec'd command alone (a forked child's own high-water
    # mark would include this process's pages at the fork)
    cmd = ["/usr/bin/time", "-f", "maxrss_kb=%M", sys.executable, *args]
    if limit_bytes:
        cmd = ["sh", "-c", f'ulimit -v {limit_bytes // 1024}; exec "$@"', "sh", *cmd]
    with tempfile.TemporaryFile("w+") as out, tempfile.TemporaryFile("w+") as err:
        t0 = time.perf_counter()
        rc = subprocess.run(cmd, env=env, stdout=out, stderr=err, cwd=str(pythonpath),
                            timeout=timeout_s).returncode
        wall = time.perf_counter() - t0
        out.seek(0)
        err.seek(0)
        stdout, lines = out.read(), err.read().strip().splitlines()
    peak = float("nan")
    if lines and lines[-1].startswith("maxrss_kb="):
        peak = int(lines.pop().split("=")[1]) / 1024
    lines = [x for x in lines if not x.startswith("Command exited with non-zero status")]
    row = None
    for line in stdout.splitlines()[::-1]:
        if line.startswith("{"):
            row = json.loads(line)
            break
    return row, wall, peak, rc, lines


# ----------------------------------------------------------------------------- main


def part_cli(tmp: Path) -> None:
    from octomerge_jax import io

    print("\n# coarse free leaves, octomerge merge of a map with itself (fresh process, compile "
          "cache off, OCTOMERGE_MEMORY_BUDGET=2G)")
    print(f"{'map':<26} {'bytes':>6} {'command':<36} {'rc':>3} {'wall s':>7} {'peak MB':>8}  "
          f"result")
    for top, extra in ((1, []), (3, ["--rpy", "0", "0", str(YAW)])):
        m = coarse_leaves_map(top=top)
        path = tmp / f"coarse{top}.bt"
        io.save(m, path)
        out = tmp / "out.bt"
        args = ["-m", "octomerge_jax", "merge", str(path), str(path), str(out), "--refine",
                "none", "--force", "-q", *extra]
        _, wall, peak, rc, err = run_child(args, ROOT, env_extra={"OCTOMERGE_MEMORY_BUDGET": "2G"})
        result = err[-1] if err else ""
        if rc == 0:
            result = f"wrote {io.load(out).num_leaves} leaves"
        label = "merge --refine none" + (" --rpy 0 0 0.3" if extra else "")
        name = f"{m.num_leaves} leaves, depths {top}-12"
        print(f"{name:<26} {path.stat().st_size:>6} {label:<36} {rc:>3} {wall:>7.1f} {peak:>8.0f}  "
              f"{result[:160]}")


def part_outdoor(tmp: Path, fractions, repeats: int, baseline: Path | None,
                 baseline_budget: int) -> None:
    from octomerge_jax import io

    t0 = time.perf_counter()
    site = outdoor_map()
    print(f"\n# outdoor: campus, 16-beam lidar, 80 m rays, {RES} m, long-observed and pruned "
          f"({site.num_leaves:,} leaves, built in {time.perf_counter() - t0:.0f} s), cropped "
          f"to a share of its x extent; transform_map yaw {YAW} rad + {SHIFT} m, each size in "
          f"a fresh process (compile cache off)")
    head = (f"{'crop':>6} {'src leaves':>11} {'min d':>5} {'out leaves':>11} "
            f"{'first s':>8} {'steady s':>9} {'us/leaf':>8} {'peak MB':>8}")
    if baseline:
        head += f" | {'before: steady s':>16} {'peak MB':>8}"
    print(head)
    for f in fractions:
        path = tmp / f"campus_{f}.bt"
        io.save(crop(site, f), path)
        row, _, peak, rc, err = run_child([str(HERE / "bench_leaves.py"), "--child", str(path),
                                           "--repeats", str(repeats)], ROOT)
        if row is None:
            print(f"{f:>6} failed: {err[-1] if err else rc}")
            continue
        us = row["steady_s"] / max(row["out_leaves"], 1) * 1e6
        line = (f"{f:>6} {row['src_leaves']:>11,} {row['min_depth']:>5} {row['out_leaves']:>11,} "
                f"{row['first_s']:>8.2f} "
                f"{row['steady_s']:>9.3f} {us:>8.2f} {peak:>8.0f}")
        if baseline:
            old, wall, old_peak, rc, err = run_child(
                [str(HERE / "bench_leaves.py"), "--child", str(path), "--repeats", str(repeats)],
                baseline, baseline_budget)
            if old is None:
                why = next((e for e in err[::-1] if "Error" in e), f"exit {rc}")
                line += f" | failed after {wall:.0f} s: {why[:60]}"
            else:
                line += f" | {old['steady_s']:>16.3f} {old_peak:>8.0f}"
        print(line, flush=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--fractions", default="0.125,0.25,0.5,1")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--baseline", type=Path, help="package checkout before this change")
    ap.add_argument("--baseline-budget", type=float, default=8.0, help="GiB of address space")
    ap.add_argument("--skip-cli", action="store_true")
    ap.add_argument("--skip-outdoor", action="store_true")
    ap.add_argument("--child", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        print(json.dumps(child_transform(args.child, args.repeats)))
        return
    import jax

    print(f"# bench_leaves: jax {jax.__version__} on {jax.default_backend()}, "
          f"{os.cpu_count()} CPUs, {time.strftime('%Y-%m-%d')}")
    with tempfile.TemporaryDirectory() as tmp:
        if not args.skip_cli:
            part_cli(Path(tmp))
        if not args.skip_outdoor:
            part_outdoor(Path(tmp), [float(x) for x in args.fractions.split(",") if x],
                         args.repeats, args.baseline, int(args.baseline_budget * 2**30))


if __name__ == "__main__":
    main()
