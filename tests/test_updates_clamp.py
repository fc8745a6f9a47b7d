"""OctoMap's early return at the clamp in voxel updates (``OccupancyOcTreeBase::updateNode``:
a hit on a node already at or above ``clamp_max`` (a miss at or below ``clamp_min``) returns
without touching it), compared bit for bit with pyoctomap through the public
``om.update_points`` / ``om.apply_voxel_updates``."""

from __future__ import annotations

import numpy as np
import pyoctomap

import octomerge_jax as om

RES = 0.1
# three voxels near the origin (centres of depth-16 cells)
VOXELS = np.array([[0.05, 0.05, 0.05], [0.15, -0.25, 0.35], [-0.45, 0.05, -0.15]])


def _octomap_value(ot, p):
    node = ot.search(np.asarray(p, np.float64))
    return None if node is None else np.float32(node.getLogOdds())


def _om_value(m, p):
    v, known = om.lookup(m, np.asarray(p, np.float32))
    return np.float32(v) if bool(known) else None


def _sequence():
    """(voxel index, occupied) rows: voxel 0 hit up to and past clamp_max then missed, voxel 1
    missed down to and past clamp_min then hit, voxel 2 alternating around the clamps."""
    rows = [(0, True)] * 7 + [(0, False), (0, True), (0, True), (0, False)]
    rows += [(1, False)] * 8 + [(1, True), (1, False), (1, False), (1, True)]
    rows += [(2, True)] * 5 + [(2, False)] * 2 + [(2, True)] * 3 + [(2, False)] * 9 + [(2, True)]
    # interleave the three voxels (row order matters only within one voxel)
    by = [[r for r in rows if r[0] == k] for k in range(3)]
    out = []
    while any(by):
        for b in by:
            if b:
                out.append(b.pop(0))
    return out


def test_update_points_reaches_the_clamps_as_octomap_does():
    seq = _sequence()
    ot = pyoctomap.OcTree(RES)
    m = om.empty(RES)
    hi = np.float32(ot.getClampingThresMaxLog())
    lo = np.float32(ot.getClampingThresMinLog())
    seen_hi = seen_lo = False
    # one call per update: every intermediate value equals OctoMap's
    for k, occ in seq:
        ot.updateNode(VOXELS[k], bool(occ))
        m = om.update_points(m, VOXELS[k], occ)
        for j in range(3):
            assert _om_value(m, VOXELS[j]) == _octomap_value(ot, VOXELS[j]), (k, occ, j)
        seen_hi |= _om_value(m, VOXELS[k]) == hi
        seen_lo |= _om_value(m, VOXELS[k]) == lo
    assert seen_hi and seen_lo  # the sequence really reaches both clamps
    # voxel 0 ends one miss below clamp_max: (clamp_max + miss) in float32
    assert _octomap_value(ot, VOXELS[0]) == np.float32(hi + np.float32(ot.getProbMissLog()))
    # the whole sequence in one call (rows in order for repeated voxels) gives the same map
    pts = VOXELS[[k for k, _ in seq]]
    occ = np.array([o for _, o in seq])
    m_all = om.update_points(om.empty(RES), pts, occ)
    for j in range(3):
        assert _om_value(m_all, VOXELS[j]) == _octomap_value(ot, VOXELS[j])
    assert m_all.num_leaves == ot.getNumLeafNodes()


def test_early_return_keeps_a_value_beyond_lowered_clamps():
    """A node at the default clamp stays there on a further hit after clamp_max is lowered
    (OctoMap returns early: no re-clamp), and the next miss goes down from it, clamped."""
    ot = pyoctomap.OcTree(RES)
    for _ in range(7):
        ot.updateNode(VOXELS[0], True)
        ot.updateNode(VOXELS[1], False)
    m = om.update_points(om.empty(RES), np.repeat(VOXELS[:2], 7, axis=0), np.repeat([True, False], 7))
    ot.setClampingThresMax(0.9)
    ot.setClampingThresMin(0.2)
    params = om.OccupancyParams.from_probabilities(clamp_min=0.2, clamp_max=0.9)
    L = m.leaves()
    m = om.from_leaves(L.codes, L.depths, L.log_odds, RES, params=params)
    top, bottom = _om_value(m, VOXELS[0]), _om_value(m, VOXELS[1])
    assert top > params.clamp_max_log_odds and bottom < params.clamp_min_log_odds
    steps = [(0, True), (1, False), (0, True), (1, False), (0, False), (1, True), (0, False), (1, True),
             (0, True)]
    for i, (k, occ) in enumerate(steps):
        ot.updateNode(VOXELS[k], occ)
        m = om.update_points(m, VOXELS[k], occ)
        got = (_om_value(m, VOXELS[0]), _om_value(m, VOXELS[1]))
        assert got == (_octomap_value(ot, VOXELS[0]), _octomap_value(ot, VOXELS[1])), i
        if i < 4:  # hits at the top / misses at the bottom: untouched, beyond the new clamps
            assert got == (top, bottom), i
        if i == 4:  # a miss goes down from the old clamp and is clamped to the new clamp_max
            assert got[0] == np.float32(params.clamp_max_log_odds)
        if i == 5:  # a hit goes up from the old clamp_min (inside the new range: no clamp)
            assert got[1] == np.float32(bottom + np.float32(params.hit_log_odds))


def test_apply_voxel_updates_clamps_per_update_in_row_order():
    """Arbitrary deltas on one voxel: each added then clamped, with the early return."""
    ot = pyoctomap.OcTree(RES)
    deltas = np.float32([2.0, 2.0, 0.5, -0.3, 1.0, -6.0, -1.0, -0.5, 0.25, 4.0, -0.1])
    p = VOXELS[0]
    for d in deltas:
        ot.updateNode(p, float(d))
    # the voxel's words from a one-voxel map; it starts known at 0, as a new OctoMap node
    base = om.update_points(om.empty(RES), p, True)
    start = om.from_leaves(base.leaves().codes, base.leaves().depths, [0.0], RES)
    words = np.asarray(base.code)[:1]
    rows = np.repeat(words, 16, axis=0)  # 16 rows (padded: one compilation for every prefix)
    padded = np.zeros(16, np.float32)
    padded[: deltas.size] = deltas
    out = om.apply_voxel_updates(start, rows, padded, np.arange(16) < deltas.size)
    assert _om_value(out, p) == _octomap_value(ot, p)
    # the running clamp matters: the plain sum clamped once differs
    hi = np.float32(ot.getClampingThresMaxLog())
    lo = np.float32(ot.getClampingThresMinLog())
    assert _om_value(out, p) != np.clip(np.sum(deltas), lo, hi)
    # and prefixes of the rows give OctoMap's intermediate values
    ot2 = pyoctomap.OcTree(RES)
    for n, d in enumerate(deltas, start=1):
        ot2.updateNode(p, float(d))
        part = om.apply_voxel_updates(start, rows, padded, np.arange(16) < n)
        assert _om_value(part, p) == _octomap_value(ot2, p), n
