"""``OccupancyMap``: an OctoMap occupancy octree as flat, Morton-sorted leaf arrays.

A map is its leaves only (thesis eq. 5.1-5.3: a set of leaf nodes with log-odds), sorted by
the Morton code of each leaf's minimum-corner finest key (see ``morton.py``). A leaf at depth
``d`` covers the Morton interval ``[code, code + 8^(16-d))``; valid leaves are disjoint.
Arrays are padded to a power-of-two **capacity** so maps of similar size share one compiled
function and stack under ``vmap``; rows at and past ``count`` are padding (sentinel code that
sorts last, depth 16, log-odds 0).
"""

from __future__ import annotations

import contextlib
import contextvars
import dataclasses
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from . import morton
from ._ops import MIN_CAPACITY, bucket_capacity

__all__ = [
    "OccupancyParams",
    "OccupancyMap",
    "Leaves",
    "bucket_capacity",
    "logit",
    "probability",
    "empty",
    "from_leaves",
    "from_words",
    "leaves_cache",
    "MIN_CAPACITY",
]

def logit(p) -> np.float32:
    """OctoMap ``logodds(p) = (float) ln(p / (1 - p))``."""
    p = np.float64(p)
    return np.float32(np.log(p / (1.0 - p)))


def probability(log_odds):
    """OctoMap ``probability(l) = 1 - 1 / (1 + exp(l))`` (works on NumPy and JAX arrays)."""
    xp = jnp if isinstance(log_odds, jax.Array) else np
    return 1.0 - 1.0 / (1.0 + xp.exp(log_odds))


_LEAVES_CACHE: contextvars.ContextVar = contextvars.ContextVar("octomerge_leaves_cache", default=None)


@contextlib.contextmanager
def leaves_cache():
    """While inside, ``OccupancyMap.leaves()`` of this thread / task computes each map's host
    leaves once and returns the same read-only arrays again. The maps and their leaves are held
    until the block ends; nested blocks share the outer cache (``docs/design.md``,
    "Host leaves once per registration")."""
    if _LEAVES_CACHE.get() is not None:
        yield
        return
    token = _LEAVES_CACHE.set({})
    try:
        yield
    finally:
        _LEAVES_CACHE.reset(token)


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class OccupancyParams:
    """Sensor-model and clamping parameters, stored as float32 log-odds like OctoMap.

    Traced leaves (not static), so one compiled function serves every setting and they can be
    differentiated. Defaults are OctoMap's: prob_hit 0.7, prob_miss 0.4, clamping
    0.1192 / 0.971, occupancy threshold 0.5.
    """

    hit_log_odds: jax.Array | float = logit(0.7)
    miss_log_odds: jax.Array | float = logit(0.4)
    clamp_min_log_odds: jax.Array | float = logit(0.1192)
    clamp_max_log_odds: jax.Array | float = logit(0.971)
    occupancy_threshold_log_odds: jax.Array | float = logit(0.5)

    @classmethod
    def from_probabilities(
        cls,
        prob_hit: float = 0.7,
        prob_miss: float = 0.4,
        clamp_min: float = 0.1192,
        clamp_max: float = 0.971,
        occupancy_threshold: float = 0.5,
    ) -> "OccupancyParams":
        for name, p in dict(prob_hit=prob_hit, prob_miss=prob_miss, clamp_min=clamp_min,
                            clamp_max=clamp_max, occupancy_threshold=occupancy_threshold).items():
            if not 0.0 < float(p) < 1.0:
                raise ValueError(f"{name} must be a probability in (0, 1), got {p!r}")
        if not clamp_min <= clamp_max:
            raise ValueError(f"clamp_min {clamp_min} must not exceed clamp_max {clamp_max}")
        return cls(logit(prob_hit), logit(prob_miss), logit(clamp_min), logit(clamp_max),
                   logit(occupancy_threshold))

    @property
    def occupancy_threshold_host(self) -> np.float32:
        """The occupancy threshold [log-odds] as a host ``np.float32``: host comparisons with
        float32 log-odds exactly as on the device, without a jitted comparison per leaf count."""
        return np.float32(np.asarray(self.occupancy_threshold_log_odds))

    def host(self) -> dict[str, float]:
        """The parameters as Python floats (log-odds), for reports and I/O."""
        return {f.name: float(np.asarray(getattr(self, f.name))) for f in dataclasses.fields(self)}


