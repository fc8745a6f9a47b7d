"""Pose candidates without an initial guess for maps whose vertical axes roughly agree
(gravity-aligned OctoMaps, a few degrees of roll / pitch): level each map by its horizontal
surfaces, the relative yaw from the histograms of wall-normal directions, and the translation
by a 3-D cross-correlation of the coarse occupancy grids (FFT), a few peaks per yaw.

- ``level_rotation``: the rotation taking the mean normal of the near-horizontal surfaces
  (floors, ceilings, tables) to +z.
- ``yaw_candidates``: wall normals' directions modulo pi, histogrammed at 1 degree and
  circularly correlated between the maps (FFT); each peak gives a yaw and its turn by pi
  (normals carry no sign), so a rectangular room's 180-degree twin is always a candidate and
  is left to the verification by free space to reject.
- ``translation_candidates``: the occupied coarse cells of both maps as 0/1 grids, their
  cross-correlation by FFT, the highest peaks (non-maximum suppressed): overlapping surface
  cells per translation, less those put into the other map's free space.
- ``cell_sets`` / ``consistency_score``: a pose's agreeing and conflicting coarse cells; a cell
  is free space only when its map saw a good part of it free (``MIN_FREE_FRACTION``), and each
  map's grid is offset so that its cell faces avoid its dense planes (``lattice_origin``). A
  map's cells are also kept as one dense table over their box (``CellTable``), so scoring a
  pose is a gather per placed cell; the candidates' half-cell nudges score hundreds of poses.

The idea is the classic one of rotation from orientation histograms and translation from
phase-free correlation (e.g. Bosse and Zlot, "Map matching and data association for large-scale
two-dimensional laser scan-based SLAM", IJRR 2008); see
``docs/design.md``, "Guess-free registration: measured choice". Host NumPy: a few thousand
coarse points and FFTs of at most a few million cells.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from ..map import OccupancyMap
from .features import CoarseCloud, cell_codes, cell_keys, coarse_cloud, neighbor_pairs, normals

__all__ = ["CellSets", "CellTable", "MAX_TABLE_CELLS", "MIN_FREE_FRACTION", "cell_sets", "cell_table",
           "consistency_score", "distinct_poses", "free_space", "horizontal_pinning", "lattice_origin",
           "level_rotation", "map_cell_sets", "net_agreement", "nudge_poses",
           "pose_distance", "rotation_z", "translation_candidates", "yaw_candidates", "CorrelationGrid",
           "correlation_grid", "translation_candidates_of_grids"]

_YAW_BINS = 180  # over [0, pi): 1 degree


def rotation_z(yaw_rad: float) -> np.ndarray:
    """``(3, 3)`` float64 rotation about +z by ``yaw_rad``."""
    c, s = np.cos(yaw_rad), np.sin(yaw_rad)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def level_rotation(normals, valid, max_tilt_rad: float = 0.35) -> np.ndarray:
    """``(3, 3)`` float64 rotation taking the mean of the unit ``normals (m, 3)`` (rows with
    ``valid (m,)``) within ``max_tilt_rad`` of +-z (signs folded to +z) onto +z; the identity
    when fewer than 20 such normals exist."""
    n = np.asarray(normals, np.float64)[np.asarray(valid, bool)]
    n = n * np.where(n[:, 2:3] < 0, -1.0, 1.0)
    up = n[n[:, 2] >= np.cos(max_tilt_rad)]
    if up.shape[0] < 20:
        return np.eye(3)
    u = up.mean(axis=0)
    u /= np.linalg.norm(u)
    axis = np.cross(u, [0.0, 0.0, 1.0])
    s, c = np.linalg.norm(axis), u[2]
    if s < 1e-12:
        return np.eye(3)
    k = axis / s
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + s * K + (1 - c) * K @ K


def _wall_histogram(normals, valid, max_vertical: float = 0.3) -> np.ndarray:
    n = np.asarray(normals, np.float64)[np.asarray(valid, bool)]
    n = n[np.abs(n[:, 2]) <= max_vertical]
    ang = np.mod(np.arctan2(n[:, 1], n[:, 0]), np.pi)
    h = np.bincount(np.minimum((ang / np.pi * _YAW_BINS).astype(np.int64), _YAW_BINS - 1),
                    minlength=_YAW_BINS).astype(np.float64)
    # a circular [1 2 1] blur: neighbours of a bin share its walls
    return 2 * h + np.roll(h, 1) + np.roll(h, -1)


def yaw_candidates(normals_1, valid_1, normals_2, valid_2, num_peaks: int = 3,
                   min_separation_rad: float = np.deg2rad(8.0)) -> np.ndarray:
    """Yaws [rad] ``(2 k,)`` turning map 2's (levelled) wall normals onto map 1's: the ``k <=
    num_peaks`` highest peaks of the circular correlation of their direction histograms
    (modulo pi, 1 degree bins), at least ``min_separation_rad`` apart, each with its turn by
    pi; best peak first. Empty when either map has no near-vertical surface."""
    h1, h2 = _wall_histogram(normals_1, valid_1), _wall_histogram(normals_2, valid_2)
    if h1.sum() == 0 or h2.sum() == 0:
        return np.zeros(0)
    # corr[s] = sum_i h1[i] h2[i - s]: map 2 turned by s bins matches map 1
    corr = np.fft.irfft(np.fft.rfft(h1) * np.conj(np.fft.rfft(h2)), n=_YAW_BINS)
    order = np.argsort(-corr, kind="stable")
    sep = int(round(min_separation_rad / np.pi * _YAW_BINS))
    kept: list[int] = []
    for s in order:
        if all(min(abs(s - t), _YAW_BINS - abs(s - t)) >= sep for t in kept):
            kept.append(int(s))
            if len(kept) == num_peaks:
                break
    yaws = np.asarray(kept, np.float64) * np.pi / _YAW_BINS
    return np.stack([yaws, yaws + np.pi], axis=1).reshape(-1)


def _grid(points, voxel: float, lo: np.ndarray, shape) -> np.ndarray:
    g = np.zeros(shape, np.float32)
    k = np.floor(points / voxel).astype(np.int64) - lo
    g[k[:, 0], k[:, 1], k[:, 2]] = 1.0
    return g


def _free_grid(points, occupied, voxel: float, lo: np.ndarray, volumes=None) -> np.ndarray:
    """1 in the free cells of the grid of ``occupied`` (those without occupied weight; with
    ``volumes (f,)`` [m^3] of the free ``points``, those at least ``MIN_FREE_FRACTION`` seen
    free, as ``cell_sets``)."""
    # one row per axis: the passes below run over contiguous rows
    q = np.array(np.asarray(points, np.float64).reshape(-1, 3).T, order="C")
    q /= voxel
    k = np.floor(q, out=q).astype(np.int64) - np.asarray(lo, np.int64)[:, None]
    s0, s1, s2 = occupied.shape
    inside = (k[0] >= 0) & (k[0] < s0) & (k[1] >= 0) & (k[1] < s1) & (k[2] >= 0) & (k[2] < s2)
    cell = ((k[0] * s1 + k[1]) * s2 + k[2])[inside]
    if volumes is None:
        g = np.zeros(occupied.size, np.float32)
        g[cell] = 1.0
        g = g.reshape(occupied.shape)
    else:
        seen = np.bincount(cell, np.asarray(volumes, np.float64)[inside], minlength=occupied.size)
        g = _seen_free(seen.reshape(occupied.shape), MIN_FREE_FRACTION).astype(np.float32)
    return np.where(occupied > 0, 0.0, g).astype(np.float32)


def _seen_free(volume, fraction: float) -> np.ndarray:
    """Which cells of ``volume`` (the free volume [m^3] each holds; any shape) count as free:
    those holding at least ``fraction`` of what the map's cells seen free throughout hold (the
    90th percentile over the cells holding free space: a map's free space may be sampled
    sparsely). None without free space."""
    held = volume[volume > 0]
    if held.size == 0:
        return np.zeros(volume.shape, bool)
    return (volume > 0) & (volume >= float(fraction) * float(np.percentile(held, 90)))


def free_space(m: OccupancyMap, voxel: float, max_points: int = 4_000_000) -> tuple[np.ndarray, np.ndarray]:
    """``(points (k, 3) float64 [m], volumes (k,) float64 [m^3])``: points filling the map's
    free leaves (log-odds below the occupancy threshold) at about one per cell of ``voxel``
    [m] (a leaf's centre, or for a leaf larger than ``voxel`` the centres of its
    ``round(size / voxel)^3`` sub-cells) and the free volume each stands for (its leaf's, or
    sub-cell's). Raises ``ValueError`` above ``max_points`` points."""
    L = m.leaves()
    # a host threshold: the device scalar would compile a comparison per leaf count
    free = L.log_odds < m.params.occupancy_threshold_host
    centers, sizes = L.centers[free], L.sizes[free]
    out, volumes = [], []
    for size in np.unique(sizes):
        c = centers[sizes == size]
        k = max(1, int(round(size / voxel)))
        if c.shape[0] * k ** 3 > max_points:
            raise ValueError(f"free space of {c.shape[0] * k ** 3} cells of {voxel:g} m exceeds {max_points}")
        g = (np.arange(k) + 0.5) * (size / k) - size / 2
        off = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)
        out.append((c[:, None, :] + off[None]).reshape(-1, 3))
        volumes.append(np.full(c.shape[0] * k ** 3, (float(size) / k) ** 3))
    if not out:
        return np.zeros((0, 3)), np.zeros((0,))
    return np.concatenate(out), np.concatenate(volumes)


