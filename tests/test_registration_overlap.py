"""Overlap extraction (Alg. 2): the thesis bbox vs the voxel-radius method under roll/pitch."""

import numpy as np
import pytest

from octomerge_jax.registration import overlap
from octomerge_jax.sim import scene_pair
from helpers import xyz_rpy64

RES = 0.4


@pytest.fixture(scope="module")
def flat_scene():
    # a low sensor (world z <= 1 m): thin maps, where the thesis saw bbox extraction fail
    return scene_pair(RES, z_max=1.0)


def _brute_bbox(p1, p2, T, margin):
    w = p2 @ T[:3, :3].T + T[:3, 3]
    lo, hi = p1.min(0), p1.max(0)
    m2 = np.all((w > lo) & (w < hi), axis=1)
    lo2, hi2 = w[m2].min(0) - margin, w[m2].max(0) + margin
    m1 = np.all((p1 > lo2) & (p1 < hi2), axis=1)
    return m1, m2


def _brute_voxel(p1, p2, T, radius):
    w = p2 @ T[:3, :3].T + T[:3, 3]
    D = ((w[:, None, :] - p1[None]) ** 2).sum(-1)
    return (D <= radius ** 2).any(0), (D <= radius ** 2).any(1)


def test_bbox_matches_appendix_a1_and_voxel_matches_brute_force(flat_scene):
    p1, p2, T12 = flat_scene
    T = xyz_rpy64(0.3, 0.0, 0.0, 0.0, 0.0, 0.1) @ T12
    o = overlap(p1, p2, T, "bbox", margin=1.0)
    m1, m2 = _brute_bbox(p1, p2, T, 1.0)
    # float32 vs float64 may flip points lying exactly on a bbox face
    assert np.mean(np.asarray(o.mask_1) != m1) < 0.01 and np.mean(np.asarray(o.mask_2) != m2) < 0.01
    v = overlap(p1, p2, T, "voxel", radius=0.6, cell_capacity=64)
    b1, b2 = _brute_voxel(p1, p2, T, 0.6)
    assert np.mean(np.asarray(v.mask_1) != b1) < 0.005 and np.mean(np.asarray(v.mask_2) != b2) < 0.005
    assert int(v.count_1) == int(np.asarray(v.mask_1).sum())
    with pytest.raises(ValueError, match="method"):
        overlap(p1, p2, T, "sphere")
    with pytest.raises(ValueError, match="T_1_2"):
        overlap(p1, p2, np.eye(3))


@pytest.mark.parametrize("rpy", [(0.0, -0.1, 0.0), (-0.1, -0.1, 0.0)])
def test_voxel_keeps_the_common_volume_where_bbox_loses_it(flat_scene, rpy):
    """Table 7.1 rows 13/14: roll/pitch errors tilt map 2 out of map 1's thin z-range."""
    p1, p2, T12 = flat_scene
    T = xyz_rpy64(0.0, 0.0, 0.0, *rpy) @ T12
    b = overlap(p1, p2, T, "bbox")
    v = overlap(p1, p2, T, "voxel")
    # the truly common part: map-2 points within 1 m of map 1 under the exact transform
    _, truth2 = _brute_voxel(p1, p2, T12, 1.0)
    assert int(v.count_2) >= 0.9 * truth2.sum()
    assert int(b.count_2) < 0.75 * int(v.count_2)
    # what bbox keeps of the common part vs voxel
    assert (np.asarray(v.mask_2) & truth2).sum() > 1.2 * (np.asarray(b.mask_2) & truth2).sum()
