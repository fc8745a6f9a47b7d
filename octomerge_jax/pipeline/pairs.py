"""The pairs of ``merge_many``: which pairs of maps to register (``screen_pairs``, a coarse
occupancy descriptor), and one pairwise measurement for the pose graph (``measure_pair``: the
transform, its information matrix from the point-to-point Hessian, and a confidence).

``measure_pair`` is the one place that calls the pairwise registration: ``register_global``
without a guess (its verdict and confidence), ``refine.register`` in the configured mode from
a guess.
"""

from __future__ import annotations

import itertools
from typing import NamedTuple

import numpy as np

from .. import registration as reg
from ..map import OccupancyMap
from .clouds import select_overlap
from .config import MergeConfig
from .globalreg import register_global
from .refine import register
from .report import MergeError, Registration
from .timings import Timings

__all__ = ["PairMeasurement", "alignment_information", "candidate_measurement", "describe_map", "measure_pair",
           "more_pairs", "screen_pairs"]

DESCRIPTOR_CELL_M = 1.0  # column size of the coarse descriptor [m]
_HEIGHT_BINS = 8  # occupied-height classes per column
_COUNT_BINS = 6  # occupied-voxel-count classes per column


class PairMeasurement(NamedTuple):
    """One pairwise measurement ``T_i_j`` for the pose graph (host values)."""

    T_i_j: np.ndarray  # (4, 4) float64: map j's frame into map i's [m]
    information: np.ndarray  # (6, 6) float64: (v [1/m^2], omega [1/rad^2]), right perturbation
    confidence: float  # in [0, 1]: the registration's own, else inlier fraction x (1 - rmse / distance)
    registration: Registration  # the registration step's outcome (its figures under ``info``)
    verdict: str  # "ok", "ambiguous", "no_overlap" or "failed" (the registration's status)


def alignment_information(points_i, points_j, T_i_j, distance_m: float, sigma_m: float) -> tuple[np.ndarray, int]:
    """The point-to-point Hessian ``J^T J`` of the alignment at ``T_i_j`` over the inlier
    pairs, scaled to one point's information: ``(Omega (6, 6) float64, inliers)``.

    A source point ``p`` of map j (``points_j (n, 3)`` [m], frame j) is an inlier when map i has
    a point (``points_i``) within ``distance_m`` of ``T_i_j p``; under ``T_i_j exp(d)`` its
    residual moves by ``R [I, -[p]x] d``, so ``J^T J = sum [[I, -[p]x], [[p]x, |p|^2 I - p p^T]]``
    (the first and second moments of the inliers). Dividing by ``n sigma_m^2`` counts the
    points as one (their errors are correlated: voxel-lattice bias dominates independent noise)
    with the registration's rmse ``sigma_m`` as its scale; the Hessian keeps the shape: which
    directions the overlap constrains; ``docs/design.md``, "Pose graph over pairwise registrations").
    Zero without inliers."""
    points_i = np.asarray(points_i, np.float32).reshape(-1, 3)
    points_j = np.asarray(points_j, np.float32).reshape(-1, 3)
    if points_i.shape[0] == 0 or points_j.shape[0] == 0:
        return np.zeros((6, 6)), 0
    _, q = select_overlap(points_i, points_j, np.asarray(T_i_j, np.float64), "voxel", float(distance_m))
    n = int(q.shape[0])
    if n == 0:
        return np.zeros((6, 6)), 0
    p = q.astype(np.float64)
    m = p.mean(0)
    S = p.T @ p / n
    K = np.array([[0.0, -m[2], m[1]], [m[2], 0.0, -m[0]], [-m[1], m[0], 0.0]])
    H = np.block([[np.eye(3), -K], [K, np.trace(S) * np.eye(3) - S]])
    return H / float(sigma_m) ** 2, n


def measure_pair(m_i: OccupancyMap, m_j: OccupancyMap, T_i_j_init, config: MergeConfig, guess_free: bool,
                 timings: Timings | None = None) -> PairMeasurement:
    """Register map j to map i and turn the result into a pose-graph measurement.

    Args:
      T_i_j_init: ``(4, 4)`` start (identity when ``guess_free``).
      guess_free: ``True``: ``register_global`` (no guess needed); ``False``:
        ``config.registration.refine`` from the guess.

    Returns a ``PairMeasurement``. Raises ``MergeError`` as ``register`` (no overlap, too few
    inliers, ...)."""
    if guess_free:
        r = register_global(m_i, m_j, config=config, timings=timings)
    else:
        if config.registration.refine == "none":
            raise MergeError("measure_pair needs a registration (refine is 'none')", "transform")
        r = register(m_i, m_j, np.asarray(T_i_j_init, np.float64), config, timings)
    info = r.info or {}
    d, rmse, sigma = _scales(info, float(m_i.resolution))
    Omega, n = alignment_information(r.points_1, r.points_2, r.T_1_2, d, sigma)
    fitness = n / max(int(np.asarray(r.points_2).shape[0]), 1)
    conf = float(np.clip(fitness * (1.0 - min(rmse if np.isfinite(rmse) else d, d) / d), 0.0, 1.0))
    if r.confidence is not None:
        conf = float(r.confidence)
    return PairMeasurement(np.asarray(r.T_1_2, np.float64), Omega, conf, r, str(info.get("verdict", "ok")))


