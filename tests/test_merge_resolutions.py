"""Merging maps of different resolutions: ``om.merge`` refuses (``MergeError``, kind
``"resolution"``) unless asked to resample map 2 onto map 1's grid; the CLI exits 3, or merges
with ``--resample``."""

from __future__ import annotations

import os
import subprocess
import sys

import numpy as np
import pytest

import octomerge_jax as om

FINE, COARSE = 0.1, 0.2
TIMEOUT_S = 600
# log-odds of the hand-made maps
V1, V1B, V2 = 0.85, 1.7, -0.4


def node_code(resolution, corner, depth):
    """Morton code of the depth-``depth`` node whose min corner is ``corner`` [m] (via a
    one-voxel map: the voxel's code truncated to ``depth``)."""
    p = np.asarray(corner, np.float64) + resolution / 2
    code = int(om.update_points(om.empty(resolution), p, True).leaves().codes[0])
    shift = 3 * (16 - depth)
    return np.uint64((code >> shift) << shift)


@pytest.fixture(scope="module")
def maps():
    """Map 1 (0.1 m): an occupied 0.8 m cube at the origin corner and a 0.4 m cube above it;
    map 2 (0.2 m): free 0.8 m cubes at the origin corner and beside it in x."""
    m1 = om.from_leaves([node_code(FINE, (0, 0, 0), 13), node_code(FINE, (0, 0, 0.8), 14)], [13, 14],
                        [V1, V1B], FINE)
    m2 = om.from_leaves([node_code(COARSE, (0, 0, 0), 14), node_code(COARSE, (0.8, 0, 0), 14)], [14, 14],
                        [V2, V2], COARSE)
    return m1, m2


def grid_centres():
    """Centres of the 0.1 m voxels of [-0.2, 1.8)^3."""
    axis = np.arange(-0.2, 1.8 - 1e-9, FINE) + FINE / 2
    return np.stack(np.meshgrid(axis, axis, axis, indexing="ij"), -1).reshape(-1, 3)


def expected(points):
    """(known, log-odds) of the merge of the two maps at voxel centres, by hand."""
    in1 = np.all((points >= 0) & (points < 0.8), axis=1)
    in1b = np.all((points >= (0, 0, 0.8)) & (points < (0.4, 0.4, 1.2)), axis=1)
    in2 = np.all((points >= 0) & (points < (1.6, 0.8, 0.8)), axis=1)
    value = np.where(in1 & in2, np.float32(V1) + np.float32(V2), np.where(in1, V1, np.where(in1b, V1B, V2)))
    return in1 | in1b | in2, value.astype(np.float32)


def test_library_refuses_different_resolutions(maps):
    m1, m2 = maps
    with pytest.raises(om.MergeError) as err:
        om.merge(m1, m2, refine="none")
    assert err.value.kind == "resolution"
    assert "map 1 is 0.1 m, map 2 is 0.2 m" in str(err.value)
    with pytest.raises(om.MergeError) as err:
        om.merge(m2, m1, refine="none", resample=False)
    assert err.value.kind == "resolution"


@pytest.fixture(scope="module")
def resampled(maps):
    m1, m2 = maps
    return om.merge(m1, m2, refine="none", resample=True)


def test_library_resample_merges_on_map_1s_grid(maps, resampled):
    merged, report = resampled
    assert merged.resolution == FINE and report.resolution == FINE
    assert any("resampled to map 1's resolution 0.1 m" in w for w in report.warnings)
    pts = grid_centres()
    value, known = om.lookup(merged, pts.astype(np.float32))
    want_known, want = expected(pts)
    np.testing.assert_array_equal(np.asarray(known), want_known)
    # map 2's constant value survives resampling (trilinear in probability) to float32 rounding
    np.testing.assert_allclose(np.asarray(value)[want_known], want[want_known], rtol=0, atol=2e-6)
    # pinned: resampled values differ from V2 in the last bits from voxel to voxel, so the
    # cubes do not prune to 3 leaves; map 1's 0.4 m cube stays one depth-14 leaf
    L = merged.leaves()
    assert merged.num_leaves == 563
    assert np.count_nonzero(L.log_odds == np.float32(V1B)) == 1


def test_cli_exit_3_and_resample(tmp_path, maps, resampled):
    m1, m2 = maps
    om.save(m1, tmp_path / "fine.ot")
    om.save(m2, tmp_path / "coarse.ot")
    env = dict(os.environ)  # the run's XLA cache (tests/conftest.py)

    def octomerge(*args):
        return subprocess.run([sys.executable, "-m", "octomerge_jax", "merge", *map(str, args)],
                              capture_output=True, text=True, timeout=TIMEOUT_S, env=env)

    out = tmp_path / "merged.ot"
    r = octomerge(tmp_path / "fine.ot", tmp_path / "coarse.ot", out)
    assert r.returncode == 3, r.stderr
    assert "resolutions differ: map 1 is 0.1 m, map 2 is 0.2 m" in r.stderr and "--resample" in r.stderr
    assert not out.exists()
    r = octomerge(tmp_path / "fine.ot", tmp_path / "coarse.ot", out, "--resample", "--refine", "none")
    assert r.returncode == 0, r.stderr
    assert "warning: map 2 was resampled to map 1's resolution 0.1 m" in r.stderr
    got, want = om.load(out).leaves(), resampled[0].leaves()
    np.testing.assert_array_equal(got.codes, want.codes)
    np.testing.assert_array_equal(got.depths, want.depths)
    np.testing.assert_array_equal(got.log_odds, want.log_odds)
