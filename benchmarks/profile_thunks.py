"""Where a jitted call spends its time on XLA:CPU: run it under ``jax.profiler.trace`` and sum the
trace's events by name (every thunk of the compiled program is an event, loop bodies once per
iteration). A table of the heaviest names, in ms per call and calls per call.

    .venv/bin/python benchmarks/profile_thunks.py icp --res 0.1
    .venv/bin/python benchmarks/profile_thunks.py icp_multi --res 0.2 --hypotheses 36
    .venv/bin/python benchmarks/profile_thunks.py fuse --size small

Thunk names are those of the optimised HLO (dump it with ``XLA_FLAGS=--xla_dump_to=DIR
--xla_dump_hlo_as_text`` to see what a fusion computes). Tracing adds a few microseconds per
event, so many small thunks look heavier than they are; compare names, not totals, with
untraced timings.
"""

from __future__ import annotations

import argparse
import collections
import glob
import gzip
import json
import tempfile

import jax
import functools

import numpy as np


def _icp_call(args):
    from octomerge_jax.registration import icp, icp_multi, overlap
    from octomerge_jax.sim import scene_pair
    from octomerge_jax import se3
    xyz_rpy64 = functools.partial(se3.from_xyz_rpy, xp=np)  # float64 ground truth

    if args.what == "icp_multi":
        p1, p2, T12 = scene_pair(args.res, crop_1=(-1.0, 11.5), crop_2=(0.5, 13.0))
        T0 = xyz_rpy64(0.0, 0.0, 0.0, 0.0, 0.0, 1.7) @ T12
        k = args.hypotheses
        return lambda: icp_multi(p2, p1, T0, resolution=args.res, yaw_step_rad=2 * np.pi / k,
                                     roll_pitch_offset_rad=0.0).best.T_target_source
    P1, P2, T12 = scene_pair(args.res)
    T0 = xyz_rpy64(0.2, 0.1, 0.0, 0.0, 0.0, 0.05) @ T12  # bench_icp's start 0
    o = overlap(P1, P2, T0, "bbox")
    p1, p2 = P1[np.asarray(o.mask_1)], P2[np.asarray(o.mask_2)]
    return lambda: icp(p2, p1, T0, resolution=args.res).T_target_source


def _fuse_call(args):
    import bench_fuse
    from octomerge_jax import map as omap

    m1, m2 = bench_fuse.make_pair(bench_fuse.SIZES[args.size])
    _, rep = bench_fuse.F.fuse_with_report(m1, m2)
    cap = omap.bucket_capacity(int(rep.refined_cells))
    return lambda: bench_fuse.F.fuse(m1, m2, capacity=cap).code


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("what", choices=("icp", "icp_multi", "fuse"))
    ap.add_argument("--res", type=float, default=0.1, help="icp: resolution of the test scene [m]")
    ap.add_argument("--hypotheses", type=int, default=36, help="icp_multi: yaw hypotheses")
    ap.add_argument("--size", default="small", help="fuse: bench_fuse pair size")
    ap.add_argument("--calls", type=int, default=3, help="traced calls (after one warm-up call)")
    ap.add_argument("--top", type=int, default=30)
    args = ap.parse_args()
    f = _fuse_call(args) if args.what == "fuse" else _icp_call(args)
    jax.block_until_ready(f())  # compile outside the trace
    with tempfile.TemporaryDirectory() as d:
        with jax.profiler.trace(d):
            for _ in range(args.calls):
                jax.block_until_ready(f())
        files = glob.glob(f"{d}/**/*.trace.json.gz", recursive=True)
        if not files:
            raise SystemExit("the profiler wrote no trace (is the profiler plugin installed?)")
        with gzip.open(files[0]) as fh:
            events = json.load(fh)["traceEvents"]
    total, count = collections.Counter(), collections.Counter()
    wall = 0.0
    for e in events:
        if e.get("ph") != "X":
            continue
        name = e["name"]
        if name == "ThunkExecutor::Execute (wait for completion)":
            wall += e["dur"]
        # thunks only: not Python frames ("$file:line", "np.asarray(...)") nor the runtime's wrappers
        if name.startswith(("$", "PjitFunction", "PythonRefManager")) or "::" in name or "(" in name:
            continue
        total[name] += e["dur"]
        count[name] += 1
    print(f"# {args.what}: {args.calls} traced calls; waited for the device {wall / args.calls / 1e3:.1f} ms "
          f"per call, of which the thunks below (ms and events per call)")
    print(f"{'ms':>9} {'events':>8}  thunk")
    for name, us in total.most_common(args.top):
        print(f"{us / args.calls / 1e3:9.2f} {count[name] / args.calls:8.1f}  {name[:100]}")


if __name__ == "__main__":
    main()