class CorrelationGrid(NamedTuple):
    """One map's side of ``translation_candidates`` (``correlation_grid``)."""

    shift: np.ndarray  # (3,) float64 [m]: the grid's offset, lattice_origin of the occupied points
    lo: np.ndarray  # (3,) int64 first cell key
    size: np.ndarray  # (3,) int64 cells per axis
    occupied: np.ndarray  # (size) float32, 1 in the occupied cells
    free: np.ndarray | None  # (size) float32, 1 in the free cells (``_free_grid``), or None


def correlation_grid(points, voxel: float, free=None, free_volumes=None) -> CorrelationGrid:
    """The occupied (and, with ``free``, free) coarse cells of edge ``voxel`` [m] of one map's
    ``points (n, 3)`` [m] as 0/1 grids, offset so that its dense planes lie mid-cell
    (``lattice_origin``); ``free (f, 3)`` [m] and ``free_volumes (f,)`` [m^3] from
    ``free_space``."""
    shift = lattice_origin(points, voxel)
    points = np.asarray(points, np.float64).reshape(-1, 3) - shift
    c = coarse_cloud(points, voxel)
    lo = c.keys.min(axis=0)
    size = c.keys.max(axis=0) - lo + 1
    occupied = _grid(points, voxel, lo, tuple(int(x) for x in size))
    free_grid = None if free is None else _free_grid(np.asarray(free, np.float64).reshape(-1, 3) - shift, occupied,
                                                     voxel, lo, free_volumes)
    return CorrelationGrid(shift, lo, size, occupied, free_grid)


