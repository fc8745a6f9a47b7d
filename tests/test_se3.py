"""se3.py: the NumPy and JAX paths agree, exp/log invert each other, and every differentiable
function's Jacobian is right forward, reverse and against finite differences (float64 inside
``jax.enable_x64``), over batch shapes and near the singular points (zero angle)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads

from octomerge_jax import se3

RNG = np.random.default_rng(7)
BATCHES = [(), (3,), (2, 4)]


def _pose(batch):
    return se3.from_xyz_rpy(*[RNG.uniform(-2, 2, batch) for _ in range(3)],
                            *[RNG.uniform(-1.2, 1.2, batch) for _ in range(3)], xp=np)


@pytest.mark.parametrize("batch", BATCHES)
def test_numpy_and_jax_paths_agree(batch):
    T = _pose(batch)
    xi = RNG.normal(size=batch + (6,))
    with jax.enable_x64(True):
        for f, args in [(se3.to_xyz_rpy, (T,)), (se3.to_quaternion, (T,)), (se3.inverse, (T,)),
                        (se3.so3_log, (T[..., :3, :3],)), (se3.se3_exp, (xi,)), (se3.se3_log, (T,)), (se3.so3_exp, (xi[..., 3:],)),
                        (se3.skew, (xi[..., :3],)), (se3.compose, (T, se3.inverse(T, xp=np)))]:
            np.testing.assert_allclose(np.asarray(jax.jit(f)(*[jnp.asarray(a) for a in args])), f(*args, xp=np),
                                       atol=1e-12, err_msg=f.__name__)
    np.testing.assert_allclose(se3.compose(T, se3.inverse(T, xp=np), xp=np),
                               np.broadcast_to(np.eye(4), batch + (4, 4)), atol=1e-12)


@pytest.mark.parametrize("batch", BATCHES)
def test_exp_log_round_trip_and_small_angles(batch):
    w = RNG.normal(size=batch + (3,))
    w *= RNG.uniform(0.0, 3.0, batch + (1,)) / np.linalg.norm(w, axis=-1, keepdims=True)
    R = se3.so3_exp(w, xp=np)
    np.testing.assert_allclose(np.swapaxes(R, -1, -2) @ R, np.broadcast_to(np.eye(3), R.shape), atol=1e-12)
    np.testing.assert_allclose(se3.so3_log(R, xp=np), w, atol=1e-9)
    for angle in (0.0, 1e-9, 1e-4, 0.099, 0.101):  # both sides of the Taylor branch at 0.1 rad
        v = np.array([0.3, -0.4, 0.5]) / np.linalg.norm([0.3, -0.4, 0.5]) * angle
        np.testing.assert_allclose(se3.so3_exp(v, xp=np), _rodrigues(v), atol=1e-15)
        np.testing.assert_allclose(se3.so3_log(se3.so3_exp(v, xp=np), xp=np), v, atol=1e-12)


def _rodrigues(w):
    th = np.linalg.norm(w)
    K = se3.skew(w, xp=np)
    if th == 0:
        return np.eye(3)
    return np.eye(3) + np.sin(th) / th * K + (1 - np.cos(th)) / th ** 2 * K @ K


def test_se3_exp_matches_matrix_exponential():
    from scipy.linalg import expm

    for scale in (1e-6, 0.05, 0.5, 2.0):
        xi = RNG.normal(size=6) * scale
        X = np.zeros((4, 4))
        X[:3, :3] = se3.skew(xi[3:], xp=np)
        X[:3, 3] = xi[:3]
        np.testing.assert_allclose(se3.se3_exp(xi, xp=np), expm(X), atol=1e-12)


_FUNCTIONS = {
    "from_xyz_rpy": (lambda x: se3.from_xyz_rpy(*[x[..., i] for i in range(6)]), 6),
    "to_xyz_rpy": (lambda x: se3.to_xyz_rpy(se3.from_xyz_rpy(*[x[..., i] for i in range(6)])), 6),
    "from_quaternion": (lambda x: se3.from_quaternion(x[..., :4], x[..., 4:]), 7),
    "to_quaternion": (lambda x: se3.to_quaternion(se3.so3_exp(x)), 3),
    "inverse": (lambda x: se3.inverse(se3.se3_exp(x)), 6),
    "compose": (lambda x: se3.compose(se3.se3_exp(x[..., :6]), se3.se3_exp(x[..., 6:])), 12),
    "transform_points": (lambda x: se3.transform_points(se3.se3_exp(x[..., :6]), x[..., None, 6:]), 9),
    "so3_exp": (se3.so3_exp, 3),
    "so3_log": (lambda x: se3.so3_log(se3.so3_exp(x)), 3),
    "se3_exp": (se3.se3_exp, 6),
    "se3_log": (lambda x: se3.se3_log(se3.se3_exp(x)), 6),
}


@pytest.mark.parametrize("name", sorted(_FUNCTIONS))
@pytest.mark.parametrize("batch", [(2,)])
def test_jacobians_forward_reverse_and_finite_differences(name, batch):
    """jaxlie's test_autodiff: ``check_grads`` compares jvp and vjp with central finite
    differences, in float64."""
    f, dim = _FUNCTIONS[name]
    x = RNG.uniform(-0.8, 0.8, batch + (dim,))
    if name == "from_quaternion":
        x[..., 0] += 2.0  # away from q = 0
    with jax.enable_x64(True):
        # jitted: the same derivatives, three compiled programs instead of every primitive compiled eagerly
        check_grads(jax.jit(f), (jnp.asarray(x, jnp.float64),), order=1, modes=("fwd", "rev"), atol=1e-6, rtol=1e-6)


@pytest.mark.parametrize("name", ["so3_exp", "se3_exp", "so3_log", "se3_log"])
def test_gradients_finite_at_zero(name):
    f, dim = _FUNCTIONS[name]
    with jax.enable_x64(True):
        J = jax.jit(jax.jacfwd(f))(jnp.zeros(dim, jnp.float64))
        Jr = jax.jit(jax.jacrev(f))(jnp.zeros(dim, jnp.float64))
    assert np.all(np.isfinite(J)) and np.all(np.isfinite(Jr))
    np.testing.assert_allclose(J, Jr, atol=1e-12)
    if name == "so3_exp":  # d exp(w) / dw at 0 is the generator: d/dw_k = [e_k]x
        np.testing.assert_allclose(np.moveaxis(np.asarray(J), -1, 0), se3.skew(np.eye(3), xp=np), atol=1e-12)


def test_project_to_rigid_and_check_rigid():
    T = _pose(())
    noisy = T.copy()
    noisy[:3, :3] += 1e-3 * RNG.normal(size=(3, 3))
    with pytest.raises(ValueError, match="noisy: rotation block is not orthonormal"):
        se3.check_rigid(noisy, "noisy")
    fixed = se3.project_to_rigid(noisy)
    se3.check_rigid(fixed, "fixed", atol=1e-12)
    np.testing.assert_allclose(fixed[:3, :3], T[:3, :3], atol=5e-3)
    np.testing.assert_array_equal(fixed[3], [0, 0, 0, 1])
    np.testing.assert_array_equal(fixed[:3, 3], noisy[:3, 3])


@pytest.mark.parametrize("batch", BATCHES)
def test_se3_log_inverts_se3_exp(batch):
    xi = RNG.normal(size=batch + (6,))
    xi[..., 3:] *= RNG.uniform(0.0, 3.0, batch + (1,)) / np.linalg.norm(xi[..., 3:], axis=-1, keepdims=True)
    np.testing.assert_allclose(se3.se3_log(se3.se3_exp(xi, xp=np), xp=np), xi, atol=1e-9)
    np.testing.assert_allclose(se3.se3_log(np.eye(4), xp=np), np.zeros(6), atol=1e-15)
