"""``octomerge merge IN1 IN2 OUT [x y z roll pitch yaw]``: merge map 2 into map 1's frame."""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import numpy as np

from ..pipeline import (COARSE_MATCHING_CHOICES, HYPOTHESES_CHOICES, POLISH_CHOICES, REFINE_CHOICES, MergeConfig,
                        load_config)
from ..io import save
from ..io.bags import write_bag
from ..pipeline import MergeError, icp_trace, merge, transform_from_xyz_rpy
from ._common import CliError
from .compile_ahead import compile_ahead
from ._inputs import add_bag_options, check_map_input, load_map_inputs
from .outputs import FIGURE_SUFFIXES, MAP_SUFFIXES, angle_warnings, check_output, writing
from .progress import StageBar, show_bars
from .plots import plot_icp_convergence, plot_map, plot_overlap
from .view import add_view_options, require_viewer, visualize_merge

# exit codes (also in the epilog)
EXIT_INPUT = 1
EXIT_RESOLUTION = 3
EXIT_NO_OVERLAP = 4
EXIT_ICP = 5
EXIT_AMBIGUOUS = 7
# a merge that ran but whose registration is not to be trusted: no merged map without --force
_STATUS_EXIT = {"no_overlap": EXIT_NO_OVERLAP, "failed": EXIT_ICP, "ambiguous": EXIT_AMBIGUOUS}
_KIND_EXIT = {"resolution": EXIT_RESOLUTION, "no_overlap": EXIT_NO_OVERLAP, "icp_failed": EXIT_ICP,
              "not_converged": EXIT_ICP, "empty": EXIT_NO_OVERLAP, "transform": EXIT_INPUT}

