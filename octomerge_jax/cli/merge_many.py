"""``octomerge merge-many OUT MAP1 MAP2 MAP3 ...``: one consistent map from N maps, no guesses."""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

from ..io import MapFormatError, load, save
from ..pipeline import MergeError, merge_many
from ._common import CliError
from .._fileutil import check_not_input
from .merge import EXIT_INPUT, EXIT_NO_OVERLAP, EXIT_RESOLUTION, config_from_args
from .plots import plot_pose_graph

EPILOG = """examples:
  octomerge merge-many team.bt robot1.bt robot2.bt robot3.bt robot4.bt --report r.json --figure graph.png
  octomerge merge-many team.ot a.ot b.ot c.ot --poses-out poses.tum   # T_0_k of each map, for evo

Every pair of maps (from 7 maps on, each map's --pairs-per-map most similar by a coarse occupancy
descriptor) is registered without a guess (multi-hypothesis search), the pairwise transforms are
made consistent by a robust pose graph over SE(3) (inconsistent pairs are rejected and reported),
and all placed maps are fused in one pass into MAP1's frame. A map that overlaps no other is left
out and reported. The TUM file has one line per placed map: index tx ty tz qx qy qz qw (map k's
frame in MAP1's).

exit codes: 0 merged (also when some maps stay unplaced: see the report), 1 bad input, 2 usage,
3 resolutions differ, 4 no map could be placed next to MAP1.
"""


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "merge-many", help="merge N maps into one consistent map (pairwise registration + pose graph)",
        description="Register every overlapping pair of maps without guesses, solve a robust pose graph "
                    "over SE(3) and fuse all maps in MAP1's frame.",
        epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("out", type=Path, metavar="OUT", help="merged map to write (.bt or .ot), in MAP1's frame")
    p.add_argument("maps", type=Path, nargs="+", metavar="MAP",
                   help="two or more maps (.bt/.ot); the first is the reference")
    a = p.add_argument_group("pipeline")
    a.add_argument("--pairs-per-map", type=int, default=4, metavar="K",
                   help="from 7 maps on, register each map with its K most similar maps (default 4; 0: all pairs)")
    a.add_argument("--min-confidence", type=float, default=0.1, help="drop pairwise results below this (default 0.1)")
    a.add_argument("--rule", choices=("sum", "max", "weighted"), help="log-odds fusion rule (default sum)")
    a.add_argument("--interpolation", choices=("trilinear", "nearest", "thesis"), help="resampling (default trilinear)")
    a.add_argument("--config", type=Path, metavar="FILE", help="TOML/JSON settings (octomerge dump-config)")
    o = p.add_argument_group("outputs")
    o.add_argument("--report", type=Path, metavar="JSON", help="write the ManyReport as JSON")
    o.add_argument("--figure", type=Path, metavar="PNG", help="footprints in MAP1's frame and the graph's edges")
    o.add_argument("--poses-out", type=Path, metavar="TUM", help="write T_0_k of the placed maps (TUM format)")
    o.add_argument("--force", action="store_true", help="allow OUT to overwrite an existing file")
    o.add_argument("-q", "--quiet", action="store_true", help="print nothing but errors")
    p.set_defaults(func=run)


def _check_out(path: Path, inputs, force: bool, map_file: bool) -> None:
    if map_file and path.suffix.lower() not in (".bt", ".ot"):
        raise CliError(f"{path}: OUT must end in .bt or .ot")
    try:
        check_not_input(path, inputs, force=False)  # never overwrite an input, even with --force
    except ValueError as err:
        raise CliError(str(err)) from None
    if map_file and path.exists() and not force:
        raise CliError(f"{path} exists; pass --force to overwrite it")
    if str(path.parent) and not path.parent.exists():
        raise CliError(f"{path}: folder {path.parent} does not exist")


def run(args) -> int:
    if len(args.maps) < 2:
        raise CliError("merge-many needs at least two maps", 2)
    if args.pairs_per_map < 0:
        raise CliError(f"--pairs-per-map must be >= 0, got {args.pairs_per_map}", 2)
    for p in args.maps:
        if not p.is_file():
            raise CliError(f"{p}: no such file")
    _check_out(args.out, args.maps, args.force, True)
    for extra in (args.report, args.figure, args.poses_out):
        if extra is not None:
            _check_out(extra, [*args.maps, args.out], args.force, False)
    try:
        cfg = config_from_args(args)
    except (ValueError, FileNotFoundError) as err:
        raise CliError(str(err)) from None
    say = (lambda *a: None) if args.quiet else (lambda *a: print(*a))
    t0 = time.perf_counter()
    maps = []
    for p in args.maps:
        try:
            maps.append(load(p))
        except MapFormatError as err:
            raise CliError(str(err)) from None
        say(f"map {len(maps) - 1}: {p} ({maps[-1].num_leaves:,} leaves, {maps[-1].resolution:g} m)")
    t_load = time.perf_counter() - t0
    try:
        merged, report = merge_many(maps, config=cfg, max_pairs_per_map=args.pairs_per_map or None,
                                    min_confidence=args.min_confidence)
    except MergeError as err:
        raise CliError(str(err), EXIT_RESOLUTION if err.kind == "resolution" else EXIT_INPUT) from None
    if report.figures["maps_placed"] < 2:
        raise CliError(f"no map could be placed next to {args.maps[0]}: no pair registered with enough "
                       "confidence (see --min-confidence)", EXIT_NO_OVERLAP)
    t1 = time.perf_counter()
    save(merged, args.out)
    timings = {**report.timings, "load": t_load, "save": time.perf_counter() - t1}
    if args.report:
        dataclasses.replace(report, timings=timings).to_json(args.report)
    if args.poses_out:
        report.write_tum(args.poses_out)
    if args.figure:
        plot_pose_graph(maps, report, args.figure)
    say(report.summary())
    say(f"wrote {args.out} ({merged.num_leaves:,} leaves)"
        + "".join(f", {p}" for p in (args.report, args.figure, args.poses_out) if p))
    for w in report.warnings:
        print(f"octomerge merge-many: warning: {w}", file=sys.stderr)
    return 0
