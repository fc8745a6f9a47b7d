"""The closed-form step of ICP (thesis eq. 3.18) and the derivative of its fixed point.

``kabsch`` solves ``argmin_{R,t} sum w |R s + t - d|^2`` for fixed correspondences (weighted
Kabsch / Umeyama: SVD of the 3x3 cross-covariance, reflection-corrected; Besl & McKay 1992).
``implicit_step`` attaches to a converged transform the derivative that the implicit function
theorem gives the least-squares fixed point, without changing its value.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from ... import se3

__all__ = ["moments", "kabsch", "implicit_step"]


def moments(src, dst, wf, stride: int = 16):
    """Weighted means ``ms, md (3,)`` [m] and cross-covariance ``H = sum wf (s - ms)(d - md)^T
    (3, 3)`` of ``src, dst (n, 3)`` [m] with weights ``wf (n,)``, in one pass of 16 scalar sums
    over columns. The sums are taken about the weighted mean of every ``stride``-th point, so
    that the one-pass formula keeps float32 precision when the inliers lie far from the
    origin."""
    ws = wf[::stride]
    k = jnp.sum(ws)

    def reference(x):  # weighted mean of every stride-th row; the origin when none has weight
        mean = jnp.stack([jnp.sum(x[::stride, i] * ws) for i in range(3)]) / jnp.maximum(k, 1e-30)
        return jnp.where(k > 0, mean, 0.0)

    cs, cd = reference(src), reference(dst)
    s = [src[:, i] - cs[i] for i in range(3)]
    d = [dst[:, i] - cd[i] for i in range(3)]
    a = [s[i] * wf for i in range(3)]
    sums = [jnp.sum(a[i] * d[j]) for i in range(3) for j in range(3)]
    sums += [jnp.sum(a[i]) for i in range(3)] + [jnp.sum(wf * d[j]) for j in range(3)] + [jnp.sum(wf)]
    m = jnp.stack(sums)
    W = jnp.maximum(m[15], 1e-30)
    ms, md = m[9:12] / W, m[12:15] / W
    H = m[:9].reshape(3, 3) - W * jnp.outer(ms, md)
    return ms + cs, md + cd, H


def kabsch(src, dst, w):
    """``T (4, 4)`` minimising ``sum w |R src + t - dst|^2`` (eq. 3.18) in closed form, for
    ``src, dst (n, 3)`` [m] and weights ``w (n,)`` (bool or float)."""
    wf = w.astype(src.dtype)
    ms, md, H = moments(src, dst, wf)
    U, _, Vt = jnp.linalg.svd(H)
    V = Vt.T
    d = jnp.sign(jnp.linalg.det(V @ U.T))
    d = jnp.where(d == 0, 1.0, d)
    R = V @ jnp.diag(jnp.stack([jnp.ones_like(d), jnp.ones_like(d), d])) @ U.T
    t = md - R @ ms
    return se3.from_rotation_translation(R, t)


def implicit_step(T_hat, src, tgt_pts, w):
    """``T_hat (4, 4)`` (value unchanged) carrying the implicit-function-theorem derivative of
    the least-squares fixed point with respect to ``src`` and ``tgt_pts (n, 3)`` [m] under the
    correspondences ``w (n,)``.

    ``T*`` satisfies ``g(T*; src, tgt) = 0``, the gradient of eq. 3.18 in a left perturbation
    about the inlier centroid ``c`` (``J_i = [I, -[p_i - c]x]``); so ``dT* = -H^{-1} dg`` with
    ``H`` the 6x6 Gauss-Newton matrix: the derivative of one Newton step ``Xi(src, tgt) T_hat``
    with ``H`` and ``c`` held fixed (``_newton_step``). The value is ``T_hat`` itself; the step
    is traced only under differentiation (a ``custom_jvp``), so a forward run computes nothing
    here. ``dT*/dT_init = 0``, and ``w`` has no derivative."""
    return _fixed_point(jax.lax.stop_gradient(T_hat), src, tgt_pts,
                        jax.lax.stop_gradient(w).astype(src.dtype))


@jax.custom_jvp
def _fixed_point(T_hat, src, tgt_pts, w):
    return T_hat


@_fixed_point.defjvp
def _fixed_point_jvp(primals, tangents):
    T_hat, src, tgt_pts, w = primals
    _, d_src, d_tgt, _ = tangents
    _, d_T = jax.jvp(lambda s, t: _newton_step(T_hat, s, t, w), (src, tgt_pts), (d_src, d_tgt))
    return T_hat, d_T


def _newton_step(T_hat, src, tgt_pts, w):
    """``Xi T_hat (4, 4)``: the Gauss-Newton step of eq. 3.18 at ``T_hat`` (``implicit_step``),
    ``H`` and the centroid ``c`` without derivative."""
    n = jnp.maximum(jnp.sum(w), 1.0)
    p = se3.transform_points(T_hat, src)
    c = jax.lax.stop_gradient(jnp.sum(w[:, None] * p, 0) / n)
    pc = p - c
    r = p - tgt_pts
    # left perturbation about c: x' = x + [omega]x (x - c) + v;  J_i = [I, -[pc_i]x]
    g = jnp.concatenate([jnp.sum(w[:, None] * r, 0), jnp.sum(w[:, None] * jnp.cross(pc, r), 0)])
    spc = jnp.sum(w[:, None] * pc, 0)
    K = se3.skew(pc)
    Hrr = -jnp.einsum("n,nij,njk->ik", w, K, K)
    Htr = -se3.skew(spc)
    H = jnp.block([[n * jnp.eye(3, dtype=src.dtype), Htr], [-Htr, Hrr]])
    H = jax.lax.stop_gradient(H)
    lam = 1e-6 * jnp.trace(H) / 6.0 + 1e-12
    delta = -jnp.linalg.solve(H + lam * jnp.eye(6, dtype=src.dtype), g)
    delta = jnp.where(jnp.all(jnp.isfinite(delta)), delta, jnp.zeros_like(delta))
    v, om = delta[:3], delta[3:]
    Om = se3.skew(om)
    Xi = jnp.zeros((4, 4), src.dtype).at[:3, :3].set(Om).at[:3, 3].set(v - Om @ c)
    return Xi @ T_hat
