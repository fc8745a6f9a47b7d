"""Dense map-to-map alignment (registration/_dense/): timing and accuracy vs ICP.

1. Time per L-BFGS iteration and to converge for three map sizes (the synthetic two-robot room
   at 0.4, 0.2 and 0.1 m): first call (compile + run) apart from the median of steady runs.
2. The Table 7.1 grid of initial errors (thesis §7.1.3, the rows of bench_icp.py; the truth is
   a pi/4 yaw plus an offset): for each row the initial eps_r / eps_t (eqs. 7.2 / 7.3), then the
   final rotation-angle error [rad] / translation distance [m] and status of ICP (Alg. 3 on the
   occupied voxel centres, bbox overlap as the pipeline), dense alignment, ICP then dense (every
   level), and ``merge(refine="icp+dense")``'s registration (``pipeline.register``: dense from the
   level of ICP's last correspondence distance, from the guess if that fails); and how many rows
   each brings within one voxel and 0.01 rad of the truth.

3. With ``--solvers`` only: the two minimiser backends (``solver="lbfgs"``, the default, and
   ``"jaxopt"``) on one small problem: compile apart from steady state, final loss, iterations.

Run: ``.venv/bin/python benchmarks/bench_dense.py [--quick] [--solvers]`` (``--quick``: one steady
repeat).
Prints markdown tables."""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import time

import jax
import functools

import numpy as np

from octomerge_jax import MergeConfig, tree
from octomerge_jax.pipeline import register
from octomerge_jax.registration import icp, metrics, overlap, pad_points, prepare_alignment, solve_alignment
from octomerge_jax.sim import surface_samples
from octomerge_jax import se3
xyz_rpy64 = functools.partial(se3.from_xyz_rpy, xp=np)  # float64 ground truth

T_TRUE = xyz_rpy64(1.0, -0.5, 0.0, 0.0, 0.0, np.pi / 4)

# Table 7.1 rows exactly as benchmarks/bench_icp.py: the thesis's guess (translation, rpy) for
# an exact transform of yaw -pi/4; the row's error E = guess exact^-1 is applied to our truth
# (rotation E_R R, translation t + E_t), so eps before refinement matches the thesis's table.
TABLE_7_1 = [((0, 0, 0), (0, 0, -0.5)), ((0, 0, 0), (0, 0, -0.52)), ((0, 0, 0), (0, 0, -0.6)),
             ((0, 0, 0), (0, 0, -np.pi / 4)), ((0, 0, 0), (0, 0, -0.8)), ((0, 0, 0), (0, 0, -0.87)),
             ((0, 0, 0), (0, 0, -0.9)), ((1, 0, 0), (0, 0, -np.pi / 4)), ((0, 1, 0), (0, 0, -np.pi / 4)),
             ((1, 1, 1), (0, 0, -0.6)), ((1, 1, 1), (0, 0, -0.8)), ((0, 0, 0), (-0.1, 0, -np.pi / 4)),
             ((0, 0, 0), (0, -0.1, -np.pi / 4)), ((0, 0, 0), (-0.1, -0.1, -np.pi / 4)),
             ((1, 1, 0), (-0.1, 0, -np.pi / 4)), ((0, 0, 1), (-0.1, 0, -np.pi / 4)),
             ((1, 1, 0), (0, -0.1, -np.pi / 4)), ((0, 0, 1), (0, -0.1, -np.pi / 4))]


def thesis_guess(t, rpy, T=T_TRUE):
    """Initial guess of a Table 7.1 row (as bench_icp.bench_grid)."""
    E = xyz_rpy64(*t, *rpy) @ np.linalg.inv(xyz_rpy64(0, 0, 0, 0, 0, -np.pi / 4))
    T0 = np.eye(4)
    T0[:3, :3] = E[:3, :3] @ T[:3, :3]
    T0[:3, 3] = T[:3, 3] + E[:3, 3]
    return T0


