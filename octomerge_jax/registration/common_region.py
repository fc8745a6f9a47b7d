"""Extraction of the commonly mapped volume of two clouds (thesis §6.2, Alg. 2).

``method="bbox"`` is the thesis (Appendix A.1): the points of cloud 2 (moved into frame 1 by
``T_1_2``) strictly inside cloud 1's bounding box, then the points of cloud 1 strictly inside
the bounding box of that selection grown by ``margin`` (the code's 1 m). The thesis found it
fails with roll/pitch errors (Table 7.1 rows 13, 16, 17): a tilted floor leaves the other map's
thin z-range, so too few points survive. ``method="voxel"`` (the better extraction the thesis
names as future work) keeps the points of each cloud that have a point of the other cloud
within ``radius`` under ``T_1_2``: a hashed-grid lookup (``neighbors.py``), jitted.

Both return boolean masks (JAX arrays) over the given rows; with NumPy input, ``points[mask]``
gives the subsets.
"""

from __future__ import annotations

from functools import partial
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from . import neighbors
from .. import se3
from .._ops import count_true, to_device

__all__ = ["Overlap", "overlap"]


class Overlap(NamedTuple):
    """``mask_1 (n1,)``, ``mask_2 (n2,)`` bool: selected rows of each cloud;
    ``count_1``, ``count_2``: ``()`` int32 numbers selected (a NamedTuple, so a pytree and
    ``mask_1, mask_2, *_ = overlap(...)`` works)."""

    mask_1: jax.Array
    mask_2: jax.Array
    count_1: jax.Array
    count_2: jax.Array


def _bbox(p, valid):
    lo = jnp.min(jnp.where(valid[:, None], p, jnp.inf), axis=0)
    hi = jnp.max(jnp.where(valid[:, None], p, -jnp.inf), axis=0)
    return lo, hi


def _inside(p, lo, hi):
    return jnp.all((p > lo) & (p < hi), axis=-1)


@jax.jit
def _overlap_bbox(p1, c1, p2, c2, T_1_2, margin):
    v1 = jnp.arange(p1.shape[0]) < c1
    v2 = jnp.arange(p2.shape[0]) < c2
    w = se3.transform_points(T_1_2, p2)
    lo1, hi1 = _bbox(p1, v1)
    m2 = v2 & _inside(w, lo1, hi1)
    lo2, hi2 = _bbox(w, m2)
    m1 = v1 & _inside(p1, lo2 - margin, hi2 + margin)
    return Overlap(m1, m2, count_true(m1), count_true(m2))


@partial(jax.jit, static_argnames=("cell_capacity", "tables"))
def _overlap_voxel(p1, c1, p2, c2, T_1_2, radius, *, cell_capacity, tables):
    v1 = jnp.arange(p1.shape[0]) < c1
    v2 = jnp.arange(p2.shape[0]) < c2
    w = se3.transform_points(T_1_2, p2)
    r = jnp.reshape(radius, (1,))
    g1 = neighbors.build_grids(p1, c1, r, table_sizes=(tables[0],), cell_capacity=cell_capacity)
    g2 = neighbors.build_grids(w, c2, r, table_sizes=(tables[1],), cell_capacity=cell_capacity)
    m2 = v2 & neighbors.any_within(g1, w, radius)
    m1 = v1 & neighbors.any_within(g2, p1, radius)
    return Overlap(m1, m2, count_true(m1), count_true(m2))


def _as_padded(points, count, name):
    p = to_device(points, np.float32)
    if p.ndim != 2 or p.shape[-1] != 3:
        raise ValueError(f"{name}: expected shape (n, 3), got {p.shape}")
    return p, to_device(p.shape[0] if count is None else count, np.int32)


def overlap(points_1, points_2, T_1_2, method: str = "bbox", *, margin: float = 1.0,
            radius: float = 1.0, cell_capacity: int = 16, count_1=None, count_2=None) -> Overlap:
    """Commonly mapped subsets of ``points_1 (n1, 3)`` (frame 1) and ``points_2 (n2, 3)``
    (frame 2) under ``T_1_2 (4, 4)`` (Alg. 2). ``method``: ``"bbox"`` (thesis, uses
    ``margin`` [m]) or ``"voxel"`` (within ``radius`` [m] of the other cloud; exact up to
    ``cell_capacity`` points per hash bucket, see ``neighbors.py``). Rows ``>= count_*`` are
    padding. Returns an ``Overlap`` of masks."""
    if method not in ("bbox", "voxel"):
        raise ValueError(f"method must be 'bbox' or 'voxel', got {method!r}")
    if not isinstance(T_1_2, jax.core.Tracer):
        se3.check_rigid(T_1_2, "T_1_2")
    p1, c1 = _as_padded(points_1, count_1, "points_1")
    p2, c2 = _as_padded(points_2, count_2, "points_2")
    T = to_device(T_1_2, np.float32)
    if method == "bbox":
        return _overlap_bbox(p1, c1, p2, c2, T, np.float32(margin))
    if not float(radius) > 0:
        raise ValueError(f"radius must be positive, got {radius!r}")
    tables = (neighbors.grid_table_size(p1.shape[0]), neighbors.grid_table_size(p2.shape[0]))
    return _overlap_voxel(p1, c1, p2, c2, T, np.float32(radius), cell_capacity=int(cell_capacity),
                          tables=tables)
