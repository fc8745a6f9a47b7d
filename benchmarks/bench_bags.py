"""Bag benchmark: maps as ``octomap_msgs/Octomap`` messages in ROS 1 / ROS 2 (sqlite3, MCAP)
bags against the same maps as ``.bt`` / ``.ot`` files.

For the synthetic room map of ``bench_io.py`` tiled to the requested sizes, and each payload
(binary ``.bt`` / full ``.ot``): write K messages with ``write_bag``, read them all back with
``read_bag``, read the last with ``select_map`` (what ``octomerge info|convert|merge BAG`` does),
and the same map with ``save`` / ``load`` as a file (the peer). Every map read back is checked
to have bit-identical leaves to the file's. Median of N runs after a first one.

Run: ``.venv/bin/python benchmarks/bench_bags.py [--sizes 0.4 2] [--messages 3] [--repeat 3]``
"""

from __future__ import annotations

import argparse
import shutil
import statistics
import tempfile
import time
from importlib.metadata import version
from pathlib import Path

import jax
import numpy as np

from bench_io import RES, room_map_leaves, tiled
from octomerge_jax.io import load, save
from octomerge_jax.io.bags import read_bag, select_map, write_bag
from octomerge_jax.map import from_leaves

KINDS = (("ROS 1 .bag", "m.bag", None), ("ROS 2 sqlite3", "m_sqlite3", "sqlite3"), ("ROS 2 MCAP", "m_mcap", "mcap"))


def timed(fn, repeat: int, before=None) -> float:
    """Median seconds of ``repeat`` runs after a first one; ``before()`` runs untimed ahead of each."""
    runs = []
    for _ in range(repeat + 1):
        if before is not None:
            before()
        t0 = time.perf_counter()
        fn()
        runs.append(time.perf_counter() - t0)
    return statistics.median(runs[1:])


def size_on_disk(path: Path) -> int:
    return sum(f.stat().st_size for f in path.rglob("*")) if path.is_dir() else path.stat().st_size


def same(a, b) -> bool:
    la, lb = a.leaves(), b.leaves()
    return all(np.array_equal(x, y) for x, y in ((la.codes, lb.codes), (la.depths, lb.depths),
                                                  (la.log_odds, lb.log_odds)))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=float, nargs="+", default=[0.4, 2.0], help="target leaf counts in millions")
    ap.add_argument("--messages", type=int, default=3, help="messages per bag")
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args(argv)
    print(f"jax {jax.__version__} ({jax.default_backend()}), rosbags {version('rosbags')}; "
          f"{args.messages} messages per bag, median of {args.repeat}")
    base = room_map_leaves()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        for target in args.sizes:
            tiles = max(1, round(target * 1e6 / base[0].size))
            m = from_leaves(*tiled(*base, tiles), RES)
            for binary, ext in ((True, ".bt"), (False, ".ot")):
                f = tmp / f"m{ext}"
                t_save = timed(lambda: save(m, f), args.repeat)
                t_load = timed(lambda: jax.block_until_ready(load(f).code), args.repeat)
                ref = load(f)
                rows.append((f"{ref.num_leaves / 1e6:.2f}M", ext, "file", 1, f.stat().st_size, t_save, t_load, t_load,
                             "-"))
                for name, fname, storage in KINDS:
                    p = tmp / fname

                    def clear(p=p):
                        shutil.rmtree(p, ignore_errors=True) if p.is_dir() else p.unlink(missing_ok=True)

                    t_w = timed(lambda: write_bag(p, [m] * args.messages, binary=binary, storage=storage,
                                                  stamps_ns=np.arange(args.messages) * 10**9 + 1), args.repeat, clear)
                    t_all = timed(lambda: [jax.block_until_ready(b.map.code) for b in read_bag(p)], args.repeat)
                    t_last = timed(lambda: jax.block_until_ready(select_map(p).map.code), args.repeat)
                    ok = all(same(b.map, ref) for b in read_bag(p))
                    rows.append((f"{ref.num_leaves / 1e6:.2f}M", ext, name, args.messages, size_on_disk(p), t_w, t_all,
                                 t_last, "yes" if ok else "NO"))
    print("| leaves | payload | container | messages | bytes | write all [s] | read all [s] | read last [s] | "
          "last / file load | leaves identical |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    file_load = {(r[0], r[1]): r[7] for r in rows if r[2] == "file"}
    for r in rows:
        ratio = r[7] / file_load[(r[0], r[1])]
        print(f"| {r[0]} | {r[1]} | {r[2]} | {r[3]} | {r[4]:,} | {r[5]:.3f} | {r[6]:.3f} | {r[7]:.3f} | "
              f"{ratio:.2f}x | {r[8]} |")


if __name__ == "__main__":
    main()
