"""Map transformation by inverse mapping and trilinear resampling (thesis §3.2, §5.2.2, §6.4,
Alg. 4-7, eqs. 3.6-3.13 and 5.13), done right, plus differentiable trilinear ``sample``.

``transform_map(m, T_dst_src)`` expresses map ``m`` (built in frame ``src``) in frame ``dst`` at
the same resolution. As in the thesis, every destination voxel centre ``x_n`` (depth 16) is
mapped back, ``x_s = T_dst_src^-1 x_n`` (eq. 5.13), and gets a value only if ``x_s`` falls
inside a known source leaf (of any depth). The value is interpolated from the 8 finest voxel
centres that enclose ``x_s`` (eqs. 3.6-3.13; a neighbour inside a pruned, coarse leaf takes
that leaf's value). Differences from the published code (Appendix A.2):

- the true rigid inverse ``(R^T, -R^T t)``: A.2 builds row 3 of ``R`` from element (0,2)
  instead of (2,1) and inverts the translation as ``-t``;
- non-rigid, NaN or non-finite transforms raise ``ValueError`` on the host;
- ``method="trilinear"`` leaves unknown neighbours out and renormalises the remaining weights,
  so unknown space is not painted free (A.2 weighs them as p = 0, which the thesis saw as
  "lower occupancy" in merged maps; that rule is kept as ``method="thesis"``);
- output log-odds are finite and clamped to the map's ``[clamp_min, clamp_max]``;
- where every contributing neighbour holds the same log-odds the output is that value
  exactly (no float round trip through probability), so uniform regions stay prunable and
  whole-voxel moves are exact permutations.

**Hybrid dense/sparse, bounded memory.** The transformed bounding box is never materialised
at the finest resolution (A.2 scans all of it). Instead, on the host, we list the *bricks*
(depth-13 nodes, 8^3 voxels) the source covers, map each brick's cube forward and collect the
destination bricks its image can touch (a brick-level bitmap). For each destination brick the
inverse image of its 512 voxel centres plus interpolation neighbours lies inside a 3x3x3
window of source bricks (image width <= 7 sqrt(3) + 1 < 16 voxels); the host also looks up
the window's 27 rows of a brick-indexed table of the source (one dense 512-value row per
brick holding leaves finer than a brick, one constant row per distinct value of whole-brick
leaves, NaN rows for unknown space). A jitted loop of dynamic length (``lax.while_loop``) then
walks the destination bricks in fixed-size chunks; the 8 neighbour reads of a voxel are plain
gathers from that table.
Per-voxel data are kept as separate arrays per axis and per corner and the blend is one
formula for every mode, so XLA's CPU loops vectorise (~0.1 us per voxel). Each brick is
pruned inside itself (levels 16 -> 13) before its leaves are appended to the output; the
final maximal prune only has to merge whole-brick leaves (few: merged on the host, then the
output is compacted in place on the device). Peak memory: the source, its dense brick table
(2 KiB per brick with fine leaves), 27 table rows per destination brick, the brick-pruned output
and one chunk of work.
"""

from __future__ import annotations

import functools
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from . import morton, tree
from .map import OccupancyMap, bucket_capacity
from .se3 import check_rigid

__all__ = [
    "METHODS",
    "SPACES",
    "check_rigid_transform",
    "transformed_bounds",
    "transform_map",
    "sample",
]

METHODS = ("trilinear", "nearest", "thesis")
SPACES = ("probability", "log_odds")

_D = morton.TREE_DEPTH
_BRICK_DEPTH = 13  # a brick is a depth-13 node: 8^3 finest voxels
_B = 8
_BV = 512
_KEY_MAX = 2 * morton.KEY_OFFSET
_SNAP = 1e-5  # offsets closer than this (in voxels) to a lattice point are snapped (transform_map)

# corner c = bx + 2 by + 4 bz (x lowest, as OctoMap's child index); offset (bx, by, bz)
_CORNERS = np.array([[c & 1, (c >> 1) & 1, (c >> 2) & 1] for c in range(8)], np.int32)


def _local_offsets() -> np.ndarray:
    """``(512, 3)`` int32 voxel offsets inside a brick, in local Morton order."""
    l = np.arange(_BV)
    return np.stack([_compact9(l >> a) for a in range(3)], axis=-1).astype(np.int32)


def _compact9(v):
    return (v & 1) | ((v >> 2) & 2) | ((v >> 4) & 4)


_LOCAL = _local_offsets()


# ----------------------------------------------------------------------------- host checks


def check_rigid_transform(T, name: str = "T_dst_src") -> np.ndarray:
    """Validate one rigid transform and return it as a ``(4, 4)`` float64 array.

    Accepts ``(4, 4)`` homogeneous or ``(3, 4)`` ``[R | t]`` matrices (translation in metres).
    A thin adapter over ``se3.check_rigid`` (the one implementation; tolerance
    1e-4): raises ``ValueError`` naming ``name`` for another shape (including a batch), a NaN
    or infinite entry, a homogeneous row other than ``[0, 0, 0, 1]``, or a rotation block that
    is not orthonormal with determinant +1 (scale, shear and reflections are rejected). The
    returned homogeneous row is exactly ``[0, 0, 0, 1]``.
    """
    A = np.asarray(T, dtype=np.float64)
    if A.shape == (3, 4):
        A = np.vstack([A, [0.0, 0.0, 0.0, 1.0]])
    if A.shape != (4, 4):
        raise ValueError(f"{name}: expected a (4, 4) or (3, 4) rigid transform, got shape {A.shape}")
    if not np.all(np.isfinite(A)):  # check_rigid says "non-finite"; callers match "NaN"
        raise ValueError(f"{name}: contains NaN or infinite entries: {A.tolist()}")
    A = check_rigid(A, name).copy()
    A[3] = [0.0, 0.0, 0.0, 1.0]
    return A