def translation_candidates(points_1, points_2, voxel: float, free_1=None, free_2=None, num_peaks: int = 3,
                           min_separation_cells: int = 3, max_cells: int = 1 << 23, free_volumes_1=None,
                           free_volumes_2=None):
    """Translations ``t (k, 3)`` [m] that place ``points_2 (n2, 3)`` onto ``points_1 (n1, 3)``
    (both [m], one orientation) with the most occupied coarse cells (edge ``voxel`` [m]) in
    common, less the occupied cells of one map that land in the other's free space
    (``free_* (f, 3)`` [m], in the same frames, optional; ``free_space``'s points; with
    ``free_volumes_* (f,)`` [m^3] from ``free_space``, free cells as ``cell_sets`` counts
    them), and those scores ``(k,)``: the ``k <= num_peaks`` highest peaks of the grids'
    cross-correlation (FFT), at least ``min_separation_cells`` apart (Chebyshev), best first.
    Raises ``ValueError`` when the padded grid would exceed ``max_cells`` cells. The same as
    ``translation_candidates_of_grids`` of both maps' ``correlation_grid``."""
    return translation_candidates_of_grids(correlation_grid(points_1, voxel, free_1, free_volumes_1),
                                           correlation_grid(points_2, voxel, free_2, free_volumes_2), voxel,
                                           num_peaks, min_separation_cells, max_cells)