EPILOG = """examples:
  octomerge merge robot1.bt robot2.bt merged.bt                  # no guess: the transform is searched for
  octomerge merge robot1.bt robot2.bt merged.bt --xyz 1.5 -0.8 0 --rpy 0 0 0.785
  octomerge merge robot1.ot robot2.ot merged.ot 1.5 -0.8 0 0 0 0.785   # thesis argument order
  octomerge merge a.bt b.bt out.bt --rpy 0 0 45 --degrees --refine multi --report r.json --figure icp.png
  octomerge merge a.bt b.bt out.bt --refine none --xyz 2 0 0            # trust the guess
  octomerge merge a.bt b.bt out.bt --refine multi --hypotheses correlation  # partial overlap, poor guess
  octomerge merge r1.bag r2.bag out.bt --topic /octomap_full --out-bag merged.bag  # ROS bags in and out

The guess T_1_2 maps map 2's frame into map 1's: x y z in metres, roll pitch yaw in radians
(R = Rz(yaw) Ry(pitch) Rx(roll), as OctoMap's Pose6D). OUT is .bt (maximum likelihood) or .ot
(log-odds) and is in map 1's frame. Outputs are written atomically and checked before any
compute; an existing file (an input too, for OUT) is overwritten only with --force. An angle
beyond 2 pi rad gets a warning (degrees without --degrees?).

Without a guess (no x y z roll pitch yaw, --xyz or --rpy) the default refinement is global:
the transform is searched for and the report gets a status and a confidence in [0, 1].

exit codes: 0 merged (an unconverged ICP is a warning unless --strict), 1 bad input (missing or
unreadable file, NaN guess, ...), 2 usage, 3 resolutions differ (see --resample), 4 no overlap
(under the guess, or none found), 5 registration failed (too few correspondences, ICP in a
wrong basin, or not converged with --strict), 7 ambiguous (two distinct poses fit alike). For
4, 5 and 7 no merged map is written unless --force (the --report is written either way).
"""


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "merge", help="merge two maps (ICP-refined transform, trilinear resampling, log-odds fusion)",
        description="Register map 2 to map 1 from an initial guess (occupied clouds, overlap, "
                    "ICP), resample map 2 into map 1's frame and fuse the log-odds (J. Jessup 2013).",
        epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("in1", type=Path, metavar="IN1", help="map 1 (.bt/.ot or a ROS bag): the reference frame")
    p.add_argument("in2", type=Path, metavar="IN2", help="map 2 (.bt/.ot or a ROS bag)")
    p.add_argument("out", type=Path, metavar="OUT", help="merged map to write (.bt or .ot)")
    p.add_argument("pose", type=float, nargs="*", metavar="x y z roll pitch yaw",
                   help="initial guess in the thesis's positional order (6 numbers)")
    g = p.add_argument_group("initial guess T_1_2 (map 2 frame -> map 1 frame)")
    g.add_argument("--xyz", type=float, nargs=3, metavar=("X", "Y", "Z"), help="translation [m]")
    g.add_argument("--rpy", type=float, nargs=3, metavar=("R", "P", "Y"), help="roll pitch yaw [rad]")
    g.add_argument("--degrees", action="store_true", help="angles are in degrees")
    g.add_argument("--true-xyz", type=float, nargs=3, metavar=("X", "Y", "Z"),
                   help="ground truth translation: report thesis errors eps_r/eps_t")
    g.add_argument("--true-rpy", type=float, nargs=3, metavar=("R", "P", "Y"), help="ground truth rotation")
    a = p.add_argument_group("pipeline (override --config)")
    a.add_argument("--refine", choices=REFINE_CHOICES,
                   help="global (default without a guess: no guess needed), icp+dense (default with a guess: "
                        "ICP, then the dense alignment of the occupancy fields, sub-voxel), icp (ICP only, "
                        "faster), multi (multi-hypothesis ICP for poor guesses), dense or none")
    a.add_argument("--hypotheses", choices=HYPOTHESES_CHOICES,
                   help="starts of --refine multi: yaw_grid (the guess turned in yaw), correlation "
                        "(global search over yaw x translation, for partial overlap and guesses metres off) or "
                        "both (default)")
    a.add_argument("--overlap", choices=("voxel", "bbox", "none"), help="points fed to ICP (default bbox, thesis Alg. 2)")
    a.add_argument("--interpolation", choices=("trilinear", "nearest", "thesis"),
                   help="resampling of map 2 (default trilinear)")
    a.add_argument("--rule", choices=("sum", "max", "weighted"), help="log-odds fusion rule (default sum)")
    a.add_argument("--max-iterations", type=int, help="ICP iteration limit")
    a.add_argument("--coarse-matching", choices=COARSE_MATCHING_CHOICES,
                   help="ICP's coarse stages (default centroid; symmetric: both clouds downsampled, "
                        "see docs/design.md, \"Centroid coarse matching\")")
    a.add_argument("--polish", choices=POLISH_CHOICES,
                   help="last step of --refine icp+dense / global: gicp (default: plane-to-plane on the occupied "
                        "voxels, sub-voxel) or none")
    a.add_argument("--resample", action="store_true",
                   help="allow maps of different resolutions (map 2 is resampled onto map 1's grid)")
    a.add_argument("--strict", action="store_true", help="fail (exit 5) if ICP does not converge")
    a.add_argument("--config", type=Path, metavar="FILE", help="TOML/JSON settings (octomerge dump-config)")
    o = p.add_argument_group("outputs")
    o.add_argument("--report", type=Path, metavar="JSON", help="write the MergeReport as JSON")
    o.add_argument("--figure", type=Path, metavar="PNG", help="overlap clouds before/after ICP (Fig. 7.6)")
    o.add_argument("--map-figure", type=Path, metavar="PNG", help="merged map, occupancy-shaded (Fig. 7.7)")
    o.add_argument("--icp-figure", type=Path, metavar="PNG", help="ICP convergence per iteration")
    o.add_argument("--visualize", action="store_true",
                   help="after merging, serve a live 3-D view (octomerge view; needs viser)")
    add_view_options(p)
    o.add_argument("--force", action="store_true",
                   help="allow outputs to overwrite existing files (OUT may replace an input), and write OUT even "
                        "when the registration's status is ambiguous, no_overlap or failed (exit code unchanged)")
    o.add_argument("--out-bag", type=Path, metavar="BAG",
                   help="also write the merged map as one octomap_msgs/Octomap message (binary for a .bt OUT, "
                        "full for .ot) in map 1's frame: BAG.bag is a ROS 1 bag, other names a ROS 2 bag folder")
    o.add_argument("--out-bag-storage", choices=("mcap", "sqlite3"), default="mcap",
                   help="storage of a ROS 2 --out-bag (default mcap)")
    o.add_argument("-q", "--quiet", action="store_true", help="print nothing but errors (no progress bar)")
    add_bag_options(p)
    p.set_defaults(func=run)


