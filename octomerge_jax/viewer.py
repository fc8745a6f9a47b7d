"""A live 3-D view of occupancy maps in the web browser, built on ``viser`` (an optional
dependency: ``pip install "octomerge_jax[viewer]"``).

``view(maps, ...)`` serves a page (``Viewer.url``) that shows each map's occupied leaves as
boxes of their own size, coloured by height or by map of origin, in map 0's frame. With a
merge's transform(s) it also shows map 2 before and after registration, the overlap clouds
that were registered, a slider over the ICP iterations, free space on demand and a toggle per
map. The page works in a notebook too (``Viewer.show()`` embeds it as an ``IFrame``).

``octomerge view`` and ``octomerge merge --visualize`` call it; the scene data
(``voxel_boxes``, ``height_colors``) are plain NumPy functions, testable without a browser.
"""

from __future__ import annotations

import dataclasses
import socket
import time
from typing import NamedTuple, Sequence

import numpy as np

from . import se3
from .map import OccupancyMap

__all__ = ["MAP_COLORS", "Viewer", "VoxelBoxes", "free_port", "height_colors", "view", "voxel_boxes"]

# colour per map of origin (map 0, 1, ...): ColorBrewer Dark2, cycled
MAP_COLORS = np.array([(27, 158, 119), (217, 95, 2), (117, 112, 179), (231, 41, 138),
                       (102, 166, 30), (230, 171, 2), (166, 118, 29), (102, 102, 102)], np.uint8)

# viridis at 9 stops (height colouring without matplotlib)
_VIRIDIS = np.array([(68, 1, 84), (71, 45, 123), (59, 82, 139), (44, 114, 142), (33, 145, 140),
                     (39, 173, 129), (92, 200, 99), (170, 220, 50), (253, 231, 37)], np.float64)

# a unit cube centred on the origin (vertices, triangles) for instanced boxes
_CUBE_VERTICES = np.array([[x, y, z] for x in (-0.5, 0.5) for y in (-0.5, 0.5) for z in (-0.5, 0.5)],
                          np.float32)
_CUBE_FACES = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
                        [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]], np.uint32)


class VoxelBoxes(NamedTuple):
    """Boxes to draw for one map (its own frame)."""

    centers: np.ndarray  # (n, 3) float32, metres
    sizes: np.ndarray  # (n,) float32, edge length [m]
    coarsened: int  # k: leaves merged into cells of 2^k voxels to stay under max_boxes (0: none)


def voxel_boxes(m: OccupancyMap, *, occupied: bool = True, max_boxes: int = 200_000) -> VoxelBoxes:
    """The occupied (or free, ``occupied=False``) leaves of ``m`` as boxes of their own size.
    Leaves finer than needed are merged into cells of ``2^k`` voxels (the smallest ``k`` that
    keeps at most ``max_boxes`` boxes; a cell is drawn when any leaf in it is), so a map of
    millions of leaves stays interactive. Raises ``ValueError`` for ``max_boxes < 1``."""
    if max_boxes < 1:
        raise ValueError(f"max_boxes must be at least 1, got {max_boxes}")
    leaves = m.leaves()
    thr = m.params.occupancy_threshold_host
    keep = leaves.log_odds > thr if occupied else leaves.log_odds <= thr
    centers, sizes = leaves.centers[keep], leaves.sizes[keep]
    k = 0
    while len(centers) > max_boxes and k < 16:
        k += 1
        cell = m.resolution * (1 << k)
        fine = sizes < cell
        idx = np.floor(centers[fine] / cell).astype(np.int64)
        idx = np.unique(idx, axis=0)
        centers = np.concatenate([(idx + 0.5) * cell, centers[~fine]])
        sizes = np.concatenate([np.full(len(idx), cell), sizes[~fine]])
    return VoxelBoxes(centers.astype(np.float32), sizes.astype(np.float32), k)


def height_colors(z: np.ndarray, lo: float | None = None, hi: float | None = None) -> np.ndarray:
    """``(n, 3)`` uint8 viridis colours for heights ``z`` [m] between ``lo`` and ``hi``
    (default: the 2nd and 98th percentiles of ``z``)."""
    z = np.asarray(z, np.float64).reshape(-1)
    if z.size == 0:
        return np.zeros((0, 3), np.uint8)
    lo = float(np.percentile(z, 2)) if lo is None else lo
    hi = float(np.percentile(z, 98)) if hi is None else hi
    t = np.clip((z - lo) / max(hi - lo, 1e-9), 0.0, 1.0) * (len(_VIRIDIS) - 1)
    i = np.minimum(t.astype(np.int64), len(_VIRIDIS) - 2)
    f = (t - i)[:, None]
    return np.round(_VIRIDIS[i] * (1 - f) + _VIRIDIS[i + 1] * f).astype(np.uint8)