def room_maps(res, T_1_2=T_TRUE, crop_1=(-1.0, 8.0), crop_2=(3.5, 13.0)):
    """Two robots' maps of the synthetic room (occupied surfaces, free interior), as in
    tests/test_dense.py."""
    occ_w = surface_samples(res / 3.0)
    grid = np.mgrid[0.05:11.95:res / 2, 0.05:8.95:res / 2, 0.05:2.95:res / 2].reshape(3, -1).T
    maps = []
    for T_w_f, crop in ((np.eye(4), crop_1), (T_1_2, crop_2)):
        T_f_w = np.linalg.inv(T_w_f)
        o = occ_w[(occ_w[:, 0] >= crop[0]) & (occ_w[:, 0] <= crop[1])]
        f = grid[(grid[:, 0] >= crop[0]) & (grid[:, 0] <= crop[1])]
        ko = np.unique(np.floor((o @ T_f_w[:3, :3].T + T_f_w[:3, 3]) / res).astype(np.int64), axis=0)
        kf = np.unique(np.floor((f @ T_f_w[:3, :3].T + T_f_w[:3, 3]) / res).astype(np.int64), axis=0)
        lin = lambda k: (k[:, 0] << 40) + (k[:, 1] << 20) + k[:, 2]  # noqa: E731
        kf = kf[~np.isin(lin(kf), lin(ko))]
        lo = np.concatenate([np.full(len(ko), 2.0), np.full(len(kf), -1.5)]).astype(np.float32)
        maps.append(tree.from_voxels((np.concatenate([ko, kf]) + 0.5) * res, lo, res))
    return maps[0], maps[1]


def guess(e, T=T_TRUE):
    return xyz_rpy64(*e[:3], 0, 0, 0) @ T @ xyz_rpy64(0, 0, 0, *e[3:])


def timed(fn, repeats):
    t = time.perf_counter()
    out = jax.block_until_ready(fn())
    first = time.perf_counter() - t
    steady = []
    for _ in range(repeats):
        t = time.perf_counter()
        jax.block_until_ready(fn())
        steady.append(time.perf_counter() - t)
    return out, first, statistics.median(steady)


