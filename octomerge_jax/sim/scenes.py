"""Synthetic scenes (trimesh meshes) for multi-robot mapping, after thesis §7.1 and §7.2.

A ``Scene`` is a triangle mesh in the world frame (z up, metres) plus two suggested robot
paths that cover different but overlapping parts of it, like the thesis's two mapping runs:

- ``lab_room``: a room with a formation of boxes and a hollow square wooden-fence structure
  (thesis §7.2, Fig. 7.9): robot 1 circles the boxes, robot 2 travels around the fence.
- ``office_floor``: a floor of rooms on both sides of a corridor (thesis §7.1's
  ``wg_collada_world``): robot 1 maps the west half, robot 2 the east half; both see the middle.
- ``campus``: an outdoor site of ~100 x 60 m (buildings, trees, open ground) along a road, for
  a spinning lidar (the scene's suggested sensor): robot 1 drives the west part, robot 2 the
  east part, overlapping in the middle. At 0.2 m each map has ~1M leaves (0.4-0.5M as a
  pruned ``.bt``), the scale of OctoMap's outdoor datasets; the ground is seen at grazing angles.
- ``mesh_scene``: any trimesh mesh (or a mesh file) with user paths.

Scenes are low-poly on purpose (boxes, wall slabs): ray casting tests every triangle.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import trimesh

from .raycast import mesh_triangles
from .sensors import SpinningLidar

__all__ = ["Scene", "lab_room", "office_floor", "campus", "mesh_scene", "make_scene"]


@dataclasses.dataclass(frozen=True)
class Scene:
    """A world mesh and two robot paths through it.

    Attributes:
      mesh: ``trimesh.Trimesh`` in the world frame [m], z up.
      name: short label.
      paths: two ``(k, 2)`` arrays of xy waypoints [m] (robot 1, robot 2).
      targets: per path, ``None`` (face along the path), an xy point [m] the sensor faces, or
        ``(k, 2)`` points, one per waypoint (see ``poses_along_path``).
      closed: per path, whether it loops back to its start.
      sensor_height: sensor height above the floor [m].
      sensor: suggested sensor (``None``: the simulation's default depth camera).
      spacing: suggested distance between scans along the paths [m] (``None``: 0.5 m).
    """

    mesh: trimesh.Trimesh
    name: str
    paths: tuple[np.ndarray, np.ndarray]
    targets: tuple[np.ndarray | None, np.ndarray | None] = (None, None)
    closed: tuple[bool, bool] = (False, False)
    sensor_height: float = 0.5
    sensor: object = None
    spacing: float | None = None

    @property
    def triangles(self) -> np.ndarray:
        """``(T, 3, 3)`` float32 triangle vertices [m]."""
        return mesh_triangles(self.mesh)

    @property
    def bounds(self) -> np.ndarray:
        """``(2, 3)`` axis-aligned bounds [m]."""
        return np.asarray(self.mesh.bounds, dtype=np.float64)


def _box(lo, hi, yaw_rad: float = 0.0) -> trimesh.Trimesh:
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    box = trimesh.creation.box(extents=hi - lo)
    T = trimesh.transformations.rotation_matrix(yaw_rad, [0, 0, 1])
    T[:3, 3] = (lo + hi) / 2
    return box.apply_transform(T)


def _room_shell(size_x: float, size_y: float, height: float, wall: float = 0.1) -> list:
    """Floor slab and four walls around ``[-sx/2, sx/2] x [-sy/2, sy/2]``."""
    hx, hy = size_x / 2, size_y / 2
    return [
        _box((-hx - wall, -hy - wall, -wall), (hx + wall, hy + wall, 0.0)),  # floor
        _box((-hx - wall, -hy - wall, 0.0), (-hx, hy + wall, height)),
        _box((hx, -hy - wall, 0.0), (hx + wall, hy + wall, height)),
        _box((-hx, -hy - wall, 0.0), (hx, -hy, height)),
        _box((-hx, hy, 0.0), (hx, hy + wall, height)),
    ]


def _loop(center, radius_x, radius_y, n: int = 12) -> np.ndarray:
    a = np.linspace(0, 2 * np.pi, n, endpoint=False)
    return np.stack([center[0] + radius_x * np.cos(a), center[1] + radius_y * np.sin(a)], 1)


def lab_room(seed: int = 0, size=(10.0, 7.0), height: float = 2.5, num_boxes: int = 6,
             fence_side: float = 2.4, fence_height: float = 0.6) -> Scene:
    """The laboratory of thesis §7.2: a box formation (left) and a hollow square
    wooden-fence structure (right) in a walled room.

    Args:
      seed: randomises box sizes, positions and yaw.
      size: room extent ``(x, y)`` [m].
      height: wall height [m].
      num_boxes: boxes in the formation (arranged on a jittered 2-row grid).
      fence_side, fence_height: outer side and height of the square fence [m].
    """
    rng = np.random.default_rng(seed)
    sx, sy = float(size[0]), float(size[1])
    if sx < 6 or sy < 4:
        raise ValueError(f"size: the lab needs at least 6 x 4 m, got {size}")
    parts = _room_shell(sx, sy, height)
    box_c = np.array([-sx / 4, 0.0])
    fence_c = np.array([sx / 4, 0.0])
    cols = max(1, int(np.ceil(num_boxes / 2)))
    for i in range(num_boxes):
        r, c = divmod(i, cols)
        cx = box_c[0] + (c - (cols - 1) / 2) * 0.9 + rng.uniform(-0.1, 0.1)
        cy = box_c[1] + (r - 0.5) * 0.9 + rng.uniform(-0.1, 0.1)
        w, d, h = rng.uniform(0.35, 0.6), rng.uniform(0.35, 0.6), rng.uniform(0.3, 0.9)
        parts.append(_box((cx - w / 2, cy - d / 2, 0.0), (cx + w / 2, cy + d / 2, h),
                          yaw_rad=rng.uniform(-0.3, 0.3)))
    # hollow square fence: corner and middle posts, two horizontal boards per side
    half, post, board = fence_side / 2, 0.08, 0.025
    for px in (-half, 0.0, half):
        for py in (-half, 0.0, half):
            if px == 0.0 and py == 0.0:
                continue
            x, y = fence_c[0] + px, fence_c[1] + py
            parts.append(_box((x - post / 2, y - post / 2, 0.0),
                              (x + post / 2, y + post / 2, fence_height)))
    for z0 in (0.12 * fence_height / 0.6, 0.4 * fence_height / 0.6):
        z1 = z0 + 0.15 * fence_height / 0.6
        for s in (-1, 1):
            y = fence_c[1] + s * half
            parts.append(_box((fence_c[0] - half, y - board / 2, z0), (fence_c[0] + half, y + board / 2, z1)))
            x = fence_c[0] + s * half
            parts.append(_box((x - board / 2, fence_c[1] - half, z0), (x + board / 2, fence_c[1] + half, z1)))
    mesh = trimesh.util.concatenate(parts)
    r1 = min(1.9, sy / 2 - 0.6)
    r2 = min(half + 1.2, sy / 2 - 0.6)
    # Each robot circles its landmark facing it, then drives towards the middle of the room
    # facing the other landmark: the maps overlap on both landmarks' near sides (§7.2).
    rx1, rx2 = min(r1 + 0.5, sx / 4 - 0.3), min(r2, sx / 4 - 0.3)
    loop1 = _loop(box_c, rx1, r1, 14)  # starts on the east side
    loop2 = _loop(fence_c, rx2, r2, 14)[np.r_[7:14, 0:8]]  # starts and ends on the west side
    path1 = np.vstack([loop1, loop1[:1], [[box_c[0] + rx1 + 0.6, 0.6]]])
    path2 = np.vstack([loop2, [[fence_c[0] - rx2 - 0.6, -0.6]]])
    t1 = np.vstack([np.tile(box_c, (len(loop1), 1)), np.tile(fence_c, (2, 1))])
    t2 = np.vstack([np.tile(fence_c, (len(loop2) - 1, 1)), np.tile(box_c, (2, 1))])
    return Scene(mesh, "lab_room", (path1, path2), (t1, t2), (False, False), 0.45)


def office_floor(seed: int = 0, size=(16.0, 10.0), height: float = 2.5,
                 corridor_width: float = 2.0, rooms_per_side: int = 3,
                 furniture_per_room: int = 2) -> Scene:
    """An office floor like thesis §7.1's world: a corridor along x with rooms on both
    sides, doors into the corridor, and desks/cabinets (boxes) in the rooms.

    Robot 1 drives the west half of the corridor and into a west room, robot 2 the east half
    and an east room; both see the middle of the corridor.
    """
    rng = np.random.default_rng(seed)
    sx, sy = float(size[0]), float(size[1])
    if corridor_width >= sy - 2:
        raise ValueError(f"corridor_width {corridor_width} leaves no room depth in size {size}")
    parts = _room_shell(sx, sy, height)
    hx, hy, cw, t = sx / 2, sy / 2, corridor_width / 2, 0.1
    room_w = sx / rooms_per_side
    door = 1.0
    for side in (-1, 1):
        y_wall = side * cw
        for i in range(rooms_per_side):
            x0 = -hx + i * room_w
            dx = x0 + room_w / 2 + rng.uniform(-0.3, 0.3) * room_w / 2
            # corridor wall with a door gap
            y_lo, y_hi = sorted((y_wall, y_wall + side * t))
            parts.append(_box((x0, y_lo, 0.0), (dx - door / 2, y_hi, height)))
            parts.append(_box((dx + door / 2, y_lo, 0.0), (x0 + room_w, y_hi, height)))
            if i > 0:  # partition between rooms
                ya, yb = sorted((y_wall + side * t, side * hy))
                parts.append(_box((x0 - t / 2, ya, 0.0), (x0 + t / 2, yb, height)))
            for _ in range(furniture_per_room):
                w, d, h = rng.uniform(0.5, 1.4), rng.uniform(0.4, 0.8), rng.uniform(0.5, 1.2)
                cx = rng.uniform(x0 + 0.3 + w / 2, x0 + room_w - 0.3 - w / 2)
                yr = sorted((side * (cw + t + 0.4 + d / 2), side * (hy - 0.2 - d / 2)))
                cy = rng.uniform(*yr)
                parts.append(_box((cx - w / 2, cy - d / 2, 0.0), (cx + w / 2, cy + d / 2, h)))
    mesh = trimesh.util.concatenate(parts)
    path1 = np.array([[-hx + 1.0, 0.0], [-hx / 2, 0.0], [0.5, 0.0], [1.5, 0.0],
                      [0.5, 0.0], [-hx / 2, 0.0]])
    path2 = np.array([[hx - 1.0, 0.0], [hx / 2, 0.0], [-0.5, 0.0], [-1.5, 0.0],
                      [-0.5, 0.0], [hx / 2, 0.0]])
    return Scene(mesh, "office_floor", (path1, path2), (None, None), (False, False), 0.5)


def campus(seed: int = 0, size=(100.0, 60.0), num_buildings: int = 14, num_trees: int = 40,
           road_half_width: float = 6.0) -> Scene:
    """An outdoor campus: a ground plane, ``num_buildings`` boxes 4-14 m high and
    ``num_trees`` trees (trunk and crown) on both sides of a road along x, with a 16-beam
    spinning lidar (40 m range) as the suggested sensor and a scan every 2 m.

    Robot 1 drives the west 55 m of the road, robot 2 the east 55 m; both see the middle.
    ``seed`` places the buildings and trees (never on the road).
    """
    rng = np.random.default_rng(seed)
    sx, sy = float(size[0]), float(size[1])
    if sx < 40 or sy < 4 * road_half_width:
        raise ValueError(f"size: the campus needs at least 40 x {4 * road_half_width:g} m, got {size}")
    hx, hy = sx / 2, sy / 2
    parts = [_box((-hx - 5, -hy - 5, -0.2), (hx + 5, hy + 5, 0.0))]  # ground
    side = lambda: rng.choice((-1.0, 1.0))  # noqa: E731
    for _ in range(num_buildings):
        w, d, h = rng.uniform(5, 15), rng.uniform(5, 12), rng.uniform(4, 14)
        r = 0.5 * np.hypot(w, d)  # keeps the turned footprint off the road
        cx = rng.uniform(-hx + r, hx - r)
        cy = side() * rng.uniform(road_half_width + r, max(hy - r, road_half_width + r + 0.1))
        parts.append(_box((cx - w / 2, cy - d / 2, 0.0), (cx + w / 2, cy + d / 2, h),
                          yaw_rad=rng.uniform(0, np.pi)))
    for _ in range(num_trees):
        cx, cy = rng.uniform(-hx, hx), side() * rng.uniform(road_half_width - 2.0, hy)
        trunk = trimesh.creation.cylinder(radius=0.25, height=3.0, sections=6)
        parts.append(trunk.apply_translation((cx, cy, 1.5)))
        parts.append(trimesh.creation.icosphere(subdivisions=0, radius=1.8).apply_translation((cx, cy, 4.0)))
    mesh = trimesh.util.concatenate(parts)
    x1 = np.linspace(-0.45 * sx, 0.1 * sx, 12)
    x2 = np.linspace(-0.1 * sx, 0.45 * sx, 12)
    path1 = np.stack([x1, np.sin(x1 / 7.0)], 1)
    path2 = np.stack([x2, np.cos(x2 / 9.0) - 1.0], 1)
    lidar = SpinningLidar(num_beams=16, azimuth_steps=900, max_range=40.0)
    return Scene(mesh, "campus", (path1, path2), (None, None), (False, False), 1.2, lidar, 2.0)


def mesh_scene(mesh, path1, path2, *, target1=None, target2=None, closed=(False, False),
               sensor_height: float = 0.5, name: str = "mesh") -> Scene:
    """A scene from any trimesh mesh (or a mesh file path trimesh can load) and two xy paths."""
    if isinstance(mesh, (str, Path)):
        mesh = trimesh.load(str(mesh), force="mesh")
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise ValueError("mesh: expected a trimesh.Trimesh with at least one face")
    paths = []
    for name_i, p in (("path1", path1), ("path2", path2)):
        p = np.asarray(p, dtype=np.float64)
        if p.ndim != 2 or p.shape[1] != 2 or len(p) < 1:
            raise ValueError(f"{name_i}: expected (k, 2) xy waypoints, got shape {p.shape}")
        paths.append(p)
    targets = tuple(None if t is None else np.asarray(t, float).reshape(2) for t in (target1, target2))
    return Scene(mesh, name, (paths[0], paths[1]), targets, tuple(closed), float(sensor_height))


def make_scene(scene, seed: int = 0) -> Scene:
    """``Scene`` or a name (``"lab"``/``"lab_room"``, ``"office"``/``"office_floor"``,
    ``"campus"``)."""
    if isinstance(scene, Scene):
        return scene
    if scene == "campus":
        return campus(seed)
    if scene in ("lab", "lab_room"):
        return lab_room(seed)
    if scene in ("office", "office_floor"):
        return office_floor(seed)
    raise ValueError(f"scene: expected a Scene or 'lab' / 'office' / 'campus', got {scene!r}")
