"""Scan files: OctoMap ScanGraph (``.graph``), plain scan logs (``.dat``/``.log``/``.txt``),
and single point clouds (PLY via trimesh, PCD, XYZ).

A ``Scan`` is one point cloud in its **sensor frame** plus the sensor pose ``T_world_sensor``
(4x4): what OctoMap's ``ScanNode`` holds and what ``graph2tree`` inserts (points transformed by
the pose, sensor origin at the pose's translation).

ScanGraph binary layout (``src/ScanGraph.cpp``, ``Pointcloud.cpp``, ``Vector3.cpp``,
``Quaternion.cpp``, ``Pose6D.cpp``; little-endian, no header)::

    uint32 num_nodes
    num_nodes x node:   uint32 num_points
                        num_points x (int32 3, float64 x, y, z)
                        pose: int32 3, float64 x, y, z; int32 4, float64 qw, qx, qy, qz
                        uint32 id
    uint32 num_edges
    num_edges x edge:   uint32 first_id, uint32 second_id, pose (as above), float64 weight

Plain log (``ScanGraph::readPlainASCII``): ``NODE x y z roll pitch yaw`` starts a scan (angles
in radians), following ``x y z`` lines are its points; empty lines and lines starting with
``#`` or a space are skipped. A file of bare ``x y z`` lines is read as one scan at the
identity pose (OctoMap rejects those; we accept them).
"""

from __future__ import annotations

import dataclasses
import io as _io
import math
import struct
from pathlib import Path

import numpy as np

from .._fileutil import atomic_output, check_input_file
from .. import se3
from .octree_format import MAX_RESOLUTION

__all__ = ["Scan", "ScanEdge", "read_scan_graph", "write_scan_graph", "read_scan_log",
           "write_scan_log", "read_point_cloud", "read_scans"]


#: Largest coordinate [m] a point or pose may have: half the extent of an OctoMap tree at
#: the coarsest supported resolution. Anything farther is a corrupt value, not a measurement.
MAX_COORDINATE = 32768 * MAX_RESOLUTION


def _check_coordinates(values, where: str, what: str) -> None:
    """``ValueError`` naming ``where`` unless every value is finite and within
    ``MAX_COORDINATE``."""
    v = np.asarray(values, np.float64).reshape(-1)
    bad = np.flatnonzero(~(np.abs(v) <= MAX_COORDINATE))
    if bad.size:
        first = float(v[bad[0]])
        problem = "not finite" if not math.isfinite(first) else "out of range"
        raise ValueError(f"{where}: {what} {first!r} is {problem} "
                         f"(|value| <= {MAX_COORDINATE:g} m)")


@dataclasses.dataclass(frozen=True)
class Scan:
    """One scan: ``points (n, 3)`` float64 [m] in the sensor frame, ``pose (4, 4)``
    ``T_world_sensor``, and the ScanGraph node ``id``."""

    points: np.ndarray
    pose: np.ndarray
    id: int = 0

    @property
    def sensor_origin(self) -> np.ndarray:
        """``(3,)`` sensor position [m] in the world frame."""
        return self.pose[:3, 3].copy()

    def world_points(self) -> np.ndarray:
        """``(n, 3)`` points [m] in the world frame."""
        return self.points @ self.pose[:3, :3].T + self.pose[:3, 3]


@dataclasses.dataclass(frozen=True)
class ScanEdge:
    """A ScanGraph edge: relative pose ``constraint`` (4x4) between node ids, and a weight."""

    first: int
    second: int
    constraint: np.ndarray
    weight: float = 1.0


# --------------------------------------------------------------------------- .graph


