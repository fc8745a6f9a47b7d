"""insert_point_cloud vs OctoMap's insertPointCloud (pyoctomap) and hand-checked rays."""

from __future__ import annotations

import numpy as np
import pytest

from octomerge_jax import insert, morton, tree
from octomerge_jax.map import empty
from octomerge_jax.sim import DepthCamera, lab_room, poses_along_path, scan

pyoctomap = pytest.importorskip("pyoctomap")


def _finest(keys, depths, values):
    """Expand leaves (min-corner keys, depths) to a dict finest-code -> value (small maps)."""
    keys = np.asarray(keys, np.int64).reshape(-1, 3)
    depths, values = np.asarray(depths), np.asarray(values, np.float32)
    codes, vals = [], []
    for d in np.unique(depths):
        sel = depths == d
        r = np.arange(1 << (16 - int(d)))
        off = np.stack(np.meshgrid(r, r, r, indexing="ij"), -1).reshape(-1, 3)
        g = (keys[sel][:, None, :] + off[None]).reshape(-1, 3)
        codes.append(morton.keys_to_codes(g.astype(np.uint16)))
        vals.append(np.repeat(values[sel], len(off)))
    if not codes:
        return {}
    return dict(zip(np.concatenate(codes).tolist(), np.concatenate(vals).tolist()))


def _ours(m):
    lv = m.leaves()
    return _finest(lv.keys, lv.depths, lv.log_odds)


def _octomap(t, res):
    keys, depths, vals = [], [], []
    for it in t.begin_leafs():
        c = np.asarray(it.getCoordinate(), np.float64)
        size = it.getSize()
        keys.append(morton.coords_to_keys(c - size / 2 + res / 2, res))
        depths.append(it.getDepth())
        vals.append(t.search(c).getLogOdds())
    return _finest(keys, depths, vals)


def _compare(ours, ref):
    """(occupied agreement, free agreement, max |log-odds diff| on common voxels) as Jaccard."""
    occ_o = {k for k, v in ours.items() if v >= 0}
    occ_r = {k for k, v in ref.items() if v >= 0}
    free_o = set(ours) - occ_o
    free_r = set(ref) - occ_r
    common = set(ours) & set(ref)
    diff = max((abs(ours[k] - ref[k]) for k in common), default=0.0)
    return (len(occ_o & occ_r) / max(len(occ_o | occ_r), 1),
            len(free_o & free_r) / max(len(free_o | free_r), 1), diff, common)


@pytest.fixture(scope="module")
def lab_scans():
    scene = lab_room(seed=3)
    poses = poses_along_path(scene.paths[0], 0.9, scene.sensor_height, scene.targets[0], True)[:3]
    cam = DepthCamera(width=48, height=36)
    clouds = scan(cam, scene.triangles, poses, seed=1)
    world = [(c.astype(np.float64) @ P[:3, :3].T + P[:3, 3]).astype(np.float32) for c, P in zip(clouds, poses)]
    return world, poses[:, :3, 3].astype(np.float32)


@pytest.mark.parametrize("max_range", [-1.0, pytest.param(2.5, marks=pytest.mark.slow)])
def test_matches_octomap_on_lab_scans(lab_scans, max_range):
    res = 0.05
    clouds, origins = lab_scans
    m = empty(res)
    t = pyoctomap.OcTree(res)
    for pts, o in zip(clouds, origins):
        m = insert.insert_point_cloud(m, pts, o, max_range)
        t.insertPointCloud(pts.astype(np.float64), o.astype(np.float64), max_range)
    occ, free, diff, common = _compare(_ours(m), _octomap(t, res))
    # measured: 1.0 / >= 0.9998 (differences are float32-vs-double DDA ties)
    assert occ >= 0.999, occ
    assert free >= 0.998, free
    assert len(common) > 10000
    assert diff == 0.0  # identical log-odds (float32) wherever both know a voxel


def test_single_ray_keys():
    """A ray along +x from a voxel centre: origin voxel and the 9 after it free, end occupied."""
    res = 0.1
    o = np.array([0.05, 0.05, 0.05], np.float32)
    p = np.array([[1.05, 0.05, 0.05]], np.float32)
    upd = insert.compute_update(p, o, res)
    n = int(upd.count)
    keys = morton.codes_to_keys(morton.join_codes(np.asarray(upd.words[:n])))
    occ = np.asarray(upd.occupied[:n])
    assert n == 11
    assert sorted(keys[~occ][:, 0].tolist()) == list(range(32768, 32778))
    assert keys[occ].tolist() == [[32778, 32768, 32768]]


