"""rigid.py, metrics.py and rendezvous.py against hand-computed and brute-force NumPy cases."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from octomerge_jax import se3 as rigid
from octomerge_jax.registration import metrics, rendezvous
from helpers import xyz_rpy64


def _octomap_matrix(roll, pitch, yaw):
    """octomath::Quaternion(roll, pitch, yaw) rotation matrix, copied term by term."""
    sr, sp, sy, cr, cp, cy = np.sin(roll), np.sin(pitch), np.sin(yaw), np.cos(roll), np.cos(pitch), np.cos(yaw)
    return np.array([[cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
                     [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
                     [-sp, cp * sr, cp * cr]])


@pytest.mark.parametrize("rpy", [(0.0, 0.0, 0.0), (0.1, -0.2, 0.3), (-1.0, 0.7, 2.9), (0.0, 0.0, -np.pi / 4)])
def test_from_xyz_rpy_matches_octomap_pose6d(rpy):
    T = np.asarray(rigid.from_xyz_rpy(1.0, -2.0, 0.5, *rpy))
    np.testing.assert_allclose(T[:3, :3], _octomap_matrix(*rpy), atol=1e-6)
    np.testing.assert_allclose(T[:3, 3], [1.0, -2.0, 0.5], atol=1e-6)
    np.testing.assert_allclose(T[3], [0, 0, 0, 1])
    back = np.asarray(rigid.to_xyz_rpy(T))
    np.testing.assert_allclose(back, [1.0, -2.0, 0.5, *rpy], atol=2e-6)


def test_quaternion_round_trip_and_octomap_order():
    rng = np.random.default_rng(0)
    q = rng.normal(size=(50, 4)).astype(np.float32)
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    q[:, 0] = np.abs(q[:, 0])
    q[0] = [0.0, 1.0, 0.0, 0.0]  # 180 degrees about x: the stable branch matters
    T = rigid.from_quaternion(q, np.zeros((50, 3), np.float32))
    back = np.asarray(rigid.to_quaternion(T))
    same = np.minimum(np.abs(back - q).max(1), np.abs(back + q).max(1))
    assert same.max() < 1e-5
    # yaw pi/2 about z: (cos pi/4, 0, 0, sin pi/4) in (w, x, y, z)
    qz = np.asarray(rigid.to_quaternion(rigid.from_xyz_rpy(0, 0, 0, 0, 0, np.pi / 2)))
    np.testing.assert_allclose(qz, [np.cos(np.pi / 4), 0, 0, np.sin(np.pi / 4)], atol=1e-6)


def test_inverse_and_transform_points_batched():
    rng = np.random.default_rng(1)
    T = rigid.from_xyz_rpy(*[jnp.asarray(rng.normal(size=(3, 5)), jnp.float32) for _ in range(6)])
    assert T.shape == (3, 5, 4, 4)
    I = np.asarray(rigid.inverse(T) @ T)
    np.testing.assert_allclose(I, np.broadcast_to(np.eye(4), I.shape), atol=1e-5)
    p = rng.normal(size=(3, 5, 7, 3)).astype(np.float32)
    got = np.asarray(rigid.transform_points(T, p))
    Tn = np.asarray(T, np.float64)
    want = np.einsum("abij,abnj->abni", Tn[..., :3, :3], p) + Tn[..., None, :3, 3]
    np.testing.assert_allclose(got, want, atol=1e-5)


def test_check_rigid_errors_name_the_argument():
    good = np.asarray(rigid.from_xyz_rpy(1, 2, 3, 0.1, 0.2, 0.3))
    rigid.check_rigid(good)
    with pytest.raises(ValueError, match="T_init.*4x4"):
        rigid.check_rigid(np.eye(3), "T_init")
    with pytest.raises(ValueError, match="non-finite"):
        rigid.check_rigid(np.full((4, 4), np.nan))
    bad = good.copy()
    bad[0, 0] += 0.1
    with pytest.raises(ValueError, match="orthonormal"):
        rigid.check_rigid(bad, "T_1_2")
    refl = np.diag([1.0, 1.0, -1.0, 1.0])
    with pytest.raises(ValueError, match="reflection"):
        rigid.check_rigid(refl)
    row = good.copy()
    row[3, 0] = 1.0
    with pytest.raises(ValueError, match="bottom row"):
        rigid.check_rigid(row)


def test_rigid_is_differentiable_and_jittable():
    f = jax.jit(lambda a: jnp.sum(rigid.inverse(rigid.from_xyz_rpy(a[0], a[1], a[2], a[3], a[4], a[5]))[:3, 3]))
    a = jnp.asarray([0.3, -0.2, 1.0, 0.1, 0.2, 0.3], jnp.float32)
    g = np.asarray(jax.grad(f)(a))
    eps = 1e-2
    fd = [(float(f(a.at[i].add(eps))) - float(f(a.at[i].add(-eps)))) / (2 * eps) for i in range(6)]
    np.testing.assert_allclose(g, fd, atol=2e-3)


# ----------------------------------------------------------------------------- metrics (eqs. 7.2, 7.3)


def test_epsilon_metrics_reproduce_table_7_1_pre_icp_values():
    """Table 7.1 'pre ICP' columns: exact = yaw -pi/4; guesses given as xyz + rpy."""
    exact = xyz_rpy64(0, 0, 0, 0, 0, -np.pi / 4)
    rows = [((0, 0, 0), (0, 0, -0.5), 0.796312, 0), ((0, 0, 0), (0, 0, -0.6), 0.521384, 0),
            ((0, 0, 0), (0, 0, -0.8), 0.0413005, 0), ((1, 1, 1), (0, 0, -0.6), 0.521384, 3),
            ((0, 0, 0), (-0.1, 0, -np.pi / 4), 0.25308, 0), ((1, 1, 0), (0, -0.1, -np.pi / 4), 0.25308, 2)]
    for t, rpy, er, et in rows:
        guess = xyz_rpy64(*t, *rpy)
        assert float(metrics.rotation_error(guess, exact)) == pytest.approx(er, abs=2e-5)
        assert float(metrics.translation_error(guess, exact)) == pytest.approx(et, abs=1e-6)


def test_geodesic_metrics_hand_computed():
    A = xyz_rpy64(1, 2, 3, 0, 0, 0.3)
    B = xyz_rpy64(1, 2, 5, 0, 0, -0.2)
    assert float(metrics.rotation_angle_error(A, B)) == pytest.approx(0.5, abs=1e-6)
    assert float(metrics.translation_distance(A, B)) == pytest.approx(2.0, abs=1e-6)
    C = xyz_rpy64(0, 0, 0, np.pi, 0, 0)
    assert float(metrics.rotation_angle_error(C, np.eye(4))) == pytest.approx(np.pi, abs=1e-6)
    # eps_r by hand for a pure yaw difference: 2|cos a - 1| + 2|sin a|
    a = 0.3
    assert float(metrics.rotation_error(xyz_rpy64(0, 0, 0, 0, 0, a), np.eye(4))) == pytest.approx(
        2 * (1 - np.cos(a)) + 2 * np.sin(a), abs=1e-6)


def test_point_displacement_hand_computed_and_frame_independent():
    A = xyz_rpy64(1, 0, 0, 0, 0, np.pi / 2)  # x -> y, then +1 m in x
    p = np.array([[0.0, 0.0, 0.0], [2.0, 0.0, 0.0], [0.0, 0.0, 5.0]])
    # A p = (1,0,0), (1,2,0), (1,0,5): displacements 1, |(-1, 2, 0)| = sqrt(5), 1
    np.testing.assert_allclose(np.asarray(metrics.point_displacement(A, np.eye(4), p)),
                               [1.0, np.sqrt(5.0), 1.0], atol=1e-6)
    # the same motion seen from a frame 100 m away: eps_t grows, displacements do not
    S = xyz_rpy64(100, 0, 0, 0, 0, 0)
    B = S @ A @ np.linalg.inv(S)
    assert float(metrics.translation_error(B, np.eye(4))) > 100
    np.testing.assert_allclose(np.asarray(metrics.point_displacement(B, np.eye(4), p + [100, 0, 0])),
                               [1.0, np.sqrt(5.0), 1.0], atol=2e-4)  # float32 at 100 m
    assert metrics.point_displacement(np.stack([A, B]), np.eye(4), p).shape == (2, 3)


# ----------------------------------------------------------------------------- rendezvous (eqs. 5.8-5.11)


def _planar(x, y, h):
    return np.array([[np.cos(h), -np.sin(h), x], [np.sin(h), np.cos(h), y], [0, 0, 1.0]])


@pytest.mark.parametrize("seed", range(5))
def test_rendezvous_2d_recovers_the_map_to_map_transform(seed):
    rng = np.random.default_rng(seed)
    T_w_m1, T_w_m2 = _planar(*rng.uniform(-5, 5, 3)), _planar(*rng.uniform(-5, 5, 3))
    T_w_c, T_w_o = _planar(*rng.uniform(-3, 3, 3)), _planar(*rng.uniform(-3, 3, 3))
    T_m1_c = np.linalg.inv(T_w_m1) @ T_w_c
    T_m2_o = np.linalg.inv(T_w_m2) @ T_w_o
    T_c_o = np.linalg.inv(T_w_c) @ T_w_o
    r = np.hypot(*T_c_o[:2, 2])
    bearing_c = np.arctan2(T_c_o[1, 2], T_c_o[0, 2])
    T_o_c = np.linalg.inv(T_c_o)
    bearing_o = np.arctan2(T_o_c[1, 2], T_o_c[0, 2])
    pose = lambda T: (T[0, 2], T[1, 2], np.arctan2(T[1, 0], T[0, 0]))
    got = np.asarray(rendezvous.rendezvous_transform_2d(pose(T_m1_c), pose(T_m2_o), r, bearing_c, bearing_o))
    want = np.linalg.inv(T_w_m1) @ T_w_m2
    np.testing.assert_allclose(got, want, atol=2e-5)
    heading = np.arctan2(T_c_o[1, 0], T_c_o[0, 0])
    got2 = rendezvous.rendezvous_transform_2d(pose(T_m1_c), pose(T_m2_o), r, bearing_c, relative_heading_rad=heading)
    np.testing.assert_allclose(np.asarray(got2), want, atol=2e-5)
    # the 3-D form with zero elevation/roll/pitch is the lifted 2-D one
    lift = lambda T: np.asarray(rendezvous.lift_2d(T))
    got3 = rendezvous.rendezvous_transform(lift(T_m1_c), lift(T_m2_o),
                                           rendezvous.relative_pose_3d(r, bearing_c, 0.0, 0.0, 0.0, heading))
    np.testing.assert_allclose(np.asarray(got3), lift(want), atol=2e-5)


def test_rendezvous_3d_recovers_the_map_to_map_transform():
    rng = np.random.default_rng(7)
    rnd = lambda: xyz_rpy64(*rng.uniform(-3, 3, 3), *rng.uniform(-0.4, 0.4, 2), rng.uniform(-3, 3))
    T_w_m1, T_w_m2, T_w_c, T_w_o = rnd(), rnd(), rnd(), rnd()
    T_c_o = np.linalg.inv(T_w_c) @ T_w_o
    t = T_c_o[:3, 3]
    r = np.linalg.norm(t)
    az, el = np.arctan2(t[1], t[0]), np.arcsin(t[2] / r)
    rpy = np.asarray(rigid.to_xyz_rpy(T_c_o.astype(np.float32)))[3:]
    got = rendezvous.rendezvous_transform(np.linalg.inv(T_w_m1) @ T_w_c, np.linalg.inv(T_w_m2) @ T_w_o,
                                          rendezvous.relative_pose_3d(r, az, el, *rpy))
    np.testing.assert_allclose(np.asarray(got), np.linalg.inv(T_w_m1) @ T_w_m2, atol=5e-5)
    with pytest.raises(ValueError, match="exactly one"):
        rendezvous.relative_pose_2d(1.0, 0.0)
