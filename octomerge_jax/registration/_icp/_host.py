"""Host-side argument handling of the ICP entry points: padding, validation, dtypes."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from ... import se3
from ..._ops import bucket_capacity, is_traced, to_device

__all__ = ["pad_points", "pad_points_host", "prepare_points", "check_transform", "as_argument", "to_number"]


def pad_points(points, capacity: int | None = None, *, name: str = "points"):
    """Host: ``(n, 3)`` points [m] -> ``(padded (C, 3) float32 jax array, count int32)`` with
    ``C = bucket_capacity(n)`` unless given. Raises ``ValueError`` naming ``name`` on a bad
    shape, non-finite coordinates or a capacity below ``n``."""
    out, n = pad_points_host(points, capacity, name)
    return jnp.asarray(out), jnp.asarray(n, jnp.int32)


def pad_points_host(points, capacity, name):
    """``pad_points`` on the host: ``(padded (C, 3) float32 NumPy array, n)``."""
    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"{name}: expected shape (n, 3), got {p.shape}")
    if not np.all(np.isfinite(p)):
        raise ValueError(f"{name}: contains non-finite coordinates")
    n = p.shape[0]
    cap = bucket_capacity(n) if capacity is None else int(capacity)
    if cap < n:
        raise ValueError(f"{name}: capacity {cap} < {n} points")
    out = np.zeros((cap, 3), np.float32)
    out[:n] = p
    return out, n


def prepare_points(points, count, name):
    """``(padded (C, 3) float32 array, count, host count or None)``: host points without a
    count are validated and padded (``pad_points_host``); JAX arrays and tracers are used as
    given, with ``count`` (default: every row). Raises ``ValueError`` on a bad shape."""
    if count is None and not is_traced(points):
        p, c = pad_points_host(points, None, name)
        return p, np.int32(c), c
    p = to_device(points, np.float32)
    if p.ndim != 2 or p.shape[-1] != 3:
        raise ValueError(f"{name}: expected shape (n, 3), got {p.shape}")
    c = to_device(p.shape[0] if count is None else count, np.int32)
    host = None if is_traced(c) else int(c)
    return p, c, host


def check_transform(T, name):
    """``T (4, 4)`` as float32: a tracer as it is, a host value checked by ``se3.check_rigid``
    (which raises ``ValueError`` naming ``name``)."""
    if is_traced(T):
        return jnp.asarray(T, jnp.float32)
    return se3.check_rigid(T, name).astype(np.float32)


def as_argument(x, dtype):
    """An argument for a jitted call: JAX arrays (and tracers) as they are, anything else as a
    NumPy array (host values go to the device with the call, not one eager op each)."""
    return jnp.asarray(x, dtype) if isinstance(x, jax.Array) else np.asarray(x, dtype)


def to_number(x) -> float:
    """``float(x)``, or NaN for anything that is not a real number (rejected by the caller)."""
    try:
        return float(x)
    except (TypeError, ValueError):
        return float("nan")
