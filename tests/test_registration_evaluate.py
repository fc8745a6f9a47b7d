"""``evaluate_registration``: correspondence statistics at a given transform, against brute
force (and Open3D's ``evaluate_registration`` where it is installed)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from octomerge_jax import registration as reg


def _brute(source, target, T, d):
    """(inliers, rmse, fitness) in float64: nearest target point of each placed source point."""
    s = source @ T[:3, :3].T + T[:3, 3]
    d2 = ((s[:, None, :] - target[None, :, :]) ** 2).sum(-1).min(1)
    inl = d2 <= d * d
    return int(inl.sum()), float(np.sqrt(d2[inl].mean())) if inl.any() else float("nan"), inl.mean()


def _clouds(n_t=3000, n_s=2000, seed=0, offset=(0.0, 0.0, 0.0)):
    rng = np.random.default_rng(seed)
    t = rng.uniform(-3, 3, (n_t, 3)) + offset
    s = t[:n_s] + rng.normal(0, 0.04, (n_s, 3))
    T = np.asarray(reg.from_xyz_rpy(0.03, -0.02, 0.01, 0.01, -0.02, 0.05), np.float64)
    return (s - T[:3, 3]) @ T[:3, :3], t, T  # T places the source back near the target


@pytest.mark.parametrize("d", [0.03, 0.08, 0.3])
def test_matches_brute_force(d):
    s, t, T = _clouds()
    st = reg.evaluate_registration(s, t, T, d)
    n, rmse, fit = _brute(s, t, T, d)
    assert int(st.num_inliers) == n and int(st.grid_overflow) == 0
    assert float(st.rmse) == pytest.approx(rmse, rel=1e-5)
    assert float(st.fitness) == pytest.approx(fit, rel=1e-6)


def test_far_from_the_origin_and_no_inliers():
    """Coordinates 5 km from the origin give the statistics of the same clouds at the origin
    (centred in float64 before the float32 search); a transform that misses: 0 inliers, NaN rmse."""
    s, t, T = _clouds()
    far = np.array([5000.0, -3000.0, 20.0])
    T_far = T.copy()
    T_far[:3, 3] += far - T[:3, :3] @ far  # the same placement of the shifted clouds
    a = reg.evaluate_registration(s, t, T, 0.08)
    b = reg.evaluate_registration(s + far, t + far, T_far, 0.08)
    assert int(a.num_inliers) == int(b.num_inliers)
    assert float(b.rmse) == pytest.approx(float(a.rmse), abs=1e-5)
    miss = T.copy()
    miss[:3, 3] += 50.0
    m = reg.evaluate_registration(s, t, miss, 0.08)
    assert int(m.num_inliers) == 0 and np.isnan(float(m.rmse)) and float(m.fitness) == 0.0


def test_subsets_padded_as_the_whole_clouds_share_one_program():
    """``source_capacity`` / ``target_capacity``: a subset of a pair's clouds padded to the whole
    clouds' buckets gives its own statistics (brute force) from the whole clouds' program."""
    from octomerge_jax.registration.evaluate import _evaluate

    s, t, T = _clouds()
    reg.evaluate_registration(s, t, T, 0.08)
    programs = _evaluate.programs()
    sub_s, sub_t = s[:700], t[:900]
    st = reg.evaluate_registration(sub_s, sub_t, T, 0.08, source_capacity=s.shape[0], target_capacity=t.shape[0])
    assert _evaluate.programs() == programs
    n, rmse, fit = _brute(sub_s, sub_t, T, 0.08)
    assert int(st.num_inliers) == n and float(st.rmse) == pytest.approx(rmse, rel=1e-5)
    assert float(st.fitness) == pytest.approx(fit, rel=1e-6)
    reg.evaluate_registration(sub_s, sub_t, T, 0.08)  # its own buckets: another program
    assert _evaluate.programs() == programs + 1


def test_jit_and_vmap_over_transforms_with_padding():
    s, t, T = _clouds()
    d = 0.08
    Ts = np.stack([T, T @ np.asarray(reg.from_xyz_rpy(0.05, 0, 0, 0, 0, 0.02)), np.eye(4)])
    sp, sc = reg.pad_points(s)
    tp, tc = reg.pad_points(t)
    f = jax.jit(jax.vmap(lambda T_: reg.evaluate_registration(sp, tp, T_, d, source_count=sc, target_count=tc)))
    out = f(jnp.asarray(Ts, jnp.float32))
    for i, T_ in enumerate(Ts):
        n, rmse, _ = _brute(s, t, T_, d)
        assert int(out.num_inliers[i]) == n
        np.testing.assert_allclose(float(out.rmse[i]), rmse, rtol=1e-4)


def test_bad_arguments_name_what_was_wrong():
    s, t, T = _clouds(200, 100)
    with pytest.raises(ValueError, match="max_correspondence_distance"):
        reg.evaluate_registration(s, t, T, 0.0)
    with pytest.raises(ValueError, match="T_target_source"):
        reg.evaluate_registration(s, t, np.ones((4, 4)), 0.1)
    with pytest.raises(ValueError, match="source"):
        reg.evaluate_registration(s[:, :2], t, T, 0.1)
    with pytest.raises(ValueError, match="target"):
        reg.evaluate_registration(s, np.full((5, 3), np.nan), T, 0.1)


def test_matches_open3d():
    o3d = pytest.importorskip("open3d", exc_type=ImportError)  # also when a system library (libusb) is missing
    s, t, T = _clouds(20000, 15000, seed=1)
    pc = lambda p: o3d.geometry.PointCloud(o3d.utility.Vector3dVector(p))  # noqa: E731
    for d in (0.05, 0.1):
        e = o3d.pipelines.registration.evaluate_registration(pc(s), pc(t), d, T)
        st = reg.evaluate_registration(s, t, T, d)
        assert int(st.num_inliers) == len(e.correspondence_set)
        assert float(st.rmse) == pytest.approx(e.inlier_rmse, rel=1e-5)
        assert float(st.fitness) == pytest.approx(e.fitness, rel=1e-6)