def guess_from_args(args, name: str = "initial guess", rpy_flag: str = "--rpy"):
    """``(x, y, z, roll, pitch, yaw)`` [m, rad] from positional numbers or --xyz/--rpy; warns
    (stderr) about an angle beyond a full turn (``outputs.angle_warnings``)."""
    pose = list(args.pose or [])
    if pose and (args.xyz or args.rpy):
        raise CliError("give the guess either as 6 positional numbers or with --xyz/--rpy, not both", 2)
    if pose and len(pose) != 6:
        raise CliError(f"the positional guess needs 6 numbers (x y z roll pitch yaw), got {len(pose)}", 2)
    xyz = pose[:3] if pose else list(args.xyz or (0.0, 0.0, 0.0))
    rpy = pose[3:] if pose else list(args.rpy or (0.0, 0.0, 0.0))
    vals = [*xyz, *rpy]
    for label, v in zip(("x", "y", "z", "roll", "pitch", "yaw"), vals):
        if not math.isfinite(v):
            raise CliError(f"{name}: {label} = {v} is not a finite number", EXIT_INPUT)
    for w in angle_warnings(("roll", "pitch", "yaw"), rpy, args.degrees, rpy_flag if not pose else name + ":"):
        print(f"octomerge: warning: {w}", file=sys.stderr)
    if args.degrees:
        rpy = [math.radians(v) for v in rpy]
    return (*xyz, *rpy)


def config_from_args(args):
    cfg = load_config(args.config) if getattr(args, "config", None) else MergeConfig()
    reg, tr, fu = {}, {}, {}
    for key, section in (("refine", reg), ("overlap", reg), ("interpolation", tr), ("rule", fu),
                         ("max_iterations", reg), ("coarse_matching", reg), ("hypotheses", reg),
                         ("polish", reg)):
        v = getattr(args, key, None)
        if v is not None:
            section[key] = v
    if getattr(args, "resample", False):
        tr["resample_resolution"] = True
    if getattr(args, "strict", False):
        reg["on_not_converged"] = "error"
    return cfg.replace(registration=reg, transform=tr, fuse=fu)


def check_outputs(args) -> None:
    """Every output of ``merge`` checked before any compute (``cli/outputs.py``)."""
    inputs = [args.in1, args.in2]
    check_output(args.out, inputs=inputs, force=args.force, suffixes=MAP_SUFFIXES)
    done = [args.out]
    if args.out_bag is not None:
        check_output(args.out_bag, inputs=inputs, force=args.force, what="--out-bag", side=True, others=done)
        done.append(args.out_bag)
    for flag, path, suffixes in (("--report", args.report, None), ("--figure", args.figure, FIGURE_SUFFIXES),
                                 ("--map-figure", args.map_figure, FIGURE_SUFFIXES),
                                 ("--icp-figure", args.icp_figure, FIGURE_SUFFIXES)):
        if path is not None:
            check_output(path, inputs=inputs, force=args.force, suffixes=suffixes, what=flag, side=True,
                         others=done)
            done.append(path)