def free_port(host: str = "127.0.0.1") -> int:
    """A TCP port free on ``host`` now (the OS picks it)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind((host, 0))
        return int(s.getsockname()[1])


def _pose(T) -> tuple[np.ndarray, np.ndarray]:
    """viser's ``(wxyz, position)`` of a rigid ``(4, 4)``."""
    T = np.asarray(T, np.float64)
    return np.asarray(se3.to_quaternion(T, xp=np)), T[:3, 3].copy()


@dataclasses.dataclass
class Viewer:
    """A running view (``view``): ``url`` to open, ``server`` (``viser.ViserServer``) for
    scripting, ``set_iteration(i)`` to place map 2 at ICP iteration ``i``, ``close()``."""

    server: object
    url: str
    frames: list
    handles: dict
    transforms: list
    trace: np.ndarray | None

    def set_iteration(self, i: int) -> None:
        """Place the last map at ICP iteration ``i`` of the trace (``0``: the initial guess)."""
        if self.trace is None:
            raise ValueError("this view has no ICP trace")
        wxyz, pos = _pose(self.trace[int(np.clip(i, 0, len(self.trace) - 1))])
        self.frames[-1].wxyz, self.frames[-1].position = wxyz, pos

    def show(self, height: int = 500):
        """The page as an ``IPython.display.IFrame`` (notebooks)."""
        from IPython.display import IFrame  # optional: only in a notebook

        return IFrame(self.url, width="100%", height=height)

    def wait(self) -> None:
        """Block until interrupted (Ctrl-C), then close the server."""
        try:
            while True:
                time.sleep(0.5)
        except KeyboardInterrupt:
            pass
        finally:
            self.close()

    def close(self) -> None:
        self.server.stop()


