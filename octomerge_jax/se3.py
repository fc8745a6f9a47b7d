"""Rigid transforms as 4x4 homogeneous matrices (thesis eq. 3.19, 5.7): the only copy of each.

Frames are in the names: ``T_a_b`` maps points of frame b into frame a (``x_a = T_a_b x_b``,
eq. 5.7), so ``T_a_b @ T_b_c = T_a_c``. Units: metres and radians.

Euler angles follow OctoMap's ``octomath::Pose6D(x, y, z, roll, pitch, yaw)`` /
``Quaternion(roll, pitch, yaw)`` (``src/math/Quaternion.cpp``): ``R = Rz(yaw) Ry(pitch) Rx(roll)``
(extrinsic x-y-z, i.e. intrinsic z-y'-x''). Quaternions are ``(w, x, y, z)`` in OctoMap's
``(u, x, y, z)`` order. Tangent vectors: ``so3_exp(w)`` takes a rotation vector ``w (..., 3)``
[rad]; ``se3_exp(xi)`` takes ``xi (..., 6) = (v [m], omega [rad])``.

Every function except the host checks (``check_rigid``, ``check_rigid_transform``,
``project_to_rigid``) is written once against an array namespace ``xp``: ``jax.numpy`` by
default (NumPy or JAX input, works under ``jit``/``vmap``/``grad``, returns a JAX array in the
input's float dtype, float32 unless the caller passes float64 with x64 enabled), or
``xp=numpy`` for float64 host arithmetic (ground truth, file formats, simulation poses).
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

__all__ = [
    "rot_x",
    "rot_y",
    "rot_z",
    "rpy_to_rotation",
    "from_rotation_translation",
    "from_xyz_rpy",
    "to_xyz_rpy",
    "from_quaternion",
    "to_quaternion",
    "inverse",
    "compose",
    "transform_points",
    "skew",
    "so3_exp",
    "so3_log",
    "se3_exp",
    "se3_log",
    "adjoint",
    "right_jacobian_inverse",
    "check_rigid",
    "project_to_rigid",
    "check_rigid_transform",
]


def _f(x, xp):
    if xp is np:
        return np.asarray(x, dtype=np.float64)
    x = jnp.asarray(x)
    return x if jnp.issubdtype(x.dtype, jnp.floating) else x.astype(jnp.float32)


def _rot(c, s, axis: int, xp):
    o, z = xp.ones_like(c), xp.zeros_like(c)
    rows = {0: ((o, z, z), (z, c, -s), (z, s, c)),
            1: ((c, z, s), (z, o, z), (-s, z, c)),
            2: ((c, -s, z), (s, c, z), (z, z, o))}[axis]
    return xp.stack([xp.stack(r, -1) for r in rows], -2)


def rot_x(angle_rad, *, xp=jnp):
    """``(..., 3, 3)`` rotation about x by ``angle_rad (...)`` [rad] (right-handed)."""
    a = _f(angle_rad, xp)
    return _rot(xp.cos(a), xp.sin(a), 0, xp)


def rot_y(angle_rad, *, xp=jnp):
    """``(..., 3, 3)`` rotation about y by ``angle_rad (...)`` [rad]."""
    a = _f(angle_rad, xp)
    return _rot(xp.cos(a), xp.sin(a), 1, xp)


def rot_z(angle_rad, *, xp=jnp):
    """``(..., 3, 3)`` rotation about z by ``angle_rad (...)`` [rad]."""
    a = _f(angle_rad, xp)
    return _rot(xp.cos(a), xp.sin(a), 2, xp)


def rpy_to_rotation(roll_rad, pitch_rad, yaw_rad, *, xp=jnp):
    """``R = Rz(yaw) Ry(pitch) Rx(roll)`` ``(..., 3, 3)``, OctoMap's ``Quaternion(roll, pitch,
    yaw).toRotMatrix()`` written out (arguments broadcast)."""
    cr, sr = xp.cos(roll_rad), xp.sin(roll_rad)
    cp, sp = xp.cos(pitch_rad), xp.sin(pitch_rad)
    cy, sy = xp.cos(yaw_rad), xp.sin(yaw_rad)
    return xp.stack([
        xp.stack([cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr], -1),
        xp.stack([sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr], -1),
        xp.stack([-sp, cp * sr, cp * cr], -1),
    ], -2)


def from_rotation_translation(R, t, *, xp=jnp):
    """``R (..., 3, 3)``, ``t (..., 3)`` [m] -> ``T (..., 4, 4)`` (leading dims broadcast)."""
    R = _f(R, xp)
    t = xp.asarray(t, R.dtype)
    batch = np.broadcast_shapes(R.shape[:-2], t.shape[:-1])
    R = xp.broadcast_to(R, batch + (3, 3))
    t = xp.broadcast_to(t, batch + (3,))
    top = xp.concatenate([R, t[..., :, None]], axis=-1)
    bottom = xp.broadcast_to(xp.asarray([0.0, 0.0, 0.0, 1.0], R.dtype), batch + (1, 4))
    return xp.concatenate([top, bottom], axis=-2)


def from_xyz_rpy(x, y, z, roll_rad, pitch_rad, yaw_rad, *, xp=jnp):
    """OctoMap ``Pose6D(x, y, z, roll, pitch, yaw)`` as ``T (..., 4, 4)``: ``R = Rz(yaw)
    Ry(pitch) Rx(roll)`` (``rpy_to_rotation``) and the translation. Metres, radians; arguments
    broadcast."""
    args = [_f(a, xp) for a in (x, y, z, roll_rad, pitch_rad, yaw_rad)]
    if xp is jnp:
        args = jnp.broadcast_arrays(*args)
        dtype = jnp.result_type(*[a.dtype for a in args])
        args = [a.astype(dtype) for a in args]
    else:
        args = np.broadcast_arrays(*args)
    x, y, z, roll, pitch, yaw = args
    return from_rotation_translation(rpy_to_rotation(roll, pitch, yaw, xp=xp), xp.stack([x, y, z], -1), xp=xp)


def to_xyz_rpy(T, *, xp=jnp):
    """Inverse of ``from_xyz_rpy`` (OctoMap ``Quaternion::toEuler``): ``T (..., 4, 4)`` ->
    ``(..., 6)`` = (x, y, z [m], roll, pitch, yaw [rad]); pitch in [-pi/2, pi/2]."""
    T = _f(T, xp)
    R = T[..., :3, :3]
    roll = xp.arctan2(R[..., 2, 1], R[..., 2, 2])
    pitch = xp.arctan2(-R[..., 2, 0], xp.sqrt(R[..., 2, 1] ** 2 + R[..., 2, 2] ** 2))
    yaw = xp.arctan2(R[..., 1, 0], R[..., 0, 0])
    return xp.concatenate([T[..., :3, 3], xp.stack([roll, pitch, yaw], -1)], axis=-1)


def from_quaternion(q_wxyz, t=None, *, xp=jnp):
    """Unit quaternion ``(..., 4)`` as ``(w, x, y, z)`` (normalised here) and optional
    translation ``(..., 3)`` [m] -> ``T (..., 4, 4)`` (OctoMap ``toRotMatrix``)."""
    q = _f(q_wxyz, xp)
    q = q / xp.linalg.norm(q, axis=-1, keepdims=True)
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    R = xp.stack([
        xp.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        xp.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        xp.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
    ], -2)
    if t is None:
        t = xp.zeros(q.shape[:-1] + (3,), q.dtype)
    return from_rotation_translation(R, t, xp=xp)


def to_quaternion(T, *, xp=jnp):
    """Rotation part of ``T (..., 4, 4)`` (or ``R (..., 3, 3)``) -> unit quaternion
    ``(..., 4)`` ``(w, x, y, z)`` with ``w >= 0``. Takes the numerically stable branch
    (largest diagonal term) without Python control flow, so it is exact near 180 degrees
    and works under ``jit``."""
    R = _f(T, xp)[..., :3, :3]
    m00, m11, m22 = R[..., 0, 0], R[..., 1, 1], R[..., 2, 2]
    tr = m00 + m11 + m22
    cands = xp.stack([
        xp.stack([1 + tr, R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], -1),
        xp.stack([R[..., 2, 1] - R[..., 1, 2], 1 + m00 - m11 - m22, R[..., 0, 1] + R[..., 1, 0], R[..., 0, 2] + R[..., 2, 0]], -1),
        xp.stack([R[..., 0, 2] - R[..., 2, 0], R[..., 0, 1] + R[..., 1, 0], 1 - m00 + m11 - m22, R[..., 1, 2] + R[..., 2, 1]], -1),
        xp.stack([R[..., 1, 0] - R[..., 0, 1], R[..., 0, 2] + R[..., 2, 0], R[..., 1, 2] + R[..., 2, 1], 1 - m00 - m11 + m22], -1),
    ], -2)  # (..., 4, 4): row k is 4 q_k * q
    k = xp.argmax(xp.stack([tr, m00, m11, m22], -1), axis=-1)
    q = xp.take_along_axis(cands, k[..., None, None], axis=-2)[..., 0, :]
    q = q / xp.linalg.norm(q, axis=-1, keepdims=True)
    return xp.where(q[..., :1] < 0, -q, q)


def inverse(T, *, xp=jnp):
    """Inverse of a rigid transform ``(..., 4, 4)``: ``[R^T, -R^T t]`` (not ``-t``, the bug of
    the published thesis code)."""
    T = _f(T, xp)
    Rt = xp.swapaxes(T[..., :3, :3], -1, -2)
    t = -(Rt @ T[..., :3, 3:])[..., 0]
    return from_rotation_translation(Rt, t, xp=xp)


def compose(T_a_b, T_b_c, *, xp=jnp):
    """``T_a_c = T_a_b @ T_b_c`` ``(..., 4, 4)`` (leading dims broadcast)."""
    return _f(T_a_b, xp) @ _f(T_b_c, xp)


def transform_points(T_a_b, points_b, *, xp=jnp):
    """Points ``(..., n, 3)`` [m] in frame b -> frame a with ``T_a_b (..., 4, 4)``."""
    T = _f(T_a_b, xp)
    p = xp.asarray(points_b, T.dtype)
    # three broadcast multiply-adds, not ``p @ R^T``: XLA:CPU fuses them into one loop, several
    # times faster than its matmul for (n, 3) x (3, 3) (docs/design.md, "Rigid transforms")
    col = lambda j: T[..., None, :3, j]  # noqa: E731
    return p[..., 0:1] * col(0) + p[..., 1:2] * col(1) + p[..., 2:3] * col(2) + col(3)


def skew(v, *, xp=jnp):
    """``[v]x (..., 3, 3)`` with ``[v]x u = v x u`` for ``v (..., 3)``."""
    z = xp.zeros_like(v[..., 0])
    return xp.stack([xp.stack([z, -v[..., 2], v[..., 1]], -1),
                     xp.stack([v[..., 2], z, -v[..., 0]], -1),
                     xp.stack([-v[..., 1], v[..., 0], z], -1)], -2)


def _exp_coefficients(t2, xp):
    """``sin t / t``, ``(1 - cos t) / t^2``, ``(t - sin t) / t^3`` of ``t2 = t^2``: a Taylor
    series below ``t = 0.1`` rad (exact to float32 there, NaN-free gradients at zero), the
    closed form above."""
    small = t2 < 1e-2
    t2s = xp.where(small, xp.ones_like(t2), t2)
    t = xp.sqrt(t2s)
    a = xp.where(small, 1.0 - t2 / 6.0 + t2 * t2 / 120.0, xp.sin(t) / t)
    b = xp.where(small, 0.5 - t2 / 24.0 + t2 * t2 / 720.0, (1.0 - xp.cos(t)) / t2s)
    c = xp.where(small, 1.0 / 6.0 - t2 / 120.0 + t2 * t2 / 5040.0, (t - xp.sin(t)) / (t2s * t))
    return a, b, c


def so3_exp(w, *, xp=jnp):
    """Rotation ``(..., 3, 3)`` of the rotation vector ``w (..., 3)`` [rad] (Rodrigues)."""
    w = _f(w, xp)
    a, b, _ = _exp_coefficients(xp.sum(w * w, axis=-1), xp)
    K = skew(w, xp=xp)
    return xp.eye(3, dtype=w.dtype) + a[..., None, None] * K + b[..., None, None] * (K @ K)


def so3_log(R, *, xp=jnp):
    """Rotation vector ``(..., 3)`` [rad] of ``R (..., 3, 3)``, for rotation angles below pi
    (accurate for small angles; the axis is ill-defined at pi)."""
    R = _f(R, xp)
    v = xp.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], -1)
    sq = xp.sum(v * v, axis=-1)
    tiny = sq < 1e-14  # 2 sin(theta) < 1e-7: first order, and no NaN gradient at zero
    s2 = xp.sqrt(xp.where(tiny, 1.0, sq))  # 2 sin(theta)
    th = xp.arctan2(0.5 * s2, 0.5 * (xp.trace(R, axis1=-2, axis2=-1) - 1.0))
    f = xp.where(tiny, 0.5, th / s2)
    return f[..., None] * v


def se3_exp(xi, *, xp=jnp):
    """se(3) exponential: ``xi (..., 6)`` = (v [m], omega [rad]) -> ``T (..., 4, 4)``."""
    xi = _f(xi, xp)
    v, w = xi[..., :3], xi[..., 3:]
    a, b, c = _exp_coefficients(xp.sum(w * w, axis=-1), xp)
    K = skew(w, xp=xp)
    K2 = K @ K
    eye = xp.eye(3, dtype=xi.dtype)
    R = eye + a[..., None, None] * K + b[..., None, None] * K2
    V = eye + b[..., None, None] * K + c[..., None, None] * K2
    return from_rotation_translation(R, (V @ v[..., None])[..., 0], xp=xp)


def check_rigid(T, name: str = "T", atol: float = 1e-4) -> np.ndarray:
    """Host-side validation: ``T`` as a float64 NumPy ``(..., 4, 4)`` array.

    Raises ``ValueError`` naming ``name`` if it is not a finite rigid transform: wrong shape,
    non-finite entries, bottom row not ``[0, 0, 0, 1]``, rotation not orthonormal within
    ``atol``, or determinant not +1 (a reflection)."""
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


def project_to_rigid(T) -> np.ndarray:
    """The nearest rigid transform (Frobenius norm of the rotation block, via SVD) to a
    nearly rigid ``T (4, 4)``, as float64 NumPy with bottom row ``[0, 0, 0, 1]``: removes the
    drift of a float32 solver's output so that ``check_rigid``'s tolerance holds."""
    T = np.array(T, dtype=np.float64)
    U, _, Vt = np.linalg.svd(T[:3, :3])
    T[:3, :3] = U @ np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))]) @ Vt
    T[3] = (0.0, 0.0, 0.0, 1.0)
    return T


# ----------------------------------------------------------------------------- host checks


def check_rigid_transform(T, name: str = "T_dst_src") -> np.ndarray:
    """One rigid transform, validated on the host (NumPy only), as a ``(4, 4)`` float64 array.

    Accepts ``(4, 4)`` homogeneous or ``(3, 4)`` ``[R | t]`` matrices (translation in metres).
    Raises ``ValueError`` naming ``name`` for another shape (including a batch), a NaN or
    infinite entry, or any failure of ``check_rigid`` (tolerance 1e-4: bottom row, orthonormal
    rotation with determinant +1; scale, shear and reflections are rejected). The returned
    homogeneous row is exactly ``[0, 0, 0, 1]``.
    """
    A = np.asarray(T, dtype=np.float64)
    if A.shape == (3, 4):
        A = np.vstack([A, [0.0, 0.0, 0.0, 1.0]])
    if A.shape != (4, 4):
        raise ValueError(f"{name}: expected a (4, 4) or (3, 4) rigid transform, "
                         f"got shape {A.shape}")
    if not np.all(np.isfinite(A)):  # check_rigid says "non-finite"; callers match "NaN"
        raise ValueError(f"{name}: contains NaN or infinite entries: {A.tolist()}")
    A = check_rigid(A, name).copy()
    A[3] = [0.0, 0.0, 0.0, 1.0]
    return A


# --- many


def se3_log(T, *, xp=jnp):
    """se(3) logarithm: ``T (..., 4, 4)`` -> ``xi (..., 6)`` = (v [m], omega [rad]) with
    ``se3_exp(xi) = T``, for rotation angles below pi (``so3_log``; ``v = V(omega)^-1 t`` with
    the closed form ``V^-1 = I - K / 2 + (1 - a / (2 b)) / theta^2 K^2``, a Taylor series
    below 0.1 rad)."""
    T = _f(T, xp)
    w = so3_log(T[..., :3, :3], xp=xp)
    t2 = xp.sum(w * w, axis=-1)
    a, b, _ = _exp_coefficients(t2, xp)
    small = t2 < 1e-2
    d = xp.where(small, 1.0 / 12.0 + t2 / 720.0 + t2 * t2 / 30240.0,
                 (1.0 - a / (2.0 * xp.where(small, 1.0, b))) / xp.where(small, 1.0, t2))
    K = skew(w, xp=xp)
    Vinv = xp.eye(3, dtype=T.dtype) - 0.5 * K + d[..., None, None] * (K @ K)
    v = (Vinv @ T[..., :3, 3:])[..., 0]
    return xp.concatenate([v, w], -1)


def adjoint(T, *, xp=jnp):
    """Adjoint ``Ad_T (..., 6, 6)`` of ``T (..., 4, 4)`` on ``xi = (v, omega)``:
    ``T exp(xi) T^-1 = exp(Ad_T xi)``; ``[[R, [t]x R], [0, R]]``."""
    T = _f(T, xp)
    R, t = T[..., :3, :3], T[..., :3, 3]
    top = xp.concatenate([R, skew(t, xp=xp) @ R], -1)
    bottom = xp.concatenate([xp.zeros_like(R), R], -1)
    return xp.concatenate([top, bottom], -2)


def right_jacobian_inverse(xi, *, xp=jnp):
    """First-order inverse right Jacobian of SE(3) ``(..., 6, 6)`` at ``xi (..., 6)``:
    ``log(exp(xi) exp(d)) ~ xi + (I + ad(xi) / 2) d`` with ``ad(xi) = [[[w]x, [v]x], [0, [w]x]]``
    (exact to second order in ``|xi|``; pose-graph residuals are small)."""
    xi = _f(xi, xp)
    V, W = skew(xi[..., :3], xp=xp), skew(xi[..., 3:], xp=xp)
    ad = xp.concatenate([xp.concatenate([W, V], -1), xp.concatenate([xp.zeros_like(W), W], -1)], -2)
    return xp.eye(6, dtype=xi.dtype) + 0.5 * ad