def translation_candidates_of_grids(g1: CorrelationGrid, g2: CorrelationGrid, voxel: float, num_peaks: int = 3,
                                    min_separation_cells: int = 3, max_cells: int = 1 << 23):
    """``translation_candidates`` from both maps' ``correlation_grid`` (edge ``voxel`` [m]):
    map 1's grid can serve every orientation of map 2."""
    s1, s2 = g1.size, g2.size
    # every shift in (-s2, s1) without wrapping, padded to lengths the FFT is fast at
    shape = tuple(_fast_length(int(x)) for x in s1 + s2)
    if int(np.prod(shape)) > max_cells:
        raise ValueError(f"correlation grid of {shape} cells of {voxel:g} m exceeds {max_cells} cells")
    axes = (0, 1, 2)
    f1, f2 = np.fft.rfftn(g1.occupied, shape, axes=axes), np.fft.rfftn(g2.occupied, shape, axes=axes)
    # corr[d] = sum_x g1[x + d] g2[x]: map 2's cell x lands on map 1's cell x + d
    spec = f1 * np.conj(f2)
    if g1.free is not None:
        spec -= np.fft.rfftn(g1.free, shape, axes=axes) * np.conj(f2)
    if g2.free is not None:
        spec -= f1 * np.conj(np.fft.rfftn(g2.free, shape, axes=axes))
    # counts of cells: whole numbers, so ties are exact and broken by index at any FFT length
    corr = np.rint(np.fft.irfftn(spec, shape, axes=axes))
    for a in range(3):  # the padding's shifts, which no pair of cells makes, are never peaks
        corr[(slice(None),) * a + (slice(int(s1[a]), shape[a] - int(s2[a]) + 1),)] = -np.inf
    corr = corr.ravel()
    # the 64 num_peaks highest cells, highest first (ties: lower index first), without sorting them all
    k = min(64 * num_peaks, corr.size)
    top = np.argpartition(-corr, k - 1)[:k] if k < corr.size else np.arange(corr.size)
    flat = top[np.lexsort((top, -corr[top]))]
    shifts, scores = [], []
    for f in flat:
        if corr[f] == -np.inf:  # only the padding's shifts are left
            break
        # shifts run over (-s2, s1): indices from s1 on are negative shifts, wrapped
        d = np.array(np.unravel_index(f, shape))
        d = np.where(d >= s1, d - np.asarray(shape), d)
        if all(np.max(np.abs(d - e)) >= min_separation_cells for e in shifts):
            shifts.append(d)
            scores.append(float(corr[f]))
            if len(shifts) == num_peaks:
                break
    d = np.asarray(shifts, np.int64).reshape(-1, 3)
    # cell lo2 + j of map 2 lands on cell lo1 + j + d of map 1
    t = (d + g1.lo - g2.lo).astype(np.float64) * voxel + g1.shift - g2.shift
    return t, np.asarray(scores, np.float64)


def _fast_length(n: int) -> int:
    """The smallest length ``>= n`` whose only prime factors are 2, 3 and 5: NumPy's FFT over a
    length with a large prime factor (158 = 2 x 79) takes several times as long."""
    best = m2 = 1 << max(int(n) - 1, 0).bit_length()  # the power of two
    while m2 >= 1:
        m3 = m2
        while m3 < best:
            m5 = m3
            while m5 < n:
                m5 *= 5
            best = min(best, m5)
            m3 *= 3
        m2 //= 2
    return int(best)


UNKNOWN, OCCUPIED, FREE = 0, 1, 2  # the cell labels of CellTable

#: the largest ``CellTable`` ``cell_sets`` builds [cells, one byte each]; a map whose cells span a
#: larger box is looked up in its sorted codes alone
MAX_TABLE_CELLS = 1 << 25


