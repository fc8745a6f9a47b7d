"""``octomerge info MAP``: what an OctoMap .bt/.ot file holds."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from .. import morton
from ..io import read_header
from ..io.bags import is_bag
from ._inputs import add_bag_options, load_map_inputs
from .outputs import check_input

EPILOG = """examples:
  octomerge info room.bt
  octomerge info robot1.ot --json
  octomerge info run1.bag --topic /octomap_full --stamp 1712345678.5
"""


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "info", help="print resolution, leaves per depth, occupancy, bounds of a map",
        description="Print what an OctoMap .bt/.ot file holds: resolution, node count (as "
                    "OctoMap's size()), leaves per depth, occupied/free leaves and volume, "
                    "metric bounds of the known space, file size.",
        epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("map", type=Path, metavar="MAP", help="a .bt or .ot file, or a ROS bag")
    p.add_argument("--json", action="store_true", help="print one JSON object instead of text")
    p.add_argument("--lenient", action="store_true",
                   help="accept trailing bytes and a wrong header size, as OctoMap does for .ot")
    add_bag_options(p)
    p.set_defaults(func=run)


#: Leaves summarised per step: bounds the per-leaf float64 temporaries to ~100 MB.
_CHUNK = 1 << 20


def summarize(path: Path, lenient: bool = False, args=None) -> dict:
    """The facts ``info`` prints, as a JSON-able dict (for a bag: of the map ``args.topic`` /
    ``args.stamp`` choose, with its topic, stamp, frame and payload size). The leaves are
    summarised in chunks, so the memory taken beyond the loaded map stays bounded."""
    if is_bag(path):
        (m, b), = load_map_inputs([path], args, strict=not lenient)
        binary, tree_id, legacy, size, nbytes = b.binary, b.tree_id, False, None, b.payload_bytes
    else:
        check_input(path, "map")
        header = read_header(path)
        (m, _), = load_map_inputs([path], args, strict=not lenient)
        binary, tree_id, legacy, size, nbytes = (header.binary, header.tree_id, header.legacy, header.size,
                                                 path.stat().st_size)
    n = m.num_leaves
    words, all_depths = np.asarray(m.code)[:n], np.asarray(m.depth)[:n]
    all_log_odds = np.asarray(m.log_odds)[:n]
    all_occupied = np.asarray(m.is_occupied())[:n]
    depth_counts = np.zeros(17, np.int64)
    occupied_leaves = nodes = 0
    volume = {True: 0.0, False: 0.0}
    lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
    for a in range(0, n, _CHUNK):
        b = min(a + _CHUNK, n)
        first = max(a - 1, 0)  # the previous leaf: nodes a leaf opens depend on it
        codes = morton.join_codes(words[first:b])
        depths = all_depths[first:b].astype(np.int32)
        opened = morton.group_sizes(codes, depths)
        nodes += int(opened[a - first:].sum())
        codes, depths = codes[a - first:], depths[a - first:]
        occupied = all_occupied[a:b]
        sizes = morton.node_size(depths, m.resolution)
        cubes = sizes ** 3
        volume[True] += float(cubes[occupied].sum())
        volume[False] += float(cubes[~occupied].sum())
        occupied_leaves += int(occupied.sum())
        depth_counts += np.bincount(depths, minlength=17)
        centers = morton.keys_to_coords(morton.codes_to_keys(codes), m.resolution, depths)
        half = sizes[:, None] / 2
        lo = np.minimum(lo, (centers - half).min(axis=0))
        hi = np.maximum(hi, (centers + half).max(axis=0))
    out = {
        "path": str(path),
        "format": "bt (binary, maximum likelihood)" if binary else "ot (full log-odds)",
        "tree_id": tree_id,
        "legacy_header": legacy,
        "file_bytes": nbytes,
        "resolution_m": m.resolution,
        "nodes": nodes,
        "header_size": nodes if size is None else size,
        "leaves": n,
        "leaves_per_depth": {str(d): int(c) for d, c in enumerate(depth_counts) if c},
        "occupied_leaves": occupied_leaves,
        "free_leaves": n - occupied_leaves,
        "occupied_volume_m3": volume[True],
        "free_volume_m3": volume[False],
        "bounds_min_m": None,
        "bounds_max_m": None,
        "log_odds_range": None,
    }
    if n:
        out["bounds_min_m"] = [float(v) for v in lo]
        out["bounds_max_m"] = [float(v) for v in hi]
        out["log_odds_range"] = [float(all_log_odds.min()), float(all_log_odds.max())]
    if is_bag(path):
        out.update(bag_topic=b.topic, bag_stamp_s=b.stamp_ns / 1e9, bag_frame_id=b.frame_id)
    return out


def _text(s: dict) -> str:
    def vec(v):
        return "-" if v is None else "(" + ", ".join(f"{x:.3f}" for x in v) + ")"

    where = f" {s['bag_topic']} @ {s['bag_stamp_s']:.9f} s, frame {s['bag_frame_id']}" if "bag_topic" in s else ""
    lines = [
        f"map:        {s['path']}{where}",
        f"format:     {s['format']}, id {s['tree_id']}"
        + (" (legacy headerless)" if s["legacy_header"] else ""),
        f"{'payload:   ' if where else 'file size: '} {s['file_bytes']:,} bytes",
        f"resolution: {s['resolution_m']:g} m",
        f"nodes:      {s['nodes']:,} (OctoMap size(); header says {s['header_size']:,})",
        f"leaves:     {s['leaves']:,} ({s['occupied_leaves']:,} occupied, "
        f"{s['free_leaves']:,} free)",
        f"volume:     {s['occupied_volume_m3']:.3f} m^3 occupied, "
        f"{s['free_volume_m3']:.3f} m^3 free",
        f"bounds:     min {vec(s['bounds_min_m'])} m, max {vec(s['bounds_max_m'])} m",
    ]
    if s["log_odds_range"] is not None:
        lo, hi = s["log_odds_range"]
        lines.append(f"log-odds:   {lo:.4f} .. {hi:.4f}")
    lines.append("leaves per depth:")
    for d, c in s["leaves_per_depth"].items():
        size = s["resolution_m"] * 2.0 ** (16 - int(d))
        lines.append(f"  depth {int(d):2d} ({size:g} m): {c:,}")
    return "\n".join(lines)


def run(args) -> int:
    s = summarize(args.map, lenient=args.lenient, args=args)
    print(json.dumps(s, indent=2) if args.json else _text(s))
    return 0
