"""The least-squares step of ICP (eq. 3.18): closed-form Kabsch vs Gauss-Newton on an se(3)
increment (hand-written normal equations, and jaxopt's ``GaussNewton`` / ``LevenbergMarquardt``).

Two measurements on the benchmark room pair's occupied clouds (``_testing.scene_pair``):

1. **One solve** on fixed correspondences (nearest target within 2 res, found at a start
   rotated / shifted from the truth like an ICP iterate): time of the jitted solve (median
   of warm calls, float32 as ICP runs) and its distance to the exact minimiser (float64
   Kabsch on the host), after 1, 2, 3 Gauss-Newton iterations started at that iterate.
2. **Outer iterations**: a plain ICP loop at a fixed correspondence distance (2 res), nearest
   neighbours by SciPy's cKDTree on the host (the same for every solver), each solver used as
   the step; iterations until the change ``sum |T_k - T_{k-1}|`` < res / 6000 (ICP's
   ``final_epsilon``) and the final distance to the Kabsch loop's fixed point. Every outer
   iteration costs one nearest-neighbour query of all source points, which is what an
   iteration of ``icp`` spends its time on (its ms per iteration is printed for scale).

    .venv/bin/python benchmarks/bench_icp_solver.py --res 0.1 0.05
"""

from __future__ import annotations

import argparse
import importlib
import platform
import time
import warnings

import _host_memory
import jax
import jax.numpy as jnp
import functools

import numpy as np
from scipy.spatial import cKDTree

from octomerge_jax import se3 as rigid
from octomerge_jax.registration import metrics, overlap
from octomerge_jax.sim import scene_pair
from octomerge_jax import se3
xyz_rpy64 = functools.partial(se3.from_xyz_rpy, xp=np)  # float64 ground truth

icp_mod = importlib.import_module("octomerge_jax.registration.icp")


def kabsch64(src, dst, w):
    """Exact weighted minimiser of eq. 3.18 in float64 (NumPy), the reference."""
    w = w.astype(np.float64)
    n = w.sum()
    ms, md = (w[:, None] * src).sum(0) / n, (w[:, None] * dst).sum(0) / n
    H = ((src - ms) * w[:, None]).T @ (dst - md)
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(Vt.T @ U.T))
    R = Vt.T @ np.diag([1.0, 1.0, d]) @ U.T
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, md - R @ ms
    return T


def _increment(T, xi):
    """``exp(xi) T`` with ``xi = (rotation vector [rad], translation [m])`` (left perturbation)."""
    R = icp_mod._so3_exp(xi[:3])
    return rigid.from_rotation_translation(R @ T[:3, :3], R @ T[:3, 3] + xi[3:])


def gauss_newton(src, dst, w, T, iters):
    """``iters`` Gauss-Newton steps on the 6x6 normal equations of eq. 3.18 (point-to-point
    Jacobian ``[-[p]x, I]``), each increment applied through the exponential map."""
    wf = w.astype(src.dtype)

    def step(T, _):
        p = rigid.transform_points(T, src)
        r = p - dst
        J_rot = -icp_mod._skew(p)  # d(R p)/d(omega) = -[p]x for a left increment
        A = jnp.concatenate([J_rot, jnp.broadcast_to(jnp.eye(3, dtype=src.dtype), J_rot.shape)], -1)
        H = jnp.einsum("n,nji,njk->ik", wf, A, A)
        g = jnp.einsum("n,nji,nj->i", wf, A, r)
        xi = -jnp.linalg.solve(H + 1e-9 * jnp.eye(6, dtype=src.dtype), g)
        return _increment(T, xi), None

    return jax.lax.scan(step, T, None, length=iters)[0]


def jaxopt_solver(kind, iters):
    with warnings.catch_warnings():  # jaxopt's "no longer maintained" notice
        warnings.filterwarnings("ignore", message="JAXopt is no longer maintained", category=DeprecationWarning)
        import jaxopt

    def residual(xi, src, dst, sw, T):
        return (sw[:, None] * (rigid.transform_points(_increment(T, xi), src) - dst)).ravel()

    cls = jaxopt.GaussNewton if kind == "gn" else jaxopt.LevenbergMarquardt
    solver = cls(residual_fun=residual, maxiter=iters, tol=0.0, implicit_diff=False, jit=True)

    def run(src, dst, w, T):
        xi, _ = solver.run(jnp.zeros((6,), src.dtype), src, dst, jnp.sqrt(w.astype(src.dtype)), T)
        return _increment(T, xi)

    return run


def solvers():
    out = {"kabsch (ours)": lambda s, d, w, T: icp_mod._kabsch(s, d, w)}
    for k in (1, 2, 3):
        out[f"GN x{k}"] = lambda s, d, w, T, k=k: gauss_newton(s, d, w, T, k)
    for k in (1, 3):
        out[f"jaxopt GN x{k}"] = jaxopt_solver("gn", k)
    out["jaxopt LM x3"] = jaxopt_solver("lm", 3)
    return {name: jax.jit(f) for name, f in out.items()}


def timed(f, *args, repeats=20):
    out = jax.block_until_ready(f(*args))
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = jax.block_until_ready(f(*args))
        ts.append(time.perf_counter() - t0)
    return out, float(np.median(ts))


def gaps(T, T_ref):
    return float(metrics.rotation_angle_error(T, T_ref)), float(metrics.translation_distance(T, T_ref))


def shifted(T, a, b):
    """``T`` re-expressed between frames shifted by ``a`` (source) and ``b`` (target) [m], as
    ``icp`` centres both clouds: ``shifted(T, cs, ct)`` centres, ``shifted(T, -cs, -ct)`` undoes it."""
    out = np.array(T, np.float64)
    out[:3, 3] = out[:3, :3] @ a + out[:3, 3] - b
    return out