def candidate_measurement(m_i: OccupancyMap, m_j: OccupancyMap, meas: PairMeasurement, c: int) -> PairMeasurement:
    """``meas`` with its registration's candidate ``c`` (``Registration.candidates``, best
    first) as the measurement: ``T_i_j`` that pose, the information matrix at it over both
    maps' occupied voxels (``alignment_information``); confidence and verdict as ``meas``.
    ``c = 0`` returns ``meas``. Raises ``IndexError`` for a candidate that does not exist."""
    if c == 0:
        return meas
    T = np.asarray(meas.registration.candidates[c]["T_1_2"], np.float64)
    d, _, sigma = _scales(meas.registration.info or {}, float(m_i.resolution))
    Omega, _ = alignment_information(reg.occupied_points(m_i), reg.occupied_points(m_j), T, d, sigma)
    return meas._replace(T_i_j=T, information=Omega)


def _scales(info: dict, res: float) -> tuple[float, float, float]:
    """``(d, rmse, sigma)`` [m] of a registration's figures ``info`` at resolution ``res``: its
    last correspondence distance (``2 res`` when missing), its rmse (nan when missing) and the
    error scale of ``alignment_information`` (the rmse, else ``d / 2``; at least ``res / 2``)."""
    d = float(info.get("correspondence_distance", 2 * res))
    d = d if np.isfinite(d) and d > 0 else 2 * res
    rmse = float(info.get("rmse", np.nan))
    return d, rmse, max(rmse if np.isfinite(rmse) else d / 2, res / 2)


def describe_map(m: OccupancyMap, cell_m: float = DESCRIPTOR_CELL_M) -> np.ndarray:
    """A coarse occupancy descriptor ``(_HEIGHT_BINS * _COUNT_BINS,)`` float64 summing to 1:
    the map's occupied voxels in columns of ``cell_m`` x ``cell_m`` [m] (its own frame), each
    column a word (its top occupied height relative to the map's lowest, and how many occupied
    voxels it holds, both quantised), the histogram of words. Nearly invariant to yaw and
    offset of the frame for gravity-aligned maps; O(leaves)."""
    p = np.asarray(reg.occupied_points(m), np.float64).reshape(-1, 3)
    h = np.zeros(_HEIGHT_BINS * _COUNT_BINS)
    if len(p) == 0:
        return h
    cells, inv = np.unique(np.floor(p[:, :2] / cell_m).astype(np.int64), axis=0, return_inverse=True)
    inv = inv.reshape(-1)
    top = np.full(len(cells), -np.inf)
    np.maximum.at(top, inv, p[:, 2])
    count = np.bincount(inv, minlength=len(cells))
    hb = np.clip(((top - p[:, 2].min()) / 1.0).astype(int), 0, _HEIGHT_BINS - 1)
    cb = np.clip(np.log2(np.maximum(count, 1)).astype(int), 0, _COUNT_BINS - 1)
    np.add.at(h, hb * _COUNT_BINS + cb, 1.0)
    return h / h.sum()


def screen_pairs(maps, max_pairs_per_map: int | None, all_below: int = 7) -> tuple[list[tuple[int, int]], np.ndarray]:
    """Candidate pairs ``(i, j)``, ``i < j``, to register, and the similarity matrix
    ``(n, n)`` of the descriptors (``describe_map``; histogram intersection).

    Every pair when ``len(maps) < all_below`` or ``max_pairs_per_map`` is ``None``; otherwise
    each map's ``max_pairs_per_map`` most similar maps (the union over maps), so the
    registrations grow as ``O(n k)`` instead of ``O(n^2)``; the descriptors cost ``O(leaves)``
    and the comparison ``O(n^2)`` vector operations."""
    n = len(maps)
    D = np.stack([describe_map(m) for m in maps])
    sim = np.minimum(D[:, None, :], D[None, :, :]).sum(-1)
    if n < all_below or max_pairs_per_map is None:
        return list(itertools.combinations(range(n), 2)), sim
    k = min(int(max_pairs_per_map), n - 1)
    chosen = set()
    for i in range(n):
        s = sim[i].copy()
        s[i] = -np.inf
        for j in np.argsort(-s, kind="stable")[:k]:
            chosen.add((min(i, int(j)), max(i, int(j))))
    return sorted(chosen), sim


def more_pairs(sim: np.ndarray, maps_to_grow, tried, k: int) -> list[tuple[int, int]]:
    """The next pairs to register for maps the measurements so far do not place: for each of
    ``maps_to_grow`` its ``k`` most similar maps (``sim (n, n)``, ``screen_pairs``') whose pair
    is not in ``tried`` (pairs ``(i, j)``, ``i < j``). Returns new pairs ``(i, j)``, ``i < j``,
    sorted; empty when every pair of those maps has been tried."""
    tried = {(min(a, b), max(a, b)) for a, b in tried}
    new: set[tuple[int, int]] = set()
    for u in maps_to_grow:
        u = int(u)
        order = [int(v) for v in np.argsort(-sim[u], kind="stable") if int(v) != u]
        fresh = [(min(u, v), max(u, v)) for v in order if (min(u, v), max(u, v)) not in tried]
        new.update(fresh[:int(k)])
    return sorted(new)