def timing_table(resolutions, max_points, repeats):
    print("\n## Time per iteration and to converge (one guess: 0.4 m, 0.1 rad yaw error)\n")
    print("| res [m] | leaves 1 / 2 | points/level | levels | compile+1st [s] | steady [s] | "
          "iterations | ms/iter | status | rot err [rad] | tr err [m] |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for res in resolutions:
        m1, m2 = room_maps(res)
        problem = prepare_alignment(m1, m2, max_points=max_points)
        T0 = guess((0.4, -0.3, 0.0, 0.0, 0.0, 0.1))
        r, first, steady = timed(lambda: solve_alignment(problem, T0), repeats)
        it = int(r.num_iterations)
        print(f"| {res:.2f} | {m1.num_leaves} / {m2.num_leaves} | {problem.points2.shape[1]} | "
              f"{problem.levels} | {first:.1f} | {steady:.2f} | {it} | {1e3 * steady / max(it, 1):.1f} | "
              f"{int(r.status)} | {float(metrics.rotation_angle_error(r.T_1_2, T_TRUE)):.4f} | "
              f"{float(metrics.translation_distance(r.T_1_2, T_TRUE)):.3f} |", flush=True)


def solver_table(res, levels, max_points, repeats):
    """The two minimiser backends (``solver="lbfgs"`` / ``"jaxopt"``) on one problem: one guess,
    then four guesses in one ``vmap``."""
    print(f"\n## Minimiser backends (res {res} m, levels {levels}, {max_points} points, maxiter 20; "
          "one guess 0.36 m / 0.1 rad off, then 4 guesses in one vmap)\n")
    print("| solver | guesses | compile+1st [s] | steady [s] | loss | iterations per level | status |")
    print("|---|---|---|---|---|---|---|")
    m1, m2 = room_maps(res)
    problem = prepare_alignment(m1, m2, levels=levels, max_points=max_points)
    errors = [(0.3, -0.2, 0.0, 0.0, 0.0, 0.1), (0.1, 0.2, 0.0, 0.0, 0.0, -0.1), (0.2, 0.0, 0.1, 0.05, 0.0, 0.0),
              (-0.2, 0.1, 0.0, 0.0, 0.0, 0.15)]
    T0 = np.stack([guess(e) for e in errors])
    ends = []
    for solver in ("lbfgs", "jaxopt"):
        for T in (T0[0], T0):
            r, first, steady = timed(lambda: solve_alignment(problem, T, maxiter=20, solver=solver), repeats)
            if T.ndim == 2:
                ends.append(r.T_1_2)
            print(f"| {solver} | {1 if T.ndim == 2 else len(T)} | {first:.1f} | {steady:.3f} | "
                  f"{np.round(np.asarray(r.loss, np.float64), 5).tolist()} | {np.asarray(r.iterations).tolist()} | "
                  f"{np.asarray(r.status).tolist()} |", flush=True)
    print(f"\none guess: the two backends' ends differ by {float(metrics.translation_distance(*ends)):.4f} m "
          f"and {float(metrics.rotation_angle_error(*ends)):.4f} rad")


def _orthonormal(T):
    """float32 results -> float64 rigid transforms (host rigidity checks)."""
    T = np.array(T, np.float64)
    U, _, Vt = np.linalg.svd(T[..., :3, :3])
    T[..., :3, :3] = U @ Vt
    T[..., 3, :] = (0.0, 0.0, 0.0, 1.0)
    return T


def run_icp(m1, m2, T_inits, res):
    """Pipeline-style ICP per row: occupied voxel centres, thesis bbox overlap (Alg. 2) under
    the row's guess, then ``icp`` (fixed capacities: one compilation for the grid).
    Returns ``(T (n, 4, 4), status (n,))``."""
    occ = lambda m: m.leaves().centers[m.leaves().log_odds > 0].astype(np.float32)  # noqa: E731
    p1, p2 = occ(m1), occ(m2)
    cap1, cap2 = pad_points(p1)[0].shape[0], pad_points(p2)[0].shape[0]
    Ts, status = [], []
    for T0 in T_inits:
        o = overlap(p1, p2, T0, "bbox")
        q1, q2 = p1[np.asarray(o.mask_1)], p2[np.asarray(o.mask_2)]
        s, sc = pad_points(q2, cap2)
        t, tc = pad_points(q1, cap1)
        r = icp(s, t, T0, resolution=res, source_count=sc, target_count=tc)
        Ts.append(np.asarray(r.T_target_source, np.float64))
        status.append(int(r.status))
    return _orthonormal(np.stack(Ts)), np.asarray(status)


def accuracy_table(res, max_points):
    print(f"\n## Table 7.1-style grid at res {res} m (synthetic two-robot room, map 2 yawed pi/4)\n")
    print("Each cell: rotation-angle error [rad] / translation distance [m] to the truth, then the "
          "status (ICP: 0 converged, 1 max iterations, 2 too few inliers; dense: 0 converged, "
          "1 max iterations, 3 poor agreement, 4 low overlap, 5 not finite: registration.Status). "
          "'*' = within one voxel and 0.01 rad.\n")
    m1, m2 = room_maps(res)
    T_inits = np.stack([thesis_guess(t, rpy) for t, rpy in TABLE_7_1])
    t0 = time.perf_counter()
    T_icp, st_icp = run_icp(m1, m2, T_inits, res)
    t_icp = time.perf_counter() - t0
    problem = prepare_alignment(m1, m2, max_points=max_points)
    t0 = time.perf_counter()
    d_res = jax.block_until_ready(solve_alignment(problem, T_inits))
    t_dense = time.perf_counter() - t0
    t0 = time.perf_counter()
    id_res = jax.block_until_ready(solve_alignment(problem, T_icp))
    t_both = time.perf_counter() - t0
    T_d, T_id = _orthonormal(d_res.T_1_2), _orthonormal(id_res.T_1_2)
    # the pipeline's refine="icp+dense" (pipeline.register): dense from ICP's result from the level of
    # ICP's last correspondence distance, then from the guess if that fails, else ICP's result kept
    cfg = MergeConfig().replace(registration={"refine": "icp+dense"})
    t0 = time.perf_counter()
    T_pipe, st_pipe = [], []
    for T0 in T_inits:
        registration = register(m1, m2, T0, cfg)
        T, info = registration.T_1_2, registration.info
        T_pipe.append(np.asarray(T, np.float64))
        st_pipe.append(int(info["dense"]["status"]))
    t_pipe = time.perf_counter() - t0

    def cell(T, status):
        er = float(metrics.rotation_angle_error(T, T_TRUE))
        et = float(metrics.translation_distance(T, T_TRUE))
        ok = er < 0.01 and et < res
        return f"{er:.4f} / {et:.3f} [{status}]{'*' if ok else ''}", ok

    print("| # | init eps_r / eps_t | init err rad / m | ICP | dense | ICP+dense | merge icp+dense |")
    print("|---|---|---|---|---|---|---|")
    wins = np.zeros(4, int)
    wrong = np.zeros(4, int)
    for i in range(len(TABLE_7_1)):
        T0 = T_inits[i]
        eps = f"{float(metrics.rotation_error(T0, T_TRUE)):.3f} / {float(metrics.translation_error(T0, T_TRUE)):.3f}"
        init = (f"{float(metrics.rotation_angle_error(T0, T_TRUE)):.3f} / "
                f"{float(metrics.translation_distance(T0, T_TRUE)):.2f}")
        cells = []
        for j, (T, st) in enumerate(((T_icp[i], st_icp[i]), (T_d[i], int(d_res.status[i])),
                                     (T_id[i], int(id_res.status[i])), (T_pipe[i], st_pipe[i]))):
            c, ok = cell(T, st)
            wins[j] += ok
            wrong[j] += (st == 0) and not (float(metrics.rotation_angle_error(T, T_TRUE)) < 0.05
                                           and float(metrics.translation_distance(T, T_TRUE)) < 2 * res)
            cells.append(c)
        print(f"| {i + 1} | {eps} | {init} | " + " | ".join(cells) + " |")
    n = len(TABLE_7_1)
    print(f"\nwithin one voxel ({res} m) and 0.01 rad: ICP {wins[0]}/{n}, dense {wins[1]}/{n}, "
          f"ICP+dense {wins[2]}/{n}, merge icp+dense {wins[3]}/{n}")
    print(f"status 0 ('converged') but off by > 0.05 rad or > 2 voxels: ICP {wrong[0]}, dense {wrong[1]}, "
          f"ICP+dense {wrong[2]}, merge icp+dense {wrong[3]}")
    print(f"wall time for all {n} rows (incl. compile): ICP {t_icp:.1f} s (row by row), dense "
          f"{t_dense:.1f} s (one vmap), ICP+dense refinement {t_both:.1f} s (one vmap), merge's "
          f"icp+dense registration {t_pipe:.1f} s (row by row)")
    print("(ICP+dense: dense from ICP's results with every level; merge icp+dense: the pipeline's "
          "refine.register, dense from the level of ICP's last correspondence distance, the guess "
          "if that fails; its status column is the dense alignment's)")


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="one steady repeat instead of --repeats")
    ap.add_argument("--grid-res", type=float, default=0.2)
    ap.add_argument("--max-points", type=int, default=8192)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--solvers", action="store_true",
                    help="only compare the minimiser backends (lbfgs vs jaxopt) on one small problem")
    args = ap.parse_args()
    print(f"# bench_dense  jax {jax.__version__}  {platform.processor() or platform.machine()}  "
          f"devices {jax.devices()}  load {os.getloadavg()[0]:.1f}")
    if args.solvers:
        solver_table(0.2, (1, 0), 2048, 1 if args.quick else args.repeats)
        return
    timing_table((0.4, 0.2, 0.1), args.max_points, 1 if args.quick else args.repeats)
    accuracy_table(args.grid_res, args.max_points)


if __name__ == "__main__":
    main()