class CellTable(NamedTuple):
    """A ``CellSets``' cells as one dense table over their bounding box grown by one cell of
    ``UNKNOWN`` on every side (a key outside the box, clipped into that border, reads
    ``UNKNOWN``): one gather per placed cell instead of a binary search per set."""

    low: np.ndarray  # (3,) int64: the key of the table's entry (1, 1, 1)
    high: np.ndarray  # (3,) int64: the largest index per axis (the far border)
    strides: np.ndarray  # (3,) int64: flat strides of the table
    label: np.ndarray  # (cells,) int8: UNKNOWN, OCCUPIED or FREE, flattened


class CellSets(NamedTuple):
    """A map's occupied and free cells on a coarse grid (``cell_sets``) whose cell corners lie
    at ``origin + k voxel`` in the map's frame."""

    occupied: CoarseCloud  # one point per occupied cell (centroids less origin, sorted codes)
    free_codes: np.ndarray  # (f,) int64 sorted codes of free cells that hold no occupied point
    origin: np.ndarray  # (3,) float64 [m]: the grid's offset, lattice_origin of the occupied points
    table: CellTable | None = None  # both as one table (None: none built, or over MAX_TABLE_CELLS)
    centres: np.ndarray | None = None  # (3, m) float64 [m]: occupied.points + origin, one row per axis


def lattice_origin(points, voxel: float, bins: int = 24) -> np.ndarray:
    """``(3,)`` float64 [m]: per axis, the offset in ``[0, voxel)`` of a grid of ``voxel`` [m]
    whose cell faces lie farthest from ``points (n, 3)`` [m]: of ``bins`` offsets, the one
    minimising the points' summed closeness to a face (1 on it, falling linearly to 0 half a
    cell away). The ground or floor, the most populated plane, then lies mid-cell instead of
    wherever the frame's origin happens to put it: on a face, the other map's copy of it
    (voxelised on its own lattice, up to a voxel apart) splits between the cell below and the
    free one above, and the truth itself loses agreement and gains conflicts
    (``docs/design.md``, "Guess-free registration: measured choice")."""
    p = np.asarray(points, np.float64).reshape(-1, 3)
    origin = np.zeros(3)
    if p.shape[0] == 0:
        return origin
    frac = np.mod(p / float(voxel), 1.0)
    half = bins // 2
    k = np.arange(-half, half)
    closeness = 1.0 - np.abs(k + 0.5) / half  # of the bin k bins past a face
    for a in range(3):
        h = np.bincount(np.minimum((frac[:, a] * bins).astype(np.int64), bins - 1), minlength=bins)
        cost = sum(c * np.roll(h, -j) for j, c in zip(k, closeness))  # cost[b]: a face at b / bins
        origin[a] = float(np.argmin(cost)) / bins * float(voxel)
    return origin


#: a coarse cell is free when its free volume is at least this share of what the map's fully seen cells hold
#: (``cell_sets``)
MIN_FREE_FRACTION = 0.25


def cell_sets(points, free, voxel: float, free_volumes=None,
              min_free_fraction: float = MIN_FREE_FRACTION, origin=None) -> CellSets:
    """``CellSets`` of occupied ``points (n, 3)`` and free-space points ``free (f, 3)`` [m]
    (``free_space``'s points) on a grid of ``voxel`` [m]. With ``free_volumes (f,)`` [m^3]
    (``free_space``), a cell without occupied points is free only when its free points' volume
    is at least ``min_free_fraction`` of what the map's cells seen free throughout hold (the
    90th percentile over the cells holding free points, so a map whose free space is sampled
    sparsely keeps its free cells): a cell that a sensor saw only in part (rays grazing the
    ground between sparse lidar rings, the air above a surface in a cell that also holds it)
    refutes nothing. Without volumes every cell holding a free point is. ``origin (3,)`` [m]:
    the grid's offset (default ``lattice_origin`` of ``points``)."""
    points = np.asarray(points, np.float64).reshape(-1, 3)
    origin = lattice_origin(points, voxel) if origin is None else np.asarray(origin, np.float64).reshape(3)
    occ = coarse_cloud(points - origin, voxel)
    free = np.asarray(free, np.float64).reshape(-1, 3) - origin
    codes, inverse = np.unique(cell_codes(np.floor(free / voxel).astype(np.int64)), return_inverse=True)
    keep = ~np.isin(codes, occ.codes)
    if free_volumes is not None:
        volume = np.bincount(inverse.ravel(), np.asarray(free_volumes, np.float64), minlength=codes.shape[0])
        keep &= _seen_free(volume, min_free_fraction)
    free_codes = codes[keep]
    return CellSets(occ, free_codes, origin, cell_table(occ.keys, cell_keys(free_codes)),
                    np.ascontiguousarray((occ.points + origin).T))