class Leaves(NamedTuple):
    """Valid leaves of a map on the host, in Morton order (``OccupancyMap.leaves()``)."""

    centers: np.ndarray  # (n, 3) float64, metres, as OctoMap's keyToCoord(key, depth)
    sizes: np.ndarray  # (n,) float64, metres
    depths: np.ndarray  # (n,) int32, 0..16
    log_odds: np.ndarray  # (n,) float32
    codes: np.ndarray  # (n,) uint64, Morton code of the min-corner finest key
    keys: np.ndarray  # (n, 3) uint16, min-corner finest key


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class OccupancyMap:
    """An occupancy octree as sorted leaf arrays (a pytree).

    Array fields (capacity ``C``):
      - ``code``: ``(C, 2)`` int32, Morton code words (hi, lo) of each leaf's min-corner
        finest key (``morton.py``); padding rows hold ``(SENTINEL_HI, 0)`` and sort last.
      - ``depth``: ``(C,)`` int32, 0..16 (16 = one voxel of ``resolution``).
      - ``log_odds``: ``(C,)`` float32 occupancy log-odds.
      - ``count``: ``()`` int32, number of valid rows.
      - ``params``: ``OccupancyParams`` (traced).
    Static: ``resolution`` (metres), ``tree_depth`` (16, OctoMap's default).
    """

    code: jax.Array
    depth: jax.Array
    log_odds: jax.Array
    count: jax.Array
    params: OccupancyParams
    resolution: float = dataclasses.field(metadata=dict(static=True), default=0.1)
    tree_depth: int = dataclasses.field(metadata=dict(static=True), default=morton.TREE_DEPTH)

    @property
    def capacity(self) -> int:
        return int(self.depth.shape[-1])

    @property
    def num_leaves(self) -> int:
        """Number of valid leaves (host int)."""
        return int(self.count)

    def valid_mask(self) -> jax.Array:
        """``(C,)`` bool: rows that hold a leaf."""
        return jnp.arange(self.capacity) < self.count

    def is_occupied(self) -> jax.Array:
        """``(C,)`` bool: valid leaves with ``log_odds >= threshold`` (OctoMap ``isNodeOccupied``)."""
        return self.valid_mask() & (self.log_odds >= self.params.occupancy_threshold_log_odds)

    def is_free(self) -> jax.Array:
        """``(C,)`` bool: valid leaves below the occupancy threshold."""
        return self.valid_mask() & (self.log_odds < self.params.occupancy_threshold_log_odds)

    def leaves(self) -> Leaves:
        """The valid leaves as NumPy arrays in Morton order (inside ``leaves_cache``: computed
        once per map, read-only)."""
        cache = _LEAVES_CACHE.get()
        if cache is None:
            return self._host_leaves()
        held = cache.get(id(self))
        if held is None or held[0] is not self:
            leaves = self._host_leaves()
            for a in leaves:
                a.flags.writeable = False
            held = cache[id(self)] = (self, leaves)
        return held[1]

    def _host_leaves(self) -> Leaves:
        n = self.num_leaves
        # slice on the host: a device slice would compile once per leaf count
        codes = morton.join_codes(np.asarray(self.code)[:n])
        depths = np.asarray(self.depth)[:n].astype(np.int32)
        keys = morton.codes_to_keys(codes)
        return Leaves(
            centers=morton.keys_to_coords(keys, self.resolution, depths),
            sizes=morton.node_size(depths, self.resolution),
            depths=depths,
            log_odds=np.asarray(self.log_odds)[:n].astype(np.float32),
            codes=codes,
            keys=keys,
        )

    def with_capacity(self, capacity: int) -> "OccupancyMap":
        """The same map padded (or trimmed to its count) to ``capacity`` rows."""
        n = self.num_leaves
        if capacity < n:
            raise ValueError(f"capacity {capacity} is smaller than the map's {n} leaves")
        return from_words(np.asarray(self.code)[:n], np.asarray(self.depth)[:n],
                          np.asarray(self.log_odds)[:n], self.resolution, self.params, capacity)

    def trimmed(self, minimum: int = 0) -> "OccupancyMap":
        """The same map at the capacity ``max(minimum, bucket_capacity(num_leaves))``: itself
        when that is not smaller than its own (padding rows dropped on the host otherwise)."""
        capacity = max(int(minimum), bucket_capacity(self.num_leaves))
        return self.with_capacity(capacity) if capacity < self.capacity else self

    def __repr__(self) -> str:  # the default would print whole arrays
        try:
            n = self.num_leaves
        except Exception:  # traced
            n = "?"
        return (f"OccupancyMap(resolution={self.resolution:g}, leaves={n}, "
                f"capacity={self.capacity})")


