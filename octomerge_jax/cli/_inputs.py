"""Map arguments that may be ROS bags: ``--topic`` / ``--stamp`` options and one loader for
"a .bt / .ot file or a bag" (``octomerge info | convert | merge``)."""

from __future__ import annotations

from pathlib import Path

from ..io import MapFormatError, load
from ..io.bags import BagMap, is_bag, select_map
from ..map import OccupancyMap
from ._common import CliError
from .outputs import check_input

BAG_HELP = ("a bag (ROS 1 .bag, ROS 2 bag folder, .db3 or .mcap) holding octomap_msgs/Octomap "
            "messages may stand in for any map")


def add_bag_options(parser) -> None:
    """``--topic T`` and ``--stamp S``, each once (for every bag input) or once per input."""
    g = parser.add_argument_group("ROS bag inputs", BAG_HELP)
    g.add_argument("--topic", action="append", metavar="T",
                   help="octomap_msgs/Octomap topic (default: the bag's only one); repeat for a second bag input")
    g.add_argument("--stamp", action="append", type=float, metavar="S",
                   help="the map published at or before S [s since the epoch] (default: the last); "
                        "repeat for a second bag input")


def _pick(values, index: int):
    return None if not values else values[0] if len(values) == 1 else values[index]


def check_map_input(path: Path, what: str = "map") -> None:
    """Raise ``CliError`` naming ``path`` if it is neither a ``what`` file nor a bag (a ROS 2
    bag is a folder)."""
    if is_bag(path) and path.exists():
        return
    check_input(path, what)


def load_map_inputs(paths, args, *, strict: bool = True) -> list[tuple[OccupancyMap, BagMap | None]]:
    """The maps of the inputs ``paths``: ``.bt`` / ``.ot`` files, or bags' maps chosen by
    ``args.topic`` / ``args.stamp`` (one value for all bags, or one per input in order).
    Returns ``[(map, BagMap or None)]``; raises ``CliError`` (exit 1 for bad input, 2 for
    ``--topic`` / ``--stamp`` without a bag input or given more often than there are inputs)."""
    topics, stamps = getattr(args, "topic", None), getattr(args, "stamp", None)
    bags = [is_bag(p) for p in paths]
    for values, option in ((topics, "--topic"), (stamps, "--stamp")):
        if values and not any(bags):
            raise CliError(f"{option} applies to bag inputs; {', '.join(map(str, paths))} holds none", 2)
        if values and len(values) > 1 and len(values) != len(paths):
            raise CliError(f"{option} given {len(values)} times for {len(paths)} inputs", 2)
    out = []
    for i, (path, bag) in enumerate(zip(paths, bags)):
        check_map_input(path)
        try:
            if bag:
                b = select_map(path, _pick(topics, i), _pick(stamps, i), strict=strict)
                out.append((b.map, b))
            else:
                out.append((load(path, strict=strict), None))
        except (MapFormatError, ModuleNotFoundError) as err:
            raise CliError(str(err)) from None
    return out
