"""octomerge_jax: merge OctoMap occupancy octrees (.bt/.ot) in JAX.

The method of J. Jessup, "Merging of Octree Based 3D Occupancy Grid Maps" (2013), on
Morton-coded leaf arrays: jitted lookups, local expansion, trilinear resampling, log-odds
fusion across depths and differentiable ICP.

The public names below load on first use (``octomerge_jax.merge`` imports the pipeline and JAX
then), so ``import octomerge_jax`` and ``octomerge --help`` stay fast: docs/design.md,
"Start-up: lazy imports".
"""

import importlib

# public name -> the module (relative to this package) that defines it
_SOURCES = {
    "examples": ("example_map",),
    "fusion": ("FuseReport", "FuseResult", "fuse", "fuse_many", "fuse_many_with_report", "fuse_with_report"),
    "hostmem": ("reuse_host_memory",),
    "insert": ("CapacityPlan", "insert_point_cloud", "insert_point_clouds"),
    "io": ("MapFormatError", "from_bytes", "from_message", "load", "save", "to_bytes", "to_message_fields"),
    "io.bags": ("BagMap", "read_bag"),
    "io.scans": ("Scan", "read_scan_graph", "write_scan_graph"),
    "map": ("Leaves", "OccupancyMap", "OccupancyParams", "bucket_capacity", "empty", "from_leaves"),
    "pipeline": ("BatchResult", "ManyReport", "MergeConfig", "MergeError", "MergeReport", "Registration",
        "load_config", "merge", "merge_batch", "merge_many"),
    "registration": ("AlignResult", "IcpResult", "Status", "align_dense", "alignment_loss", "correlation_search",
        "evaluate_registration", "icp", "icp_multi", "occupied_points", "overlap", "rendezvous_transform",
        "rotation_error", "translation_error"),
    "resample": ("sample", "transform_map", "transformed_bounds"),
    "se3": ("from_xyz_rpy",),
    "sim": ("make_two_robot_maps",),
    "tree": ("apply_voxel_updates", "clamp", "expand", "from_voxels", "lookup", "num_nodes", "prune",
        "to_max_likelihood", "update_points"),
}
_LAZY = {name: module for module, names in _SOURCES.items() for name in names}


def __getattr__(name):
    if name in _LAZY:
        value = getattr(importlib.import_module(f"{__name__}.{_LAZY[name]}"), name)
        globals()[name] = value  # later look-ups skip this function
        return value
    if name == "__version__":
        from importlib.metadata import PackageNotFoundError, version

        try:
            return version("octomerge_jax")
        except PackageNotFoundError:  # pragma: no cover - running from a source tree
            return "0.0.0"
    raise AttributeError(f"module 'octomerge_jax' has no attribute {name!r}")


def __dir__():
    return sorted(set(globals()) | set(_LAZY))


__all__ = [
    "AlignResult",
    "BagMap",
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
    "correlation_search",
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
    "read_bag",
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
]