class _Reader:
    def __init__(self, data: bytes, path):
        self.data, self.pos, self.path = data, 0, path

    def need(self, n: int, what: str):
        if self.pos + n > len(self.data):
            raise ValueError(f"{self.path}: truncated ScanGraph at byte offset {self.pos}: "
                             f"expected {n} bytes for {what}, {len(self.data) - self.pos} left")

    def u32(self, what: str) -> int:
        self.need(4, what)
        (v,) = struct.unpack_from("<I", self.data, self.pos)
        self.pos += 4
        return v

    def tag(self, expected: int, what: str):
        at = self.pos
        self.need(4, what)
        (v,) = struct.unpack_from("<i", self.data, self.pos)
        if v != expected:
            raise ValueError(f"{self.path}: bad ScanGraph {what} at byte offset {at}: expected "
                             f"element count {expected}, found {v}")
        self.pos += 4

    def f64(self, n: int, what: str) -> np.ndarray:
        self.need(8 * n, what)
        v = np.frombuffer(self.data, "<f8", count=n, offset=self.pos).astype(np.float64)
        self.pos += 8 * n
        return v

    def pose(self, what: str) -> np.ndarray:
        self.tag(3, f"{what} translation")
        at = self.pos
        t = self.f64(3, f"{what} translation")
        _check_coordinates(t, f"{self.path}: byte offset {at}", f"{what} translation")
        self.tag(4, f"{what} rotation")
        at = self.pos
        q = self.f64(4, f"{what} rotation")
        scale = float(np.max(np.abs(q))) if np.all(np.isfinite(q)) else 0.0
        if not 1e-150 < scale:  # non-finite, zero or denormal: no rotation
            raise ValueError(f"{self.path}: invalid quaternion {q.tolist()} at byte offset {at}")
        q = q / scale  # largest component 1: its norm neither overflows nor underflows
        T = np.eye(4)
        T[:3, :3] = se3.from_quaternion(q, xp=np)[:3, :3]
        T[:3, 3] = t
        return T


def read_scan_graph(path, *, with_edges: bool = False):
    """Read an OctoMap ScanGraph ``.graph`` file -> ``list[Scan]`` (or ``(scans, edges)``).

    Raises ``ValueError`` naming the byte offset of the first malformed element.
    """
    path = Path(path)
    data = path.read_bytes()
    r = _Reader(data, path)
    n_nodes = r.u32("node count")
    if n_nodes > len(data) // 4:
        raise ValueError(f"{path}: implausible node count {n_nodes} at byte offset 0 "
                         f"(file has {len(data)} bytes); not a ScanGraph file?")
    scans = []
    for i in range(n_nodes):
        at = r.pos
        n_pts = r.u32(f"node {i} point count")
        if n_pts * 28 > len(data) - r.pos:
            raise ValueError(f"{path}: node {i} at byte offset {at} claims {n_pts} points but "
                             f"only {len(data) - r.pos} bytes remain")
        block = r.data[r.pos:r.pos + 28 * n_pts]
        rec = np.frombuffer(block, dtype=np.dtype([("n", "<i4"), ("xyz", "<f8", 3)]), count=n_pts)
        bad = np.flatnonzero(rec["n"] != 3)
        if bad.size:
            raise ValueError(f"{path}: bad ScanGraph point {bad[0]} of node {i} at byte offset "
                             f"{r.pos + 28 * int(bad[0])}: expected element count 3, found "
                             f"{int(rec['n'][bad[0]])}")
        pts = rec["xyz"].astype(np.float64)
        far = np.flatnonzero(np.any(np.abs(pts) > MAX_COORDINATE, axis=1))
        if far.size:  # NaN points are OctoMap's invalid returns: kept, dropped on insertion
            _check_coordinates(pts[far[0]], f"{path}: byte offset {r.pos + 28 * int(far[0])}",
                               f"point {int(far[0])} of node {i}: coordinate")
        r.pos += 28 * n_pts
        pose = r.pose(f"node {i} pose")
        node_id = r.u32(f"node {i} id")
        scans.append(Scan(pts, pose, node_id))
    edges = []
    if r.pos == len(data):
        raise ValueError(f"{path}: truncated ScanGraph at byte offset {r.pos}: missing edge count")
    n_edges = r.u32("edge count")
    ids = {s.id for s in scans}
    for i in range(n_edges):
        at = r.pos
        first, second = r.u32(f"edge {i} first id"), r.u32(f"edge {i} second id")
        if first not in ids or second not in ids:
            raise ValueError(f"{path}: edge {i} at byte offset {at} refers to unknown node "
                             f"{first if first not in ids else second}")
        constraint = r.pose(f"edge {i} constraint")
        (weight,) = r.f64(1, f"edge {i} weight")
        edges.append(ScanEdge(first, second, constraint, float(weight)))
    if r.pos != len(data):
        raise ValueError(f"{path}: {len(data) - r.pos} unexpected trailing bytes at byte offset {r.pos}")
    return (scans, edges) if with_edges else scans


