"""octomerge_jax: merge OctoMap occupancy octrees (.bt/.ot) in JAX.

The method of J. Jessup, "Merging of Octree Based 3D Occupancy Grid Maps" (2013), on
Morton-coded leaf arrays: jitted lookups, local expansion, trilinear resampling, log-odds
fusion across depths and differentiable ICP.
"""

from importlib.metadata import PackageNotFoundError, version as _version

from .examples import example_map
from .fusion import FuseReport, FuseResult, fuse, fuse_many, fuse_many_with_report, fuse_with_report
from .hostmem import reuse_host_memory
from .io import MapFormatError, from_bytes, from_message, load, save, to_bytes, to_message_fields
from .insert import CapacityPlan, insert_point_cloud, insert_point_clouds
from .map import Leaves, OccupancyMap, OccupancyParams, bucket_capacity, empty, from_leaves
from .pipeline import (BatchResult, ManyReport, MergeConfig, MergeError, MergeReport, Registration, load_config,
                       merge, merge_batch, merge_many)
from .registration import (
    AlignResult,
    align_dense,
    alignment_loss,
    evaluate_registration,
    IcpResult,
    Status,
    icp,
    icp_multi,
    occupied_points,
    overlap,
    rendezvous_transform,
    rotation_error,
    translation_error,
)
from .resample import sample, transform_map, transformed_bounds
from .se3 import from_xyz_rpy
from .tree import (
    apply_voxel_updates,
    clamp,
    expand,
    from_voxels,
    lookup,
    num_nodes,
    prune,
    to_max_likelihood,
    update_points,
)
# --- bags
from .io.bags import BagMap, read_bag

# Heavier parts (trimesh scenes, scan readers) load on first use, keeping `import` fast.
_LAZY = {
    "make_two_robot_maps": "octomerge_jax.sim",
    "Scan": "octomerge_jax.io.scans",
    "read_scan_graph": "octomerge_jax.io.scans",
    "write_scan_graph": "octomerge_jax.io.scans",
}


def __getattr__(name):
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'octomerge_jax' has no attribute {name!r}")


try:
    __version__ = _version("octomerge_jax")
except PackageNotFoundError:  # pragma: no cover - running from a source tree
    __version__ = "0.0.0"

__all__ = [
    "AlignResult",
    "BatchResult",
    "CapacityPlan",
    "FuseReport",
    "FuseResult",
    "IcpResult",
    "Leaves",
    "ManyReport",
    "MapFormatError",
    "MergeConfig",
    "MergeError",
    "MergeReport",
    "Registration",
    "OccupancyMap",
    "OccupancyParams",
    "Scan",
    "Status",
    "align_dense",
    "alignment_loss",
    "apply_voxel_updates",
    "bucket_capacity",
    "clamp",
    "empty",
    "evaluate_registration",
    "example_map",
    "expand",
    "from_bytes",
    "from_leaves",
    "from_message",
    "from_voxels",
    "from_xyz_rpy",
    "fuse",
    "fuse_many",
    "fuse_many_with_report",
    "fuse_with_report",
    "icp",
    "icp_multi",
    "insert_point_cloud",
    "insert_point_clouds",
    "load",
    "load_config",
    "lookup",
    "make_two_robot_maps",
    "merge",
    "merge_batch",
    "merge_many",
    "num_nodes",
    "occupied_points",
    "overlap",
    "prune",
    "read_scan_graph",
    "rendezvous_transform",
    "reuse_host_memory",
    "rotation_error",
    "sample",
    "save",
    "to_bytes",
    "to_max_likelihood",
    "to_message_fields",
    "transform_map",
    "transformed_bounds",
    "translation_error",
    "update_points",
    "write_scan_graph",
    # --- bags
    "BagMap",
    "read_bag",
]
