"""Export maps for viewing and for other tools: occupied voxels as a mesh of cubes (or as
points) via trimesh, leaf centres as a PCL ``.pcd`` point cloud, and transforms as TUM trajectories.

Formats by extension: ``.ply``, ``.glb``, ``.obj`` (meshes; ``.ply`` also for points), ``.pcd``
(points only: ``x y z`` float32 and a packed ``rgb``, binary or ascii, as PCL's ``PointXYZRGB``
and Open3D read them). Colours by ``"height"`` (z of the voxel centre through a colour map) or
``"occupancy"`` (probability, blue = threshold to red = certain), as per-face colours of each cube.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .. import se3
from .._fileutil import atomic_output, atomic_write_bytes
from ..map import OccupancyMap, probability

__all__ = ["voxel_mesh", "voxel_points", "export_map", "EXPORT_FORMATS", "pcd_bytes", "write_tum"]

EXPORT_FORMATS = (".ply", ".glb", ".obj", ".pcd")

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


def pcd_bytes(points, colors=None, *, ascii: bool = False) -> bytes:
    """A PCD v0.7 file (PCL's format) of ``points (n, 3)`` [m] as float32 ``x y z`` and, if
    ``colors (n, 3 or 4)`` uint8 are given, ``rgb`` packed as PCL does (``r << 16 | g << 8 | b``,
    stored as an unsigned 32-bit field, which PCL and Open3D both read). ``DATA binary``
    (little-endian records) or ``ascii``. ``WIDTH`` = n, ``HEIGHT`` = 1, viewpoint at the origin."""
    pts = np.asarray(points, np.float32).reshape(-1, 3)
    n = len(pts)
    fields = [("x", "F"), ("y", "F"), ("z", "F")] + ([("rgb", "U")] if colors is not None else [])
    rec = np.zeros(n, [(name, "<f4" if t == "F" else "<u4") for name, t in fields])
    rec["x"], rec["y"], rec["z"] = pts[:, 0], pts[:, 1], pts[:, 2]
    if colors is not None:
        c = np.asarray(colors, np.uint32).reshape(n, -1)
        rec["rgb"] = (c[:, 0] << 16) | (c[:, 1] << 8) | c[:, 2]
    header = ("# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\n"
              f"FIELDS {' '.join(f for f, _ in fields)}\nSIZE {' '.join('4' for _ in fields)}\n"
              f"TYPE {' '.join(t for _, t in fields)}\nCOUNT {' '.join('1' for _ in fields)}\n"
              f"WIDTH {n}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {n}\n"
              f"DATA {'ascii' if ascii else 'binary'}\n")
    if not ascii:
        return header.encode("ascii") + rec.tobytes()
    cols = [np.char.mod("%.9g", rec[f].astype(np.float64)) if t == "F" else rec[f].astype(str) for f, t in fields]
    body = "\n".join(" ".join(row) for row in zip(*cols)) + ("\n" if n else "")
    return (header + body).encode("ascii")


def export_map(m: OccupancyMap, path, *, which: str = "occupied", color_by: str = "height",
               points: bool = False, ascii: bool = False) -> None:
    """Write the selected voxels of ``m`` to ``path`` (``.ply``/``.glb``/``.obj``/``.pcd``),
    atomically. ``points=True`` writes leaf centres instead of cubes (``.ply``; a ``.pcd`` is
    always points). ``ascii=True`` writes a ``.pcd`` as text."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in EXPORT_FORMATS:
        raise ValueError(f"{path}: unsupported export format {suffix!r}; use one of {EXPORT_FORMATS}")
    if points and suffix not in (".ply", ".pcd"):
        raise ValueError(f"{path}: point export needs .ply or .pcd, got {suffix!r}")
    if suffix == ".pcd":
        centers, _, log_odds = _selected(m, which)
        rgba = _colors(centers, log_odds, color_by, float(np.asarray(m.params.occupancy_threshold_log_odds)))
        atomic_write_bytes(path, pcd_bytes(centers, rgba, ascii=ascii))
        return
    geom = voxel_points(m, which=which, color_by=color_by) if points else \
        voxel_mesh(m, which=which, color_by=color_by)
    data = geom.export(file_type=suffix[1:])
    if isinstance(data, str):
        data = data.encode("utf-8")
    with atomic_output(path, suffix=suffix) as tmp:
        Path(tmp).write_bytes(data)


def write_tum(path, stamps, transforms) -> None:
    """Write poses in the TUM RGB-D trajectory format (what ``evo`` and the TUM tools read): one
    line ``timestamp tx ty tz qx qy qz qw`` per pose, atomically.

    Args:
      path: the text file to write.
      stamps: ``(n,)`` times [s] (written with 9 decimals: nanoseconds).
      transforms: ``(n, 4, 4)`` rigid transforms ``T_a_b`` (the pose of frame b in frame a);
        translation [m], rotation as a unit quaternion with ``qw >= 0``.

    Raises ``ValueError`` for a length mismatch, a non-finite stamp or a transform that is not
    rigid (naming its index)."""
    T = np.asarray(transforms, np.float64).reshape(-1, 4, 4)
    t = np.asarray(stamps, np.float64).reshape(-1)
    if len(t) != len(T):
        raise ValueError(f"{path}: {len(t)} stamps but {len(T)} transforms")
    for i in range(len(T)):
        if not np.isfinite(t[i]):
            raise ValueError(f"{path}: stamp {i} is {t[i]}, not a finite time")
        se3.check_rigid(T[i], f"{path}: transform {i}")
    q = np.asarray(se3.to_quaternion(T, xp=np)).reshape(-1, 4)  # (w, x, y, z)
    lines = [f"{t[i]:.9f} " + " ".join(f"{v:.17g}" for v in (*T[i, :3, 3], q[i, 1], q[i, 2], q[i, 3], q[i, 0]))
             for i in range(len(T))]
    atomic_write_bytes(path, ("# timestamp tx ty tz qx qy qz qw\n" + "".join(f"{line}\n" for line in lines))
                       .encode("ascii"))