def _pose_bytes(T) -> bytes:
    T = np.asarray(T, dtype=np.float64)
    q = se3.to_quaternion(T, xp=np)
    return struct.pack("<i3di4d", 3, *T[:3, 3], 4, *q)


def write_scan_graph(path, scans, edges=None, *, connect_previous: bool = True) -> None:
    """Write scans (``Scan`` or ``(points, pose)`` pairs) as an OctoMap ``.graph`` file
    (atomically). Without ``edges``, consecutive nodes are linked as OctoMap's
    ``connectPrevious`` does (constraint ``pose_a^-1 pose_b``, weight 1)."""
    scans = [s if isinstance(s, Scan) else Scan(np.asarray(s[0], float), np.asarray(s[1], float), i)
             for i, s in enumerate(scans)]
    buf = _io.BytesIO()
    buf.write(struct.pack("<I", len(scans)))
    for s in scans:
        pts = np.asarray(s.points, dtype=np.float64).reshape(-1, 3)
        rec = np.zeros(len(pts), dtype=np.dtype([("n", "<i4"), ("xyz", "<f8", 3)]))
        rec["n"] = 3
        rec["xyz"] = pts
        buf.write(struct.pack("<I", len(pts)))
        buf.write(rec.tobytes())
        buf.write(_pose_bytes(s.pose))
        buf.write(struct.pack("<I", int(s.id)))
    if edges is None:
        edges = [ScanEdge(a.id, b.id, np.linalg.inv(a.pose) @ b.pose, 1.0)
                 for a, b in zip(scans[:-1], scans[1:])] if connect_previous else []
    buf.write(struct.pack("<I", len(edges)))
    for e in edges:
        buf.write(struct.pack("<II", int(e.first), int(e.second)))
        buf.write(_pose_bytes(e.constraint))
        buf.write(struct.pack("<d", float(e.weight)))
    with atomic_output(path) as tmp:
        Path(tmp).write_bytes(buf.getvalue())


# --------------------------------------------------------------------------- plain logs


def read_scan_log(path) -> list[Scan]:
    """Read a plain scan log (``NODE x y z roll pitch yaw`` + ``x y z`` lines), or bare
    ``x y z`` lines as one scan at the identity pose. Errors name the line number."""
    path = Path(path)
    scans: list[Scan] = []
    pose = None
    pts: list[tuple[float, float, float]] = []
    bare = None
    with open(path, encoding="utf-8", errors="strict") as f:
        try:
            lines = f.read().splitlines()
        except UnicodeDecodeError as err:
            raise ValueError(f"{path}: not a text scan log ({err})") from None
    for lineno, line in enumerate(lines, 1):
        if not line or line.startswith("#") or line.startswith(" ") or not line.strip():
            continue
        tok = line.split()
        if tok[0] == "NODE":
            if bare:
                raise ValueError(f"{path}:{lineno}: NODE after bare points (points must follow a NODE line)")
            if len(tok) != 7:
                raise ValueError(f"{path}:{lineno}: expected 'NODE x y z roll pitch yaw', got {line!r}")
            try:
                vals = [float(v) for v in tok[1:]]
            except ValueError:
                raise ValueError(f"{path}:{lineno}: non-numeric NODE pose {line!r}") from None
            _check_coordinates(vals[:3], f"{path}:{lineno}", "NODE position")
            if not all(np.isfinite(vals[3:])):
                raise ValueError(f"{path}:{lineno}: non-finite NODE angles {line!r}")
            if pose is not None:
                scans.append(Scan(np.asarray(pts, np.float64).reshape(-1, 3), pose, len(scans)))
            pose, pts, bare = se3.from_xyz_rpy(*vals, xp=np), [], False
            continue
        if len(tok) < 3:
            raise ValueError(f"{path}:{lineno}: expected 'x y z', got {line!r}")
        try:
            p = (float(tok[0]), float(tok[1]), float(tok[2]))
        except ValueError:
            raise ValueError(f"{path}:{lineno}: non-numeric point {line!r}") from None
        if not all(np.isfinite(p)):
            raise ValueError(f"{path}:{lineno}: non-finite point {line!r}")
        _check_coordinates(p, f"{path}:{lineno}", "point coordinate")
        if pose is None:
            pose, bare = np.eye(4), True
        pts.append(p)
    if pose is not None:
        scans.append(Scan(np.asarray(pts, np.float64).reshape(-1, 3), pose, len(scans)))
    if not scans:
        raise ValueError(f"{path}: no scans found (expected NODE lines or x y z points)")
    return scans


