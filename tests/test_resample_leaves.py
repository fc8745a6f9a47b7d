"""``transform_map`` on maps with coarse leaves (depths 1-12): cost follows the output's leaves,
values match brute-force references, and the memory budget stops what cannot fit.

References: (a) for right-angle rotations every destination voxel takes its source voxel's value,
so the output is the image of each source leaf (a NumPy permutation of leaf cubes), pruned;
(b) Alg. 7 evaluated voxel by voxel in float64 NumPy (source values found by binary search in
the leaf ranges) on every destination voxel of the transformed bounding box, or on sampled
voxels where the box is too large.
"""

from __future__ import annotations

import numpy as np
import pytest

from octomerge_jax import io, morton, resample, tree
from octomerge_jax import map as mp
from octomerge_jax.budget import MemoryBudgetError, memory_budget

from test_resample import make_T, rot

RES = 0.1
OFF = morton.KEY_OFFSET
L_MIN = float(mp.logit(0.1192))
L_MAX = float(mp.logit(0.971))
CAP = 8192
CORNERS8 = np.array([[c & 1, (c >> 1) & 1, (c >> 2) & 1] for c in range(8)])


def staircase(rng, top: int = 1, fine: bool = True):
    """Leaves at every depth ``top..12`` nested towards the origin: at each depth, 5 of the 8
    children of the node above are leaves (free, a second value, or equal to a neighbour that
    is not a sibling), one is unknown and one is split further; at depth 12 a 16^3 block of
    finest voxels with random values and holes. Returns ``(keys (n, 3) int64, depths, values)``."""
    keys, depths, vals = [], [], []
    node = np.full(3, ((OFF - 1) >> (17 - top)) << (17 - top), np.int64)
    choices = [L_MIN, L_MIN, 0.4, -0.2, L_MAX]
    for d in range(top, 13):
        size = 1 << (16 - d)
        # the child holding key 32767 (next to the origin) is split further
        split = np.full(3, ((OFF - 1) >> (16 - d)) << (16 - d), np.int64)
        for c in range(8):
            child = node + CORNERS8[c] * size
            if np.array_equal(child, split):
                continue
            if c == 3:  # unknown
                continue
            keys.append(child)
            depths.append(d)
            vals.append(np.float32(choices[(c + d) % len(choices)]))
        node = split
    if fine:
        for o in np.stack(np.meshgrid(*[np.arange(16)] * 3, indexing="ij"), -1).reshape(-1, 3):
            if rng.random() < 0.7:
                keys.append(node + o)
                depths.append(16)
                vals.append(np.float32(rng.choice([L_MIN, L_MAX, 0.3, -1.0])))
    return np.array(keys, np.int64), np.array(depths, np.int32), np.array(vals, np.float32)


def to_map(keys, depths, vals, capacity=CAP) -> mp.OccupancyMap:
    m = mp.from_leaves(morton.keys_to_codes(keys.astype(np.uint64)), depths, vals, RES,
                       capacity=capacity)
    return tree.prune(m)


def leaf_ranges(m: mp.OccupancyMap):
    lv = m.leaves()
    span = np.uint64(1) << (np.uint64(3) * (16 - lv.depths).astype(np.uint64))
    return lv.codes, lv.codes + span, lv.log_odds.astype(np.float64)


def lookup(ranges, keys) -> np.ndarray:
    """Values at finest ``keys (..., 3)`` from leaf ranges; NaN where unknown."""
    starts, ends, vals = ranges
    ok = np.all((keys >= 0) & (keys < 2 * OFF), axis=-1)
    codes = morton.keys_to_codes(np.clip(keys, 0, 2 * OFF - 1).astype(np.uint64))
    j = np.searchsorted(starts, codes, side="right") - 1
    jj = np.maximum(j, 0)
    hit = ok & (j >= 0) & (ends[jj] > codes)
    return np.where(hit, vals[jj], np.nan)


