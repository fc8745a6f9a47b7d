"""Export maps for viewing: occupied voxels as a mesh of cubes (or as points) via trimesh.

Formats by extension: ``.ply``, ``.glb``, ``.obj`` (meshes; ``.ply`` also for points). Colours
by ``"height"`` (z of the voxel centre through a colour map) or ``"occupancy"`` (probability,
blue = threshold to red = certain), as per-face colours of each cube.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .._fileutil import atomic_output
from ..map import OccupancyMap, probability

__all__ = ["voxel_mesh", "voxel_points", "export_map", "EXPORT_FORMATS"]

EXPORT_FORMATS = (".ply", ".glb", ".obj")

# unit cube: 8 corners, 12 triangles (outward normals)
_CORNERS = np.array([[x, y, z] for z in (0, 1) for y in (0, 1) for x in (0, 1)], np.float64) - 0.5
_FACES = np.array([
    [0, 2, 1], [1, 2, 3],  # -z
    [4, 5, 6], [5, 7, 6],  # +z
    [0, 1, 4], [1, 5, 4],  # -y
    [2, 6, 3], [3, 6, 7],  # +y
    [0, 4, 2], [2, 4, 6],  # -x
    [1, 3, 5], [3, 7, 5],  # +x
], np.int64)


def _selected(m: OccupancyMap, which: str):
    lv = m.leaves()
    occ = np.asarray(m.is_occupied())[: m.num_leaves]
    if which == "occupied":
        keep = occ
    elif which == "free":
        keep = ~occ
    elif which == "all":
        keep = np.ones_like(occ)
    else:
        raise ValueError(f"which: expected 'occupied', 'free' or 'all', got {which!r}")
    return lv.centers[keep], lv.sizes[keep], lv.log_odds[keep]


def _colors(centers, log_odds, color_by: str, threshold: float) -> np.ndarray:
    """``(n, 4)`` uint8 RGBA per voxel."""
    import matplotlib

    n = len(centers)
    if n == 0:
        return np.zeros((0, 4), np.uint8)
    if color_by == "height":
        z = centers[:, 2]
        span = z.max() - z.min()
        t = (z - z.min()) / span if span > 0 else np.zeros(n)
        rgba = matplotlib.colormaps["viridis"](t)
    elif color_by == "occupancy":
        p = np.asarray(probability(np.asarray(log_odds, np.float64)))
        p0 = float(probability(np.float64(threshold)))
        t = np.clip((p - p0) / max(1.0 - p0, 1e-9), 0.0, 1.0) if p0 < 1 else np.zeros(n)
        rgba = matplotlib.colormaps["coolwarm"](t)
    else:
        raise ValueError(f"color_by: expected 'height' or 'occupancy', got {color_by!r}")
    return (np.asarray(rgba) * 255).round().astype(np.uint8)


def voxel_mesh(m: OccupancyMap, *, which: str = "occupied", color_by: str = "height"):
    """A ``trimesh.Trimesh`` with one cube (12 triangles) per selected leaf, sized by its
    depth, coloured per face. Coordinates in metres, in the map frame."""
    import trimesh

    centers, sizes, log_odds = _selected(m, which)
    n = len(centers)
    verts = (centers[:, None, :] + _CORNERS[None] * sizes[:, None, None]).reshape(-1, 3)
    faces = (_FACES[None] + 8 * np.arange(n)[:, None, None]).reshape(-1, 3)
    colors = np.repeat(_colors(centers, log_odds, color_by,
                               float(np.asarray(m.params.occupancy_threshold_log_odds))), 12, axis=0)
    return trimesh.Trimesh(vertices=verts, faces=faces, face_colors=colors, process=False)


def voxel_points(m: OccupancyMap, *, which: str = "occupied", color_by: str = "height"):
    """A ``trimesh.PointCloud`` of the selected leaf centres, coloured per point."""
    import trimesh

    centers, _, log_odds = _selected(m, which)
    colors = _colors(centers, log_odds, color_by, float(np.asarray(m.params.occupancy_threshold_log_odds)))
    return trimesh.PointCloud(centers, colors=colors)


def export_map(m: OccupancyMap, path, *, which: str = "occupied", color_by: str = "height",
               points: bool = False) -> None:
    """Write the selected voxels of ``m`` to ``path`` (``.ply``/``.glb``/``.obj``),
    atomically. ``points=True`` writes leaf centres instead of cubes (``.ply`` only)."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in EXPORT_FORMATS:
        raise ValueError(f"{path}: unsupported export format {suffix!r}; use one of {EXPORT_FORMATS}")
    if points and suffix != ".ply":
        raise ValueError(f"{path}: point export needs .ply, got {suffix!r}")
    geom = voxel_points(m, which=which, color_by=color_by) if points else \
        voxel_mesh(m, which=which, color_by=color_by)
    data = geom.export(file_type=suffix[1:])
    if isinstance(data, str):
        data = data.encode("utf-8")
    with atomic_output(path, suffix=suffix) as tmp:
        Path(tmp).write_bytes(data)
