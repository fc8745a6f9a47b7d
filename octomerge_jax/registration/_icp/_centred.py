"""Both clouds about their own centroids: the hashed grids are then anchored to the target,
not to the frame's origin, so results do not depend on where the maps lie in their frames
(translation-equivariant) and float32 keeps its precision for maps kilometres from the
origin. The stop rule's ``sum |dT|`` is measured between the centred frames.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from ._result import IcpResult

__all__ = ["centroid", "centred", "uncentre_result"]


def centroid(points, count):
    """``(3,)`` [m]: mean of the first ``count`` rows of ``points (n, 3)`` (0 for none)."""
    valid = (jnp.arange(points.shape[0]) < count)[:, None]
    return jnp.sum(jnp.where(valid, points, 0.0), 0) / jnp.maximum(count, 1).astype(points.dtype)


def centred(source, source_count, target, target_count, T):
    """``(source', target', T', uncentre)``: both clouds ``(n, 3)`` [m] about their own
    centroids (no gradient through the centroids), ``T (..., 4, 4)`` re-expressed between the
    centred frames, and ``uncentre(T') = T`` mapping a centred transform back."""
    cs = jax.lax.stop_gradient(centroid(source, source_count))
    ct = jax.lax.stop_gradient(centroid(target, target_count))
    shift = lambda T, a, b: T.at[..., :3, 3].add(jnp.einsum("...ij,j->...i", T[..., :3, :3], a) - b)  # noqa: E731
    return source - cs, target - ct, shift(T, cs, ct), lambda Tc: shift(Tc, -cs, -ct)


def uncentre_result(r: IcpResult, uncentre) -> IcpResult:
    """``r`` with its transform mapped back from the centred frames (``centred``)."""
    return dataclasses.replace(r, T_target_source=uncentre(r.T_target_source))
