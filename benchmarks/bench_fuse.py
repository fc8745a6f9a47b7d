"""Benchmark: log-odds fusion of two maps (``fuse``) and of m maps (``fuse_many`` vs a fold).

Maps: a generated building (rooms of voxelised walls, floor and ceiling, free space inside;
noisy log-odds so only part of the free space prunes), cut into two overlapping crops along x
(~20 % overlap); the second crop is converted to maximum likelihood (clamp values), so it is
pruned coarser than the first - the depth conflicts of thesis §5.2.3 cases 3 and 4.
Leaf arrays are built directly in NumPy (finest voxels + a NumPy maximal prune).

Anchor (issue 4): the thesis merge loop (Alg. 8) in C++ on OctoMap 1.10 on this 2-core CPU,
real building map pairs: merge 0.10 s / 0.37 s / 1.53 s for 258k+311k / 1.1M+1.2M /
4.4M+4.7M leaves, plus pruning 0.05 / 0.20 / 0.74 s. We compare leaves per second
(n1 + n2) / (merge + prune) at the nearest anchor size. Target: >= 3x.

Live peer: that loop itself, ``alg8_octomap.cpp`` (Alg. 8 on OctoMap 1.10 with A.3's bugs fixed,
one root-to-leaf walk of M1 per M2 leaf, then ``OcTree::prune``), built when g++ and
cmeel-octomap exist (the ``bench`` extra) and run on the same pair in the same run (median of
``--repeats``, trees rebuilt untimed before each): ``x octomap`` is its merge + prune time over
ours, and ``same`` says whether its merged leaves equal ours (an independent check at 4M leaves).
Its trees are built in Morton order, the node layout ``OcTree::read`` gives a ``.bt`` file; ``x
shuffled`` is the same ratio on trees built in a random order (nodes scattered in memory, as in a map
grown by scan insertion over a long run), where each walk misses the cache far more.

``fuse_many`` vs the fold ``fuse(fuse(m0, m1), m2) ...`` on m crops of the small building in two
layouts (``many_maps``): ``slide`` (each voxel in one or two maps) and ``shared`` (each voxel in
up to m maps, as m robots exploring the same building).

Pair kind ``robots`` (``--pairs ml,noisy,robots``, sizes small / medium): two simulated robots' maps
of the office read from ``.bt`` bytes, map 2 transformed into map 1's frame, as ``fuse`` gets them in
a merge (slow to simulate; ``gaps`` column: gap cells of the refinement).

Usage: ``python benchmarks/bench_fuse.py [--sizes small,medium,large] [--pairs ml,noisy] [--repeats 3] [--no-cpp]``
Each pair is timed at its refinement's own capacity bucket (``capacity=``, as a batch that reuses
a report would call it); ``def cap`` / ``x default``: the capacity ``fuse(m1, m2)`` plans without
one and that call's anchor ratio (median, timed alternately with the call at ``cap``).
Prints a table; compile (first call) is reported apart from the steady-state median
(``block_until_ready``; ``fuse`` with and without pruning called alternately, at least
``--repeats`` times each and 2 s in all, since a 20 ms call's median over 3 calls swings 1.5x on
this VM; ``x, IQR``: the anchor ratio at the quartiles of the call times). Peak memory is the
process peak RSS after each row.
"""

from __future__ import annotations

import argparse
import os
import resource
import statistics
import time

import _host_memory
import _octomap_peer
import jax
import numpy as np

from octomerge_jax import map as omap
from octomerge_jax import morton

from octomerge_jax import fusion as F

RES = 0.1
P = omap.OccupancyParams()
LMIN, LMAX = np.float32(P.clamp_min_log_odds), np.float32(P.clamp_max_log_odds)
U1 = np.uint64(1)

# size name -> building grid (x, y, z voxels); rows give ~0.2M / ~0.8M / ~3M leaves per crop
SIZES = {"small": (120, 96, 36), "medium": (240, 180, 38), "large": (480, 280, 48)}
ANCHORS = [  # (n1 + n2, merge s, prune s) of the thesis C++ loop
    (258_000 + 311_000, 0.10, 0.05),
    (1_100_000 + 1_200_000, 0.37, 0.20),
    (4_400_000 + 4_700_000, 1.53, 0.74),
]