def view(maps: Sequence[OccupancyMap], *, names: Sequence[str] | None = None, transforms=None,
         transforms_init=None, trace=None, overlap_points=None, color_by: str = "height",
         max_boxes: int = 200_000, host: str = "127.0.0.1", port: int | None = None) -> Viewer:
    """Serve a live 3-D view of ``maps`` (``viser``) and return the running ``Viewer``.

    Args:
      maps: occupancy maps; map 0 is the reference frame.
      names: one label per map (default ``map 1``, ``map 2``, ...).
      transforms: per map a ``(4, 4)`` transform of its frame into map 0's [m] (``T_0_k``;
        ``None`` entries or no list: identity), e.g. a merge's ``T_1_2`` for map 2.
      transforms_init: the same before registration (e.g. ``T_1_2_init``); with it, a
        "before / after registration" switch.
      trace: ``(K+1, 4, 4)`` transforms of the last map per ICP iteration
        (``pipeline.icp_trace(...)["T_1_2"]``); with it, an iteration slider.
      overlap_points: ``(points_1 (n1, 3), points_2 (n2, 3))`` the clouds registered, each in
        its own map's frame (``MergeReport.points_1`` / ``points_2``), drawn as points.
      color_by: ``"height"`` or ``"map"`` (switchable on the page).
      max_boxes: per map and kind (occupied / free), see ``voxel_boxes``.
      host, port: where to serve (``port=None``: a free port).

    Raises ``ValueError`` for an empty ``maps``, lists of the wrong length or a bad
    ``color_by``; ``ModuleNotFoundError`` naming the extra when viser is not installed.
    """
    try:
        import viser  # optional dependency
    except ModuleNotFoundError:
        raise ModuleNotFoundError("the viewer needs viser: pip install 'octomerge_jax[viewer]'",
                                  name="viser") from None
    maps = list(maps)
    if not maps:
        raise ValueError("view: no maps given")
    if color_by not in ("height", "map"):
        raise ValueError(f"color_by must be 'height' or 'map', got {color_by!r}")
    names = [f"map {i + 1}" for i in range(len(maps))] if names is None else list(names)
    Ts = _per_map(transforms, len(maps), "transforms")
    Ts_init = None if transforms_init is None else _per_map(transforms_init, len(maps), "transforms_init")
    if len(names) != len(maps):
        raise ValueError(f"view: {len(names)} names for {len(maps)} maps")
    trace = None if trace is None else np.asarray(trace, np.float64).reshape(-1, 4, 4)

    server = viser.ViserServer(host=host, port=free_port(host) if port is None else port, verbose=False)
    server.scene.set_up_direction("+z")
    occupied = [voxel_boxes(m, max_boxes=max_boxes) for m in maps]
    world = np.concatenate([se3.transform_points(T, b.centers.astype(np.float64), xp=np)
                            for T, b in zip(Ts, occupied)])
    if len(world):
        lo, hi = np.percentile(world, 2, axis=0), np.percentile(world, 98, axis=0)
    else:
        lo, hi = np.zeros(3), np.ones(3)
    z_lo, z_hi = float(lo[2]), float(hi[2])
    # look at the maps from above one corner, far enough to see them whole
    centre, extent = (lo + hi) / 2, float(np.linalg.norm(hi - lo)) + 4 * maps[0].resolution
    server.initial_camera.look_at = centre
    server.initial_camera.position = centre + extent * np.array([-0.55, -0.75, 0.65])
    server.initial_camera.up = (0.0, 0.0, 1.0)

    frames, handles = [], {}
    for i, (m, name, T, boxes) in enumerate(zip(maps, names, Ts, occupied)):
        wxyz, pos = _pose(T)
        frame = server.scene.add_frame(f"/maps/{i}", wxyz=wxyz, position=pos, show_axes=False)
        frames.append(frame)
        z_world = se3.transform_points(T, boxes.centers.astype(np.float64), xp=np)[:, 2]
        colors = {"height": height_colors(z_world, z_lo, z_hi),
                  "map": np.broadcast_to(MAP_COLORS[i % len(MAP_COLORS)], (len(boxes.sizes), 3)).copy()}
        handles[(i, "occupied")] = (server.scene.add_batched_meshes_simple(
            f"/maps/{i}/occupied", _CUBE_VERTICES, _CUBE_FACES,
            batched_wxyzs=np.tile(np.array([1.0, 0, 0, 0], np.float32), (len(boxes.sizes), 1)),
            batched_positions=boxes.centers, batched_scales=boxes.sizes,
            batched_colors=colors[color_by], flat_shading=True, cast_shadow=False,
            receive_shadow=False), colors)

    with server.gui.add_folder("Maps"):
        for i, name in enumerate(names):
            toggle = server.gui.add_checkbox(f"{name}", initial_value=True)
            toggle.on_update(lambda _e, f=frames[i], t=toggle: setattr(f, "visible", t.value))
        colour = server.gui.add_dropdown("Colour by", ("height", "map"), initial_value=color_by)

        @colour.on_update
        def _(_event) -> None:
            for key, (handle, colors) in handles.items():
                handle.batched_colors = colors[colour.value]

        free = server.gui.add_checkbox("Free space", initial_value=False)

        @free.on_update
        def _(_event) -> None:
            for i, m in enumerate(maps):
                key = (i, "free")
                if key not in handles and free.value:
                    b = voxel_boxes(m, occupied=False, max_boxes=max_boxes)
                    gray = np.full((len(b.sizes), 3), 200, np.uint8)
                    handles[key] = (server.scene.add_batched_meshes_simple(
                        f"/maps/{i}/free", _CUBE_VERTICES, _CUBE_FACES,
                        batched_wxyzs=np.tile(np.array([1.0, 0, 0, 0], np.float32), (len(b.sizes), 1)),
                        batched_positions=b.centers, batched_scales=b.sizes * 0.9, batched_colors=gray,
                        opacity=0.15, cast_shadow=False, receive_shadow=False),
                        {"height": gray, "map": gray})
                if key in handles:
                    handles[key][0].visible = free.value

    if Ts_init is not None:
        with server.gui.add_folder("Registration"):
            after = server.gui.add_checkbox("After registration", initial_value=True)

            @after.on_update
            def _(_event) -> None:
                for frame, T, T0 in zip(frames, Ts, Ts_init):
                    frame.wxyz, frame.position = _pose(T if after.value else T0)

    if overlap_points is not None:
        p1, p2 = (np.asarray(p, np.float32).reshape(-1, 3) for p in overlap_points)
        size = 0.4 * maps[0].resolution
        server.scene.add_point_cloud("/maps/0/overlap", p1, (255, 255, 255), point_size=size)
        server.scene.add_point_cloud(f"/maps/{len(maps) - 1}/overlap", p2, (255, 0, 0), point_size=size)

    viewer = Viewer(server=server, url=f"http://{'localhost' if host in ('0.0.0.0', '127.0.0.1') else host}:"
                                       f"{server.get_port()}", frames=frames, handles=handles,
                    transforms=Ts, trace=trace)
    if trace is not None:
        with server.gui.add_folder("ICP"):
            slider = server.gui.add_slider("Iteration", min=0, max=len(trace) - 1, step=1,
                                           initial_value=len(trace) - 1)
            slider.on_update(lambda _e: viewer.set_iteration(slider.value))
    return viewer


def _per_map(Ts, n: int, name: str) -> list[np.ndarray]:
    if Ts is None:
        return [np.eye(4) for _ in range(n)]
    Ts = list(Ts)
    if len(Ts) != n:
        raise ValueError(f"view: {name} has {len(Ts)} entries for {n} maps")
    out = []
    for k, T in enumerate(Ts):
        out.append(np.eye(4) if T is None else se3.check_rigid_transform(T, f"{name}[{k}]"))
    return out
