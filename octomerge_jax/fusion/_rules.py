"""The fusion rules (thesis eq. 5.15 and two alternatives), traced so that one compiled
kernel serves all of them."""

from __future__ import annotations

import jax.numpy as jnp

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
