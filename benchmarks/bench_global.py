"""Registration without a guess: ours (``register`` with ``refine="global"``, what ``merge`` runs
without a guess: ``register_global`` and the dense step from its result) vs KISS-Matcher +
small_gicp GICP vs Open3D FPFH + RANSAC + ICP, same clouds, same cases, one run.

Maps: the simulated two-robot pairs (``sim.make_two_robot_maps``, built in one frame and saved
as ``.bt`` under ``--maps``; built here when missing). Each case turns map 2 into a new frame by
``T_1_2`` (``resample.transform_map`` with its inverse: a re-voxelised map, as a robot with
another start would build): uniform random yaw, roll / pitch up to ``--tilt-deg``, offsets up to
half the map's extent in x / y (5 % in z). Every method gets the occupied leaf centres of map 1
and of the moved map 2 (ours also the maps, for their free space). "Right" = rotation error
below 0.05 rad and translation error below 0.25 m (after the peers' and our local refinement).
Reported: right k/n, median / worst rotation [rad] and translation [m] error over all cases, the
median / worst mean displacement of map 2's occupied voxels [m] over the right cases (the
sub-voxel figure: a translation error also holds the rotation error's lever arm about the origin),
median / worst seconds per pair once compiled (our first call per scene, mostly XLA compilation,
apart),
and our status and confidence per case, binned (the reliability table). One extra case per run
pairs two different scenes (no common region), which must not come out "ok".

    timeout 900 .venv/bin/python benchmarks/bench_global.py --scenes lab office --cases 8
"""

from __future__ import annotations

import argparse
import math
import platform
import statistics
import time
from pathlib import Path

import numpy as np

from octomerge_jax import registration as reg
from octomerge_jax import se3
from octomerge_jax.io import load, save
from octomerge_jax.pipeline import MergeConfig, Timings, register
from octomerge_jax.resample import transform_map
from octomerge_jax.sim import make_two_robot_maps

ROT_OK, TRANS_OK = 0.05, 0.25  # [rad], [m]
BINS = (0.0, 0.25, 0.5, 0.75, 1.0001)


def maps(scene: str, res: float, folder: Path):
    """The scene's two maps in one frame (built and saved on first use)."""
    f1, f2 = folder / f"{scene}_{res:g}_1.bt", folder / f"{scene}_{res:g}_2.bt"
    if not (f1.exists() and f2.exists()):
        kw = dict(max_range=30.0) if scene == "campus" else {}
        m1, m2, _ = make_two_robot_maps(scene, res, yaw_2_rad=0.0, offset_2=(0.0, 0.0, 0.0), **kw)
        folder.mkdir(parents=True, exist_ok=True)
        save(m1, f1)
        save(m2, f2)
    return load(f1), load(f2)


def cloud(m) -> np.ndarray:
    return np.asarray(reg.occupied_points(m), np.float64).reshape(-1, 3)


def errors(T, T_true) -> tuple[float, float]:
    return float(reg.rotation_angle_error(T, T_true)), float(reg.translation_distance(T, T_true))


def kiss_small_gicp(p1, p2, res):
    """KISS-Matcher (voxel 0.3 m) then small_gicp GICP from its result: T_1_2 (4, 4)."""
    import kiss_matcher
    import small_gicp

    km = kiss_matcher.KISSMatcher(kiss_matcher.KISSMatcherConfig(0.3))
    sol = km.estimate(p2, p1)
    T = np.eye(4)
    T[:3, :3] = np.asarray(sol.rotation)
    T[:3, 3] = np.asarray(sol.translation).ravel()
    r = small_gicp.align(p1, p2, T, registration_type="GICP", downsampling_resolution=max(res, 0.1),
                         max_correspondence_distance=1.0, num_threads=2)
    return np.asarray(r.T_target_source)


def open3d_ransac_icp(p1, p2, res):
    """Open3D FPFH (voxel 0.3 m) + RANSAC, then point-to-plane ICP: T_1_2 (4, 4)."""
    import open3d as o3d

    v = 0.3

    def prep(p):
        pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(p)).voxel_down_sample(v)
        pc.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=2 * v, max_nn=30))
        f = o3d.pipelines.registration.compute_fpfh_feature(pc, o3d.geometry.KDTreeSearchParamHybrid(radius=5 * v,
                                                                                                   max_nn=100))
        return pc, f

    (a, fa), (b, fb) = prep(p1), prep(p2)
    reg_ = o3d.pipelines.registration
    r = reg_.registration_ransac_based_on_feature_matching(
        b, a, fb, fa, True, 1.5 * v, reg_.TransformationEstimationPointToPoint(False), 3,
        [reg_.CorrespondenceCheckerBasedOnEdgeLength(0.9), reg_.CorrespondenceCheckerBasedOnDistance(1.5 * v)],
        reg_.RANSACConvergenceCriteria(100000, 0.999))
    fa_ = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(p1)).voxel_down_sample(max(res, 0.1))
    fb_ = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(p2)).voxel_down_sample(max(res, 0.1))
    fa_.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=4 * max(res, 0.1), max_nn=30))
    icp = reg_.registration_icp(fb_, fa_, 2 * v, r.transformation, reg_.TransformationEstimationPointToPlane())
    return np.asarray(icp.transformation)


def run_ours(m1, m2c, cfg):
    tm = Timings()
    r = register(m1, m2c, None, cfg, tm)
    return r.T_1_2, r.info["verdict"], r.confidence, tm


