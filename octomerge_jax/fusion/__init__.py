"""Log-odds fusion of occupancy maps across octree depths (thesis §5.2.3, Alg. 8, §6.5).

``fuse(m1, m2)`` integrates a map already in M1's frame (the output of ``transform_map``)
into M1. The result is, exactly, "expand both maps to depth 16, combine the log-odds where
both know a voxel, keep the one value where only one does, clamp to M1's
``[clamp_min, clamp_max]`` (eq. 2.10), prune maximally" - reached with **local expansion
only**, as the thesis asks: a leaf is split only where the other map holds finer leaves inside
it, and only into the few cells needed.

How, on flat Morton intervals (a leaf at depth ``d`` covers ``[code, code + 8^(16-d))``):

1. One merge of the two sorted leaf lists (merge path, nothing re-sorted) tells every leaf
   which leaf of the other map starts at or before it: hence whether it is covered by an
   equal or coarser leaf (thesis case 2 / 3), strictly contains finer leaves (case 3 for
   M1, case 4 for M2: it is *split*), or lies in unknown space (case 1). (``_sides``)
2. A split leaf emits no cell itself. Each finer leaf inside it emits itself (with both
   values combined, eqs. 5.17 / 5.19) plus the *gap* before it (and after it, if it is the
   last one) inside the split leaf: the part of the coarse leaf that the finer map does not
   know, which keeps the coarse value alone (eq. 5.16 / 5.18 then case 1, eq. 5.14). A gap
   ``[s, e)`` is cut into the minimal set of aligned octree cells (at most 7 per level and
   side), counted and enumerated in closed form from the octal digits of ``-s`` and ``e``
   (digit sums, no loop over levels). (``_gaps``)
3. Cell counts per leaf, one prefix sum in merged order: every leaf scatters its own cell to
   its slot, and each gap cell finds its leaf by a cumulative max over a short list of the
   leaves with gaps and computes its cell: the common refinement comes out already sorted.
   When no leaf has a gap, their counts and layout are skipped. Values are combined per
   rule, clamped, and pruned maximally in one pass (``tree.prune_runs``: a node collapses
   iff its interval lies in one run of contiguous, equal-valued leaves). (``_pair``,
   ``_layout``)

Rules (``rule=``):

- ``"sum"`` (default): ``L1 + L2`` where both maps know a voxel (eq. 5.15): the Bayesian
  update for independent observations with prior 0.5 (eq. 2.6). Use for maps built from
  different sensor data.
- ``"max"``: ``max(L1, L2)``: conservative, for maps that are not independent (built from
  shared data, or a map fused with itself), so evidence is not counted twice.
- ``"weighted"``: ``w1 L1 + w2 L2`` (a log-linear opinion pool; a map that does not know a
  voxel contributes log-odds 0, the prior, so a voxel known only to map k gets ``w_k L_k``).
  Use to discount a robot with worse localisation (e.g. ``weights=(1.0, 0.5)``).
  ``weights=(1, 1)`` equals ``"sum"``. Weights are traced (no recompilation).

Unknown space never becomes free or occupied: only leaves of the inputs produce cells.
The thesis code's bugs (adding probabilities where M2 is finer, forcing M2's occupied leaves
to p = 0.6) are not reproduced.

``fuse_many(maps)`` fuses m maps in one pass, one common refinement of all of them
(``_many``); two maps take the pair kernel above, which is that refinement. For ``"sum"``
it is bit-identical to folding ``fuse`` left to right.

Everything is jitted with static capacities; a refinement larger than the capacity is never
silently truncated: ``fuse`` / ``fuse_many`` raise on the host, ``fuse_with_report`` /
``fuse_many_with_report`` set ``FuseReport.overflow``. On the host without ``capacity=``,
the output gets the refinement's own power-of-two bucket (``_sizing``).
"""

from __future__ import annotations

import warnings
from typing import Sequence

import numpy as np

from .. import morton
from .._ops import is_traced, to_device
from ..map import OccupancyMap
from ._many import fuse_maps
from ._pair import fuse_pair, plan_pair_shapes, precompile_emit_pair
from ._report import FuseReport, FuseResult
from ._rules import MODE, RULES, check_rule, check_weights
from ._sizing import default_gap_capacity, default_gap_leaves, refinement_cells

__all__ = ["RULES", "FuseReport", "FuseResult", "fuse", "fuse_many", "fuse_with_report",
           "fuse_many_with_report", "default_gap_capacity", "default_gap_leaves", "fuse_plan_shapes",
           "precompile_fuse", "refinement_cells"]