def _span(depth):
    return U1 << (np.uint64(3) * (np.uint64(16) - np.asarray(depth).astype(np.uint64)))


def numpy_prune(codes, depths, values):
    """Maximal prune on host arrays (8 equal siblings -> parent, bottom-up, not the root)."""
    for d in range(16, 1, -1):
        at = np.flatnonzero(depths == d)
        if at.size == 0:
            continue
        parent = codes[at] & ~(_span(d - 1) - U1)
        vals = values[at]
        brk = np.flatnonzero(np.diff(parent)) + 1
        start = np.concatenate([[0], brk])
        cnt = np.diff(np.concatenate([start, [at.size]]))
        vmin = np.minimum.reduceat(vals, start)
        vmax = np.maximum.reduceat(vals, start)
        ok = (cnt == 8) & (vmin == vmax)
        if not ok.any():
            continue
        grp = np.repeat(np.arange(start.size), cnt)
        drop = at[ok[grp]]
        keep = np.ones(codes.size, bool)
        keep[drop] = False
        first = at[start[ok]]
        keep[first] = True  # the first child's row becomes the parent (same min code)
        depths = depths.copy()
        values = values.copy()
        depths[first] = d - 1
        values[first] = vmin[ok]
        codes, depths, values = codes[keep], depths[keep], values[keep]
    return codes, depths, values


def building(shape, rng):
    """Finest voxels of a building: keys (n, 3) and two independent noisy log-odds fields."""
    X, Y, Z = shape
    x, y, z = np.meshgrid(np.arange(X), np.arange(Y), np.arange(Z), indexing="ij")
    wall = (x % 40 == 0) | (y % 40 == 0) | (x == X - 1) | (y == Y - 1) | (z == 0) | (z == Z - 1)
    door = ((x % 40 == 0) & (y % 40 > 15) & (y % 40 < 24) & (z < 22)) | \
           ((y % 40 == 0) & (x % 40 > 15) & (x % 40 < 24) & (z < 22))
    occ = (wall & ~door).ravel()
    keys = np.stack([x.ravel(), y.ravel(), z.ravel()], -1).astype(np.int64) + 32768 - 64
    fields = []
    for _ in range(2):
        r = rng.random(occ.size)
        v = np.where(occ, np.where(r < 0.7, LMAX, np.float32(0.85) * (1 + (r * 10).astype(np.int32) % 3)),
                     np.where(r < 0.85, LMIN, np.float32(-0.4) * (1 + (r * 10).astype(np.int32) % 4)))
        fields.append(np.clip(v.astype(np.float32), LMIN, LMAX))
    return keys.astype(np.uint16), fields


def crop_map(keys, values, mask, ml=False):
    codes = morton.keys_to_codes(keys[mask])
    v = values[mask]
    if ml:
        v = np.where(v >= 0, LMAX, LMIN).astype(np.float32)
    order = np.argsort(codes)
    c, d, v = numpy_prune(codes[order], np.full(codes.size, 16, np.int64), v[order])
    return omap.from_leaves(c, d, v, RES, check=False)


# pair kind "robots": the package's simulated office, two robots' maps at this resolution per size
ROBOT_RES = {"small": 0.05, "medium": 0.025}


def robot_pair(name):
    """``name`` a key of ``ROBOT_RES``. Two simulated robots' maps of the office (``make_two_robot_maps``), each written and read
    back as ``.bt`` bytes (maximum likelihood, as maps are exchanged), map 2 transformed into
    map 1's frame by the true transform (``transform_map``): what ``fuse`` gets in a merge. Gap
    cells are far more common here (3-8 % of the refinement) than on the building crops."""
    import octomerge_jax as om

    m1, m2, T = om.make_two_robot_maps("office", resolution=ROBOT_RES[name], seed=0)
    m1, m2 = (om.from_bytes(om.to_bytes(m, True, header=True)) for m in (m1, m2))
    return m1, om.transform_map(m2, T)


