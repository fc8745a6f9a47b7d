"""The dense alignment loss: the agreement of two signed occupancy fields under a transform,
read by trilinear interpolation (thesis eqs. 3.6-3.13) at map 2's sample points.

Each map holds a *signed occupancy* ``s = 2 p - 1 = tanh(l / 2)`` in known voxels (+1
occupied, -1 free) and ``0`` in unknown space. ``s_1`` is interpolated at ``y_j = T_1_2 x_j``
over the 8 voxel centres around ``y_j`` with unknown neighbours counted as ``0``, i.e.
``s_1(y) = 2 A(y) - C(y)`` with ``A = sample(m1, y, method="thesis")`` and ``C`` the known
coverage of the 8 weights. The field is continuous everywhere and piecewise smooth. The loss
is a mean agreement over the commonly known space::

    L(T_1_2) = - sum_j w_j s_2(x_j) s_1(y_j) / D,    D = sum_j w_j C(y_j) + 0.1 sum_j w_j

over sample points ``x_j`` of map 2 (``prepare_alignment``), the occupied and free classes
weighted ``1 : free_weight`` in total. ``coverage_norm = a`` blends in the plain mean:
``D = a (sum w C + 0.1 sum w) + (1 - a) sum w``. At the finest level of a symmetric problem
the loss is the mean of this one and the same loss of map 1's points in map 2 under
``T_1_2^-1`` (``AlignProblem.reverse``).
"""

from __future__ import annotations

from functools import partial
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ... import morton, se3
from ...leaf_index import LeafIndex, lookup_keys
from ...map import OccupancyMap
from ._problem import AlignProblem, Level, LevelPair, both_at, prepare_alignment

__all__ = ["alignment_loss", "fine_scores", "level_losses", "pair_loss", "pair_loss_and_checks", "problem_loss",
           "score_alignment"]

_OVERLAP_PRIOR = 0.1  # pseudo-weight added to the commonly known weight (loss denominator)
_CORNERS = np.array([[c & 1, (c >> 1) & 1, (c >> 2) & 1] for c in range(8)], np.int32)


class _Corners(NamedTuple):
    """The 8 voxel centres of map 1 around each of ``P`` points."""

    weight: jax.Array    # (P, 8) float32 trilinear weights (the gradient flows through them)
    known: jax.Array     # (P, 8) bool
    log_odds: jax.Array  # (P, 8) float32


class _LevelTerms(NamedTuple):
    """A level's one-way loss under a transform and what the status checks read."""

    loss: jax.Array      # () float32
    coverage: jax.Array  # (P,) float32, known share of each point's 8 trilinear weights
    corners: _Corners


def _corners(m1: OccupancyMap, y, index: LeafIndex | None = None) -> _Corners:
    """The 8 voxel centres of ``m1`` around points ``y (P, 3)`` [m] of map 1's frame (the
    lookups are piecewise constant, so gradients reach ``y`` only through the weights),
    looked up through ``m1``'s ``index`` when given."""
    u = y / jnp.float32(m1.resolution) - jnp.float32(0.5)  # centres at integer u
    finite = jnp.all(jnp.isfinite(u), axis=-1)
    base = jax.lax.stop_gradient(jnp.floor(jnp.where(finite[:, None], u, 0.0)))
    f = jnp.where(finite[:, None], u - base, 0.0)
    base = jnp.clip(base, -morton.KEY_OFFSET - 2, morton.KEY_OFFSET + 1).astype(jnp.int32)
    keys = base[:, None, :] + morton.KEY_OFFSET + jnp.asarray(_CORNERS)  # (P, 8, 3)
    row, known = lookup_keys(m1, keys, index)
    known = known & finite[:, None]
    c = jnp.asarray(_CORNERS, jnp.float32)  # (8, 3)
    w = jnp.prod(jnp.where(c == 1, f[:, None, :], 1.0 - f[:, None, :]), axis=-1)  # (P, 8)
    return _Corners(w, known, m1.log_odds[row])