def _check_resolution(resolution) -> float:
    r = float(resolution)
    if not (math.isfinite(r) and r > 0):
        raise ValueError(f"resolution must be a positive finite number of metres, got {resolution!r}")
    return r


def from_words(words, depths, log_odds, resolution, params=None, capacity=None) -> OccupancyMap:
    """A map from sorted leaves given as two-word codes ``words (n, 2) int32`` (``morton.split_codes``),
    ``depths (n,)``, ``log_odds (n,)``, padded to ``capacity`` (default ``bucket_capacity(n)``).
    Raises ``ValueError`` if ``capacity < n`` or the resolution is not a positive number of metres."""
    n = int(words.shape[0])
    cap = bucket_capacity(n) if capacity is None else int(capacity)
    if cap < n:
        raise ValueError(f"capacity {cap} is smaller than the {n} leaves")
    code = np.zeros((cap, 2), np.int32)
    code[:, 0] = morton.SENTINEL_HI
    code[:n] = words
    depth = np.full((cap,), morton.TREE_DEPTH, np.int32)
    depth[:n] = depths
    lo = np.zeros((cap,), np.float32)
    lo[:n] = log_odds
    return OccupancyMap(
        code=jax.device_put(code),
        depth=jax.device_put(depth),
        log_odds=jax.device_put(lo),
        count=jax.device_put(np.int32(n)),
        params=params if params is not None else OccupancyParams(),
        resolution=_check_resolution(resolution),
    )


def empty(resolution: float, params: OccupancyParams | None = None,
          capacity: int | None = None) -> OccupancyMap:
    """A map with no leaves (everything unknown)."""
    return from_words(np.zeros((0, 2), np.int32), np.zeros(0, np.int32), np.zeros(0, np.float32),
                      resolution, params, capacity)


def from_leaves(codes, depths, log_odds, resolution: float,
                params: OccupancyParams | None = None, capacity: int | None = None,
                *, check: bool = True) -> OccupancyMap:
    """Build a map from host leaf arrays: ``codes (n,)`` uint64 min-corner Morton codes,
    ``depths (n,)`` 0..16, ``log_odds (n,)``. Leaves are sorted by code here.

    With ``check`` (default) raises ``ValueError`` if a code is not aligned to its depth or
    two leaves overlap.
    """
    codes = np.asarray(codes, dtype=np.uint64).reshape(-1)
    depths = np.asarray(depths).astype(np.int32).reshape(-1)
    log_odds = np.asarray(log_odds, dtype=np.float32).reshape(-1)
    if not (codes.shape == depths.shape == log_odds.shape):
        raise ValueError(f"codes, depths and log_odds must have one length, got "
                         f"{codes.shape}, {depths.shape}, {log_odds.shape}")
    order = np.argsort(codes, kind="stable")
    codes, depths, log_odds = codes[order], depths[order], log_odds[order]
    if check and codes.size:
        if depths.min() < 0 or depths.max() > morton.TREE_DEPTH:
            raise ValueError("depths must lie in 0..16")
        span = np.uint64(1) << (np.uint64(3) * (morton.TREE_DEPTH - depths).astype(np.uint64))
        if np.any(codes & (span - np.uint64(1))):
            raise ValueError("a leaf code is not aligned to its depth (not a min-corner code)")
        if codes.max() >= (np.uint64(1) << np.uint64(48)):
            raise ValueError("a leaf code exceeds 48 bits")
        if np.any(codes[:-1] + span[:-1] > codes[1:]):
            raise ValueError("leaves overlap: each volume must be covered by at most one leaf")
    return from_words(morton.split_codes(codes), depths, log_odds, resolution, params, capacity)