def cell_table(occupied_keys, free_keys) -> CellTable | None:
    """The ``CellTable`` of the cells with keys ``occupied_keys (m, 3)`` and ``free_keys (f, 3)``
    (int), or ``None`` when there are none or their box grown by a cell on every side holds over
    ``MAX_TABLE_CELLS`` cells."""
    occupied_keys = np.asarray(occupied_keys, np.int64).reshape(-1, 3)
    free_keys = np.asarray(free_keys, np.int64).reshape(-1, 3)
    keys = np.concatenate([occupied_keys, free_keys])
    if keys.shape[0] == 0:
        return None
    low = keys.min(axis=0)
    shape = keys.max(axis=0) - low + 3
    if int(np.prod(shape)) > MAX_TABLE_CELLS:
        return None
    strides = np.array([shape[1] * shape[2], shape[2], 1], np.int64)
    label = np.zeros(int(np.prod(shape)), np.int8)
    label[(free_keys - low + 1) @ strides] = FREE
    label[(occupied_keys - low + 1) @ strides] = OCCUPIED
    return CellTable(low, shape - 1, strides, label)


def _labels_at(table: CellTable, keys) -> np.ndarray:
    """``(n,)`` int8 labels of the cells with ``keys (3, n)`` int64 (``UNKNOWN`` outside the table)."""
    k = keys - (table.low - 1)[:, None]
    np.clip(k, 0, table.high[:, None], out=k)
    return table.label.take(k[0] * table.strides[0] + k[1] * table.strides[1] + k[2])


def map_cell_sets(points, m: OccupancyMap, voxel: float, free=None) -> CellSets:
    """``cell_sets`` of a map's occupied ``points (n, 3)`` [m] and its free space
    (``free_space``, volumes counted) on a grid of ``voxel`` [m]. ``free``: ``free_space(m,
    voxel)`` when the caller has it already (not computed again)."""
    free, volumes = free_space(m, voxel) if free is None else free
    return cell_sets(points, free, voxel, volumes)


def net_agreement(s1: CellSets, s2: CellSets, T_1_2, conflict_weight: float) -> float:
    """``agree - conflict_weight x conflict`` of ``consistency_score`` at ``T_1_2 (4, 4)``
    [coarse cells]: how well a pose explains both maps, free space included."""
    agree, conflict = consistency_score(s1, s2, T_1_2)
    return float(agree - conflict_weight * conflict)


def nudge_poses(s1: CellSets, s2: CellSets, poses, step: float, conflict_weight: float, rounds: int = 3):
    """``(poses (k, 4, 4) float64, net agreements (k,))``: each pose ``T_1_2`` of ``poses (k,
    4, 4)`` moved by up to ``rounds`` steps of ``step`` [m] along x, y or z of map 1's frame,
    each step the one that raises its net agreement (``consistency_score``: agree -
    ``conflict_weight`` x conflict) most, while one does. Candidates from a grid of whole cells
    lie up to half a cell off, and a pose a third of a cell off conflicts on every surface:
    unnudged, it can rank below a wrong pose (half a cell is ``step = voxel / 2``)."""
    moves = [sign * float(step) * np.eye(3)[k] for k in range(3) for sign in (-1.0, 1.0)]
    out, scores = [], []
    for T in np.asarray(poses, np.float64).reshape(-1, 4, 4):
        best = net_agreement(s1, s2, T, conflict_weight)
        for _ in range(rounds):
            tried = np.repeat(T[None], len(moves), axis=0)
            for T2, d in zip(tried, moves):
                T2[:3, 3] += d
            nets = _nets_at(s1, s2, tried, conflict_weight)
            k = int(np.argmax(nets))  # the first of the highest
            if nets[k] <= best:
                break
            best, T = float(nets[k]), tried[k]
        out.append(T)
        scores.append(best)
    return np.asarray(out, np.float64).reshape(-1, 4, 4), np.asarray(scores, np.float64)


