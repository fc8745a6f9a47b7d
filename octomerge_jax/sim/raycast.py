"""Batched ray-triangle intersection (Moller-Trumbore) in JAX, chunked with ``lax.map``.

Every ray is tested against every triangle of the scene: scenes built here are low-poly
(boxes and wall slabs, a few hundred triangles), where the brute force is a dense, branch-free
``(chunk, T)`` computation that XLA fuses well. A uniform grid or BVH only pays for meshes
with many thousands of triangles; see the note in ``sim/__init__.py`` for the measurement.

Reference: T. Moller and B. Trumbore, "Fast, minimum storage ray-triangle intersection",
J. Graphics Tools 2(1), 1997. Tested against trimesh's ``ray_triangle`` intersector.
"""

from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp
import numpy as np

__all__ = ["mesh_triangles", "cast_rays", "cast_rays_host"]

_EPS_DET = 1e-12


def mesh_triangles(mesh) -> np.ndarray:
    """``(T, 3, 3)`` float32 vertex coordinates [m] of a trimesh mesh's faces."""
    tris = np.asarray(mesh.triangles, dtype=np.float32)
    if tris.ndim != 3 or tris.shape[1:] != (3, 3):
        raise ValueError(f"mesh: expected triangles of shape (T, 3, 3), got {tris.shape}")
    return tris


def _intersect_chunk(origins, directions, tri, t_min):
    """Nearest hit distance of ``(R,)`` rays against all triangles -> ``(R,)``, inf on miss.

    ``tri`` is a tuple of 9 ``(1, T)`` rows: v0, e1 = v1 - v0, e2 = v2 - v0 per axis. Written
    component-wise on ``(R, T)`` planes so XLA fuses the whole test into one loop nest.
    """
    v0x, v0y, v0z, e1x, e1y, e1z, e2x, e2y, e2z = tri
    ox, oy, oz = (origins[:, i:i + 1] for i in range(3))
    dx, dy, dz = (directions[:, i:i + 1] for i in range(3))
    px = dy * e2z - dz * e2y
    py = dz * e2x - dx * e2z
    pz = dx * e2y - dy * e2x
    det = e1x * px + e1y * py + e1z * pz
    ok_det = jnp.abs(det) > _EPS_DET
    inv_det = 1.0 / jnp.where(ok_det, det, 1.0)
    sx, sy, sz = ox - v0x, oy - v0y, oz - v0z
    u = (sx * px + sy * py + sz * pz) * inv_det
    qx = sy * e1z - sz * e1y
    qy = sz * e1x - sx * e1z
    qz = sx * e1y - sy * e1x
    v = (dx * qx + dy * qy + dz * qz) * inv_det
    t = (e2x * qx + e2y * qy + e2z * qz) * inv_det
    hit = ok_det & (u >= 0.0) & (v >= 0.0) & (u + v <= 1.0) & (t > t_min)
    return jnp.min(jnp.where(hit, t, jnp.inf), axis=1)


@partial(jax.jit, static_argnames=("chunk",))
def cast_rays(triangles, origins, directions, t_min=1e-6, *, chunk: int = 1024):
    """Distance along each ray to the nearest triangle.

    Args:
      triangles: ``(T, 3, 3)`` float32 vertices [m].
      origins: ``(R, 3)`` ray origins [m].
      directions: ``(R, 3)`` ray directions; distances are in units of their length (pass
        unit vectors to get metres).
      t_min: hits at ``t <= t_min`` are ignored (self-intersection guard).
      chunk: rays per ``lax.map`` step (static).

    Returns:
      ``(R,)`` float32 distances, ``inf`` where the ray hits nothing.
    """
    tris = jnp.asarray(triangles, jnp.float32)
    origins = jnp.asarray(origins, jnp.float32)
    directions = jnp.asarray(directions, jnp.float32)
    v0 = tris[:, 0]
    e1 = tris[:, 1] - v0
    e2 = tris[:, 2] - v0
    tri = tuple(a[None, :, i] for a in (v0, e1, e2) for i in range(3))
    r = origins.shape[0]
    n_chunks = max(1, -(-r // chunk))
    pad = n_chunks * chunk - r
    o = jnp.pad(origins, ((0, pad), (0, 0))).reshape(n_chunks, chunk, 3)
    dr = jnp.pad(directions, ((0, pad), (0, 0)), constant_values=1.0).reshape(n_chunks, chunk, 3)
    t_min = jnp.asarray(t_min, jnp.float32)
    out = jax.lax.map(lambda od: _intersect_chunk(od[0], od[1], tri, t_min), (o, dr))
    return out.reshape(-1)[:r]


def cast_rays_host(triangles, origins, directions, *, chunk: int = 1024) -> np.ndarray:
    """Host wrapper of ``cast_rays``: pads the ray count to a power of two (so calls with
    similar ray counts share one compiled function) and returns a NumPy ``(R,)`` array."""
    origins = np.asarray(origins, np.float32).reshape(-1, 3)
    directions = np.asarray(directions, np.float32).reshape(-1, 3)
    r = origins.shape[0]
    if r == 0:
        return np.zeros(0, np.float32)
    cap = max(chunk, 1 << int(np.ceil(np.log2(r))))
    o = np.zeros((cap, 3), np.float32)
    d = np.zeros((cap, 3), np.float32)
    d[:, 0] = 1.0
    o[:r], d[:r] = origins, directions
    return np.asarray(cast_rays(triangles, o, d, chunk=min(chunk, cap)))[:r]
