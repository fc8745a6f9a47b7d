"""Trilinear, nearest and thesis blends of the 8 voxel centres around a point (thesis §3.2,
eqs. 3.6-3.13), and the differentiable ``sample`` built on them.

A point's 8 neighbours are the finest voxel centres at keys ``k0 + (bx, by, bz)``, corner
``c = bx + 2 by + 4 bz`` (x lowest, as OctoMap's child index); ``f = (fx, fy, fz)`` in
``[0, 1)`` are the point's offsets from corner 0 in voxels. ``blend`` is one formula for every
mode (selected by a traced index), shared by ``sample`` and the ``transform_map`` kernel.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from .. import morton, tree
from ..map import OccupancyMap
from ..types import METHODS, SPACES

__all__ = [
    "METHODS",
    "SPACES",
    "CORNERS",
    "KEY_MAX",
    "check_choice",
    "mode_index",
    "blend",
    "sample",
]


KEY_MAX = 2 * morton.KEY_OFFSET  # finest keys lie in [0, KEY_MAX) per axis

# corner c = bx + 2 by + 4 bz (x lowest, as OctoMap's child index): (8, 3) int32 (bx, by, bz)
CORNERS = np.array([[c & 1, (c >> 1) & 1, (c >> 2) & 1] for c in range(8)], np.int32)


def check_choice(value, choices, name):
    """Raise ``ValueError`` naming ``name`` unless ``value`` is one of ``choices``."""
    if value not in choices:
        raise ValueError(f"{name} must be one of {choices}, got {value!r}")


def mode_index(method: str, space: str) -> int:
    """The blend rule as an int for ``blend``'s traced ``mode`` (one compiled kernel serves
    every mode): 0 trilinear in probability, 1 trilinear in log-odds, 2 nearest, 3 thesis."""
    if method == "trilinear":
        return 0 if space == "probability" else 1
    return 2 if method == "nearest" else 3


def _logit(p):
    return jnp.log(p) - jnp.log1p(-p)


def _safe_logit(p):
    tiny = jnp.float32(1e-7)
    return _logit(jnp.clip(p, tiny, 1.0 - tiny))


def _probability(log_odds):
    """OctoMap ``probability(l) = 1 - 1 / (1 + e^l)`` in a form stable for large ``|l|``."""
    return jax.nn.sigmoid(log_odds)


def _corner_weights(f):
    """Trilinear weights (eqs. 3.6-3.13) of the 8 corners: offsets ``f = (fx, fy, fz)``
    (arrays of one shape) -> list of 8 arrays, corner ``c = bx + 2 by + 4 bz``."""
    w1 = [(1.0 - a, a) for a in f]
    return [w1[2][c >> 2] * w1[1][(c >> 1) & 1] * w1[0][c & 1] for c in range(8)]


def _select_corner(f, vals):
    """Value at the corner whose voxel contains the sample point (nearest centre): a binary
    select tree over the 8 corner arrays ``vals`` (no gather)."""
    bits = [a >= 0.5 for a in f]
    v = list(vals)
    for axis in range(3):  # x pairs (c, c+1), then y, then z
        v = [jnp.where(bits[axis], v[i + 1], v[i]) for i in range(0, len(v), 2)]
    return v[0]


def _sum8(terms):
    """Pairwise sum of 8 arrays."""
    t = list(terms)
    while len(t) > 1:
        t = [t[i] + t[i + 1] for i in range(0, len(t), 2)]
    return t[0]


def blend(lo8, known8, f, mode):
    """Interpolate 8 neighbour log-odds at offsets ``f = (fx, fy, fz)`` in [0, 1) from
    corner 0 (eqs. 3.6-3.13). ``lo8``, ``known8``: lists of 8 arrays (corner
    ``c = bx + 2 by + 4 bz``) of the shape of ``fx``.

    ``mode`` (traced int, ``mode_index``): 0 trilinear in probability, 1 trilinear in
    log-odds (both leave unknown neighbours out and renormalise), 2 nearest, 3 thesis (unknown
    neighbours weigh as probability 0, Appendix A.2). Returns ``(probability, log_odds,
    center_known, exact)``: the blended value in both spaces (unclamped), whether the voxel
    containing the point is known (thesis: only then is a destination voxel made) and
    ``exact``, the log-odds to use where every contributing neighbour holds the same value
    (NaN elsewhere) so such values stay bit-exact.

    Per-corner arrays (not a trailing axis of 8) and one formula for all modes selected by
    ``where`` (not ``lax.switch``) let XLA fuse the whole blend into one vectorised loop.
    """
    zero = jnp.float32(0)
    lo8 = [jnp.where(k, l, zero) for l, k in zip(lo8, known8)]
    w = _corner_weights(f)
    lo_c = _select_corner(f, lo8)
    k_c = _select_corner(f, known8)
    wk = [jnp.where(k, wc, zero) for wc, k in zip(w, known8)]
    num_p = _sum8([a * _probability(b) for a, b in zip(wk, lo8)])  # unknown: p = 0 (thesis)
    num_l = _sum8([a * b for a, b in zip(wk, lo8)])
    den = _sum8(wk)
    ok = den > 0
    safe = jnp.where(ok, den, jnp.float32(1))
    tri_p = jnp.where(ok, num_p / safe, jnp.float32(0.5))
    tri_l = jnp.where(ok, num_l / safe, zero)
    is_thesis = mode == 3
    p = jnp.where(mode == 0, tri_p,
                  jnp.where(is_thesis, num_p, _probability(jnp.where(mode == 1, tri_l, lo_c))))
    lo = jnp.where(mode == 1, tri_l, jnp.where(mode == 2, lo_c, _safe_logit(p)))
    # Every contributing neighbour equal to the centre one (thesis: and known).
    same = functools.reduce(jnp.logical_and, [
        (wc <= 0) | (k & (l == lo_c)) | (~k & ~is_thesis) for wc, k, l in zip(w, known8, lo8)])
    exact = jnp.where(same | (mode == 2), lo_c, jnp.nan)
    return p, lo, k_c, jnp.where(k_c, exact, jnp.nan)


def _split_points(points, resolution):
    """Metric points -> (integer key of corner 0 ``(..., 3)`` int32, offsets ``f`` in [0, 1),
    in-range mask). Centres sit at integer ``u = x / res - 0.5`` relative to key 32768, which
    keeps float32 precision near the origin instead of near key 32768."""
    u = points / jnp.float32(resolution) - jnp.float32(0.5)
    base = jnp.floor(u)
    f = u - jax.lax.stop_gradient(base)
    finite = jnp.all(jnp.isfinite(u), axis=-1)
    base = jnp.where(jnp.isfinite(base), base, 0.0)
    base = jnp.clip(base, -morton.KEY_OFFSET - 2, morton.KEY_OFFSET + 1)
    key0 = base.astype(jnp.int32) + morton.KEY_OFFSET
    return key0, jnp.where(finite[..., None], f, 0.0), finite


def _lookup_keys(m: OccupancyMap, keys):
    """Log-odds and known flag of the leaves containing finest ``keys (..., 3)`` (any depth)."""
    row, known = tree.lookup_keys(m, keys)
    return jnp.where(known, m.log_odds[row], jnp.float32(0)), known


@jax.jit
def _sample(m: OccupancyMap, points, mode, log_odds_out):
    key0, f, finite = _split_points(points, m.resolution)
    keys = key0[..., None, :] + jnp.asarray(CORNERS)
    lo8, known8 = _lookup_keys(m, keys)
    known8 = known8 & finite[..., None]
    p, lo, center_known, _ = blend([lo8[..., c] for c in range(8)],
                                   [known8[..., c] for c in range(8)],
                                   (f[..., 0], f[..., 1], f[..., 2]), mode)
    return jnp.where(log_odds_out, lo, p), center_known


def sample(m: OccupancyMap, points, *, space: str = "probability", method: str = "trilinear"):
    """Interpolated occupancy at metric ``points (..., 3)`` [m, float32] in the map's frame.

    Returns ``(value (...,) float32, known (...,) bool)``: ``value`` is a probability
    (``space="probability"``, interpolated in probability as the thesis) or log-odds
    (``space="log_odds"``); ``known`` says the voxel containing the point is known. The value
    blends the 8 voxel centres around the point (eqs. 3.6-3.13) with ``method`` as in
    ``transform_map``; where no weight falls on known data it is the neutral 0.5 / 0.
    Values are not clamped (clamping is applied when a map is written).

    Differentiable with respect to ``points`` (and so to a transform applied to them) for
    ``"trilinear"`` and ``"thesis"``: the gradient is that of the trilinear weights, finite at
    voxel centres; it is discontinuous across voxel faces where neighbours change.
    Raises ``ValueError`` for an unknown ``space`` or ``method`` or points not of shape
    ``(..., 3)``.
    """
    check_choice(space, SPACES, "space")
    check_choice(method, METHODS, "method")
    pts = jnp.asarray(points)
    if pts.shape[-1:] != (3,):
        raise ValueError(f"points: expected shape (..., 3), got {pts.shape}")
    if not jnp.issubdtype(pts.dtype, jnp.floating):
        pts = pts.astype(jnp.float32)
    return _sample(m, pts, jnp.int32(mode_index(method, space)), jnp.bool_(space == "log_odds"))
