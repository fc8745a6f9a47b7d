"""Reading and writing maps: OctoMap ``.bt`` / ``.ot`` files, ``octomap_msgs`` payloads and ROS bags."""

from .errors import MapFormatError
from .octree_format import (
    Header,
    from_bytes,
    from_message,
    load,
    max_likelihood_prune,
    num_nodes,
    read_header,
    save,
    to_bytes,
    to_message_fields,
)
from .bags import BagMap, read_bag

__all__ = [
    "Header",
    "MapFormatError",
    "from_bytes",
    "from_message",
    "load",
    "max_likelihood_prune",
    "num_nodes",
    "read_header",
    "save",
    "to_bytes",
    "to_message_fields",
    "BagMap",
    "read_bag",
]
