"""Reader memory benchmark: peak host memory to read a dense ``.bt`` (a full subtree of 8^h
depth-16 leaves, alternating free / occupied so nothing prunes), octomerge_jax ``load`` vs
OctoMap's ``readBinary`` (pyoctomap), and what ``octomerge info`` takes.

Each measurement runs in a fresh process and reports its peak resident set size above the
process's baseline after imports (``ru_maxrss``), per leaf, and the wall time. The last row
is a crafted ~40 MB file (8^9 leaves), refused by the default leaf limit before it is read.

Run: ``.venv/bin/python benchmarks/bench_read_memory.py [--heights 7 8] [--bomb]``
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

HEAD = (b"# Octomap OcTree binary file\n# (feel free to add / change comments, but leave the "
        b"first line as it is!)\n#\nid OcTree\nsize %d\nres 0.1\ndata\n")

CHILD = r"""
import json, resource, sys, time
import numpy as np
kind, path = sys.argv[1], sys.argv[2]
if kind == "octomap":
    import pyoctomap
else:
    import octomerge_jax.io, octomerge_jax.cli
base = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
t = time.perf_counter()
result = ""
try:
    if kind == "octomap":
        tree = pyoctomap.OcTree(0.1)
        tree.readBinary(path)
        leaves = tree.getNumLeafNodes()
    elif kind == "ours":
        m = octomerge_jax.io.load(path)
        leaves = m.num_leaves
    else:
        import contextlib, io
        with contextlib.redirect_stdout(io.StringIO()):
            rc = octomerge_jax.cli.main(["info", path])
        leaves = -1
except Exception as err:
    leaves, result = -1, f"{type(err).__name__}: {err}"
dt = time.perf_counter() - t
peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
print(json.dumps({"leaves": leaves, "seconds": dt, "bytes": peak - base, "result": result}))
"""


def dense_bt(height: int) -> bytes:
    s = np.array([0x9999], np.uint16)
    for _ in range(height - 1):
        s = np.concatenate([[0xFFFF], np.tile(s, 8)]).astype(np.uint16)
    body = np.concatenate([np.full(16 - height, 3, np.uint16), s])
    return HEAD % (body.size + 8 ** height) + body.astype("<u2").tobytes()


def measure(kind: str, path: Path) -> dict:
    out = subprocess.run([sys.executable, "-c", CHILD, kind, str(path)], capture_output=True,
                         text=True, timeout=1800)
    if out.returncode:
        return {"leaves": -1, "seconds": float("nan"), "bytes": float("nan"),
                "result": out.stderr.strip().splitlines()[-1]}
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--heights", type=int, nargs="+", default=[7, 8])
    p.add_argument("--bomb", action="store_true", help="add the crafted 8^9-leaf file")
    args = p.parse_args()
    print("| file | leaves | ours load MiB (B/leaf) | s | OctoMap MiB (B/leaf) | s | "
          "ours / OctoMap | info MiB |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|")
    with tempfile.TemporaryDirectory() as tmp:
        for h in args.heights + ([9] if args.bomb else []):
            path = Path(tmp) / f"dense{h}.bt"
            path.write_bytes(dense_bt(h))
            n = 8 ** h
            name = f"dense {path.stat().st_size / 1e6:.1f} MB"
            ours = measure("ours", path)
            if ours["result"]:
                print(f"| {name} | {n:,} | refused in {ours['seconds']:.1f} s, "
                      f"{ours['bytes'] / 2**20:.0f} MiB: {ours['result'][:70]} | | | | | |")
                continue
            ref = measure("octomap", path)
            info = measure("info", path)
            print(f"| {name} | {n:,} | {ours['bytes'] / 2**20:.0f} ({ours['bytes'] / n:.0f}) | "
                  f"{ours['seconds']:.1f} | {ref['bytes'] / 2**20:.0f} ({ref['bytes'] / n:.0f}) | "
                  f"{ref['seconds']:.1f} | {ours['bytes'] / ref['bytes']:.2f} | "
                  f"{info['bytes'] / 2**20:.0f} |")


if __name__ == "__main__":
    main()
