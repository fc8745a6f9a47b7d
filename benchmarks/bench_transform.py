"""Benchmark: map transformation (``resample.transform_map``) on generated building maps.

Sizes: one generated building floor (~0.4M leaves), tiled 2x2 (~1.7M) and 4x4 (~7M), all
transformed by yaw pi/4 plus a translation. For each size, in a fresh subprocess (so peak
memory is per size): first call (compile + run) apart from the median of steady runs of the
public ``transform_map`` (wall and process CPU, ``block_until_ready``), the phases of a
steady run timed apart (host planning, jitted brick kernel, maximal prune), destination
voxels per second and the peak resident memory.

Peer: the thesis algorithm (Alg. 7 with the correct inverse, a dense scan of the transformed
bounding box) in C++ on OctoMap 1.10. If ``benchmarks/alg7_octomap.cpp`` can be built
(g++ and ``pip install cmeel-octomap``) it runs on the same maps in the same run; otherwise the
anchor figures measured on this 2-core machine are quoted (1.37 s / 6.3 s / 27.6 s for
311k / 1.2M / 4.7M-leaf sources of a real 0.08 m building map).

Usage: ``.venv/bin/python benchmarks/bench_transform.py [--sizes 1,2,4] [--repeats 3]
[--method trilinear] [--no-cpp]``
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

import _octomap_peer

HERE = Path(__file__).resolve().parent

RES = 0.05
TOP = 50  # ceiling height in voxels (2.5 m)
NOISE = 0.03  # share of surface voxels with less than saturated values (tunes the leaf count)
GRID = (256, 256, 64)  # one building floor: 12.8 m x 12.8 m x 3.2 m at 5 cm
ANCHOR_S = {1: 1.37, 2: 6.3, 4: 27.6}  # C++ Alg. 7, 311k / 1.2M / 4.7M-leaf sources
ANCHOR_LEAVES = {1: 311_000, 2: 1_200_000, 4: 4_700_000}


# ----------------------------------------------------------------------------- map generator


def building_floor(seed: int = 0) -> np.ndarray:
    """Dense ``GRID`` of log-odds (NaN = unknown) for one floor: outer walls, partition walls
    with doors, floor and ceiling slabs, furniture boxes (occluded insides unknown), free
    space with the value spread of real scans near surfaces, a few unobserved pockets."""
    from octomerge_jax.map import logit

    rng = np.random.default_rng(seed)
    nx, ny, nz = GRID
    l_min, l_max = float(logit(0.1192)), float(logit(0.971))
    hit, miss = float(logit(0.7)), float(logit(0.4))
    v = np.full(GRID, np.nan, np.float32)
    x0, x1, y0, y1 = 6, nx - 6, 6, ny - 6
    v[x0:x1, y0:y1, 0:TOP] = l_min  # observed free space inside the building
    occ = np.zeros(GRID, bool)
    occ[x0:x1, y0:y1, 0:2] = True  # floor slab
    occ[x0:x1, y0:y1, TOP - 2:TOP] = True  # ceiling slab
    for a, b in ((x0, x0 + 2), (x1 - 2, x1)):
        occ[a:b, y0:y1, :TOP] = True
    for a, b in ((y0, y0 + 2), (y1 - 2, y1)):
        occ[x0:x1, a:b, :TOP] = True
    for wx in (70, 140, 200):  # partition walls with doors
        occ[wx:wx + 2, y0:y1, :TOP] = True
        for d in rng.integers(y0 + 10, y1 - 30, size=2):
            occ[wx:wx + 2, d:d + 18, 2:44] = False
    for wy in (90, 170):
        occ[x0:x1, wy:wy + 2, :TOP] = True
        for d in rng.integers(x0 + 10, x1 - 30, size=3):
            occ[d:d + 18, wy:wy + 2, 2:44] = False
    inside_unknown = np.zeros(GRID, bool)
    for _ in range(40):  # furniture: occupied shell, unknown inside
        sx, sy, sz = rng.integers(6, 30), rng.integers(6, 30), rng.integers(8, 36)
        cx, cy = rng.integers(x0 + 4, x1 - sx - 4), rng.integers(y0 + 4, y1 - sy - 4)
        occ[cx:cx + sx, cy:cy + sy, 2:2 + sz] = True
        inside_unknown[cx + 1:cx + sx - 1, cy + 1:cy + sy - 1, 2:1 + sz] = True
    # Free voxels near surfaces carry the spread of real updates (1..4 misses, or mixed).
    near = np.zeros(GRID, bool)
    for ax in range(3):
        for s in (-2, -1, 1, 2):
            near |= np.roll(occ, s, axis=ax)
    free_noisy = near & ~occ & ~np.isnan(v) & (rng.random(GRID) < NOISE)
    v[free_noisy] = np.maximum(l_min, miss * rng.integers(1, 5, size=int(free_noisy.sum())))
    occ_vals = np.where(rng.random(int(occ.sum())) < NOISE, hit * rng.integers(1, 4, size=int(occ.sum())),
                        l_max).astype(np.float32)
    v[occ] = occ_vals
    v[inside_unknown & ~occ] = np.nan
    for _ in range(300):  # unobserved pockets in free space
        c = rng.integers([x0, y0, 4], [x1 - 8, y1 - 8, 52])
        s = rng.integers(2, 8, size=3)
        pocket = v[c[0]:c[0] + s[0], c[1]:c[1] + s[1], c[2]:c[2] + s[2]]
        pocket[pocket == l_min] = np.nan
    return v


def grid_to_leaves(v: np.ndarray, origin_key) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Maximal pruning of a dense grid (NaN unknown) -> (codes uint64, depths, log_odds)."""
    from octomerge_jax import morton

    codes, depths, values = [], [], []
    val, uni = v, ~np.isnan(v)
    level = 0
    origin = np.asarray(origin_key, np.int64)
    while True:
        can_up = all(s % 2 == 0 for s in val.shape) and level < 6
        if can_up:
            X, Y, Z = (s // 2 for s in val.shape)
            cv = val.reshape(X, 2, Y, 2, Z, 2).transpose(0, 2, 4, 1, 3, 5).reshape(X, Y, Z, 8)
            cu = uni.reshape(X, 2, Y, 2, Z, 2).transpose(0, 2, 4, 1, 3, 5).reshape(X, Y, Z, 8)
            puni = cu.all(-1) & (cv == cv[..., :1]).all(-1)
            parent_uni_here = np.repeat(np.repeat(np.repeat(puni, 2, 0), 2, 1), 2, 2)
        else:
            parent_uni_here = np.zeros(val.shape, bool)
        leaf = uni & ~parent_uni_here
        idx = np.argwhere(leaf)
        keys = origin + idx * (1 << level)
        codes.append(morton.keys_to_codes(keys.astype(np.uint16)))
        depths.append(np.full(len(idx), 16 - level, np.int32))
        values.append(val[leaf].astype(np.float32))
        if not can_up:
            break
        val, uni, level = cv[..., 0], puni, level + 1
    return np.concatenate(codes), np.concatenate(depths), np.concatenate(values)


def tiled_map(tiles: int):
    """The floor tiled ``tiles x tiles`` (neighbouring copies share no voxels)."""
    from octomerge_jax import map as mp

    v = building_floor()
    origin = np.array([32768 - 512, 32768 - 512, 32768 - 32])
    c, d, lo = grid_to_leaves(v, origin)
    from octomerge_jax import morton
    keys = morton.codes_to_keys(c).astype(np.int64)
    parts_c, parts_d, parts_l = [], [], []
    for i in range(tiles):
        for j in range(tiles):
            k = keys + np.array([i * GRID[0], j * GRID[1], 0])
            parts_c.append(morton.keys_to_codes(k.astype(np.uint16)))
            parts_d.append(d)
            parts_l.append(lo)
    return mp.from_leaves(np.concatenate(parts_c), np.concatenate(parts_d),
                          np.concatenate(parts_l), RES)


def transform(tiles: int) -> np.ndarray:
    yaw = np.pi / 4
    T = np.eye(4)
    T[:3, :3] = [[np.cos(yaw), -np.sin(yaw), 0], [np.sin(yaw), np.cos(yaw), 0], [0, 0, 1]]
    T[:3, 3] = [1.3, -0.7, 0.2]
    return T


# ----------------------------------------------------------------------------- one size


def _rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def run_size(tiles: int, repeats: int, method: str, dump: str | None) -> dict:
    import jax

    from octomerge_jax import resample

    m = tiled_map(tiles)
    jax.block_until_ready(m.code)
    if dump:
        with open(dump, "wb") as fh:
            _octomap_peer.write_leaves(fh, m)
            transform(tiles).astype(np.float64).tofile(fh)
    rss_before = _rss_mb()
    T = transform(tiles)
    t0 = time.perf_counter()
    out = resample.transform_map(m, T, method=method)
    jax.block_until_ready(out.code)
    first = time.perf_counter() - t0
    totals, plans, kernels, prunes, cpus = [], [], [], [], []
    for _ in range(repeats):
        # The public call, end to end (checks, bounds, plan, kernel, prune).
        c0 = time.process_time()
        t0 = time.perf_counter()
        out = resample.transform_map(m, T, method=method)
        jax.block_until_ready(out.code)
        totals.append(time.perf_counter() - t0)
        cpus.append(time.process_time() - c0)  # all threads
        # Its phases, timed apart.
        t0 = time.perf_counter()
        plan = resample._bricks.make_plan(m, resample.check_rigid_transform(T), method,
                                         "probability", 128, None)
        jax.block_until_ready(plan.inputs)
        t1 = time.perf_counter()
        raw, _ = resample._kernel.run_kernel(plan)
        jax.block_until_ready(raw.code)
        t2 = time.perf_counter()
        again = resample._kernel.run_kernel(plan)  # kernel again + prune
        c = plan.cells
        jax.block_until_ready(resample._merge.merge_with_cells(
            *again, c.codes, c.depths, c.log_odds, m).code)
        t3 = time.perf_counter()
        plans.append(t1 - t0)
        kernels.append(t2 - t1)
        prunes.append(max(0.0, (t3 - t2) - (t2 - t1)))
    n_out = out.num_leaves
    vox_known = int(np.sum(8.0 ** (16 - np.asarray(out.depth[:n_out]).astype(np.float64))))
    n_src = m.num_leaves
    src_bytes = n_src * 16
    dense_bytes = plan.inputs.table.nbytes + plan.inputs.A.nbytes
    out_bytes = n_out * 16
    return dict(tiles=tiles, src_leaves=n_src, out_leaves=n_out, dest_bricks=plan.n_dest_bricks,
                dense_bricks=plan.n_dense_bricks, dest_voxels=vox_known,
                scanned_voxels=plan.n_dest_bricks * 512, first_s=first,
                median_s=statistics.median(totals), cpu_s=statistics.median(cpus), plan_s=statistics.median(plans),
                kernel_s=statistics.median(kernels), prune_s=statistics.median(prunes),
                rss_before_mb=rss_before, peak_rss_mb=_rss_mb(), src_mb=src_bytes / 2**20,
                dense_mb=dense_bytes / 2**20, out_mb=out_bytes / 2**20)


# ----------------------------------------------------------------------------- main


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sizes", default="1,2,4", help="tilings to run (1 = one floor)")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--method", default="trilinear")
    ap.add_argument("--no-cpp", action="store_true", help="skip the C++ Alg. 7 peer")
    ap.add_argument("--child", type=int, help=argparse.SUPPRESS)
    ap.add_argument("--dump", help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.child:
        print(json.dumps(run_size(a.child, a.repeats, a.method, a.dump)))
        return
    exe = None if a.no_cpp else _octomap_peer.build("alg7_octomap")
    import jax
    print(f"# transform_map benchmark: yaw pi/4 + translation, method={a.method}, "
          f"jax {jax.__version__} on {jax.devices()[0].platform}, {os.cpu_count()} CPUs, "
          f"res {RES} m")
    hdr = (f"{'tiles':>5} {'src leaves':>10} {'out leaves':>10} {'dest vox':>11} "
           f"{'first s':>8} {'median s':>8} {'cpu s':>6} {'plan':>6} {'kernel':>6} {'prune':>6} "
           f"{'Mvox/s':>7} {'peak MB':>8} {'src/dense/out MB':>17} {'peer s':>7} {'peer cpu':>8} "
           f"{'x wall':>7} {'x cpu':>6}")
    print(hdr)
    for tiles in [int(s) for s in a.sizes.split(",")]:
        dump = str(HERE / "_build" / f"map_{tiles}.bin") if exe else None
        cmd = [sys.executable, __file__, "--child", str(tiles), "--repeats", str(a.repeats),
               "--method", a.method] + (["--dump", dump] if dump else [])
        r = subprocess.run(cmd, capture_output=True, text=True)
        if r.returncode != 0:
            print(r.stderr[-3000:], file=sys.stderr)
            continue
        s = json.loads(r.stdout.strip().splitlines()[-1])
        peer, peer_cpu, label = None, None, ""
        if exe and dump:
            c = _octomap_peer.run(exe, dump)
            if c:
                peer, peer_cpu = c["seconds"], c["cpu_seconds"]
                label = "C++"
        if peer is None and tiles in ANCHOR_S:
            peer, label = ANCHOR_S[tiles], "anch"
        ratio = f"{peer / s['median_s']:6.1f}x" if peer else "     -"
        ratio_cpu = f"{peer_cpu / s['cpu_s']:5.1f}x" if peer_cpu else "     -"
        mb = f"{s['src_mb']:.0f}/{s['dense_mb']:.0f}/{s['out_mb']:.0f}"
        print(f"{tiles:>3}x{tiles:<1} {s['src_leaves']:>10,} {s['out_leaves']:>10,} "
              f"{s['dest_voxels']:>11,} {s['first_s']:>8.2f} {s['median_s']:>8.3f} {s['cpu_s']:>6.2f} "
              f"{s['plan_s']:>6.2f} {s['kernel_s']:>6.2f} {s['prune_s']:>6.2f} "
              f"{s['dest_voxels'] / s['median_s'] / 1e6:>7.1f} {s['peak_rss_mb']:>8.0f} "
              f"{mb:>17} {(f'{peer:.2f}' if peer else '-'):>6}{label[:1]} "
              f"{(f'{peer_cpu:.2f}' if peer_cpu else '-'):>8} {ratio:>7} {ratio_cpu:>6}")
        sys.stdout.flush()
    print("# median s / cpu s: wall / process CPU time (all threads; robust on a shared, loaded"
          " machine) of a steady transform_map call; plan, kernel, prune: its phases timed apart;"
          " x wall / x cpu: peer time / ours.")
    print("# dest vox: known destination voxels at depth 16 (after expansion of the output);"
          " Mvox/s = dest vox / median.")
    print("# peak MB: process peak RSS (includes the map generator); src/dense/out MB: source "
          "leaves, dense source brick table, output leaves (16 B per leaf).")
    print("# peer: 'C' = C++ Alg. 7 on OctoMap in this run; 'a' = anchor measured earlier on "
          f"a real 0.08 m map of {', '.join(f'{v:,}' for v in ANCHOR_LEAVES.values())} leaves.")


if __name__ == "__main__":
    main()