def _check_maps(maps: Sequence[OccupancyMap], names):
    for m, name in zip(maps, names):
        if not isinstance(m, OccupancyMap):
            raise ValueError(f"{name} must be an OccupancyMap, got {type(m).__name__}")
        if m.tree_depth != morton.TREE_DEPTH:
            raise ValueError(f"{name}.tree_depth must be {morton.TREE_DEPTH}, got {m.tree_depth}")
    r0 = maps[0].resolution
    for m, name in zip(maps[1:], names[1:]):
        if m.resolution != r0:
            raise ValueError(
                f"resolutions differ: {names[0]}.resolution = {r0:g} m, {name}.resolution = "
                f"{m.resolution:g} m; resample with transform_map to a common resolution first")


def _raise_on_overflow(result: FuseResult, capacity, maps, what: str) -> OccupancyMap:
    """The map of ``result``; ``ValueError`` on the host when a given ``capacity`` was too
    small (without one the host sizes the output to fit)."""
    rep = result.report
    if capacity is not None and not is_traced(*[m.count for m in maps]) and bool(rep.overflow):
        raise ValueError(f"{what}: capacity {capacity} is too small for the "
                         f"{int(rep.refined_cells)} cells of the common refinement")
    return result.map


def _deprecated_report(result: FuseResult, what: str) -> FuseResult:
    """The ``return_report=True`` path of earlier releases: the ``FuseResult`` with a warning."""
    warnings.warn(f"{what}(..., return_report=True) is deprecated: call {what}_with_report(...), which returns "
                  "FuseResult(map, report)", DeprecationWarning, stacklevel=3)
    return result


def fuse_with_report(m1: OccupancyMap, m2: OccupancyMap, rule: str = "sum", *, weights=(1.0, 1.0),
                     capacity: int | None = None, prune: bool = True,
                     gap_capacity: int | None = None) -> FuseResult:
    """``fuse`` with its counts: ``FuseResult(map, report)``. Never raises on overflow: a
    ``capacity`` too small sets ``report.overflow`` (the map is truncated, ``refined_cells``
    the rows needed or a lower bound). Arguments and other errors as ``fuse``."""
    _check_maps([m1, m2], ["m1", "m2"])
    check_rule(rule)
    if rule != "weighted":
        weights = (1.0, 1.0)
    check_weights(weights, 2)
    w1, w2 = (to_device(w, np.float32) for w in weights)
    mode = to_device(MODE[rule], np.int32)
    return FuseResult(*fuse_pair(m1, m2, w1, w2, mode, capacity, prune, gap_capacity, "fuse"))


def fuse_plan_shapes(m1: OccupancyMap, m2: OccupancyMap, *, gap_capacity: int | None = None):
    """The shapes of the first phase a host ``fuse(m1, m2, gap_capacity=gap_capacity)`` computes
    (a pytree of ``jax.ShapeDtypeStruct``), by abstract evaluation through the trace the phase's
    program compiles from: the fuse that follows does not trace it again. For
    ``precompile_fuse``. Raises as ``fuse`` for maps it cannot fuse."""
    _check_maps([m1, m2], ["m1", "m2"])
    return plan_pair_shapes(m1, m2, gap_capacity)


def precompile_fuse(m1: OccupancyMap, m2: OccupancyMap, plan_shapes, *, prune: bool = True) -> bool:
    """Make ready, without running anything, the program that lays out a host ``fuse(m1, m2,
    prune=prune)``'s output (its second phase, sized by counting the common refinement on the
    host) after a first phase of ``plan_shapes`` (``fuse_plan_shapes``), loaded from or
    compiled into the open kernel store. A thread beside one that calls ``fuse`` on the same
    maps makes the two phases compile side by side (the command line's work ahead). Returns
    ``False`` (nothing done) without an open store. Raises as ``fuse`` for maps it cannot fuse."""
    _check_maps([m1, m2], ["m1", "m2"])
    return precompile_emit_pair(m1, m2, bool(prune), plan_shapes)