def make_pair(shape, seed=0, kind="ml"):
    """Two crops of one building: ``"ml"``, the second converted to maximum likelihood (pruned
    coarser: fewer, larger leaves, depth conflicts); ``"noisy"``, both with their own noise
    (leaf counts alike, as two robots' maps of one building). (``"robots"``: ``robot_pair``.)"""
    rng = np.random.default_rng(seed)
    keys, (f1, f2) = building(shape, rng)
    x = keys[:, 0].astype(np.int64) - keys[:, 0].min()
    X = shape[0]
    m1 = crop_map(keys, f1, x < int(0.6 * X))
    m2 = crop_map(keys, f2, x >= int(0.4 * X), ml=(kind == "ml"))
    return m1, m2


def timed_pair(f, g, repeats, min_seconds=0.0, spread=False):
    """Steady-state medians of two functions, calls alternated (load drifts on a shared VM):
    at least ``repeats`` calls each, more until both together took ``min_seconds`` (a short
    call's median over 3 calls swings 1.5x here). ``spread``: also each one's (25 %, 75 %)
    quantiles."""
    jax.block_until_ready(f())
    jax.block_until_ready(g())
    ts = ([], [])
    r, t_start = 0, time.perf_counter()
    while r < repeats or time.perf_counter() - t_start < min_seconds:
        for k in ((0, 1) if r % 2 == 0 else (1, 0)):
            t0 = time.perf_counter()
            jax.block_until_ready((f, g)[k]())
            ts[k].append(time.perf_counter() - t0)
        r += 1
    med = statistics.median(ts[0]), statistics.median(ts[1])
    if not spread:
        return med
    return med, tuple(tuple(np.quantile(t, (0.25, 0.75))) for t in ts)


def peak_rss_gb():
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6


def anchor_rate(n):
    n_a, merge, prune = min(ANCHORS, key=lambda a: abs(np.log(a[0] / n)))
    return n_a / (merge + prune), n_a


def _read_merged(path):
    """``alg8_octomap``'s merged leaves as (Morton codes, depths, log-odds), sorted by code."""
    keys, depths, lo = _octomap_peer.read_leaves(path)
    codes = morton.keys_to_codes(keys)
    order = np.argsort(codes, kind="stable")
    return codes[order], depths[order], lo[order]


def run_octomap_peer(exe, name, m1, m2, repeats):
    """Alg. 8 on OctoMap (``alg8_octomap``) on the pair: (its JSON result, merged leaves)."""
    build_dir = _octomap_peer.HERE / "_build"
    dump, merged = build_dir / f"fuse_{name}.bin", build_dir / f"fused_{name}.bin"
    with open(dump, "wb") as fh:
        _octomap_peer.write_leaves(fh, m1)
        _octomap_peer.write_leaves(fh, m2)
        np.array([LMIN, LMAX], np.float32).tofile(fh)
    res = _octomap_peer.run(exe, dump, repeats, merged)
    if res:  # the same merge on trees whose nodes are scattered in memory
        res["shuffled"] = _octomap_peer.run(exe, dump, repeats, "-", "shuffled")
    return (res, _read_merged(merged)) if res else (None, None)


def same_leaves(m, ref):
    codes, depths, lo = ref
    n = m.num_leaves
    lv = m.leaves()
    return (n == codes.size and np.array_equal(morton.keys_to_codes(np.asarray(lv.keys, np.uint16)), codes)
            and np.array_equal(np.asarray(lv.depths), depths) and np.array_equal(np.asarray(lv.log_odds), lo))