def alg7_at(ranges, T, dest, method="trilinear"):
    """Alg. 7 (corrected, float64) at destination keys ``dest (n, 3)``: ``(value (n,), ambiguous
    (n,))``, value NaN where no voxel is made; ambiguous where float32 may pick either voxel."""
    R, t = T[:3, :3], T[:3, 3]
    x_s = ((dest - OFF + 0.5) * RES - t) @ R
    u = x_s / RES - 0.5
    base = np.floor(u)
    f = u - base
    base = base.astype(np.int64) + OFF
    lc = lookup(ranges, base + (f >= 0.5))
    vals = lookup(ranges, base[:, None, :] + CORNERS8)
    known = ~np.isnan(vals)
    vals = np.where(known, vals, 0.0)
    w = np.prod(np.where(CORNERS8 == 1, f[:, None, :], 1 - f[:, None, :]), axis=-1)
    with np.errstate(divide="ignore", invalid="ignore"):
        if method == "nearest":
            v = lc
        else:
            same = np.all(~((w > 0) & known) | (vals == lc[:, None]), axis=1)
            wk = np.where(known, w, 0.0)
            pv = np.sum(wk / (1.0 + np.exp(-vals)), axis=1) / wk.sum(1)
            v = np.where(same, lc, np.log(pv / (1 - pv)))
    v = np.where(np.isnan(lc), np.nan, np.clip(v, L_MIN, L_MAX))
    return v, np.any(np.abs(f - 0.5) < 1e-4, axis=1)