def _nets_at(s1: CellSets, s2: CellSets, poses, conflict_weight: float) -> np.ndarray:
    """``net_agreement`` at each of ``poses (k, 4, 4)`` that share one rotation (translated
    copies of one pose), all at once: each map's rotated centres are computed once, and the
    cells of all poses looked up together, with the arithmetic of one pose at a time (the same
    values to the bit). Falls back to one pose at a time without both cell tables."""
    Ts = np.asarray(poses, np.float64).reshape(-1, 4, 4)
    T_invs = np.linalg.inv(Ts)
    same = np.all(Ts[:, :3, :3] == Ts[:1, :3, :3]) and np.all(T_invs[:, :3, :3] == T_invs[:1, :3, :3])
    if s1.table is None or s2.table is None or not same:
        return np.array([net_agreement(s1, s2, T, conflict_weight) for T in Ts], np.float64)
    agree, conflict = _table_scores(s1, s2, Ts, T_invs)
    return np.array([float(int(a) - conflict_weight * int(c)) for a, c in zip(agree, conflict)], np.float64)


def _table_scores(s1: CellSets, s2: CellSets, Ts, T_invs) -> tuple[np.ndarray, np.ndarray]:
    """``consistency_score`` from both maps' cell tables at each of ``Ts (k, 4, 4)`` (one
    rotation; ``T_invs`` their inverses): ``(agree (k,), conflict (k,))`` int64."""
    in_1 = _label_counts(s1.table, _placed_keys_at(s2, s1, Ts), Ts.shape[0])
    in_2 = _label_counts(s2.table, _placed_keys_at(s1, s2, T_invs), Ts.shape[0])
    return in_1[:, OCCUPIED], in_1[:, FREE] + in_2[:, FREE]


def _placed_keys_at(source: CellSets, target: CellSets, Ts) -> np.ndarray:
    """``_placed_keys`` under each of ``Ts (k, 4, 4)`` that share ``Ts[0]``'s rotation: ``(3, k
    m)`` int64, pose after pose (its centres rotated once)."""
    centres = source.centres if source.centres is not None else (source.occupied.points + source.origin).T
    q = np.repeat((Ts[0, :3, :3] @ centres)[None], Ts.shape[0], axis=0)
    q += (Ts[:, :3, 3] - target.origin)[:, :, None]
    q /= target.occupied.voxel
    return np.floor(q, out=q).astype(np.int64).transpose(1, 0, 2).reshape(3, -1)


def _label_counts(table: CellTable, keys, k: int) -> np.ndarray:
    """``(k, 3)`` int64: how many of each label the ``keys (3, k m)`` of ``k`` consecutive
    blocks find in ``table``."""
    labels = _labels_at(table, keys).reshape(k, -1)
    return np.stack([np.bincount(row, minlength=3) for row in labels])


def _lookup(sorted_codes, codes) -> tuple[np.ndarray, np.ndarray]:
    """``(index, found)``: where each of ``codes`` sits in ``sorted_codes`` (non-empty) and
    whether it is there."""
    j = np.minimum(np.searchsorted(sorted_codes, codes), sorted_codes.shape[0] - 1)
    return j, sorted_codes[j] == codes


def _member(sorted_codes, codes) -> np.ndarray:
    if sorted_codes.shape[0] == 0:
        return np.zeros(codes.shape, bool)
    return _lookup(sorted_codes, codes)[1]