def write_scan_log(path, scans) -> None:
    """Write scans as a plain log (``NODE x y z roll pitch yaw`` + points), atomically."""
    out = _io.StringIO()
    for s in scans:
        s = s if isinstance(s, Scan) else Scan(np.asarray(s[0], float), np.asarray(s[1], float))
        roll, pitch, yaw = (float(a) for a in se3.to_xyz_rpy(s.pose, xp=np)[3:])
        x, y, z = (float(v) for v in s.pose[:3, 3])
        out.write(f"NODE {x!r} {y!r} {z!r} {roll!r} {pitch!r} {yaw!r}\n")
        for px, py, pz in np.asarray(s.points, np.float64).reshape(-1, 3).tolist():
            out.write(f"{px!r} {py!r} {pz!r}\n")
    with atomic_output(path) as tmp:
        Path(tmp).write_text(out.getvalue(), encoding="utf-8")


# --------------------------------------------------------------------------- point clouds


#: PCD ``TYPE`` letters and the ``SIZE`` values each allows (PCL's ``pcl::PCLPointField``).
_PCD_TYPES = {"F": (4, 8), "I": (1, 2, 4, 8), "U": (1, 2, 4, 8)}


def _pcd_ints(vals, where: str, key: str, minimum: int) -> list[int]:
    try:
        out = [int(v) for v in vals]
    except ValueError:
        raise ValueError(f"{where}: PCD {key} {' '.join(vals)!r} is not a list of integers") from None
    if not out or min(out) < minimum:
        raise ValueError(f"{where}: PCD {key} needs integers >= {minimum}, got {' '.join(vals)!r}")
    return out