def fuse(m1: OccupancyMap, m2: OccupancyMap, rule: str = "sum", *, weights=(1.0, 1.0),
         capacity: int | None = None, prune: bool = True,
         gap_capacity: int | None = None, return_report: bool = False) -> OccupancyMap:
    """Fuse ``m2`` (already in ``m1``'s frame) into ``m1`` (thesis Alg. 8, §5.2.3 cases 1-4,
    eqs. 5.14-5.19).

    Args:
      m1, m2: maps of equal ``resolution`` (metres); ``m1``'s ``params`` (clamping) are kept.
      rule: ``"sum"`` (eq. 5.15), ``"max"`` or ``"weighted"`` (see the module docstring).
      weights: ``(w1, w2)`` for ``"weighted"`` (traced floats; ignored by other rules).
      capacity: static row count of the output. ``None`` (host only) plans it: the
        refinement has between ``max(n1, n2)`` and ``n1 + n2`` cells plus gap cells. When
        those bounds share a power-of-two bucket the kernel runs in it (re-run if gap cells
        overflow it); else a first phase counts the cells and the output gets their own
        bucket. Under ``jit``/``vmap`` pass it explicitly (and use ``fuse_with_report`` to
        see ``overflow``).
      prune: prune maximally (never into a depth-0 root leaf, as OctoMap). With ``False``
        the clamped common refinement is returned (sorted, disjoint, not pruned).
      gap_capacity: static room for *gap cells* (parts of a split leaf that the finer map
        does not know, thesis case 1 inside cases 3 / 4), and for the leaves that have them.
        ``None``: on the host ``max(capacity / 8, 512)`` (the leaves: half that), re-run
        with room for all when there are more; under ``jit``/``vmap`` room for all (every
        leaf, ``capacity`` cells: never short). A value that proves too small under ``jit``
        sets ``overflow``.
      return_report: deprecated; ``True`` warns and returns ``fuse_with_report(...)``'s
        ``FuseResult``. Call ``fuse_with_report`` instead.

    Returns the fused ``OccupancyMap`` (``capacity`` rows, or the planned bucket).
    Raises ``ValueError`` (host) for different resolutions, an unknown rule, a missing
    ``capacity`` under ``jit``/``vmap``, or a ``capacity`` too small for the refinement.
    """
    result = fuse_with_report(m1, m2, rule, weights=weights, capacity=capacity, prune=prune,
                              gap_capacity=gap_capacity)
    if return_report:
        return _deprecated_report(result, "fuse")
    return _raise_on_overflow(result, capacity, (m1, m2), "fuse")


def fuse_many_with_report(maps: Sequence[OccupancyMap], rule: str = "sum", *, weights=None,
                          capacity: int | None = None, prune: bool = True) -> FuseResult:
    """``fuse_many`` with its counts: ``FuseResult(map, report)``. Never raises on overflow
    (sets ``report.overflow``). Arguments and other errors as ``fuse_many``."""
    maps = list(maps)
    if not maps:
        raise ValueError("maps must hold at least one OccupancyMap")
    _check_maps(maps, [f"maps[{i}]" for i in range(len(maps))])
    check_rule(rule)
    if weights is None or rule != "weighted":
        weights = [1.0] * len(maps)
    check_weights(weights, len(maps))
    w = np.asarray(weights, np.float32)
    mode = to_device(MODE[rule], np.int32)
    if len(maps) == 2:  # the pair kernel is the one-pass refinement of two maps
        return FuseResult(*fuse_pair(maps[0], maps[1], to_device(w[0]), to_device(w[1]), mode, capacity, prune, None,
                                     "fuse_many"))
    return FuseResult(*fuse_maps(tuple(maps), to_device(w), mode, capacity, prune))


def fuse_many(maps: Sequence[OccupancyMap], rule: str = "sum", *, weights=None,
              capacity: int | None = None, prune: bool = True, return_report: bool = False) -> OccupancyMap:
    """Fuse ``m`` maps (all in the first map's frame) in one pass (thesis Alg. 8 for m maps).

    All leaf boundaries are merged into one sorted list (a merge tree of the maps' sorted
    boundary lists, no sort), the elementary intervals between them form one common
    refinement, the nested leaves covering each interval are found level by level, and one
    value per cell is computed (two maps take the pair kernel of ``fuse``, the same
    refinement).

    Args:
      maps: ``m >= 1`` maps of equal ``resolution`` (metres); the first map's ``params``
        (clamping) are kept.
      rule: ``"sum"``: accumulated in map order with a clamp after each map, so the result
        is bit-identical to ``fuse(fuse(m0, m1), m2) ...``; ``"max"``: the maximum;
        ``"weighted"``: ``sum_k w_k L_k`` over the maps that know the voxel, clamped once.
      weights: ``(m,)`` floats for ``"weighted"``.
      capacity: static rows of the output; ``None`` (host only): the refinement is counted
        first and laid out in its own bucket. Under ``jit``/``vmap`` pass it (the boundary
        lists then have twice each map's capacity, always enough).
      prune: as ``fuse``.
      return_report: deprecated, as ``fuse``'s (use ``fuse_many_with_report``).

    Returns the fused ``OccupancyMap``.
    Raises ``ValueError`` (host) for no maps, different resolutions, an unknown rule, a
    weight count other than ``m``, a missing ``capacity`` under ``jit``/``vmap``, or a
    ``capacity`` too small for the refinement.
    """
    maps = list(maps)
    result = fuse_many_with_report(maps, rule, weights=weights, capacity=capacity, prune=prune)
    if return_report:
        return _deprecated_report(result, "fuse_many")
    return _raise_on_overflow(result, capacity, maps, "fuse_many")