def consistency_score(s1: CellSets, s2: CellSets, T_1_2) -> tuple[int, int]:
    """``(agree, conflict)`` of map 2's cells placed by ``T_1_2 (4, 4)`` in map 1's frame
    (both ``CellSets`` of one voxel): occupied cells of map 2 landing in occupied cells of map
    1, and occupied cells of either map landing in the other's free cells (both directions):
    the measure the translation correlation maximises (``agree - conflict``), at any pose."""
    T = np.asarray(T_1_2, np.float64)
    T_inv = np.linalg.inv(T)
    if s1.table is not None and s2.table is not None:
        agree, conflict = _table_scores(s1, s2, T[None], T_inv[None])
        return int(agree[0]), int(conflict[0])
    c = _placed_codes(s2, s1, T)
    agree = int(_member(s1.occupied.codes, c).sum())
    conflict = int(_member(s1.free_codes, c).sum())
    conflict += int(_member(s2.free_codes, _placed_codes(s1, s2, T_inv)).sum())
    return agree, conflict


def _placed_keys(source: CellSets, target: CellSets, T_target_source) -> np.ndarray:
    """``(3, m)`` int64 keys (one row per axis) of the cells of ``target``'s grid that
    ``source``'s occupied cells (their centroids) land in under ``T_target_source (4, 4)``."""
    return _placed_keys_at(source, target, np.asarray(T_target_source)[None])


def _placed_codes(source: CellSets, target: CellSets, T_target_source) -> np.ndarray:
    """``(m,)`` ``cell_codes`` of ``_placed_keys``."""
    return cell_codes(_placed_keys(source, target, T_target_source).T)


def horizontal_pinning(s1: CellSets, s2: CellSets, T_1_2, radius: float) -> float:
    """How firmly the surfaces on which both maps agree at ``T_1_2 (4, 4)`` pin the pose in
    the horizontal plane [coarse cells]: the smaller eigenvalue of ``sum n_h n_h^T`` over map
    1's occupied cells that map 2's land on, ``n_h`` the horizontal part of the cell's unit
    surface normal (``normals`` over neighbours within ``radius`` [m]). Wall cells facing a
    direction count up to one each; floors and ceilings nothing. Near zero when the shared
    surfaces leave a horizontal direction free: a corridor's parallel walls, or a strip of
    floor and one wall shared by maps placed side by side (Zhang, Kaess and Singh, "On
    degeneracy of optimization-based state estimation problems", ICRA 2016: the same test on
    the constraints' normals)."""
    c1 = s1.occupied
    if c1.codes.shape[0] == 0 or s2.occupied.codes.shape[0] == 0:
        return 0.0
    at, found = _lookup(c1.codes, _placed_codes(s2, s1, np.asarray(T_1_2, np.float64)))
    shared = np.unique(at[found])
    n, ok = normals(c1, neighbor_pairs(c1, radius))
    h = n[shared][ok[shared], :2]
    return float(np.linalg.eigvalsh(h.T @ h)[0])


def pose_distance(T_a, T_b, length: float) -> np.ndarray:
    """A distance between poses: rotation angle [rad] x ``length`` [m] + translation [m]
    (broadcast over leading axes)."""
    Ra, Rb = np.asarray(T_a)[..., :3, :3], np.asarray(T_b)[..., :3, :3]
    c = (np.einsum("...ij,...ij->...", Ra, Rb) - 1.0) / 2.0
    ang = np.arccos(np.clip(c, -1.0, 1.0))
    dt = np.linalg.norm(np.asarray(T_a)[..., :3, 3] - np.asarray(T_b)[..., :3, 3], axis=-1)
    return ang * length + dt


def distinct_poses(T, scores, length: float, min_distance: float, k: int) -> np.ndarray:
    """Indices of up to ``k`` poses of ``T (h, 4, 4)``, highest ``scores (h,)`` first, no two
    closer than ``min_distance`` by ``pose_distance(., ., length)``."""
    order = np.argsort(-np.asarray(scores, np.float64), kind="stable")
    kept: list[int] = []
    for i in order:
        if all(pose_distance(T[i], T[j], length) >= min_distance for j in kept):
            kept.append(int(i))
            if len(kept) == k:
                break
    return np.asarray(kept, np.int64)