def bbox_keys(m, T, block: int = 1 << 20):
    """Every destination key of the transformed bounding box (plus a voxel), in blocks of about
    ``block`` keys ``(n, 3)`` int64."""
    p_min, p_max = resample.transformed_bounds(m, T)
    lo = np.floor(p_min / RES).astype(np.int64) + OFF - 1
    hi = np.floor(p_max / RES).astype(np.int64) + OFF + 1
    xy = np.stack(np.meshgrid(np.arange(lo[0], hi[0] + 1), np.arange(lo[1], hi[1] + 1),
                              indexing="ij"), -1).reshape(-1, 2)
    step = max(1, block // xy.shape[0])
    for z0 in range(lo[2], hi[2] + 1, step):
        z = np.arange(z0, min(z0 + step, hi[2] + 1))
        yield np.concatenate([np.repeat(xy, z.size, axis=0),
                              np.tile(z, xy.shape[0])[:, None]], axis=1)


def maximal(m) -> bool:
    lv = m.leaves()
    for d in range(1, 17):
        sel = lv.depths == d
        parent = lv.codes[sel] >> np.uint64(3 * (17 - d))
        _, start, size = np.unique(parent, return_index=True, return_counts=True)
        for s in start[size == 8]:
            if np.all(lv.log_odds[sel][s:s + 8] == lv.log_odds[sel][s]):
                return False
    return True


# ----------------------------------------------------------------------------- right angles


def image_reference(keys, depths, vals, T) -> mp.OccupancyMap:
    """A right-angle rotation about the origin plus a whole-leaf shift maps each leaf cube onto
    a destination cube: every destination voxel takes its source voxel's value."""
    R = np.rint(T[:3, :3]).astype(np.int64)
    shift = np.rint(T[:3, 3] / RES).astype(np.int64)
    size = (1 << (16 - depths.astype(np.int64)))[:, None]
    centres = [(keys + CORNERS8[c] * (size - 1)) - OFF for c in range(8)]
    moved = [(2 * c + 1) @ R.T for c in centres]  # twice the centre: integer arithmetic
    lo = (np.min(moved, axis=0) - 1) // 2 + OFF + shift
    out = mp.from_leaves(morton.keys_to_codes(lo.astype(np.uint64)), depths,
                         np.clip(vals, L_MIN, L_MAX), RES, capacity=CAP)
    return tree.prune(out)


@pytest.mark.parametrize("T", [
    make_T(),
    make_T(rot("z", np.pi / 2)),
    make_T(rot("x", np.pi) @ rot("z", -np.pi / 2)),
], ids=["identity", "yaw90", "roll180-yaw-90"])
def test_right_angles_with_leaves_at_depths_1_to_12_match_image(T):
    rng = np.random.default_rng(1)
    keys, depths, vals = staircase(rng)
    m = to_map(keys, depths, vals)
    assert set(np.asarray(m.depth)[:m.num_leaves]) >= set(range(1, 13))
    out = resample.transform_map(m, T)
    ref = image_reference(keys, depths, vals, T)
    assert tree.equal(out, ref)
    # the cost follows the leaves: no more output leaves than source leaves
    assert out.num_leaves <= m.num_leaves
    # and the values agree with Alg. 7 voxel by voxel at sampled keys (all scales)
    dest = sampled_keys(rng, out, 3000)
    ref_v, _ = alg7_at(leaf_ranges(m), T, dest)
    got = lookup(leaf_ranges(out), dest)
    np.testing.assert_array_equal(np.isnan(got), np.isnan(ref_v))
    np.testing.assert_allclose(got[~np.isnan(got)], ref_v[~np.isnan(got)], rtol=0, atol=1e-6)


def sampled_keys(rng, m, n):
    """Finest keys inside and just outside ``m``'s leaves: random points of random leaves,
    at offsets of every scale from their faces."""
    lv = m.leaves()
    keys = morton.codes_to_keys(lv.codes).astype(np.int64)
    size = 1 << (16 - lv.depths.astype(np.int64))
    i = rng.integers(0, keys.shape[0], n)
    frac = rng.random((n, 3))
    pick = rng.random(n) < 0.5  # half near a face: -2..+1 voxels around the min corner
    off = np.where(pick[:, None], rng.integers(-2, 2, (n, 3)), (frac * size[i, None]).astype(np.int64))
    return np.clip(keys[i] + off, 0, 2 * OFF - 1)


# ----------------------------------------------------------------------------- general rotations


def _check_bbox(m, T, method="trilinear"):
    out = resample.transform_map(m, T, method=method)
    src, dst = leaf_ranges(m), leaf_ranges(out)
    n_known = n_amb = n_all = 0
    for dest in bbox_keys(m, T):
        ref, amb = alg7_at(src, T, dest, method)
        got = lookup(dst, dest)
        ok = ~amb
        np.testing.assert_array_equal(np.isnan(got[ok]), np.isnan(ref[ok]))
        known = ok & ~np.isnan(ref)
        # float32 offsets ~200 voxels from the kernel's anchor are good to ~1e-5 voxel, and
        # the logit of a probability blend near saturation changes by ~25 per voxel
        np.testing.assert_allclose(got[known], ref[known], rtol=0, atol=1e-3)
        n_known += np.count_nonzero(~np.isnan(got))
        n_amb += np.count_nonzero(amb)
        n_all += dest.shape[0]
    assert n_amb < 0.002 * n_all
    # nothing outside the box: the output's voxels are exactly the known ones inside it
    lv = out.leaves()
    assert np.sum(8.0 ** (16 - lv.depths)) == n_known
    assert maximal(out)
    return out


@pytest.mark.parametrize("depth", [pytest.param(11, marks=pytest.mark.slow), 12])
def test_coarse_leaves_rotated_match_bruteforce(depth):
    rng = np.random.default_rng(depth)
    keys, depths, vals = staircase(rng, top=depth)
    m = to_map(keys, depths, vals)
    T = make_T(rot("z", 0.61) @ rot("y", -0.23) @ rot("x", 0.17), (0.037, -0.41, 0.113))
    out = _check_bbox(m, T)
    assert np.asarray(out.depth)[:out.num_leaves].min() <= 13  # coarse cells carried over


@pytest.mark.slow
@pytest.mark.parametrize("depth", [10])
@pytest.mark.parametrize("method", ["trilinear", "nearest"])
def test_coarser_leaves_rotated_match_bruteforce(depth, method):
    rng = np.random.default_rng(depth)
    keys, depths, vals = staircase(rng, top=depth)
    m = to_map(keys, depths, vals)
    T = make_T(rot("z", 0.3) @ rot("x", 0.05), (0.13, 0.2, -0.05))
    _check_bbox(m, T, method)


def voxels(keys, depths, vals) -> dict:
    """Leaves (small, any alignment) as ``{finest key: value}``."""
    out = {}
    for k, d, v in zip(keys, depths, vals):
        s = 1 << (16 - int(d))
        g = np.stack(np.meshgrid(*[np.arange(s)] * 3, indexing="ij"), -1).reshape(-1, 3) + k
        out.update(zip(map(tuple, g.tolist()), [float(v)] * g.shape[0]))
    return out


def test_whole_voxel_shift_of_coarse_leaves_is_exact():
    rng = np.random.default_rng(2)
    keys, depths, vals = staircase(rng, top=12)
    m = to_map(keys, depths, vals)
    T = make_T(t=(0.3, -0.2, 0.1))  # 3, -2, 1 voxels
    out = resample.transform_map(m, T)
    lv = out.leaves()
    got = voxels(morton.codes_to_keys(lv.codes).astype(np.int64), lv.depths, lv.log_odds)
    want = voxels(keys + np.array([3, -2, 1]), depths, np.clip(vals, L_MIN, L_MAX))
    assert got == want and maximal(out) and lv.depths.min() <= 13


# ----------------------------------------------------------------------------- budget


def test_rotated_huge_leaves_stop_at_the_budget():
    # free leaves at depth 3 (409.6 m cubes at 0.1 m): a yaw moves their faces off the
    # lattice, so the output needs billions of finest leaves; refused before allocating
    keys, depths, vals = staircase(np.random.default_rng(0), top=3, fine=False)
    m = to_map(keys, depths, vals)
    with memory_budget("256M"), pytest.raises(MemoryBudgetError) as err:
        resample.transform_map(m, make_T(rot("z", 0.3)))
    msg = str(err.value)
    assert "transform_map" in msg and "leaves at 0.1 m" in msg and "\n" not in msg


@pytest.mark.slow
def test_depth1_bt_file_is_tiny_and_merges(tmp_path):
    from octomerge_jax.cli import main

    s = 1 << 15
    keys = np.array([[0, 0, 0], [s, 0, 0], [0, s, 0]], np.int64)
    m = mp.from_leaves(morton.keys_to_codes(keys.astype(np.uint64)), np.full(3, 1),
                       np.full(3, mp.logit(0.3)), RES)
    src = tmp_path / "d1.bt"
    io.save(m, src)
    assert src.stat().st_size < 200
    out = resample.transform_map(m, make_T())
    assert tree.equal(out, m)
    with memory_budget("512M"):
        assert main(["merge", str(src), str(src), str(tmp_path / "o.bt"), "--refine", "none",
                     "-q"]) == 0
    assert io.load(tmp_path / "o.bt").num_leaves == 3


def test_device_merge_of_cells_equals_host_merge(monkeypatch):
    # outputs above HOST_MERGE_MAX leaves join coarse cells and kernel leaves on the device
    rng = np.random.default_rng(3)
    keys, depths, vals = staircase(rng, top=11)
    m = to_map(keys, depths, vals)
    T = make_T(rot("z", 0.4), (0.05, 0.02, 0.0))
    host = resample.transform_map(m, T)
    monkeypatch.setattr(resample._merge, "HOST_MERGE_MAX", 0)
    device = resample.transform_map(m, T)
    assert tree.equal(host, device) and maximal(device)
    assert np.asarray(host.depth)[:host.num_leaves].min() <= 13