def clouds(res):
    P1, P2, T12 = scene_pair(res)
    o = overlap(P1, P2, T12, "bbox")
    return P1[np.asarray(o.mask_1)], P2[np.asarray(o.mask_2)], T12


def bench_one_solve(res, starts, table):
    tgt, src, T12 = clouds(res)
    tree = cKDTree(tgt)
    # centred, as icp works (float32 precision does not depend on where the maps lie)
    cs, ct = src.mean(0), tgt.mean(0)
    for yaw, shift in starts:
        T0 = T12 @ xyz_rpy64(shift, -shift, 0.0, 0.0, 0.0, yaw)
        d, j = tree.query(src @ T0[:3, :3].T + T0[:3, 3], distance_upper_bound=2 * res)
        w = np.isfinite(d)
        dst = np.where(w[:, None], tgt[np.minimum(j, len(tgt) - 1)], 0.0)
        s, q = src - cs, dst - ct
        T0c = shifted(T0, cs, ct)
        T_ref = kabsch64(s[w], q[w], np.ones(w.sum()))
        args = (jnp.asarray(s, jnp.float32), jnp.asarray(q, jnp.float32), jnp.asarray(w), jnp.asarray(T0c, jnp.float32))
        step = gaps(T0c, T_ref)
        for name, f in table.items():
            T, t = timed(f, *args)
            er, et = gaps(np.asarray(T, np.float64), T_ref)
            print(f"{res:5.2f} {len(src):7d} {int(w.sum()):7d} {yaw:6.2f} {shift:6.2f} {step[0]:8.4f} {step[1]:7.4f} "
                  f"| {name:>14} {t * 1e3:8.3f} {er:10.2e} {et:10.2e}", flush=True)


def icp_loop(src, tgt, T0, res, step, max_iter=300):
    """Plain point-to-point ICP at distance 2 res on the host's kd-tree; ``step`` solves."""
    tree = cKDTree(tgt)
    T = T0.astype(np.float64)
    eps = res / 6000.0
    s32 = jnp.asarray(src, jnp.float32)
    for it in range(1, max_iter + 1):
        d, j = tree.query(src @ T[:3, :3].T + T[:3, 3], distance_upper_bound=2 * res)
        w = np.isfinite(d)
        dst = np.where(w[:, None], tgt[np.minimum(j, len(tgt) - 1)], 0.0)
        T_new = np.asarray(step(s32, jnp.asarray(dst, jnp.float32), jnp.asarray(w), jnp.asarray(T, jnp.float32)),
                           np.float64)
        change = np.abs(T_new - T).sum()
        T = T_new
        if change < eps:
            return T, it
    return T, max_iter


def bench_outer(res, starts, table):
    tgt, src, T12 = clouds(res)
    cs, ct = src.mean(0), tgt.mean(0)
    s, q = src - cs, tgt - ct
    r = icp_mod.icp(src, tgt, T12, resolution=res)
    t_icp = timed(lambda: icp_mod.icp(src, tgt, T12, resolution=res).T_target_source, repeats=3)[1]
    print(f"(scale: icp from the truth at {res} m: {int(r.num_iterations)} iterations in {t_icp:.2f} s, "
          f"{1e3 * t_icp / max(int(r.num_iterations), 1):.1f} ms per iteration incl. grid build)")
    for yaw, shift in starts:
        T0c = shifted(T12 @ xyz_rpy64(shift, -shift, 0.0, 0.0, 0.0, yaw), cs, ct)
        T_fix, n_ref = icp_loop(s, q, T0c, res, table["kabsch (ours)"])
        for name, f in table.items():
            T, n = (T_fix, n_ref) if name == "kabsch (ours)" else icp_loop(s, q, T0c, res, f)
            er, et = gaps(T, T_fix)
            e_true = gaps(shifted(T, -cs, -ct), T12)
            print(f"{res:5.2f} {yaw:6.2f} {shift:6.2f} | {name:>14} {n:6d} {er:10.2e} {et:10.2e} "
                  f"{e_true[0]:9.4f} {e_true[1]:8.4f}", flush=True)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--res", type=float, nargs="+", default=[0.1, 0.05])
    _host_memory.add_flag(ap)
    args = ap.parse_args()
    reuse = _host_memory.apply(args)
    print(f"# bench_icp_solver  jax {jax.__version__}  {platform.machine()}  cpu x{len(jax.devices('cpu'))}  "
          f"reuse-host-memory {reuse}")
    table = solvers()
    starts = [(0.01, 0.02), (0.05, 0.1), (0.2, 0.3)]
    print("\n## one solve on fixed correspondences (time: median warm call; error: to the float64 minimiser)")
    print(f"{'res':>5} {'n_src':>7} {'inliers':>7} {'yaw':>6} {'shift':>6} {'step rad':>8} {'step m':>7} "
          f"| {'solver':>14} {'ms':>8} {'rot err':>10} {'t err':>10}")
    for res in args.res:
        bench_one_solve(res, starts, table)
    print("\n## outer iterations of a plain ICP loop at 2 res (host kd-tree), each solver as the step")
    print(f"{'res':>5} {'yaw':>6} {'shift':>6} | {'solver':>14} {'iters':>6} {'rot gap':>10} {'t gap':>10} "
          f"{'rot err':>9} {'t err':>8}   (gap: to the Kabsch loop's end; err: to the truth)")
    for res in args.res:
        bench_outer(res, starts[:2], table)


if __name__ == "__main__":
    main()