def timed(f, *a):
    t0 = time.perf_counter()
    out = f(*a)
    return out, time.perf_counter() - t0


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenes", nargs="+", default=["lab", "office"])
    ap.add_argument("--res", type=float, default=0.05)
    ap.add_argument("--cases", type=int, default=8)
    ap.add_argument("--tilt-deg", type=float, default=3.0)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--maps", type=Path, default=Path("/tmp/octomerge_bench_global"))
    ap.add_argument("--peers", nargs="*", default=["kiss", "open3d"])
    args = ap.parse_args()
    cfg = MergeConfig().replace(registration={"refine": "global"})
    peers = {"kiss": ("KISS-Matcher + small_gicp", kiss_small_gicp), "open3d": ("Open3D FPFH+RANSAC+ICP", open3d_ransac_icp)}
    methods = ["ours"] + [p for p in args.peers if p in peers]
    rows = {m: [] for m in methods}  # (scene, rot err, trans err, seconds, displacement)
    calib = []  # (confidence, verdict, right)
    first_call = {}  # scene: seconds of ours' first call (a new map size compiles anew)
    rng = np.random.default_rng(args.seed)
    loaded = {}
    for scene in args.scenes:
        m1, m2 = maps(scene, args.res, args.maps)
        loaded[scene] = (m1, m2)
        p1 = cloud(m1)
        ext = np.ptp(cloud(m2), axis=0)
        print(f"{scene} {args.res:g} m: {m1.num_leaves:,} + {m2.num_leaves:,} leaves, "
              f"{p1.shape[0]:,} occupied in map 1", flush=True)
        for c in range(args.cases):
            yaw = rng.uniform(-math.pi, math.pi)
            rp = np.deg2rad(rng.uniform(-args.tilt_deg, args.tilt_deg, 2))
            t = rng.uniform(-1, 1, 3) * ext * np.array([0.5, 0.5, 0.05])
            T_true = se3.from_xyz_rpy(*t, rp[0], rp[1], yaw, xp=np)
            m2c = transform_map(m2, np.linalg.inv(T_true))
            p2 = cloud(m2c)
            if scene not in first_call:
                _, first_call[scene] = timed(run_ours, m1, m2c, cfg)
            line = [f"  case {c} yaw {yaw:+.2f}"]
            for m in methods:
                if m == "ours":
                    (T, verdict, conf, tm), dt = timed(run_ours, m1, m2c, cfg)
                else:
                    T, dt = timed(peers[m][1], p1, p2, args.res)
                er, et = errors(T, T_true)
                rows[m].append((scene, er, et, dt, float(np.mean(reg.point_displacement(T, T_true, p2)))))
                right = er < ROT_OK and et < TRANS_OK
                if m == "ours":
                    calib.append((conf, verdict, right))
                    line.append(f"ours {er:.3f} rad {et:.3f} m {dt:.1f} s {verdict} {conf:.2f}")
                else:
                    line.append(f"{m} {er:.3f} rad {et:.3f} m {dt:.1f} s")
            print(" | ".join(line), flush=True)
    if len(args.scenes) >= 2:  # two different scenes: no common region
        (a, _), (_, b) = loaded[args.scenes[0]], loaded[args.scenes[1]]
        T, verdict, conf, _ = run_ours(a, b, cfg)
        print(f"  no-overlap pair ({args.scenes[0]} vs {args.scenes[1]}): {verdict}, confidence {conf:.2f}")
        calib.append((conf, verdict, False))
    print(f"\nmachine: {platform.processor() or platform.machine()}, {platform.system()}; "
          "ours' first call per scene (compile + run): "
          + ", ".join(f"{k} {v:.1f} s" for k, v in first_call.items()))
    print("\n| method | right | rot err median / worst [rad] | trans err median / worst [m] | "
          "displacement (right) median / worst [m] | s/pair median / worst |")
    print("|---|---|---|---|---|---|")
    for m in methods:
        r = rows[m]
        n = len(r)
        k = sum(1 for _, er, et, _, _ in r if er < ROT_OK and et < TRANS_OK)
        dr = [x[4] for x in r if x[1] < ROT_OK and x[2] < TRANS_OK]
        dcol = f"{statistics.median(dr):.4f} / {max(dr):.4f}" if dr else "-"
        name = "ours (global)" if m == "ours" else peers[m][0]
        er = [x[1] for x in r]
        et = [x[2] for x in r]
        dt = [x[3] for x in r]
        print(f"| {name} | {k}/{n} | {statistics.median(er):.4f} / {max(er):.3f} | {statistics.median(et):.4f} / "
              f"{max(et):.3f} | {dcol} | {statistics.median(dt):.2f} / {max(dt):.2f} |")
    print("\nour status vs right (no-overlap pair counted as not right):")
    print("| status | right | wrong |")
    print("|---|---|---|")
    for v in ("ok", "ambiguous", "no_overlap", "failed"):
        print(f"| {v} | {sum(1 for _, s, ok in calib if s == v and ok)} | {sum(1 for _, s, ok in calib if s == v and not ok)} |")
    print("\nconfidence calibration (right rate per bin):")
    print("| confidence | cases | right | right rate |")
    print("|---|---|---|---|")
    for lo, hi in zip(BINS[:-1], BINS[1:]):
        sel = [ok for c, _, ok in calib if lo <= c < hi]
        rate = f"{sum(sel) / len(sel):.2f}" if sel else "-"
        print(f"| [{lo:.2f}, {min(hi, 1.0):.2f}{']' if hi > 1 else ')'} | {len(sel)} | {sum(sel)} | {rate} |")


if __name__ == "__main__":
    main()
