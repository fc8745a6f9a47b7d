"""Reading and writing maps: OctoMap ``.bt`` / ``.ot`` files and ``octomap_msgs`` payloads."""

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
]
