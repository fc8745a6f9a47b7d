"""``octomerge info MAP``: what an OctoMap .bt/.ot file holds."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from ..io import load, num_nodes, read_header
from .outputs import check_input

EPILOG = """examples:
  octomerge info room.bt
  octomerge info robot1.ot --json
"""


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "info", help="print resolution, leaves per depth, occupancy, bounds of a map",
        description="Print what an OctoMap .bt/.ot file holds: resolution, node count (as "
                    "OctoMap's size()), leaves per depth, occupied/free leaves and volume, "
                    "metric bounds of the known space, file size.",
        epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("map", type=Path, metavar="MAP", help="a .bt or .ot file")
    p.add_argument("--json", action="store_true", help="print one JSON object instead of text")
    p.add_argument("--lenient", action="store_true",
                   help="accept trailing bytes and a wrong header size, as OctoMap does for .ot")
    p.set_defaults(func=run)


def summarize(path: Path, lenient: bool = False) -> dict:
    """The facts ``info`` prints, as a JSON-able dict."""
    check_input(path, "map")
    header = read_header(path)
    m = load(path, strict=not lenient)
    lv = m.leaves()
    occupied = np.asarray(m.is_occupied())[: m.num_leaves]
    volume = lv.sizes ** 3
    depth_counts = np.bincount(lv.depths, minlength=17)
    out = {
        "path": str(path),
        "format": "bt (binary, maximum likelihood)" if header.binary else "ot (full log-odds)",
        "tree_id": header.tree_id,
        "legacy_header": header.legacy,
        "file_bytes": path.stat().st_size,
        "resolution_m": m.resolution,
        "nodes": num_nodes(m),
        "header_size": header.size,
        "leaves": m.num_leaves,
        "leaves_per_depth": {str(d): int(c) for d, c in enumerate(depth_counts) if c},
        "occupied_leaves": int(occupied.sum()),
        "free_leaves": int((~occupied).sum()),
        "occupied_volume_m3": float(volume[occupied].sum()),
        "free_volume_m3": float(volume[~occupied].sum()),
        "bounds_min_m": None,
        "bounds_max_m": None,
        "log_odds_range": None,
    }
    if m.num_leaves:
        half = lv.sizes[:, None] / 2
        out["bounds_min_m"] = [float(v) for v in (lv.centers - half).min(axis=0)]
        out["bounds_max_m"] = [float(v) for v in (lv.centers + half).max(axis=0)]
        out["log_odds_range"] = [float(lv.log_odds.min()), float(lv.log_odds.max())]
    return out


def _text(s: dict) -> str:
    def vec(v):
        return "-" if v is None else "(" + ", ".join(f"{x:.3f}" for x in v) + ")"

    lines = [
        f"map:        {s['path']}",
        f"format:     {s['format']}, id {s['tree_id']}"
        + (" (legacy headerless)" if s["legacy_header"] else ""),
        f"file size:  {s['file_bytes']:,} bytes",
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
    s = summarize(args.map, lenient=args.lenient)
    print(json.dumps(s, indent=2) if args.json else _text(s))
    return 0