def _signed_field(corners: _Corners):
    """``(s_1 (P,), coverage (P,))``: ``s_1 = sum_c w_c k_c tanh(l_c / 2)`` and ``coverage =
    sum_c w_c k_c`` over the 8 corners ``c`` (``k_c``: the corner is known). The same values as
    ``2 sample(.., "thesis") - coverage`` from one leaf lookup per corner."""
    w, known, lo = corners
    s = jnp.where(known, jnp.tanh(0.5 * lo), 0.0)
    return jnp.sum(w * s, axis=-1), jnp.sum(w * known.astype(w.dtype), axis=-1)


def _level_terms(lv: Level, T_1_2) -> _LevelTerms:
    """The one-way loss of level ``lv`` under ``T_1_2 (4, 4)`` (module docstring)."""
    y = se3.transform_points(jnp.asarray(T_1_2, jnp.float32), lv.points2)
    corners = _corners(lv.map1, y * lv.scale, lv.index)
    s1, cov = _signed_field(corners)
    w, a = lv.weight2, lv.coverage_norm
    den = a * (jnp.sum(w * cov) + _OVERLAP_PRIOR * jnp.sum(w)) + (1.0 - a) * jnp.sum(w)
    loss = -jnp.sum(w * lv.signed2 * s1) / den
    return _LevelTerms(loss, cov, corners)


def _symmetrised(loss, pair: LevelPair, T_1_2):
    """The one-way ``loss`` of ``pair.forward``, averaged with the reverse direction's (map 2
    sampled at map 1's points under ``T_1_2^-1``) at the finest level of a symmetric problem
    (a ``cond`` when ``pair.finest`` is traced)."""
    if pair.reverse is None:
        return loss

    def both():
        T_2_1 = se3.inverse(jnp.asarray(T_1_2, jnp.float32))
        return 0.5 * (loss + _level_terms(pair.reverse, T_2_1).loss)

    if isinstance(pair.finest, (bool, np.bool_)):
        return both() if pair.finest else loss
    return jax.lax.cond(pair.finest, both, lambda: loss)


def pair_loss(pair: LevelPair, T_1_2):
    """The loss of one level (``both_at``) under ``T_1_2 (4, 4)``: a float32 scalar."""
    return _symmetrised(_level_terms(pair.forward, T_1_2).loss, pair, T_1_2)


def problem_loss(problem: AlignProblem, T_1_2, level: int = -1):
    """The alignment loss (module docstring) of a prepared problem at ``level`` (index into
    ``problem.levels``, default the finest) under ``T_1_2 (4, 4)``: a float32 scalar in
    [-1, 1], lower is better. Pure, jittable, differentiable w.r.t. ``T_1_2`` (and map 2's
    signed values)."""
    return pair_loss(both_at(problem, level), T_1_2)


def alignment_loss(m1: OccupancyMap, m2: OccupancyMap, T_1_2, *, level: int = 0,
                   max_points: int = 8192, free_weight: float = 0.5, seed: int = 0,
                   jitter: bool = True, coverage_norm: float = 1.0, symmetric: bool = True):
    """Differentiable score of how well map 2 agrees with map 1 under ``T_1_2`` (lower is better).

    ``-sum_j w_j s_2(x_j) s_1(T_1_2 x_j)`` over known voxel centres ``x_j`` of map 2 (a seeded
    subset of at most ``max_points``), with ``s = tanh(l / 2)`` the signed occupancy (unknown
    = 0) and ``s_1`` trilinear in map 1, normalised by the commonly known weight (module
    docstring); with ``symmetric`` (default) averaged with the same score of map 1's points in
    map 2 under ``T_1_2^-1``; ``level = k`` compares copies coarsened by ``2^k``.
    ``T_1_2 (4, 4)`` [m] may be traced (``jax.grad`` w.r.t. it works); the maps must be
    concrete (planning runs on the host). For repeated calls prepare once with
    ``prepare_alignment`` and use ``problem_loss``.
    """
    problem = prepare_alignment(m1, m2, levels=(level,), max_points=max_points,
                                free_weight=free_weight, seed=seed, jitter=jitter,
                                coverage_norm=coverage_norm, symmetric=symmetric)
    return problem_loss(problem, T_1_2)


