"""I/O benchmark: load/save of OctoMap .bt/.ot files, octomerge_jax vs OctoMap (pyoctomap).

Builds a synthetic room map (walls, floor, boxes, free space with graded log-odds, unknown
shadows) at 5 cm, prunes it maximally, and tiles it to ~0.4M and ~2M leaves. For each size
it writes the files with our writer, then times (median of N runs, first run apart):

  ours:  load(.bt), load(.ot), save(.bt), save(.ot)       (host NumPy + device put)
  OctoMap (pyoctomap 1.2.2, C++): readBinary, read (.ot), writeBinary, write (.ot)

and prints a table with the ratio ours / OctoMap, plus peak host memory of our calls
(tracemalloc: NumPy buffers; JAX device buffers are not counted).

Run: ``.venv/bin/python benchmarks/bench_io.py [--sizes 0.4 2] [--repeat 5]``
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
import tracemalloc
from pathlib import Path

import numpy as np

from octomerge_jax import morton
from octomerge_jax.io import load, num_nodes, save
from octomerge_jax.map import from_leaves

RES = 0.05
# MASKS[d] keeps the top d octal digits of a 48-bit Morton code (the min corner at depth d)
MASKS = np.array([((1 << 48) - 1) & ~((1 << (3 * (morton.TREE_DEPTH - d))) - 1)
                  for d in range(morton.TREE_DEPTH + 1)], dtype=np.uint64)


def _prune_max(codes, depths, values):
    """Maximal prune of sorted host leaves (8 equal siblings -> parent, bottom-up)."""
    for d in range(15, -1, -1):
        idx = np.flatnonzero(depths == d + 1)
        if idx.size < 8:
            continue
        parent = codes[idx] & MASKS[d]
        starts = np.flatnonzero(np.r_[True, parent[1:] != parent[:-1]])
        run = np.diff(np.r_[starts, idx.size])
        cand = starts[run == 8]
        if not cand.size:
            continue
        block = idx[cand[:, None] + np.arange(8)]
        ok = np.all(values[block] == values[block[:, :1]], axis=1)
        block = block[ok]
        depths = depths.copy()
        depths[block[:, 0]] = d
        keep = np.ones(codes.size, bool)
        keep[block[:, 1:]] = False
        codes, depths, values = codes[keep], depths[keep], values[keep]
    return codes, depths, values


def room_map_leaves(seed: int = 0):
    """Finest voxels of a 12.8 x 9.6 x 3.2 m room -> maximally pruned leaves."""
    rng = np.random.default_rng(seed)
    nx, ny, nz = 256, 192, 64
    occ = np.zeros((nx, ny, nz), np.int8)  # 0 free, 1 occupied, -1 unknown
    occ[[0, -1], :, :] = 1
    occ[:, [0, -1], :] = 1
    occ[:, :, [0, -1]] = 1
    for _ in range(40):  # boxes: occupied shell, unknown inside and behind
        lo = rng.integers([8, 8, 1], [nx - 40, ny - 40, 2])
        size = rng.integers([6, 6, 6], [36, 36, 40])
        hi = np.minimum(lo + size, [nx - 1, ny - 1, nz - 1])
        occ[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]] = 1
        occ[lo[0] + 1:hi[0] - 1, lo[1] + 1:hi[1] - 1, lo[2] + 1:hi[2] - 1] = -1
        occ[hi[0]:min(hi[0] + 12, nx - 1), lo[1]:hi[1], lo[2]:hi[2]] = -1  # shadow
    ijk = np.argwhere(occ >= 0)
    state = occ[occ >= 0]
    # graded log-odds: free gets more certain away from walls, occupied by a hit count
    dist = np.minimum.reduce([ijk[:, 0], nx - 1 - ijk[:, 0], ijk[:, 1], ny - 1 - ijk[:, 1]])
    free_lo = np.maximum(-0.4054651 * np.minimum(dist // 8 + 1, 5), -2.0).astype(np.float32)
    hits = rng.integers(1, 6, ijk.shape[0])
    occ_lo = np.minimum(0.84729785 * hits, 3.5110307).astype(np.float32)
    values = np.where(state == 1, occ_lo, free_lo).astype(np.float32)
    keys = ijk + (morton.KEY_OFFSET - np.array([nx // 2, ny // 2, 8]))
    codes = morton.keys_to_codes(keys.astype(np.uint16))
    order = np.argsort(codes)
    codes, values = codes[order], values[order]
    return _prune_max(codes, np.full(codes.size, 16, np.uint8), values)


def tiled(codes, depths, values, tiles: int):
    """``tiles`` copies of the map side by side (offsets aligned to 512 voxels)."""
    keys = morton.codes_to_keys(codes).astype(np.int64)
    grid = int(np.ceil(tiles ** (1 / 3)))
    out = []
    for t in range(tiles):
        off = 512 * (np.array([t % grid, (t // grid) % grid, t // grid // grid]) - grid // 2)
        out.append(morton.keys_to_codes((keys + off).astype(np.uint16)))
    c = np.concatenate(out)
    order = np.argsort(c)
    return c[order], np.tile(depths, tiles)[order], np.tile(values, tiles)[order]


def _time(fn, repeat):
    t0 = time.perf_counter()
    fn()
    first = time.perf_counter() - t0
    runs = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        runs.append(time.perf_counter() - t0)
    return first, statistics.median(runs)


def _peak(fn):
    tracemalloc.start()
    tracemalloc.reset_peak()
    fn()
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    return peak


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=float, nargs="+", default=[0.4, 2.0],
                    help="target leaf counts in millions")
    ap.add_argument("--repeat", type=int, default=5)
    args = ap.parse_args(argv)
    import jax
    import pyoctomap

    base = room_map_leaves()
    print(f"base room map: {base[0].size} leaves; jax {jax.__version__} "
          f"({jax.default_backend()}), pyoctomap {getattr(pyoctomap, '__version__', '1.2.2')}")
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        for target in args.sizes:
            tiles = max(1, round(target * 1e6 / base[0].size))
            codes, depths, values = tiled(*base, tiles)
            m = from_leaves(codes, depths, values, RES)
            bt, ot = tmp / "m.bt", tmp / "m.ot"
            save(m, bt)
            save(m, ot)
            ref = pyoctomap.OcTree(RES)
            ref.readBinary(str(bt))
            n_bt_leaves = ref.getNumLeafNodes()
            cases = [
                ("load .bt", lambda: jax.block_until_ready(load(bt).code),
                 lambda: pyoctomap.OcTree(RES).readBinary(str(bt)), "readBinary"),
                ("load .ot", lambda: jax.block_until_ready(load(ot).code),
                 lambda: pyoctomap.OcTree(RES).read(str(ot)), "read"),
                ("save .bt", lambda: save(m, tmp / "o.bt"),
                 lambda: ref.writeBinary(str(tmp / "r.bt")), "writeBinary"),
                ("save .ot", lambda: save(m, tmp / "o.ot"),
                 lambda: ref_ot.write(str(tmp / "r.ot")), "write"),
            ]
            ref_ot = pyoctomap.OcTree(RES).read(str(ot))
            for name, ours, theirs, their_name in cases:
                f_o, t_o = _time(ours, args.repeat)
                _, t_r = _time(theirs, args.repeat)
                peak = _peak(ours)
                leaves = n_bt_leaves if "bt" in name else m.num_leaves
                rows.append((f"{leaves / 1e6:.2f}M", name, f_o, t_o, their_name, t_r, t_o / t_r,
                             peak / 2**20))
            # agreement at full size: OctoMap re-writes our files byte for byte, and loads
            # the same number of leaves and nodes
            same_bt = (tmp / "o.bt").read_bytes() == (tmp / "r.bt").read_bytes()
            same_ot = (tmp / "o.ot").read_bytes() == (tmp / "r.ot").read_bytes()
            nodes_ok = ref.size() == num_nodes(load(bt)) and ref_ot.size() == num_nodes(m)
            print(f"  {tiles} tile(s): {m.num_leaves} leaves, .bt {bt.stat().st_size / 2**20:.1f} "
                  f"MiB, .ot {ot.stat().st_size / 2**20:.1f} MiB; OctoMap rewrites ours "
                  f"byte-identically: .bt {same_bt}, .ot {same_ot}; node counts agree: {nodes_ok}")
    head = ("leaves", "op", "first [s]", "median [s]", "OctoMap op", "OctoMap [s]", "ratio", "peak MiB")
    print("\n| " + " | ".join(head) + " |")
    print("|" + "---|" * len(head))
    for r in rows:
        print(f"| {r[0]} | {r[1]} | {r[2]:.3f} | {r[3]:.3f} | {r[4]} | {r[5]:.3f} | "
              f"{r[6]:.2f}x | {r[7]:.0f} |")


if __name__ == "__main__":
    main()