def bench_pairs(sizes, kinds, repeats, exe=None):
    print("\n## fuse(m1, m2): two overlapping crops; pair ml: m2 max-likelihood (coarser pruned), "
          "noisy: both noisy; robots: simulated office maps via .bt, map 2 transformed (see robot_pair)")
    hdr = (f"{'size':>7} {'pair':>5} {'n1':>9} {'n2':>9} {'refined':>9} {'gaps':>7} {'out':>9} {'cap':>9} "
           f"{'compile s':>9} {'merge s':>8} {'+prune s':>8} {'Mleaf/s':>8} {'anchor':>12} "
           f"{'x anchor':>8} {'x, IQR':>11} {'def cap':>8} {'x default':>9} {'octomap s':>14} {'x octomap':>9} {'x shuffled':>9} {'same':>5} {'peakGB':>6}")
    print(hdr)
    for name, kind in ((n, k) for n in sizes for k in kinds):
        if kind == "robots" and name not in ROBOT_RES:
            print(f"{name:>7} {kind:>5} (no simulated pair at this size)")
            continue
        m1, m2 = robot_pair(name) if kind == "robots" else make_pair(SIZES[name], kind=kind)
        _, rep = F.fuse_with_report(m1, m2)  # host capacity planning
        cap = omap.bucket_capacity(int(rep.refined_cells))  # the refinement's own bucket
        # gap cells of the refinement: its cells less those of the leaves that are not split
        # (a same-depth pair is one cell)
        n_gap = int(rep.refined_cells) - (m1.num_leaves - int(rep.split[0]) + m2.num_leaves - int(rep.split[1])
                                          - int(rep.same_depth))
        jax.clear_caches()  # the planning call above may have compiled this capacity already
        t0 = time.perf_counter()
        jax.block_until_ready(F.fuse(m1, m2, capacity=cap).code)
        first = time.perf_counter() - t0
        (total, merge), (q_total, _) = timed_pair(
            lambda: F.fuse(m1, m2, capacity=cap).code,
            lambda: F.fuse(m1, m2, capacity=cap, prune=False).code, repeats, min_seconds=2.0, spread=True)
        compile_s = first - total
        n = m1.num_leaves + m2.num_leaves
        rate = n / total
        a_rate, a_n = anchor_rate(n)
        # the default call fuse(m1, m2): the host sizes the output (see fuse's capacity=)
        t_default = timed_pair(lambda: F.fuse(m1, m2, capacity=cap).code, lambda: F.fuse(m1, m2).code,
                               repeats, min_seconds=2.0)[1]
        x_lo, x_hi = (n / q / a_rate for q in q_total[::-1])  # x anchor at the 75 % / 25 % quantile times
        peer, ref = run_octomap_peer(exe, f"{name}_{kind}", m1, m2, repeats) if exe else (None, None)
        if peer:
            p_total = peer["merge_s"] + peer["prune_s"]
            octo = f"{peer['merge_s']:.3f}+{peer['prune_s']:.3f}"
            x_octo = f"{p_total / total:9.2f}"
            sh = peer.get("shuffled")
            x_shuf = f"{(sh['merge_s'] + sh['prune_s']) / total:9.2f}" if sh else "-"
            same = str(same_leaves(F.fuse(m1, m2, capacity=cap), ref))
        else:
            octo, x_octo, x_shuf, same = "-", "-", "-", "-"
        print(f"{name:>7} {kind:>5} {m1.num_leaves:>9} {m2.num_leaves:>9} {int(rep.refined_cells):>9} {n_gap:>7} "
              f"{int(rep.leaves_out):>9} {cap:>9} {compile_s:>9.2f} {merge:>8.3f} "
              f"{total - merge:>8.3f} {rate / 1e6:>8.2f} {f'{a_rate / 1e6:.2f}@{a_n / 1e6:.1f}M':>12} "
              f"{rate / a_rate:>8.2f} {x_lo:>5.2f}-{x_hi:<5.2f} {rep.capacity:>8} {n / t_default / a_rate:>9.2f} {octo:>14} {x_octo:>9} {x_shuf:>9} {same:>5} "
              f"{peak_rss_gb():>6.2f}", flush=True)
    print(f"load average {os.getloadavg()[0]:.2f}")