def _check_choice(value, choices, name):
    if value not in choices:
        raise ValueError(f"{name} must be one of {choices}, got {value!r}")


@jax.jit
def _key_bounds(m: OccupancyMap):
    """Per-axis min key and max key + 1 ``(3,) int32`` over the leaves' cubes (on device:
    no host copy of the leaves)."""
    valid = m.valid_mask()[:, None]
    keys = morton.words_to_keys(m.code)
    end = keys + jnp.left_shift(1, _D - m.depth)[:, None]
    return (jnp.min(jnp.where(valid, keys, _KEY_MAX), axis=0),
            jnp.max(jnp.where(valid, end, 0), axis=0))


def transformed_bounds(m: OccupancyMap, T_dst_src) -> tuple[np.ndarray, np.ndarray]:
    """Alg. 4: axis-aligned bounds ``(p_min, p_max)`` [m, float64 (3,)] in frame ``dst`` of
    the source map's leaf extent (OctoMap ``getMetricMin/Max``) after ``T_dst_src``.

    The 8 corners of the source bounding box are transformed and their extremes taken.
    Raises ``ValueError`` for an empty map or an invalid transform.
    """
    T = check_rigid_transform(T_dst_src)
    if m.num_leaves == 0:
        raise ValueError("transformed_bounds: the map has no leaves")
    kmin, kmax = (np.asarray(k, np.float64) for k in _key_bounds(m))
    bmin = (kmin - morton.KEY_OFFSET) * m.resolution
    bmax = (kmax - morton.KEY_OFFSET) * m.resolution
    corners = np.array([[bmax[0] if c & 1 else bmin[0], bmax[1] if c & 2 else bmin[1],
                         bmax[2] if c & 4 else bmin[2]] for c in range(8)])
    moved = corners @ T[:3, :3].T + T[:3, 3]
    return moved.min(axis=0), moved.max(axis=0)


# ----------------------------------------------------------------------------- interpolation


def _logit(p):
    return jnp.log(p) - jnp.log1p(-p)


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


def _mode_index(method: str, space: str) -> int:
    """Traced selector of the blend rule (one compiled kernel serves every mode)."""
    if method == "trilinear":
        return 0 if space == "probability" else 1
    return 2 if method == "nearest" else 3


def _blend(lo8, known8, f, mode):
    """Interpolate 8 neighbour log-odds at offsets ``f = (fx, fy, fz)`` in [0, 1) from
    corner 0 (eqs. 3.6-3.13). ``lo8``, ``known8``: lists of 8 arrays (corner
    ``c = bx + 2 by + 4 bz``) of the shape of ``fx``.

    ``mode`` (traced int, ``_mode_index``): 0 trilinear in probability, 1 trilinear in
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
    p = jnp.where(mode == 0, tri_p, jnp.where(is_thesis, num_p, _probability(jnp.where(mode == 1, tri_l, lo_c))))
    lo = jnp.where(mode == 1, tri_l, jnp.where(mode == 2, lo_c, _safe_logit(p)))
    # Every contributing neighbour equal to the centre one (thesis: and known).
    same = functools.reduce(jnp.logical_and, [
        (wc <= 0) | (k & (l == lo_c)) | (~k & ~is_thesis) for wc, k, l in zip(w, known8, lo8)])
    exact = jnp.where(same | (mode == 2), lo_c, jnp.nan)
    return p, lo, k_c, jnp.where(k_c, exact, jnp.nan)


def _probability(log_odds):
    """OctoMap ``probability(l) = 1 - 1 / (1 + e^l)`` in a form stable for large ``|l|``."""
    return jax.nn.sigmoid(log_odds)


def _safe_logit(p):
    tiny = jnp.float32(1e-7)
    return _logit(jnp.clip(p, tiny, 1.0 - tiny))


# ----------------------------------------------------------------------------- sample


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
    in_range = jnp.all((keys >= 0) & (keys < _KEY_MAX), axis=-1)
    words = morton.keys_to_words(jnp.clip(keys, 0, _KEY_MAX - 1))
    row, known = tree.lookup_words(m, words)
    known = known & in_range
    return jnp.where(known, m.log_odds[row], jnp.float32(0)), known


@jax.jit
def _sample(m: OccupancyMap, points, mode, log_odds_out):
    key0, f, finite = _split_points(points, m.resolution)
    keys = key0[..., None, :] + jnp.asarray(_CORNERS)
    lo8, known8 = _lookup_keys(m, keys)
    known8 = known8 & finite[..., None]
    p, lo, center_known, _ = _blend([lo8[..., c] for c in range(8)],
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
    """
    _check_choice(space, SPACES, "space")
    _check_choice(method, METHODS, "method")
    pts = jnp.asarray(points)
    if pts.shape[-1:] != (3,):
        raise ValueError(f"points: expected shape (..., 3), got {pts.shape}")
    if not jnp.issubdtype(pts.dtype, jnp.floating):
        pts = pts.astype(jnp.float32)
    return _sample(m, pts, jnp.int32(_mode_index(method, space)), jnp.bool_(space == "log_odds"))


# ----------------------------------------------------------------------------- source view


def _aligned_full(shape, fill, dtype, align: int = 64) -> np.ndarray:
    """``np.full`` whose data start on an ``align``-byte boundary (zero-copy to XLA:CPU)."""
    dtype = np.dtype(dtype)
    n = int(np.prod(shape))
    raw = np.empty(n * dtype.itemsize + align, np.uint8)
    start = -raw.ctypes.data % align
    out = raw[start:start + n * dtype.itemsize].view(dtype).reshape(shape)
    out.fill(fill)
    return out