def run(args) -> int:
    for p in (args.in1, args.in2):
        check_map_input(p)
    check_outputs(args)
    if args.visualize:
        require_viewer()
    guess = guess_from_args(args)
    truth = None
    if args.true_xyz or args.true_rpy:
        ns = argparse.Namespace(pose=[], xyz=args.true_xyz, rpy=args.true_rpy, degrees=args.degrees)
        truth = transform_from_xyz_rpy(*guess_from_args(ns, "ground truth", "--true-rpy"))
    try:
        cfg = config_from_args(args)
    except (ValueError, FileNotFoundError) as err:
        raise CliError(str(err)) from None
    t0 = time.perf_counter()
    (m1, b1), (m2, b2) = load_map_inputs([args.in1, args.in2], args)
    t_load = time.perf_counter() - t0
    say = (lambda *a: None) if args.quiet else (lambda *a: print(*a))
    say(f"map 1: {args.in1} ({m1.num_leaves:,} leaves, {m1.resolution:g} m)")
    say(f"map 2: {args.in2} ({m2.num_leaves:,} leaves, {m2.resolution:g} m)")
    given = bool(args.pose or args.xyz or args.rpy)
    bar = StageBar(show_bars(args.quiet), "merge")
    try:
        T_init = transform_from_xyz_rpy(*guess) if given else None
        with bar.watch(), compile_ahead(m1, m2, T_init, cfg):
            merged, report = merge(m1, m2, T_init, refine=args.refine, T_1_2_true=truth, config=cfg)
    except MergeError as err:
        raise CliError(str(err), _KIND_EXIT.get(err.kind, EXIT_INPUT)) from None
    finally:
        bar.close()
    code = _STATUS_EXIT.get(report.status, 0)
    if code and not args.force:
        if args.report:
            with writing(args.report):
                report.with_timings(load=t_load).to_json(args.report)
        say(report.summary())
        print(f"octomerge merge: registration {report.status}: {args.out} not written (--force writes it); "
              + "; ".join(report.warnings), file=sys.stderr)
        return code
    t1 = time.perf_counter()
    with writing(args.out):
        save(merged, args.out)
    if args.out_bag is not None:  # map 1's frame; the later input stamp (now if neither is a bag)
        stamps = [b.stamp_ns for b in (b1, b2) if b is not None]
        with writing(args.out_bag):
            write_bag(args.out_bag, merged, binary=args.out.suffix.lower() == ".bt",
                      frame_id=b1.frame_id if b1 else "map", stamps_ns=[max(stamps)] if stamps else None,
                      storage=None if args.out_bag.suffix.lower() == ".bag" else args.out_bag_storage)
    report = report.with_timings(load=t_load, save=time.perf_counter() - t1)
    if args.report:
        with writing(args.report):
            report.to_json(args.report)
    write_figures(report, merged, args.figure, args.map_figure, args.icp_figure, cfg, truth)
    say(report.summary())
    say(f"wrote {args.out} ({merged.num_leaves:,} leaves)" + "".join(
        f", {p}" for p in (args.out_bag, args.report, args.figure, args.map_figure, args.icp_figure) if p))
    for w in report.warnings:
        print(f"octomerge merge: warning: {w}", file=sys.stderr)
    if args.visualize:
        visualize_merge(m1, m2, report, cfg, args)
    return code


def write_figures(report, merged, figure, map_figure, icp_figure, cfg, truth=None):
    """Figures for a finished merge (each optional)."""
    if figure is not None:
        eps = None
        if report.epsilon_r is not None:
            eps = ((report.epsilon_r_init, report.epsilon_t_init), (report.epsilon_r, report.epsilon_t))
        with writing(figure):
            plot_overlap(report.points_1, report.points_2, report.T_1_2_init, report.T_1_2, figure,
                         epsilons=eps)
    if map_figure is not None:
        with writing(map_figure):
            plot_map(merged, map_figure, title="merged map (map 1 frame)")
    if icp_figure is not None:
        if report.icp is None or report.refine == "dense":
            print(f"octomerge merge: warning: --icp-figure needs ICP (refine is {report.refine}); skipped",
                  file=sys.stderr)
        else:
            try:
                trace = _reported_trace(report, cfg, truth)
            except ValueError as err:  # the run could not be reproduced: no figure of another run
                print(f"octomerge merge: warning: {err}; --icp-figure skipped", file=sys.stderr)
            else:
                with writing(icp_figure):
                    plot_icp_convergence(trace, icp_figure)


def _reported_trace(report, cfg, truth) -> dict:
    """``icp_trace`` of the ICP run ``report`` reports (checked to be that run), with the
    transform used (``T_1_2_used``) where a later step (dense alignment) moved it. With
    ``refine="multi"`` the winning hypothesis's run is replayed from its start (unchecked:
    ``icp_multi`` runs its hypotheses as one program)."""
    if report.refine == "multi":
        start = report.icp_result.hypotheses[int(report.icp_result.best_index)]
        tr = icp_trace(report.points_1, report.points_2, start, report.resolution, cfg, T_1_2_true=truth)
    else:
        tr = icp_trace(report.points_1, report.points_2, report.T_1_2_init, report.resolution, cfg,
                       T_1_2_true=truth, result=report.icp_result)
    if not np.allclose(report.T_1_2, tr["T_1_2"][-1], rtol=0.0, atol=1e-6):
        tr["T_1_2_used"] = np.asarray(report.T_1_2, np.float64)
        if truth is not None:
            tr["epsilon_used"] = (float(report.epsilon_r), float(report.epsilon_t))
    return tr
