"""What ICP returns: ``IcpResult`` for one registration, ``IcpMultiResult`` for many starts."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from ... import se3

__all__ = ["IcpResult", "IcpMultiResult", "invert_result"]


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class IcpResult:
    """Result of one ICP registration (all fields arrays; batched under ``vmap``).

    - ``T_target_source``: ``(4, 4)`` float32, maps source points into the target frame.
    - ``converged``: ``()`` bool, converged at the floor correspondence distance.
    - ``num_iterations``: ``()`` int32, correspondence searches performed.
    - ``num_inliers``: ``()`` int32, source points with a target point within the floor
      (smallest) correspondence distance under ``T_target_source``.
    - ``rmse``: ``()`` float32 [m], root mean square inlier distance.
    - ``fitness``: ``()`` float32, ``num_inliers / valid source points``.
    - ``num_close``: ``()`` int32, source points within a quarter of the floor distance
      (half a voxel at the defaults): the tight overlap ``icp_multi`` ranks candidates by.
    - ``correspondence_distance``: ``()`` float32 [m], the distance of the last stage reached.
    - ``status``: ``()`` int32, a ``registration.Status``: ``CONVERGED``, ``MAX_ITERATIONS``
      or ``TOO_FEW_INLIERS`` (fewer than ``min_inliers`` correspondences: the transform is the
      last valid one).
    - ``grid_overflow``: ``()`` int32, target points dropped by the final-stage grid (0 means
      the nearest-neighbour search was exact).
    - ``swapped``: ``()`` bool, the clouds were swapped (larger one as model) and the result
      inverted.
    """

    T_target_source: jax.Array
    converged: jax.Array
    num_iterations: jax.Array
    num_inliers: jax.Array
    rmse: jax.Array
    fitness: jax.Array
    num_close: jax.Array
    correspondence_distance: jax.Array
    status: jax.Array
    grid_overflow: jax.Array
    swapped: jax.Array


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class IcpMultiResult:
    """``icp_multi`` output.

    - ``best``: the best candidate's ``IcpResult``.
    - ``candidates``: every candidate's ``IcpResult`` (leading axis ``k``); counts and rmse
      are measured at the returned transforms.
    - ``best_index``: ``()`` int32, the index of ``best``.
    - ``scores``: ``(k,)`` float32, ``num_close - rmse / d_floor`` (higher is better).
    - ``hypotheses``: ``(k, 4, 4)`` float32, the initial guesses used.
    - ``basin``: ``(k,)`` int32, the candidate whose run each candidate's result is
      (``basin[i] == i`` unless candidate ``i`` left a stage within ``basin_tolerance_m`` of
      an earlier one and was merged into it, see ``icp_multi``).
    - ``num_iterations_run``: ``(k,)`` int32, the iterations each hypothesis's own run took
      before it stopped or merged (``candidates.num_iterations`` of a merged candidate is its
      leader's); their sum is the call's work. ``None`` where the candidates do not come from
      ``icp_multi``.
    """

    best: IcpResult
    candidates: IcpResult
    best_index: jax.Array
    scores: jax.Array
    hypotheses: jax.Array
    basin: jax.Array
    num_iterations_run: jax.Array | None = None


def invert_result(r: IcpResult) -> IcpResult:
    """The result of the swapped problem read back: ``T_target_source`` inverted, ``swapped`` set."""
    return dataclasses.replace(r, T_target_source=se3.inverse(r.T_target_source),
                               swapped=jnp.ones_like(r.swapped))
