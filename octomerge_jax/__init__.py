"""octomerge_jax: merge OctoMap occupancy octrees in JAX (Jessup 2013, done right)."""

from importlib.metadata import PackageNotFoundError, version as _version

from .map import Leaves, OccupancyMap, OccupancyParams, bucket_capacity, empty, from_leaves

try:
    __version__ = _version("octomerge_jax")
except PackageNotFoundError:  # pragma: no cover - running from a source tree
    __version__ = "0.0.0"

__all__ = [
    "Leaves",
    "OccupancyMap",
    "OccupancyParams",
    "bucket_capacity",
    "empty",
    "from_leaves",
]