def pair_loss_and_checks(pair: LevelPair, T_1_2):
    """``(loss, (overlap, agreement))``, each ``()`` float32, of one level (``both_at``) under
    ``T_1_2 (4, 4)``: ``pair_loss`` and what the status checks read, from one evaluation.
    ``overlap``: the share of map 2's occupied sample weight landing in map 1's known space;
    ``agreement``: of that, the share landing next to map 1's surfaces (one of the 8 voxels the
    point interpolates from is occupied). Both are one-way (map 2 in map 1)."""
    fwd = pair.forward
    terms = _level_terms(fwd, T_1_2)
    loss = _symmetrised(terms.loss, pair, T_1_2)
    cov, known, lo = terms.coverage, terms.corners.known, terms.corners.log_odds
    w_occ = jnp.where(fwd.occupied2, fwd.weight2, 0.0)
    overlap = jnp.sum(w_occ * cov) / jnp.maximum(jnp.sum(w_occ), 1e-30)
    near = jnp.any(known & (lo >= fwd.map1.params.occupancy_threshold_log_odds), axis=-1)
    agree = jnp.sum(w_occ * cov * near.astype(jnp.float32)) / jnp.maximum(jnp.sum(w_occ * cov), 1e-30)
    return loss, (overlap, agree)


def fine_scores(problem: AlignProblem, T_1_2):
    """``(loss, overlap, agreement)``, each ``()`` float32, at the finest level under
    ``T_1_2 (4, 4)`` (``AlignResult``'s fields of the same names; ``pair_loss_and_checks``)."""
    loss, (overlap, agree) = pair_loss_and_checks(both_at(problem, problem.num_levels - 1), T_1_2)
    return loss, overlap, agree


@jax.jit
def _scores_jit(problem, T_1_2s):
    return jax.vmap(lambda T: fine_scores(problem, T))(T_1_2s)


@partial(jax.jit, static_argnames="level")
def level_losses(problem: AlignProblem, T_1_2s, level: int = -1):
    """``problem_loss`` at ``level`` (index into ``problem.levels``) for each of ``T_1_2s (k,
    4, 4)``: ``(k,)`` float32, lower is better. A coarse level scores poses a cell or so from
    a minimum close to it (``correlation_search``'s poses are re-ranked this way)."""
    return jax.vmap(lambda T: problem_loss(problem, T, level))(jnp.asarray(T_1_2s, jnp.float32))


def score_alignment(problem: AlignProblem, T_1_2s):
    """Score candidate transforms ``T_1_2s (k, 4, 4)`` (e.g. ``icp_multi``'s candidates) by the
    finest-level alignment loss, without solving: ``(loss, overlap, agreement)``, each ``(k,)``
    float32 (``AlignResult`` fields of the same names; lower loss is better, non-finite
    transforms score ``+inf``). Unlike point inlier counts, the loss sees free space: a
    candidate that puts map 2's surfaces into map 1's free space (e.g. a room turned by 180
    degrees, whose walls still match) scores worse than the truth.

    Raises:
      ValueError: ``T_1_2s`` is not ``(k, 4, 4)``.
    """
    T = jnp.asarray(T_1_2s, jnp.float32)
    if T.ndim != 3 or T.shape[-2:] != (4, 4):
        raise ValueError(f"T_1_2s: expected shape (k, 4, 4), got {T.shape}")
    finite = jnp.all(jnp.isfinite(T), axis=(1, 2))
    loss, overlap, agree = _scores_jit(problem, jnp.where(finite[:, None, None], T, jnp.eye(4)))
    return jnp.where(finite, loss, jnp.inf), overlap, agree