def many_maps(shape, m, layout):
    """m crops of one building: ``"slide"``, windows sliding along x, each overlapping the next
    by 30 % (every voxel in one or two maps); ``"shared"``, every map sees 85 % of the building
    (windows shifted by up to 15 %) with its own noise (every voxel in up to m maps). Odd maps
    are maximum likelihood (coarser pruned)."""
    fields = []
    for s in range(1 if layout == "slide" else (m + 1) // 2):
        keys, fs = building(shape, np.random.default_rng(1 + s))
        fields += fs
    x = keys[:, 0].astype(np.int64) - keys[:, 0].min()
    X = shape[0]
    maps = []
    for k in range(m):
        if layout == "slide":
            width = X / (0.7 * m + 0.3)
            lo, vals = int(k * 0.7 * width), fields[k % 2]
        else:
            width, lo, vals = 0.85 * X, int(0.15 * X * k / max(m - 1, 1)), fields[k]
        maps.append(crop_map(keys, vals, (x >= lo) & (x < lo + int(width)), ml=(k % 2 == 1)))
    return maps


def bench_many(shape, ms, layout, repeats):
    print(f"\n## fuse_many vs fold of fuse (sum), m crops of a {shape} building, {layout!r} layout")
    print(f"{'m':>3} {'leaves':>9} {'fold s':>8} {'many s':>8} {'fold/many':>9} {'equal':>6}")
    for m in ms:
        maps = many_maps(shape, m, layout)
        # plan the fold's capacities once (host), then time the steady fold with them; every
        # call (each fold step and fuse_many) runs at its own refinement's bucket
        caps, acc = [], maps[0]
        for mk in maps[1:]:
            acc, rep = F.fuse_with_report(acc, mk)
            caps.append(omap.bucket_capacity(int(rep.refined_cells)))
        fold_out = acc

        def fold():
            a = maps[0]
            for mk, c in zip(maps[1:], caps):
                a = F.fuse(a, mk, capacity=c)
            return a.code

        many_out, rep = F.fuse_many_with_report(maps)
        cap = omap.bucket_capacity(int(rep.refined_cells))
        tf, tm = timed_pair(fold, lambda: F.fuse_many(maps, capacity=cap).code, repeats)
        n = fold_out.num_leaves
        same = (n == many_out.num_leaves and
                np.array_equal(np.asarray(fold_out.code[:n]), np.asarray(many_out.code[:n])) and
                np.array_equal(np.asarray(fold_out.log_odds[:n]), np.asarray(many_out.log_odds[:n])))
        print(f"{m:>3} {sum(mm.num_leaves for mm in maps):>9} {tf:>8.3f} {tm:>8.3f} {tf / tm:>9.2f} "
              f"{str(same):>6}", flush=True)
    print(f"load average {os.getloadavg()[0]:.2f}")


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", default="small,medium,large")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--many", default="2,4,8", help="m values for fuse_many vs fold ('' to skip)")
    ap.add_argument("--layouts", default="slide,shared", help="fuse_many map layouts (see many_maps)")
    ap.add_argument("--pairs", default="ml,noisy", help="pair kinds (see make_pair)")
    ap.add_argument("--no-cpp", action="store_true", help="skip the C++ Alg. 8 peer on OctoMap")
    _host_memory.add_flag(ap)
    args = ap.parse_args()
    exe = None if args.no_cpp else _octomap_peer.build("alg8_octomap")
    print(f"host memory reuse: {_host_memory.apply(args)}")
    print(f"jax {jax.__version__}, backend {jax.default_backend()}, devices {jax.devices()}, "
          f"load average {os.getloadavg()[0]:.2f} (and at the end of each table)")
    print(f"C++ Alg. 8 peer on OctoMap 1.10: {exe or 'not built (needs g++ and cmeel-octomap)'}")
    bench_pairs([s for s in args.sizes.split(",") if s], args.pairs.split(","), args.repeats, exe)
    if args.many:
        for layout in args.layouts.split(","):
            bench_many(SIZES["small"], [int(m) for m in args.many.split(",")], layout, args.repeats)


if __name__ == "__main__":
    main()
