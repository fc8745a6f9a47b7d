"""Anderson acceleration of the ICP fixed-point map (Walker & Ni 2011; for ICP: AA-ICP,
Pavlov et al. 2018, and the energy safeguard of Zhang et al. 2021, "Fast and robust ICP").

The map ``T -> kabsch(matches(T))`` is extrapolated from its last ``ANDERSON_HISTORY``
iterates in 6-vector coordinates (rotation vector [rad], translation [m]) about a reference
transform ``T_ref`` (``chart`` / ``unchart``). The loop keeps an accelerated iterate only if
it lowers the truncated energy, and restarts the history otherwise and at each new stage.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from ... import se3

__all__ = ["ANDERSON_HISTORY", "History", "empty_history", "chart", "unchart", "extrapolate", "accelerate", "restarted"]

ANDERSON_HISTORY = 5  # iterates the extrapolation combines


class History(NamedTuple):
    """Anderson history of one stage, in coordinates about ``T_ref``."""

    T_ref: jax.Array  # (4, 4) float32, the chart's origin (the stage's, or last restart's, first iterate)
    dF: jax.Array  # (m, 6) float32, differences of consecutive residuals f = g - x, newest first
    dG: jax.Array  # (m, 6) float32, differences of consecutive images g, newest first
    count: jax.Array  # () int32, iterates since the restart, at most m + 1
    f_prev: jax.Array  # (6,) float32, the last residual
    g_prev: jax.Array  # (6,) float32, the last image


def empty_history(T_ref, m: int = ANDERSON_HISTORY) -> History:
    """A restarted history about ``T_ref (4, 4)`` holding ``m`` differences."""
    hist0 = jnp.zeros((m, 6), jnp.float32)
    zero6 = jnp.zeros((6,), jnp.float32)
    return History(T_ref, hist0, hist0, jnp.int32(0), zero6, zero6)


def chart(T, T_ref):
    """``(6,)`` coordinates ``(rotation vector of R R_ref^T [rad], t - t_ref [m])`` of ``T``
    about ``T_ref`` (both ``(4, 4)``)."""
    return jnp.concatenate([se3.so3_log(T[:3, :3] @ T_ref[:3, :3].T), T[:3, 3] - T_ref[:3, 3]])


def unchart(x, T_ref):
    """Inverse of ``chart``: ``x (6,)`` about ``T_ref`` -> ``T (4, 4)``."""
    return se3.from_rotation_translation(se3.so3_exp(x[:3]) @ T_ref[:3, :3], x[3:] + T_ref[:3, 3])


def extrapolate(x_g, f, dF, dG, n_hist):
    """Anderson acceleration (type II, Walker & Ni 2011) of the fixed-point map ``x -> g``:
    ``x_g - dG gamma`` with ``gamma = argmin |f - dF gamma|``; ``dF, dG (m, 6)`` hold the
    last ``n_hist`` differences of residuals ``f = g - x`` and of images ``g`` (older rows
    unused). Falls back to ``x_g`` if the solve is not finite."""
    m = dF.shape[0]
    used = (jnp.arange(m) < n_hist).astype(f.dtype)
    A = dF * used[:, None]
    M = A @ A.T
    reg = 1e-8 * jnp.max(jnp.diag(M)) + 1e-20
    gamma = jnp.linalg.solve(M + reg * jnp.eye(m, dtype=f.dtype) + jnp.diag(1.0 - used), A @ f)
    x = x_g - (dG * used[:, None]).T @ gamma
    return jnp.where(jnp.all(jnp.isfinite(x)), x, x_g)


def accelerate(history: History, T, G):
    """One Anderson step: ``T (4, 4)`` the current iterate, ``G (4, 4)`` its plain ICP image.
    Returns ``(T_acc (4, 4), used () bool, history')``: the extrapolated iterate (``G`` while
    the history is empty) and the history with this pair appended."""
    m = history.dF.shape[0]
    g = chart(G, history.T_ref)
    f = g - chart(T, history.T_ref)
    has_prev = history.count > 0
    dF = jnp.where(has_prev, jnp.roll(history.dF, 1, 0).at[0].set(f - history.f_prev), history.dF)
    dG = jnp.where(has_prev, jnp.roll(history.dG, 1, 0).at[0].set(g - history.g_prev), history.dG)
    n_used = jnp.minimum(history.count, m)
    used = n_used > 0
    T_acc = jnp.where(used, unchart(extrapolate(g, f, dF, dG, n_used), history.T_ref), G)
    count = jnp.minimum(history.count + 1, m + 1).astype(jnp.int32)
    return T_acc, used, History(history.T_ref, dF, dG, count, f, g)


def restarted(restart, T_ref, history: History) -> History:
    """``empty_history(T_ref)`` where ``restart`` (``()`` bool), else ``history``."""
    empty = empty_history(T_ref, history.dF.shape[0])
    return History(*(jnp.where(restart, a, b) for a, b in zip(empty, history)))
