"""``octomerge view MAP [MAP ...] [--report r.json]``: a live 3-D view in the web browser."""

from __future__ import annotations

import argparse
import importlib.util
import json
from pathlib import Path

import numpy as np

from ..io import MapFormatError, load
from ..pipeline import icp_trace
from ..viewer import view
from ._common import CliError

EPILOG = """examples:
  octomerge view room.bt
  octomerge view robot1.bt robot2.bt --report r.json      # map 2 placed by a merge's report
  octomerge view a.bt b.bt --color-by map --port 8080 --host 0.0.0.0

The page (viser) shows occupied voxels as boxes coloured by height or by map, a toggle per map,
free space on demand, and with a merge report map 2 before / after registration. A report of
`octomerge merge` places map 2 by its T_1_2 (T_1_2_init before); a report with "transforms"
(one 4x4 or null per map, map k's frame into map 0's) places every map. Ctrl-C stops it.
"""


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "view", help="live 3-D view of maps in the web browser (viser)",
        description="Serve a live 3-D view of one or more maps (viser) and print its address.",
        epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("maps", type=Path, nargs="+", metavar="MAP", help=".bt / .ot maps; the first is the frame")
    p.add_argument("--report", type=Path, metavar="JSON", help="merge report placing the maps")
    add_view_options(p)
    p.set_defaults(func=run)


def add_view_options(p) -> None:
    """The viewer's options, shared with ``merge --visualize``."""
    g = p.add_argument_group("viewer")
    g.add_argument("--color-by", choices=("height", "map"), default="height", help="box colours")
    g.add_argument("--max-boxes", type=int, default=200_000, metavar="N",
                   help="per map: coarser cells above N boxes (default %(default)s)")
    g.add_argument("--host", default="127.0.0.1", help="address to serve on (0.0.0.0: every interface)")
    g.add_argument("--port", type=int, default=8080, help="port (0: any free one; default %(default)s)")


def require_viewer() -> None:
    """Raise ``CliError`` (before any compute) when viser is not installed."""
    if importlib.util.find_spec("viser") is None:
        raise CliError("the viewer needs viser: pip install 'octomerge_jax[viewer]'")


def transforms_from_report(path: Path, n_maps: int) -> tuple[list, list | None]:
    """``(transforms, transforms_init)`` for ``n_maps`` maps from a merge report (``T_1_2``,
    ``T_1_2_init``: two maps) or a report with ``transforms`` (one per map). Raises
    ``CliError`` naming the file and what is wrong."""
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError, RecursionError) as err:
        raise CliError(f"{path}: not a readable JSON report ({type(err).__name__})") from None
    if not isinstance(data, dict):
        raise CliError(f"{path}: a report is a JSON object")
    if "transforms" in data:
        Ts = data["transforms"]
        if not isinstance(Ts, list) or len(Ts) != n_maps:
            raise CliError(f"{path}: 'transforms' must list one 4x4 (or null) per map ({n_maps})")
        return [None if T is None else _matrix(T, path, f"transforms[{k}]") for k, T in enumerate(Ts)], None
    if "T_1_2" in data:
        if n_maps != 2:
            raise CliError(f"{path}: a pair's report places map 2; give exactly two maps, not {n_maps}")
        init = data.get("T_1_2_init")
        return ([None, _matrix(data["T_1_2"], path, "T_1_2")],
                None if init is None else [None, _matrix(init, path, "T_1_2_init")])
    raise CliError(f"{path}: no 'T_1_2' or 'transforms' in the report")


def _matrix(value, path, name) -> np.ndarray:
    try:
        T = np.asarray(value, np.float64)
    except (TypeError, ValueError):
        T = np.zeros(0)
    if T.shape != (4, 4) or not np.isfinite(T).all():
        raise CliError(f"{path}: {name} is not a finite 4x4 matrix")
    return T


def serve(maps, names, args, **kw):
    """Start the viewer with the command's options, print its address, block until Ctrl-C."""
    if args.max_boxes < 1:
        raise CliError(f"--max-boxes must be at least 1, got {args.max_boxes}")
    if not 0 <= args.port <= 65535:
        raise CliError(f"--port must be in 0..65535, got {args.port}")
    try:
        viewer = view(maps, names=names, color_by=args.color_by, max_boxes=args.max_boxes,
                      host=args.host, port=None if args.port == 0 else args.port, **kw)
    except OSError as err:
        raise CliError(f"cannot serve on {args.host}:{args.port}: {err.strerror or err}") from None
    print(f"viewer: {viewer.url}  (Ctrl-C to stop)", flush=True)
    viewer.wait()


def visualize_merge(m1, m2, report, config, args) -> None:
    """``merge --visualize``: both maps, map 2 before / after registration, the overlap clouds
    and, when ICP ran, a slider over the iterations of the reported run."""
    trace = None
    if report.icp is not None and report.points_1 is not None:
        start = report.T_1_2_init
        if report.refine == "multi":
            start = report.icp_result.hypotheses[int(report.icp_result.best_index)]
        trace = icp_trace(report.points_1, report.points_2, start, report.resolution, config)["T_1_2"]
    overlap = None if report.points_1 is None else (report.points_1, report.points_2)
    serve([m1, m2], [str(args.in1), str(args.in2)], args, transforms=[None, report.T_1_2],
          transforms_init=[None, report.T_1_2_init], trace=trace, overlap_points=overlap)


def run(args) -> int:
    require_viewer()
    maps = []
    for path in args.maps:
        if path.is_dir():
            raise CliError(f"{path}: is a directory, not a map")
        if not path.is_file():
            raise CliError(f"{path}: no such file")
        try:
            maps.append(load(path))
        except MapFormatError as err:
            raise CliError(str(err)) from None
    Ts, Ts_init = (None, None) if args.report is None else transforms_from_report(args.report, len(maps))
    serve(maps, [str(p) for p in args.maps], args, transforms=Ts, transforms_init=Ts_init)
    return 0