def test_occupied_wins_and_max_range():
    res = 0.1
    o = np.zeros(3, np.float32)
    # ray 1 ends at x=0.55 (voxel 5); ray 2 passes through that voxel to x=1.05
    pts = np.array([[0.55, 0.05, 0.05], [1.05, 0.05, 0.05]], np.float32)
    m = insert.insert_point_cloud(empty(res), pts, o)
    lo, known = tree.lookup(m, np.array([[0.55, 0.05, 0.05], [0.35, 0.05, 0.05], [1.05, 0.05, 0.05]]))
    hit, miss = float(m.params.hit_log_odds), float(m.params.miss_log_odds)
    assert np.all(np.asarray(known))
    np.testing.assert_array_equal(np.asarray(lo), np.float32([hit, miss, hit]))
    # max range 0.8: ray 2 is cut, its end is not a hit and nothing past 0.8 m is touched
    m2 = insert.insert_point_cloud(empty(res), pts, o, max_range=0.8)
    # (the cut end 0.8 m lands in float32 just below 0.8: voxel 7 is the end voxel, as in OctoMap)
    q = np.array([[0.55, 0.05, 0.05], [1.05, 0.05, 0.05], [0.65, 0.05, 0.05], [0.75, 0.05, 0.05]])
    lo2, known2 = tree.lookup(m2, q)
    assert np.asarray(known2).tolist() == [True, False, True, False]
    assert float(lo2[0]) == np.float32(hit) and float(lo2[2]) == np.float32(miss)
    t = pyoctomap.OcTree(res)
    t.insertPointCloud(pts.astype(np.float64), o.astype(np.float64), 0.8)
    assert [t.search(p) is not None for p in q] == [True, False, True, False]


def test_repeated_scans_clamp():
    res = 0.1
    pts = np.array([[0.55, 0.05, 0.05]], np.float32)
    m = empty(res)
    for _ in range(8):
        m = insert.insert_point_cloud(m, pts, np.zeros(3, np.float32))
    lo, _ = tree.lookup(m, pts)
    assert float(lo[0]) == np.float32(m.params.clamp_max_log_odds)
    lo, _ = tree.lookup(m, np.array([[0.25, 0.05, 0.05]]))
    expected = np.float32(0.0)
    for _ in range(8):
        expected = np.float32(max(expected + np.float32(m.params.miss_log_odds),
                                  np.float32(m.params.clamp_min_log_odds)))
    assert float(lo[0]) == expected


def test_batched_equals_sequential(lab_scans):
    """Batches of two scans give the map of inserting them one by one (the settings of
    ``test_matches_octomap_on_lab_scans``, whose sequential kernels this reuses)."""
    clouds, origins = lab_scans
    res = 0.05
    seq = empty(res)
    for pts, o in zip(clouds, origins):
        seq = insert.insert_point_cloud(seq, pts, o)
    bat = insert.insert_point_clouds(empty(res), clouds, origins, batch_size=2)
    assert tree.equal(seq, bat)


def test_no_recompile_same_bucket():
    rng = np.random.default_rng(0)
    res = 0.1

    def cloud():
        d = rng.normal(size=(700, 3))
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        return (d * rng.uniform(0.5, 2.0, (700, 1))).astype(np.float32)

    plan = insert.CapacityPlan(points=1024, bricks=4096, marked=1 << 15, marked_bricks=1024)
    insert.compute_update(cloud(), np.zeros(3), res, plan=plan)
    traces, extracts = insert._trace.programs(), insert._extract.programs()
    insert.compute_update(cloud(), np.array([0.01, 0.02, 0.0]), res, plan=plan)
    assert insert._trace.programs() == traces
    assert insert._extract.programs() == extracts


def test_a_shared_plan_compiles_the_tree_updates_once_per_run(lab_scans):
    """Maps of one run sharing a ``CapacityPlan`` (as the two robots of ``sim.make_two_robot_maps``
    do): the later map starts at the capacity and work sizes the earlier one reached, so its
    updates compile nothing; its leaves are those of inserting without a plan. With the run's
    plan a map keeps the headroom its updates grew with; without one it is trimmed off."""
    clouds, origins = lab_scans
    res = 0.05
    plan = insert.CapacityPlan()
    first = insert.insert_point_clouds(empty(res), clouds, origins, batch_size=1, plan=plan)
    assert first.capacity == plan.leaves > insert.bucket_capacity(first.num_leaves)
    programs = (tree._apply_updates.programs(), tree._plan_splits.programs())
    second = insert.insert_point_clouds(empty(res), clouds, origins, batch_size=1, plan=plan)
    assert (tree._apply_updates.programs(), tree._plan_splits.programs()) == programs
    assert tree.equal(second, first) and second.capacity == first.capacity
    alone = insert.insert_point_clouds(empty(res), clouds, origins, batch_size=2)  # test_batched_equals_sequential's
    assert tree.equal(first, alone) and alone.capacity == insert.bucket_capacity(alone.num_leaves)
    trimmed = first.trimmed()  # the run's end
    assert tree.equal(trimmed, first) and trimmed.capacity == alone.capacity and alone.trimmed() is alone


def test_bad_arguments():
    with pytest.raises(ValueError, match="points"):
        insert.compute_update(np.zeros((4, 2)), np.zeros(3), 0.1)
    with pytest.raises(ValueError, match="sensor_origin"):
        insert.compute_update(np.zeros((4, 3)), np.array([1e6, 0, 0]), 0.1)
    with pytest.raises(ValueError, match="sensor_origin"):
        insert.compute_update(np.zeros((4, 3)), np.array([np.nan, 0, 0]), 0.1)
    # empty and all-NaN clouds insert nothing
    m = insert.insert_point_cloud(empty(0.1), np.full((3, 3), np.nan), np.zeros(3))
    assert m.num_leaves == 0