def _read_pcd(path: Path) -> np.ndarray:
    """PCD v0.7 (``ascii`` / ``binary``) -> ``(n, 3)`` float64; NaN points (PCL's invalid
    returns) are dropped. Errors name the file and the header line or byte offset."""
    data = path.read_bytes()
    fields = sizes = types = counts = None
    points = None
    pos = 0
    lineno = 0
    kind = ""
    while True:
        end = data.find(b"\n", pos)
        if end < 0:
            raise ValueError(f"{path}: PCD header has no DATA line")
        lineno += 1
        where = f"{path}:{lineno}"
        line = data[pos:end].decode("ascii", "replace").strip()
        pos = end + 1
        if not line or line.startswith("#"):
            continue
        key, *vals = line.split()
        key = key.upper()
        if key == "FIELDS":
            fields = vals
        elif key == "SIZE":
            sizes = _pcd_ints(vals, where, key, 1)
        elif key == "TYPE":
            types = [v.upper() for v in vals]
            unknown = [t for t in types if t not in _PCD_TYPES]
            if unknown or not types:
                raise ValueError(f"{where}: PCD TYPE {' '.join(vals)!r}: each must be F, I or U")
        elif key == "COUNT":
            counts = _pcd_ints(vals, where, key, 1)
        elif key == "POINTS":
            if len(vals) != 1:
                raise ValueError(f"{where}: PCD POINTS needs one value, got {' '.join(vals)!r}")
            points = _pcd_ints(vals, where, key, 0)[0]
        elif key == "DATA":
            kind = vals[0].lower() if vals else ""
            break
    if fields is None or points is None:
        raise ValueError(f"{path}:{lineno}: PCD header lacks FIELDS or POINTS")
    for axis in "xyz":
        if axis not in fields:
            raise ValueError(f"{path}: PCD has no '{axis}' field (fields {fields})")
    counts = counts or [1] * len(fields)
    for key, vals in (("COUNT", counts), ("SIZE", sizes), ("TYPE", types)):
        if vals is not None and len(vals) != len(fields):
            raise ValueError(f"{path}: PCD {key} has {len(vals)} entries for {len(fields)} FIELDS")
    if kind == "ascii":
        try:
            rows = data[pos:].decode("ascii").split("\n")
        except UnicodeDecodeError as err:
            raise ValueError(f"{path}: PCD ascii data is not ASCII (byte offset "
                             f"{pos + err.start})") from None
        vals = []
        for i, row in enumerate(rows):
            if not row.strip():
                continue
            tok = row.split()
            if len(tok) != sum(counts):
                raise ValueError(f"{path}:{lineno + 1 + i}: expected {sum(counts)} values, got {len(tok)}")
            try:
                vals.append([float(t) for t in tok])
            except ValueError:
                raise ValueError(f"{path}:{lineno + 1 + i}: non-numeric value in {row.strip()[:80]!r}") from None
        if len(vals) != points:
            raise ValueError(f"{path}: PCD POINTS says {points} but the data has {len(vals)} rows")
        arr = np.asarray(vals, np.float64).reshape(-1, sum(counts))
        col = np.cumsum([0] + counts)
        xyz = np.stack([arr[:, col[fields.index(a)]] for a in "xyz"], axis=1)
    elif kind == "binary":
        if sizes is None or types is None:
            raise ValueError(f"{path}: binary PCD needs SIZE and TYPE")
        for f, t, size in zip(fields, types, sizes):
            if size not in _PCD_TYPES[t]:
                raise ValueError(f"{path}: PCD field {f!r} has TYPE {t} with SIZE {size} "
                                 f"(allowed {_PCD_TYPES[t]})")
        dt = np.dtype([(f"_{i}", f"<{t.lower()}{s}", (c,)) for i, (t, s, c)
                       in enumerate(zip(types, sizes, counts))])
        if len(data) - pos < dt.itemsize * points:
            raise ValueError(f"{path}: binary PCD truncated at byte offset {len(data)}: "
                             f"{points} points need {dt.itemsize * points} bytes after offset {pos}")
        rec = np.frombuffer(data, dt, count=points, offset=pos)
        with np.errstate(invalid="ignore"):  # signalling NaNs (invalid points) widen quietly
            xyz = np.stack([rec[f"_{fields.index(a)}"][:, 0].astype(np.float64) for a in "xyz"],
                           axis=1)
    else:
        raise ValueError(f"{path}: unsupported PCD DATA kind {kind!r} (ascii and binary are supported)")
    xyz = xyz[~np.any(np.isnan(xyz), axis=1)]
    far = np.flatnonzero(np.any(~(np.abs(xyz) <= MAX_COORDINATE), axis=1))
    if far.size:
        _check_coordinates(xyz[far[0]], f"{path}: point {int(far[0])}", "coordinate")
    return xyz


def read_point_cloud(path) -> np.ndarray:
    """A single point cloud file -> ``(n, 3)`` float64 [m]: ``.ply`` (trimesh; mesh vertices
    or point clouds), ``.pcd`` (ascii/binary), ``.xyz``/``.txt``/``.csv`` (x y z per line)."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix == ".pcd":
        return _read_pcd(path)
    if suffix in (".ply", ".obj", ".off", ".stl", ".glb"):
        import trimesh

        try:
            geom = trimesh.load(str(path))
        except Exception as err:  # trimesh raises many types for broken files
            raise ValueError(f"{path}: cannot read point cloud ({err})") from None
        if isinstance(geom, trimesh.Scene):
            geom = geom.to_geometry() if hasattr(geom, "to_geometry") else geom.dump(concatenate=True)
        return np.asarray(geom.vertices, dtype=np.float64).reshape(-1, 3)
    scans = read_scan_log(path)
    if len(scans) != 1 or not np.allclose(scans[0].pose, np.eye(4)):
        raise ValueError(f"{path}: expected bare 'x y z' lines, found {len(scans)} NODE scans")
    return scans[0].points


def read_scans(path) -> list[Scan]:
    """Any supported scan file -> ``list[Scan]``: ``.graph`` (ScanGraph), ``.dat``/``.log``/
    ``.txt`` (plain log), or one point cloud (``.ply``/``.pcd``/``.xyz``) at the identity pose."""
    path = Path(path)
    check_input_file(path)
    suffix = path.suffix.lower()
    if suffix == ".graph":
        return read_scan_graph(path)
    if suffix in (".dat", ".log", ".txt"):
        return read_scan_log(path)
    return [Scan(read_point_cloud(path), np.eye(4), 0)]
