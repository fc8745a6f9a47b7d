"""Rigid transforms as 4x4 homogeneous matrices (thesis eq. 3.19, 5.7).

Frames are in the names: ``T_1_2`` maps points of frame 2 into frame 1 (``x_1 = T_1_2 x_2``,
eq. 5.7), so ``T_1_2 @ T_2_3 = T_1_3``. Units: metres and radians.

Euler angles follow OctoMap's ``octomath::Pose6D(x, y, z, roll, pitch, yaw)`` /
``Quaternion(roll, pitch, yaw)`` (``src/math/Quaternion.cpp``): ``R = Rz(yaw) Ry(pitch) Rx(roll)``
(extrinsic x-y-z, i.e. intrinsic z-y'-x''). Quaternions are ``(w, x, y, z)`` in OctoMap's
``(u, x, y, z)`` order.

Every function except ``check_rigid`` is written in ``jax.numpy``: it accepts NumPy or JAX
input, works under ``jit``/``vmap``/``grad`` and returns a JAX array in the input's float dtype
(float32 unless the caller passes float64 with x64 enabled).
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

__all__ = [
    "from_xyz_rpy",
    "to_xyz_rpy",
    "from_rotation_translation",
    "from_quaternion",
    "to_quaternion",
    "inverse",
    "transform_points",
    "rot_x",
    "rot_y",
    "rot_z",
    "check_rigid",
]


def _f(x):
    x = jnp.asarray(x)
    return x if jnp.issubdtype(x.dtype, jnp.floating) else x.astype(jnp.float32)


def rot_x(angle_rad):
    """3x3 rotation about x by ``angle_rad`` (right-handed). Batched over leading dims."""
    a = _f(angle_rad)
    c, s = jnp.cos(a), jnp.sin(a)
    o, z = jnp.ones_like(a), jnp.zeros_like(a)
    return jnp.stack([jnp.stack([o, z, z], -1), jnp.stack([z, c, -s], -1), jnp.stack([z, s, c], -1)], -2)


def rot_y(angle_rad):
    """3x3 rotation about y by ``angle_rad``."""
    a = _f(angle_rad)
    c, s = jnp.cos(a), jnp.sin(a)
    o, z = jnp.ones_like(a), jnp.zeros_like(a)
    return jnp.stack([jnp.stack([c, z, s], -1), jnp.stack([z, o, z], -1), jnp.stack([-s, z, c], -1)], -2)


def rot_z(angle_rad):
    """3x3 rotation about z by ``angle_rad``."""
    a = _f(angle_rad)
    c, s = jnp.cos(a), jnp.sin(a)
    o, z = jnp.ones_like(a), jnp.zeros_like(a)
    return jnp.stack([jnp.stack([c, -s, z], -1), jnp.stack([s, c, z], -1), jnp.stack([z, z, o], -1)], -2)


def from_rotation_translation(R, t):
    """``R (..., 3, 3)``, ``t (..., 3)`` [m] -> ``T (..., 4, 4)``."""
    R = _f(R)
    t = jnp.asarray(t, R.dtype)
    batch = jnp.broadcast_shapes(R.shape[:-2], t.shape[:-1])
    R = jnp.broadcast_to(R, batch + (3, 3))
    t = jnp.broadcast_to(t, batch + (3,))
    top = jnp.concatenate([R, t[..., :, None]], axis=-1)
    bottom = jnp.broadcast_to(jnp.asarray([0.0, 0.0, 0.0, 1.0], R.dtype), batch + (1, 4))
    return jnp.concatenate([top, bottom], axis=-2)


def from_xyz_rpy(x, y, z, roll_rad, pitch_rad, yaw_rad):
    """OctoMap ``Pose6D(x, y, z, roll, pitch, yaw).rot().toRotMatrix()`` + translation as a
    4x4 matrix: ``R = Rz(yaw) Ry(pitch) Rx(roll)``. Metres, radians; arguments broadcast."""
    args = jnp.broadcast_arrays(*[_f(a) for a in (x, y, z, roll_rad, pitch_rad, yaw_rad)])
    dtype = jnp.result_type(*[a.dtype for a in args])
    x, y, z, roll, pitch, yaw = [a.astype(dtype) for a in args]
    R = rot_z(yaw) @ rot_y(pitch) @ rot_x(roll)
    return from_rotation_translation(R, jnp.stack([x, y, z], -1))


def to_xyz_rpy(T):
    """Inverse of ``from_xyz_rpy`` (OctoMap ``Quaternion::toEuler``): ``T (..., 4, 4)`` ->
    ``(..., 6)`` = (x, y, z, roll, pitch, yaw); pitch in [-pi/2, pi/2]."""
    T = _f(T)
    R = T[..., :3, :3]
    roll = jnp.arctan2(R[..., 2, 1], R[..., 2, 2])
    pitch = jnp.arctan2(-R[..., 2, 0], jnp.sqrt(R[..., 2, 1] ** 2 + R[..., 2, 2] ** 2))
    yaw = jnp.arctan2(R[..., 1, 0], R[..., 0, 0])
    return jnp.concatenate([T[..., :3, 3], jnp.stack([roll, pitch, yaw], -1)], axis=-1)


def from_quaternion(q_wxyz, t=None):
    """Unit quaternion ``(..., 4)`` as ``(w, x, y, z)`` (normalised here) and optional
    translation ``(..., 3)`` [m] -> ``T (..., 4, 4)`` (OctoMap ``toRotMatrix``)."""
    q = _f(q_wxyz)
    q = q / jnp.linalg.norm(q, axis=-1, keepdims=True)
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    R = jnp.stack([
        jnp.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        jnp.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        jnp.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
    ], -2)
    if t is None:
        t = jnp.zeros(q.shape[:-1] + (3,), q.dtype)
    return from_rotation_translation(R, t)


def to_quaternion(T):
    """Rotation part of ``T (..., 4, 4)`` (or ``R (..., 3, 3)``) -> unit quaternion
    ``(..., 4)`` ``(w, x, y, z)`` with ``w >= 0``. Uses the numerically stable branch
    (largest diagonal term), so it is exact near 180 degrees too."""
    R = _f(T)[..., :3, :3]
    m00, m11, m22 = R[..., 0, 0], R[..., 1, 1], R[..., 2, 2]
    tr = m00 + m11 + m22
    cands = jnp.stack([
        jnp.stack([1 + tr, R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], -1),
        jnp.stack([R[..., 2, 1] - R[..., 1, 2], 1 + m00 - m11 - m22, R[..., 0, 1] + R[..., 1, 0], R[..., 0, 2] + R[..., 2, 0]], -1),
        jnp.stack([R[..., 0, 2] - R[..., 2, 0], R[..., 0, 1] + R[..., 1, 0], 1 - m00 + m11 - m22, R[..., 1, 2] + R[..., 2, 1]], -1),
        jnp.stack([R[..., 1, 0] - R[..., 0, 1], R[..., 0, 2] + R[..., 2, 0], R[..., 1, 2] + R[..., 2, 1], 1 - m00 - m11 + m22], -1),
    ], -2)  # (..., 4, 4): row k is 4 q_k * q
    k = jnp.argmax(jnp.stack([tr, m00, m11, m22], -1), axis=-1)
    q = jnp.take_along_axis(cands, k[..., None, None], axis=-2)[..., 0, :]
    q = q / jnp.linalg.norm(q, axis=-1, keepdims=True)
    return jnp.where(q[..., :1] < 0, -q, q)


def inverse(T):
    """Inverse of a rigid transform ``(..., 4, 4)``: ``[R^T, -R^T t]`` (not ``-t``, the bug of
    the published thesis code)."""
    T = _f(T)
    Rt = jnp.swapaxes(T[..., :3, :3], -1, -2)
    t = -(Rt @ T[..., :3, 3:])[..., 0]
    return from_rotation_translation(Rt, t)


def transform_points(T_a_b, points_b):
    """Points ``(..., n, 3)`` in frame b -> frame a with ``T_a_b (..., 4, 4)``."""
    T = _f(T_a_b)
    p = jnp.asarray(points_b, T.dtype)
    # three broadcast multiply-adds, not ``p @ R^T``: XLA:CPU fuses them into one loop, ~8x
    # faster than its matmul for (n, 3) x (3, 3) (ICP transforms every source point per iteration)
    col = lambda j: T[..., None, :3, j]  # noqa: E731
    return p[..., 0:1] * col(0) + p[..., 1:2] * col(1) + p[..., 2:3] * col(2) + col(3)


def check_rigid(T, name: str = "T", atol: float = 1e-4) -> np.ndarray:
    """Host-side validation: return ``T`` as a float64 NumPy ``(..., 4, 4)`` array or raise
    ``ValueError`` naming ``name`` if it is not a finite rigid transform (wrong shape,
    non-finite entries, bottom row not ``[0, 0, 0, 1]``, rotation not orthonormal within
    ``atol``, or determinant not +1, i.e. a reflection)."""
    a = np.asarray(T, dtype=np.float64)
    if a.shape[-2:] != (4, 4):
        raise ValueError(f"{name}: expected a 4x4 homogeneous transform, got shape {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name}: contains non-finite entries")
    if np.max(np.abs(a[..., 3, :] - np.array([0.0, 0.0, 0.0, 1.0]))) > atol:
        raise ValueError(f"{name}: bottom row must be [0, 0, 0, 1], got {a[..., 3, :].tolist()}")
    R = a[..., :3, :3]
    err = np.max(np.abs(np.swapaxes(R, -1, -2) @ R - np.eye(3)))
    if err > atol:
        raise ValueError(f"{name}: rotation block is not orthonormal (max |R^T R - I| = {err:.3g} "
                         f"> {atol:g}); re-orthonormalise it (e.g. via to/from_quaternion)")
    det = np.linalg.det(R)
    if np.any(det < 0):
        raise ValueError(f"{name}: rotation block has determinant {np.min(det):.3g} (a reflection, "
                         "not a rotation)")
    return a
