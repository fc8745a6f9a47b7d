"""The fusion rules (thesis eq. 5.15 and two alternatives), traced so that one compiled
kernel serves all of them."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from .._ops import is_traced
from ..types import RULES

# ``mode`` (a traced int32) per rule: 0 sum, 1 max, 2 weighted; "sum" runs as "weighted"
# with weights 1, which is exact in IEEE arithmetic.
MODE = {"sum": 0, "max": 1, "weighted": 2}


def combine(mode, a, b, wa, wb):
    """The value of a voxel both maps know: ``max(a, b)`` (mode 1) or ``wa a + wb b``.

    XLA on CPU may contract ``wa * a + wb * b`` into a fused multiply-add, so "weighted" can
    differ from separately rounded float32 products by an ulp (exact for power-of-two
    weights)."""
    return jnp.where(mode == 1, jnp.maximum(a, b), wa * a + wb * b)


def single(mode, a, wa):
    """The value of a voxel one map knows: ``a`` (mode 1) or ``wa a`` (the other map
    contributes the prior, log-odds 0)."""
    return jnp.where(mode == 1, a, wa * a)


def check_rule(rule):
    """Raise ``ValueError`` unless ``rule`` is one of ``RULES``."""
    if rule not in RULES:
        raise ValueError(f"rule must be one of {RULES}, got {rule!r}")


# --- cli
MAX_WEIGHT = 1e6  # a larger weight turns float32 log-odds (|L| <= ~4) into inf / nan


def check_weights(weights, n: int, name: str = "weights"):
    """Raise ``ValueError`` naming ``name`` unless ``weights`` holds ``n`` finite numbers in
    ``[0, MAX_WEIGHT]``, not all zero (a log-linear pool with a negative weight turns
    evidence around; all zero erases every voxel). Traced weights (under ``jit``) are not
    read; their count is still checked."""
    if isinstance(weights, (str, bytes)) or not hasattr(weights, "__len__"):
        raise ValueError(f"{name} must be a list of {n} numbers, got {weights!r}")
    if len(weights) != n:
        raise ValueError(f"{name} must hold one weight per map ({n}), got {len(weights)}: {list(weights)!r}")
    if is_traced(*weights) or is_traced(weights):
        return
    w = np.asarray(weights, np.float64)
    if not (np.all(np.isfinite(w)) and np.all(w >= 0) and np.all(w <= MAX_WEIGHT)):
        raise ValueError(f"{name} must be finite numbers in [0, {MAX_WEIGHT:g}], got {w.tolist()}")
    if not np.any(w > 0):
        raise ValueError(f"{name} must not all be 0 (that erases every voxel), got {w.tolist()}")