def _to_device(x: np.ndarray, like: jax.Array) -> jax.Array:
    """Host array -> an array on the device of ``like``. On a CPU device an aligned array is
    shared, not copied (the source table is hundreds of MB and fresh pages are costly);
    elsewhere a plain transfer."""
    devices = like.devices() if isinstance(like, jax.Array) else set()
    device = next(iter(devices)) if len(devices) == 1 else None
    if device is not None and device.platform == "cpu" and x.ctypes.data % 64 == 0:
        shared = jnp.from_dlpack(x)
        return shared if shared.devices() == devices else jax.device_put(shared, device)
    return jax.device_put(x, device)


def _source_view(m: OccupancyMap):
    """Host: the brick-indexed view of the source.

    Returns ``(table (rows * 512,) float32, bricks (n, 3) int64, brick_rows (n,) int32,
    nan_row, n_dense)``. ``table`` holds, in local Morton order, one dense row per brick that
    contains leaves finer than a brick (NaN = unknown; ``n_dense`` rows), then one constant
    row per distinct value of the leaves that cover whole bricks (depth <= 13), then NaN rows
    (the first is ``nan_row``). ``bricks`` lists the key (finest key >> 3) of every brick a
    leaf covers and ``brick_rows`` its table row. Memory: 2 KiB per dense brick. Works on the
    int32 code words (hi, lo: 24 bits each; a brick is ``hi, lo >> 9``): every full-length
    temporary is a page-faulted pass here.
    """
    n = m.num_leaves
    words = np.asarray(m.code)[:n]
    depth = np.asarray(m.depth)[:n]
    lo = np.asarray(m.log_odds)[:n]
    fine = depth > _BRICK_DEPTH
    hi_w, lo_w, d, v = words[fine, 0], words[fine, 1], depth[fine], lo[fine]
    # leaves are Morton-sorted, so a brick's leaves are contiguous
    first = np.ones(hi_w.shape, bool)
    np.not_equal(lo_w[1:] >> 9, lo_w[:-1] >> 9, out=first[1:])
    first[1:] |= hi_w[1:] != hi_w[:-1]
    n_db = int(np.count_nonzero(first))
    uniq, inv = np.unique(lo[~fine], return_inverse=True)
    rows = _fine_bucket(n_db + uniq.size + 1)
    table = _aligned_full((rows, _BV), np.nan, np.float32)
    itype = np.int32 if rows * _BV < 2 ** 31 else np.int64
    flat = np.cumsum(first, dtype=itype)  # slot + 1, then the voxel index in the table
    flat -= 1
    flat *= _BV
    flat += lo_w & (_BV - 1)
    for depth_l in (14, 15, 16):
        sel = d == depth_l
        if sel.any():
            span = 8 ** (_D - depth_l)
            table.reshape(-1, span)[flat[sel] // span] = v[sel, None]
    table[n_db:n_db + uniq.size] = uniq[:, None]
    keys = [morton.codes_to_keys(morton.join_codes(np.stack([hi_w[first], lo_w[first]], -1)))
            .astype(np.int64) >> 3]
    brick_rows = [np.arange(n_db, dtype=np.int32)]
    ck, cd = morton.join_codes(words[~fine]), depth[~fine]
    crow = n_db + inv.reshape(-1).astype(np.int32)
    for dl in np.unique(cd):  # a depth-d leaf covers 8^(13 - d) bricks
        sel = cd == dl
        w = 1 << (_BRICK_DEPTH - int(dl))
        g = np.stack(np.meshgrid(*[np.arange(w)] * 3, indexing="ij"), -1).reshape(-1, 3)
        base = morton.codes_to_keys(ck[sel]).astype(np.int64) >> 3
        keys.append((base[:, None, :] + g[None]).reshape(-1, 3))
        brick_rows.append(np.repeat(crow[sel], g.shape[0]))
    return (table.reshape(-1), np.concatenate(keys), np.concatenate(brick_rows),
            n_db + uniq.size, n_db)


def _fine_bucket(n: int, minimum: int = 64) -> int:
    """Static size for ``n`` rows of the large work arrays (source table, kernel output): the
    smallest ``q 2^k >= n`` with ``q`` in 4..8 (four steps per octave). Wastes <= 25% instead
    of up to 50% of a power of two, which matters at hundreds of MB (first-touch page faults),
    at the price of more distinct compiled shapes."""
    n = max(int(n), int(minimum), 4)
    k = max(n.bit_length() - 3, 0)
    q = -(-n // (1 << k))
    return q << k


def _brick_lin(k):
    """Brick keys ``(..., 3)`` (each in ``[0, 8192)``) -> one int64 per brick."""
    return (k[..., 0] << 26) | (k[..., 1] << 13) | k[..., 2]


def _plan_dest_bricks(src_bkeys: np.ndarray, T_key) -> np.ndarray:
    """Host: Morton-sorted ``(n, 3)`` int64 keys of destination bricks whose voxel centres may
    map back into a source brick. ``T_key``: ``(R, t_key)`` forward map in key units
    (``u' = R u + t_key``, voxel centres at integer ``u``)."""
    R, t_key = T_key
    if src_bkeys.shape[0] == 0:
        return np.zeros((0, 3), np.int64)
    centre = (src_bkeys.astype(np.float64) * _B + 3.5) @ R.T + t_key
    half = 4.0 * np.abs(R).sum(axis=1) + 1e-3  # image of the brick cube [8b - .5, 8b + 7.5]
    bmin = np.floor_divide(np.ceil(centre - half), _B).astype(np.int64)
    bmax = np.floor_divide(np.floor(centre + half), _B).astype(np.int64)
    lo = np.maximum(bmin.min(axis=0), 0)
    hi = np.minimum(bmax.max(axis=0), _KEY_MAX // _B - 1)
    if np.any(hi < lo):
        return np.zeros((0, 3), np.int64)
    ext = hi - lo + 1
    total = int(np.prod(ext))
    itype = np.int32 if total < 2 ** 31 else np.int64
    # candidates bmin + {0, 1, 2} per axis (an image spans <= 3 bricks), kept where <= bmax
    # and inside the key range; linear index x + ext_x (y + ext_y z), built axis by axis
    q = [(bmin[:, a, None] + np.arange(3) - lo[a]).astype(itype) for a in range(3)]
    ok = [(q[a] <= bmax[:, a, None] - lo[a]) & (q[a] >= 0) & (q[a] < ext[a]) for a in range(3)]
    lin = (q[2][:, :, None, None] * itype(ext[1]) + q[1][:, None, :, None]) * itype(ext[0]) \
        + q[0][:, None, None, :]
    lin = lin[ok[2][:, :, None, None] & ok[1][:, None, :, None] & ok[0][:, None, None, :]]
    if total <= (1 << 28):  # a brick-level bitmap (1 byte per 512 voxels of the bounding box)
        bitmap = np.zeros(total, bool)
        bitmap[lin] = True
        u = np.flatnonzero(bitmap)
    else:
        u = np.unique(lin)
    keys = np.stack([u % ext[0], (u // ext[0]) % ext[1], u // (ext[0] * ext[1])], axis=-1) + lo
    order = np.argsort(morton.keys_to_codes(keys.astype(np.uint64) * _B), kind="stable")
    return keys[order]


# ----------------------------------------------------------------------------- kernel


def _spread3bits(v):
    """Bits (b2 b1 b0) -> (b2 0 0 b1 0 0 b0): one axis of a local Morton index."""
    return (v & 1) | ((v & 2) << 2) | ((v & 4) << 4)


_WINDOW_MARGIN = 0.05  # voxels; covers float32 rounding of the kernel's inverse map


def _dest_windows(dest, R, t_key, bricks, brick_rows, nan_row):
    """Host: each destination brick's source window, 3x3x3 source bricks from ``wb``.

    ``dest (n, 3)`` destination brick keys; ``R, t_key`` the forward map in key units;
    ``bricks``/``brick_rows`` the source bricks and their table rows. Returns ``(wb (n, 3)
    int64, rows (n, 27) int32)``, window brick ``x + 3 y + 9 z`` -> table row (``nan_row``
    where no leaf covers it). Every neighbour key ``k0 + {0, 1}`` of every voxel lies in the
    window: the inverse image of a brick's centres spans <= 7 sqrt(3) < 12.2 voxels per axis,
    so with the margin the neighbours span <= 15 keys from at most 7 into the first brick.
    """
    n = dest.shape[0]
    if n == 0 or bricks.shape[0] == 0:
        return np.zeros((n, 3), np.int64), np.full((n, 27), nan_row, np.int32)
    umin = np.full((n, 3), np.inf)
    for corner in _CORNERS:  # the extremes of an affine map over a cube are at its corners
        k = (dest * _B + 7 * corner).astype(np.float64)
        umin = np.minimum(umin, (k - t_key) @ R)  # R^T (k - t_key), row-wise
    wb = np.floor_divide(np.floor(umin - _WINDOW_MARGIN).astype(np.int64), _B)
    # Window bricks as linear indices into the source bricks' bounding box.
    lo = bricks.min(axis=0)
    ext = bricks.max(axis=0) - lo + 1
    q = [wb[:, a, None] + np.arange(3) - lo[a] for a in range(3)]  # (n, 3) per axis
    inside = [(qa >= 0) & (qa < ext[a]) for a, qa in enumerate(q)]
    lin = (q[2][:, :, None, None] * ext[1] + q[1][:, None, :, None]) * ext[0] + q[0][:, None, None, :]
    ok = inside[2][:, :, None, None] & inside[1][:, None, :, None] & inside[0][:, None, None, :]
    lin, ok = lin.reshape(n, 27), ok.reshape(n, 27)  # window brick x + 3 y + 9 z
    src = ((bricks[:, 2] - lo[2]) * ext[1] + bricks[:, 1] - lo[1]) * ext[0] + bricks[:, 0] - lo[0]
    if np.prod(ext) <= max(1 << 22, 8 * src.size):  # a dense grid of rows (4 B per brick)
        grid = np.full(int(np.prod(ext)), nan_row, np.int32)
        grid[src] = brick_rows
        rows = grid[np.where(ok, lin, 0)]
    else:  # sparse source: binary search in the sorted bricks
        order = np.argsort(src)
        i = np.minimum(np.searchsorted(src[order], lin), src.size - 1)
        ok &= src[order][i] == lin
        rows = brick_rows[order][i]
    return wb, np.where(ok, rows, nan_row).astype(np.int32)


def _resample_chunk(m, table, A, c, K_d, K_s, bkeys, wb, wrows, bvalid, mode):
    """Resample one chunk of destination bricks ``bkeys (B, 3)`` with source windows from
    ``wb (B, 3)`` (brick keys) and window table offsets ``wrows (B * 27,)`` (row * 512): per
    voxel ``(log_odds (B, 512) clamped, known (B, 512))`` in local Morton order, and the number
    of in-range neighbour keys of valid bricks outside their window (0 unless the host's
    window planning is wrong; checked by ``_run``).

    Every per-voxel quantity is a ``(B, 512)`` array per axis or per corner (no trailing axis
    of 3 or 8): XLA's CPU loops then vectorise, and the 8 neighbour reads are 8 flat gathers.
    """
    nb = bkeys.shape[0]
    nan_off = table.shape[0] - _BV  # the table's last row is NaN (unknown)

    def per_axis():
        """Offsets ``f`` (3 x (B, 512) f32) and, per axis ``i`` and bit ``b``, the neighbour
        key ``k0 + b`` packed in one int32: window brick ``q 3^i`` (bits 16+), out-of-window
        flag (bit 13) and local Morton bits (bits 0-8), so a corner sums three of them."""
        # eq. 5.13 in key units, relative to K_s: per brick corner plus per local offset
        # (elementwise, not a matmul, so the rounding does not depend on the chunk size)
        d0 = (bkeys * _B - K_d).astype(jnp.float32)  # (B, 3)
        dl = jnp.asarray(_LOCAL, jnp.float32)  # (512, 3)
        f, packed, misses = [], [], jnp.int32(0)
        for i in range(3):
            u0 = d0[:, 0] * A[i, 0] + d0[:, 1] * A[i, 1] + d0[:, 2] * A[i, 2] + c[i]
            du = dl[:, 0] * A[i, 0] + dl[:, 1] * A[i, 1] + dl[:, 2] * A[i, 2]
            u = u0[:, None] + du[None, :]
            base = jnp.floor(u)
            fi = u - base
            # Snap offsets within float32 noise of a lattice point (exact whole-voxel moves).
            up = fi > 1.0 - _SNAP
            base = jnp.where(up, base + 1.0, base)
            f.append(jnp.where(up | (fi < _SNAP), jnp.float32(0), fi))
            key0 = base.astype(jnp.int32) + K_s[i]
            for k in (key0, key0 + 1):
                q = jnp.right_shift(k, 3) - wb[:, i, None]
                in_range = (k >= 0) & (k < _KEY_MAX)
                outside = (q < 0) | (q > 2)
                bad = ~in_range | outside
                misses += jnp.sum(outside & in_range & bvalid[:, None], dtype=jnp.int32)
                packed.append((jnp.clip(q, 0, 2) * 3 ** i << 16) | (bad.astype(jnp.int32) << 13)
                              | (_spread3bits(k & 7) << i))
        return f, packed, misses

    def nothing():
        return ([jnp.zeros((nb, _BV), jnp.float32)] * 3,
                [jnp.full((nb, _BV), 1 << 13, jnp.int32)] * 6, jnp.int32(0))

    # A conditional's results are materialised: without it XLA's CPU fusion would recompute
    # all the index arithmetic inside each of the 8 gathers and at every use in the blend.
    f, packed, misses = jax.lax.cond(bvalid[0], per_axis, nothing)
    brick0 = (jnp.arange(nb, dtype=jnp.int32) * 27)[:, None]
    vals = []
    for corner in range(8):
        s = packed[corner & 1] + packed[2 + ((corner >> 1) & 1)] + packed[4 + (corner >> 2)]
        row = wrows.at[brick0 + jnp.right_shift(s, 16)].get(mode="promise_in_bounds")
        idx = jnp.where((s & (3 << 13)) != 0, nan_off, row + (s & (_BV - 1)))
        vals.append(table.at[idx].get(mode="promise_in_bounds"))  # in bounds by construction
    known8 = [~jnp.isnan(v) for v in vals]
    _, lo, center_known, exact = _blend(vals, known8, tuple(f), mode)
    lo = jnp.where(jnp.isnan(exact), lo, exact)
    lo = jnp.clip(lo, m.params.clamp_min_log_odds, m.params.clamp_max_log_odds)
    known = center_known & bvalid[:, None]
    return jnp.where(known, lo, jnp.float32(0)), known, misses


def _brick_prune(lo, known):
    """Prune inside each brick (levels 16 -> 13). ``(B, 512)`` -> per voxel
    ``(emit (B, 512) bool, depth (B, 512) int32)``: a voxel emits the leaf it starts.

    A voxel's local Morton index is ``64 a + 8 b + c``: groups of 8 (same ``a, b``) are
    uniform when all known and equal, groups of 64 when their 8 groups are uniform with
    equal values, the brick likewise; each uniform level above a voxel lowers its depth."""
    nb = lo.shape[0]
    l4, k4 = lo.reshape(nb, 8, 8, 8), known.reshape(nb, 8, 8, 8)
    u8 = jnp.all(k4, axis=-1) & jnp.all(l4 == l4[..., :1], axis=-1)  # (B, 8, 8)
    v8 = l4[..., 0]
    u64 = jnp.all(u8, axis=-1) & jnp.all(v8 == v8[..., :1], axis=-1)  # (B, 8)
    u512 = jnp.all(u64, axis=-1) & jnp.all(v8[..., 0] == v8[:, :1, 0], axis=-1)  # (B,)
    u8, u64, u512 = u8[..., None], u64[..., None, None], u512[:, None, None, None]
    depth = _D - u8.astype(jnp.int32) - u64.astype(jnp.int32) - u512.astype(jnp.int32)
    i = jnp.arange(8, dtype=jnp.int32)
    emit = (k4 & ((i == 0) | ~u8) & ((i[:, None] == 0) | ~u64)
            & ((i[:, None, None] == 0) | ~u512))
    return emit.reshape(nb, _BV), jnp.broadcast_to(depth, l4.shape).reshape(nb, _BV)


def _padding_rows(n: int, hi, depth):
    """``n`` padding rows of the kernel's output: ``(code (n, 2), depth (n,), log_odds (n,))``.
    The fill values are traced arguments, so XLA does not constant-fold (and embed) buffers
    of hundreds of MB at compile time."""
    return (jnp.zeros((n, 2), jnp.int32).at[:, 0].set(hi), jnp.full((n,), depth, jnp.int32),
            jnp.zeros((n,), jnp.float32))


@functools.partial(jax.jit, static_argnames=("capacity",))
def _empty_output(hi, depth, *, capacity: int):
    """Empty kernel output buffers of ``capacity`` rows (``hi = SENTINEL_HI``, ``depth = 16``)."""
    return _padding_rows(capacity, hi, depth)


@functools.partial(jax.jit, static_argnames=("capacity",))
def _grow_output(bufs, hi, depth, *, capacity: int):
    """The kernel's output buffers extended with padding rows to ``capacity``."""
    pad = _padding_rows(capacity - bufs[0].shape[0], hi, depth)
    return tuple(jnp.concatenate([b, p]) for b, p in zip(bufs, pad))


@functools.partial(jax.jit, static_argnames=("chunk",), donate_argnums=(11,))
def _transform_kernel(m, table, A, c, K_d, K_s, bkeys, wb, wrows, n_bricks, mode, bufs, offset,
                      start, *, chunk):
    """Loop over chunks of destination bricks from chunk ``start``; append each chunk's
    brick-pruned leaves to ``bufs`` (``_empty_output``, donated) from row ``offset``.

    Stops at the first chunk whose leaves do not fit (nothing of it is committed; its
    partial writes lie past ``offset`` and are overwritten when the caller resumes with
    larger buffers). Returns ``(bufs, offset, next chunk, window misses)``: all chunks are
    done when ``next chunk * chunk >= n_bricks``; ``misses > 0`` is a planning bug (see
    ``_resample_chunk``).
    """
    n_chunks = bkeys.shape[0] // chunk
    cap = bufs[0].shape[0]

    def compute(i):
        bk = jax.lax.dynamic_slice_in_dim(bkeys, i * chunk, chunk)
        w = jax.lax.dynamic_slice_in_dim(wb, i * chunk, chunk)
        wr = jax.lax.dynamic_slice_in_dim(wrows, i * chunk * 27, chunk * 27)
        bvalid = i * chunk + jnp.arange(chunk) < n_bricks
        lo, known, misses = _resample_chunk(m, table, A, c, K_d, K_s, bk, w, wr, bvalid, mode)
        emit, depth = _brick_prune(lo, known)
        return lo, emit, depth, misses

    def skip(i):
        return (jnp.zeros((chunk, _BV), jnp.float32), jnp.zeros((chunk, _BV), bool),
                jnp.full((chunk, _BV), _D, jnp.int32), jnp.int32(0))

    def step(carry):
        (out_code, out_depth, out_lo), offset, i, misses, _ = carry
        # The loop visits valid chunks only; the cond (never false there) stays because a
        # conditional's results are materialised: inlined, XLA fuses the blend into the
        # append's fusions and recomputes it (measured 1.5x slower).
        lo, emit, depth, miss = jax.lax.cond(i * chunk < n_bricks, compute, skip, i)
        bk = jax.lax.dynamic_slice_in_dim(bkeys, i * chunk, chunk)
        bwords = morton.keys_to_words(bk * _B)  # (B, 2); local Morton index fills low 9 bits
        vcode = jnp.stack([jnp.broadcast_to(bwords[:, None, 0], (chunk, _BV)),
                           bwords[:, None, 1] | jnp.arange(_BV, dtype=jnp.int32)[None, :]], -1)
        emit = emit.reshape(-1)
        n_emit = jnp.sum(emit, dtype=jnp.int32)
        # Append the emitted leaves in order: one scatter per array (past capacity: dropped).
        pos = jnp.where(emit, offset + jnp.cumsum(emit, dtype=jnp.int32) - 1, cap)
        out_code = out_code.at[pos].set(vcode.reshape(-1, 2), mode="drop")
        out_depth = out_depth.at[pos].set(depth.reshape(-1), mode="drop")
        out_lo = out_lo.at[pos].set(lo.reshape(-1), mode="drop")
        fits = offset + n_emit <= cap
        return ((out_code, out_depth, out_lo), jnp.where(fits, offset + n_emit, offset),
                jnp.where(fits, i + 1, i), misses + jnp.where(fits, miss, 0), ~fits)

    # A loop of dynamic length over the chunks holding valid bricks: padding chunks cost
    # nothing (a scan over all of them spent ~0.7 ms per padding chunk on the append).
    n_valid = jnp.minimum((n_bricks + chunk - 1) // chunk, n_chunks)
    bufs, offset, nxt, misses, _ = jax.lax.while_loop(
        lambda cr: (cr[2] < n_valid) & ~cr[4], step,
        (bufs, jnp.int32(offset), jnp.int32(start), jnp.int32(0), jnp.bool_(False)))
    return bufs, offset, nxt, misses


def _run_kernel(plan: "_Plan") -> tuple[OccupancyMap, int]:
    """Run the kernel over all destination bricks: ``(map of brick-pruned leaves, count)``.
    When the output buffers fill up, they grow (to the leaves per chunk so far, extrapolated)
    and the kernel resumes at the chunk that did not fit: no chunk is computed twice except
    that one."""
    n_chunks = -(-plan.n_dest_bricks // plan.chunk)
    fills = (jnp.int32(morton.SENTINEL_HI), jnp.int32(_D))
    bufs = _empty_output(*fills, capacity=plan.out_capacity)
    offset, start, misses = 0, 0, 0
    while True:
        bufs, offset, start, miss = _transform_kernel(*plan.args, bufs, offset, start,
                                                      chunk=plan.chunk)
        offset, start, misses = int(offset), int(start), misses + int(miss)
        if start >= n_chunks:
            break
        estimate = offset / max(start, 1) * n_chunks * 1.05 + plan.chunk * _BV
        bufs = _grow_output(bufs, *fills,
                            capacity=_fine_bucket(max(estimate, 1.25 * bufs[0].shape[0])))
    if misses:
        raise RuntimeError(f"transform_map: {misses} interpolation neighbours fell outside "
                           "their planned source window (a bug; please report the transform)")
    m = plan.args[0]
    return OccupancyMap(*bufs, jnp.int32(offset), m.params, m.resolution, m.tree_depth), offset


def _prune_whole_bricks(codes, values):
    """Host: maximal prune of whole-brick leaves ``codes (n,) uint64`` (sorted, all depth
    13) with log-odds ``values (n,)``: eight siblings of equal log-odds (exact float
    equality, as ``tree.prune``) merge into their parent, level by level. A merged node keeps
    its first child's code and value. Returns ``(drop (k,), head (r,), head_depth (r,))``:
    indices of the children that disappear, and of the first children that now stand for a
    coarser node, with its depth."""
    n = codes.size
    depth = np.full(n, _BRICK_DEPTH, np.int32)
    dropped = np.zeros(n, bool)
    row = np.arange(n)  # the first original row under each active node
    c, v = codes, values
    for d in range(_BRICK_DEPTH, 0, -1):
        if c.size < 8:
            break
        shift = np.uint64(3 * (_D - d + 1))
        parent = c >> shift
        start = np.ones(c.size, bool)
        start[1:] = parent[1:] != parent[:-1]
        gid = np.cumsum(start) - 1
        first = np.flatnonzero(start)
        size = np.diff(np.append(first, c.size))
        uniform = np.bincount(gid, weights=v != v[first][gid], minlength=first.size) == 0
        merge = (size == 8) & uniform
        if not merge.any():
            break
        merged = merge[gid]
        dropped[row[merged & ~start]] = True
        keep = first[merge]
        depth[row[keep]] = d - 1
        c, v, row = parent[keep] << shift, v[keep], row[keep]
    head = np.flatnonzero((depth != _BRICK_DEPTH) & ~dropped)
    return np.flatnonzero(dropped), head, depth[head]


_COMPACT_CHUNK = 1 << 16  # rows per step of the in-place compaction


@functools.partial(jax.jit, donate_argnums=(0, 1, 2), static_argnames=("step",))
def _apply_brick_merges(code, depth, log_odds, count, drop, head, head_depth, *,
                        step: int = _COMPACT_CHUNK):
    """In place (the buffers are donated): drop rows ``drop`` (sorted ascending, padded with
    the capacity) of the brick-pruned output ``code (n, 2), depth (n,), log_odds (n,)``
    holding ``count`` rows, and set the depth of rows ``head`` to ``head_depth`` (padding: out
    of range). Returns ``(code, depth, log_odds, new_count)``, order kept.

    Only the rows after the first dropped one move, each by the number of drops before it:
    a loop over chunks of rows reads a chunk, compacts it and writes it back at its new start,
    which is never after its old start, so no unread row is overwritten. A compaction into
    new buffers would page-fault hundreds of MB at millions of leaves. ``step``: rows per
    loop step (static; capped to the largest power of two dividing the capacity)."""
    cap = code.shape[0]
    step = min(step, cap & -cap)  # capacities are q 2^k
    depth = depth.at[head].set(head_depth, mode="drop")
    n_drop = jnp.sum(drop < cap, dtype=jnp.int32)
    fills = (jnp.array([morton.SENTINEL_HI, 0], jnp.int32), jnp.int32(_D), jnp.float32(0))

    def body(k, bufs):
        start = k * step
        local = jnp.where(drop >= start, drop - start, step)  # no negative (wrapping) index
        keep = jnp.ones(step, bool).at[local].set(False, mode="drop")
        pos = jnp.where(keep, jnp.cumsum(keep) - 1, step)
        dst = start - jnp.searchsorted(drop, start).astype(jnp.int32)
        out = []
        for buf, fill in zip(bufs, fills):
            rows = jax.lax.dynamic_slice_in_dim(buf, start, step)
            packed = jnp.full_like(rows, fill).at[pos].set(rows, mode="drop")
            out.append(jax.lax.dynamic_update_slice_in_dim(buf, packed, dst, axis=0))
        return tuple(out)

    first = jnp.where(n_drop > 0, drop[0] // step, 0)
    last = jnp.where(n_drop > 0, (count + step - 1) // step, 0)
    bufs = jax.lax.fori_loop(first, last, body, (code, depth, log_odds))
    new_count = count - n_drop
    stale = jnp.where(jnp.arange(drop.shape[0]) < n_drop,
                      new_count + jnp.arange(drop.shape[0], dtype=jnp.int32), cap)
    bufs = [buf.at[stale].set(fill, mode="drop") for buf, fill in zip(bufs, fills)]
    return (*bufs, new_count)


def _padded(x, dtype, fill):
    """``x`` padded with ``fill`` to a power-of-two length (few compiled shapes)."""
    out = np.full(bucket_capacity(x.size, minimum=64), fill, dtype)
    out[:x.size] = x
    return out


def _key_transform(T, resolution):
    """Forward map in key units: ``u' = R u + t_key`` for voxel-centre coordinates
    ``u = x / res + 32768 - 0.5`` (integer at centres)."""
    R = T[:3, :3]
    o = morton.KEY_OFFSET - 0.5
    t_key = T[:3, 3] / resolution + o - R @ np.full(3, o)
    return R, t_key


class _Plan(NamedTuple):
    """Host planning result of ``transform_map`` (inputs of the jitted kernel)."""

    args: tuple
    chunk: int
    out_capacity: int
    n_dest_bricks: int
    n_dense_bricks: int


def _plan(m: OccupancyMap, T: np.ndarray, method: str, space: str, chunk: int,
          out_capacity: int | None) -> _Plan:
    """Host: destination bricks, the source's brick table and the key-frame constants."""
    R, t_key = _key_transform(T, m.resolution)
    table, bricks, brick_rows, nan_row, n_db = _source_view(m)
    dest = _plan_dest_bricks(bricks, (R, t_key))
    wb, rows = _dest_windows(dest, R, t_key, bricks, brick_rows, nan_row)
    live = np.any(rows != nan_row, axis=1)  # an all-unknown window gives nothing
    dest, wb, rows = dest[live], wb[live], rows[live]
    # Relative coordinates keep float32 precision: u_rel = R^T (k - K_d) + c, with
    # K_s = round(R^T (K_d - t_key)) so that |c| <= 0.5.
    n_b = dest.shape[0]
    K_d = np.round(dest.mean(axis=0) * _B).astype(np.int64) if n_b else np.zeros(3, np.int64)
    u_s = R.T @ (K_d.astype(np.float64) - t_key)
    K_s = np.round(u_s).astype(np.int64)
    c = u_s - K_s
    b_cap = max(bucket_capacity(n_b, minimum=1024), chunk)
    b_cap = int(math.ceil(b_cap / chunk) * chunk)
    bkeys = np.zeros((b_cap, 3), np.int32)
    bkeys[:n_b] = dest
    wbp = np.zeros((b_cap, 3), np.int32)
    wbp[:n_b] = wb
    wrows = np.full((b_cap, 27), nan_row * _BV, np.int32)
    wrows[:n_b] = rows * _BV
    if out_capacity is None:
        out_capacity = _fine_bucket(2 * m.num_leaves + 8 * n_b, minimum=1 << 15)
    args = (m, _to_device(table, m.log_odds), jnp.asarray(R.T, jnp.float32),
            jnp.asarray(c, jnp.float32), jnp.asarray(K_d, jnp.int32), jnp.asarray(K_s, jnp.int32),
            jnp.asarray(bkeys), jnp.asarray(wbp), jnp.asarray(wrows.reshape(-1)), jnp.int32(n_b),
            jnp.int32(_mode_index(method, space)))
    return _Plan(args, chunk, int(out_capacity), n_b, n_db)


def _run(plan: _Plan) -> OccupancyMap:
    """Run the kernel, then prune maximally: leaves finer than a brick are maximal already,
    so only the whole-brick leaves (few) are merged, on the host, and the kernel's output is
    compacted in place on the device."""
    out, total = _run_kernel(plan)
    rows13 = np.flatnonzero(np.asarray(out.depth)[:total] == _BRICK_DEPTH)
    codes = morton.join_codes(np.asarray(out.code)[rows13])
    drop, head, head_depth = _prune_whole_bricks(codes, np.asarray(out.log_odds)[rows13])
    oob = out.capacity  # padding index: dropped by the scatters
    code, depth, log_odds, count = _apply_brick_merges(
        out.code, out.depth, out.log_odds, out.count, _padded(rows13[drop], np.int32, oob),
        _padded(rows13[head], np.int32, oob), _padded(head_depth, np.int32, _D))
    return OccupancyMap(code, depth, log_odds, count, out.params, out.resolution, out.tree_depth)


def transform_map(m: OccupancyMap, T_dst_src, method: str = "trilinear", *,
                  space: str = "probability", chunk_bricks: int = 128,
                  out_capacity: int | None = None) -> OccupancyMap:
    """Alg. 7 (corrected): the map ``m`` of frame ``src`` expressed in frame ``dst``.

    Args:
      m: source map (leaves at any depth).
      T_dst_src: ``(4, 4)`` rigid transform mapping points of ``src`` into ``dst`` (metres).
      method: ``"trilinear"`` (unknown neighbours left out, weights renormalised),
        ``"nearest"`` (value of the source leaf containing ``x_s``) or ``"thesis"``
        (unknown neighbours weigh as probability 0, as Appendix A.2; bugs fixed).
      space: interpolate in ``"probability"`` (thesis) or ``"log_odds"``; ``"thesis"``
        requires ``"probability"``.
      chunk_bricks: destination bricks (8^3 voxels) per loop step (static; a step's work
        arrays take roughly ``chunk_bricks * 512 * 8 * 16`` bytes).
      out_capacity: static output capacity before the final prune; default a guess from the
        leaf and brick counts, grown (the kernel resumes where it stopped) if it fills up.

    Returns a maximally pruned map with the source's resolution and parameters: destination
    voxels (depth 16) whose centre maps back into a known source leaf, log-odds clamped.
    Raises ``ValueError`` for an invalid transform or when the transformed map would leave
    OctoMap's key range.
    """
    _check_choice(method, METHODS, "method")
    _check_choice(space, SPACES, "space")
    if method == "thesis" and space != "probability":
        raise ValueError('method="thesis" interpolates in probability; use space="probability"')
    if chunk_bricks < 1:
        raise ValueError(f"chunk_bricks must be positive, got {chunk_bricks}")
    T = check_rigid_transform(T_dst_src)
    res = m.resolution
    if m.num_leaves == 0:
        return m
    p_min, p_max = transformed_bounds(m, T)
    limit = morton.KEY_OFFSET * res
    if np.any(p_min < -limit) or np.any(p_max > limit):
        raise ValueError(
            f"T_dst_src: the transformed map spans {p_min.round(3).tolist()} .. "
            f"{p_max.round(3).tolist()} m, outside OctoMap's key range +-{limit:g} m at "
            f"resolution {res:g} m")
    plan = _plan(m, T, method, space, int(chunk_bricks), out_capacity)
    out = _run(plan)
    n = out.num_leaves
    cap = bucket_capacity(n)
    if cap < out.capacity:
        out = OccupancyMap(out.code[:cap], out.depth[:cap], out.log_odds[:cap], out.count,
                           out.params, out.resolution, out.tree_depth)
    return out
