"""Many merges: ``merge_batch`` (pairs grouped by capacity bucket, one jitted ``vmap`` call per
group) and ``run_manifest`` (a CSV of file pairs, resumable, locally or on a Dask cluster).

``merge_batch(pairs)`` plans on the host, then runs the jittable stages batched:

1. per pair: resolution/guess checks, occupied clouds and overlap (host, cheap); a pair that
   fails gets ``status="error"`` and a message, the others go on;
2. ICP (``refine="icp"``): pairs grouped by (resolution, source bucket, target bucket) and each
   group registered by **one** jitted call of ``registration.icp_padded_stack`` (all pairs of
   a group share the compiled function and run as one XLA call: pair after pair on CPUs,
   where each then stops at its own convergence, one ``vmap`` batch on accelerators);
3. ``transform_map`` per pair (its brick plan is host work; pairs of one bucket share the
   compiled kernel);
4. fusion: pairs grouped by (map-1 capacity, transformed map-2 capacity) and each group fused
   by one ``vmap`` of ``fuse`` with a static output capacity and gap-cell list; a pair whose
   refinement or gap cells overflowed them is re-fused alone (its result is never truncated).

``run_manifest`` reads ``map1,map2,output[,x,y,z,roll,pitch,yaw]`` rows (paths relative to the
manifest), skips pairs whose output exists (resume), writes each output atomically as soon as
it is done, and keeps ``summary.csv`` in the output folder up to date (one row per pair:
status ``ok`` / ``skipped`` / ``error`` with the message, thesis errors, ICP figures, seconds).
With ``scheduler="tcp://host:8786"`` (or ``workers=N`` for a local cluster) every pair is one
Dask task: workers import this package and run the same jitted kernels; JAX on a worker with a
GPU (``pip install "jax[cuda12]"`` there) uses it automatically, nothing to configure.
"""

from __future__ import annotations

import csv
import dataclasses
import os
import sys
import time
from pathlib import Path
from typing import Sequence

import jax
import jax.numpy as jnp
import numpy as np

from . import hostmem
from .config import MergeConfig, config_from_dict, config_to_dict
from .map import OccupancyMap, bucket_capacity
from .pipeline import (MergeError, MergeReport, _check_T, _displacements, _epsilons, check_resolutions, merge,
                       transform_from_xyz_rpy)
from .refine import (_fill_point_stats, _icp_dict, _icp_kwargs, _icp_modules, _multi_candidates, _rank_and_refine,
                     _select_overlap, _with_local_step, overlap_margin)

__all__ = ["BatchResult", "merge_batch", "read_manifest", "run_manifest", "SUMMARY_FIELDS"]


@dataclasses.dataclass(frozen=True)
class BatchResult:
    """One pair of a batch: ``status`` ``"ok"`` or ``"error"`` (with ``message`` and the
    ``MergeError`` kind in ``kind``); ``merged`` and ``report`` are ``None`` on error."""

    status: str
    merged: OccupancyMap | None = None
    report: MergeReport | None = None
    message: str = ""
    kind: str = ""


def _as_pair(p, i):
    if isinstance(p, dict):
        return p["m1"], p["m2"], p.get("T_1_2_init"), p.get("T_1_2_true")
    p = tuple(p)
    if len(p) == 2:
        return p[0], p[1], None, None
    if len(p) == 3:
        return p[0], p[1], p[2], None
    if len(p) == 4:
        return p
    raise ValueError(f"pairs[{i}]: expected (m1, m2[, T_1_2_init[, T_1_2_true]]), got {len(p)} items")


def _merge_one(p, i, cfg) -> BatchResult:
    from .pipeline import MergeError, merge

    try:
        m1, m2, T_init, T_true = _as_pair(p, i)
        merged, report = merge(m1, m2, T_init, T_1_2_true=T_true, config=cfg)
        return BatchResult("ok", merged, report)
    except MergeError as err:
        return BatchResult("error", message=str(err), kind=getattr(err, "kind", "error"))
    except ValueError as err:
        return BatchResult("error", message=str(err), kind="input")


def _stack(trees):
    return jax.tree_util.tree_map(lambda *xs: jnp.stack(xs), *trees)


def _unstack(tree, i):
    return jax.tree_util.tree_map(lambda a: a[i], tree)


def merge_batch(pairs: Sequence, *, config: MergeConfig | None = None) -> list[BatchResult]:
    """Merge many pairs; returns one ``BatchResult`` per pair, in order.

    ``pairs``: items ``(m1, m2)``, ``(m1, m2, T_1_2_init)`` or ``(m1, m2, T_1_2_init,
    T_1_2_true)`` (or dicts with keys ``m1, m2, T_1_2_init, T_1_2_true``). Results equal
    ``merge`` pair by pair (same kernels); a bad pair never stops the batch. ``refine="multi"``
    runs its hypotheses batched per pair (already one ``vmap``).
    """
    icp_mod, neighbors = _icp_modules()

    cfg = MergeConfig() if config is None else config
    rc = cfg.registration
    if rc.refine in ("dense", "icp+dense"):  # the dense solver runs per pair (vmapped inside)
        return [_merge_one(p, i, cfg) for i, p in enumerate(pairs)]
    n = len(pairs)
    results: list[BatchResult | None] = [None] * n
    state = {}
    # 1. host checks and clouds
    for i, p in enumerate(pairs):
        t0 = time.perf_counter()
        try:
            m1, m2, T_init, T_true = _as_pair(p, i)
            check_resolutions([m1, m2], [f"pairs[{i}].m1", f"pairs[{i}].m2"], False)
            T_init = np.eye(4) if T_init is None else _check_T(T_init, f"pairs[{i}].T_1_2_init")
            T_true = None if T_true is None else _check_T(T_true, f"pairs[{i}].T_1_2_true")
            from . import registration as reg

            timings = {}
            p1 = np.asarray(reg.occupied_points(m1), np.float32).reshape(-1, 3)
            p2 = np.asarray(reg.occupied_points(m2), np.float32).reshape(-1, 3)
            counts = {"leaves_1": m1.num_leaves, "leaves_2": m2.num_leaves,
                      "occupied_1": int(p1.shape[0]), "occupied_2": int(p2.shape[0])}
            q1, q2 = p1, p2
            if rc.refine != "none":
                method = "none" if rc.refine == "multi" else rc.overlap
                q1, q2 = _select_overlap(p1, p2, T_init, method, overlap_margin(cfg, m1.resolution))
                counts["overlap_1"], counts["overlap_2"] = int(q1.shape[0]), int(q2.shape[0])
                if min(q1.shape[0], q2.shape[0]) < rc.min_overlap_points:
                    raise MergeError(f"no overlap: {q1.shape[0]} / {q2.shape[0]} common points under "
                                     f"the initial guess (need {rc.min_overlap_points})", "no_overlap")
            timings["occupied_points+overlap"] = time.perf_counter() - t0
            state[i] = dict(m1=m1, m2=m2, T_init=T_init, T_true=T_true, q1=q1, q2=q2, counts=counts,
                            timings=timings, warnings=[], T=T_init, info=None, result=None)
        except (MergeError, ValueError) as err:
            results[i] = BatchResult("error", message=str(err), kind=getattr(err, "kind", "input"))

    # 2. registration
    if rc.refine == "icp":
        groups: dict = {}
        for i, s in state.items():
            # ICP uses the larger cloud as the model (target), as registration.icp does
            swap = s["q2"].shape[0] > s["q1"].shape[0]
            src, tgt = (s["q1"], s["q2"]) if swap else (s["q2"], s["q1"])
            key = (s["m1"].resolution, bucket_capacity(src.shape[0]), bucket_capacity(tgt.shape[0]))
            groups.setdefault(key, []).append((i, swap, src, tgt))
        for (res, cs, ct), members in groups.items():
            t0 = time.perf_counter()
            kw = _icp_kwargs(cfg, res)
            dists = icp_mod.stage_distances(res, kw["max_correspondence_distance"],
                                            kw["min_correspondence_distance"], kw["shrink_factor"])
            eps = res / 60.0 if kw["transformation_epsilon"] is None else kw["transformation_epsilon"]
            S, SC, T_, TC, T0 = [], [], [], [], []
            for i, swap, src, tgt in members:
                s_p, s_c = icp_mod.pad_points(src, cs)
                t_p, t_c = icp_mod.pad_points(tgt, ct)
                T_init = state[i]["T_init"]
                S.append(s_p), SC.append(s_c), T_.append(t_p), TC.append(t_c)
                T0.append(np.linalg.inv(T_init) if swap else T_init)
            out = icp_mod.icp_padded_stack(
                jnp.stack(S), jnp.stack(SC), jnp.stack(T_), jnp.stack(TC), jnp.asarray(np.stack(T0), jnp.float32),
                jnp.asarray(dists, jnp.float32), jnp.float32(eps), jnp.float32(eps * 0.01),
                jnp.int32(kw["min_inliers"]), max_iterations=int(kw["max_iterations"]),
                cell_capacity=int(kw["cell_capacity"]), table_sizes=neighbors.level_table_sizes(ct, dists),
                coarse_matching=kw["coarse_matching"], sequential=icp_mod.sequential_default())
            jax.block_until_ready(out)
            dt = (time.perf_counter() - t0) / len(members)
            for j, (i, swap, _, _) in enumerate(members):
                r = _unstack(out, j)
                if swap:
                    r = icp_mod.invert_result(r)
                state[i]["timings"]["icp"] = dt
                _finish_icp(i, state, results, r, cfg)
    elif rc.refine == "multi":
        from . import registration as reg

        for i in list(state):
            s = state[i]
            t0 = time.perf_counter()
            r, origin, problem = _multi_candidates(s["m1"], s["m2"], s["q1"], s["q2"], s["T_init"], cfg,
                                                   _icp_kwargs(cfg, s["m1"].resolution), s["timings"])
            jax.block_until_ready(r)
            r, _, *local = _rank_and_refine(s["m1"], s["m2"], s["q1"], s["q2"], r, origin == "yaw_grid",
                                            cfg, _icp_kwargs(cfg, s["m1"].resolution), s["timings"],  # as merge
                                            problem, origin)
            s["timings"]["icp"] = time.perf_counter() - t0
            _finish_icp(i, state, results, r, cfg, local)

    # 3. transform, 4. fuse (grouped by bucket)
    moved = {}
    for i, s in state.items():
        from .resample import transform_map

        t0 = time.perf_counter()
        tc = cfg.transform
        try:
            moved[i] = transform_map(s["m2"], s["T"], tc.interpolation, space=tc.space,
                                     chunk_bricks=tc.chunk_bricks)
            jax.block_until_ready(moved[i])
        except ValueError as err:
            results[i] = BatchResult("error", message=f"transforming map 2: {err}", kind="transform")
        s["timings"]["transform"] = time.perf_counter() - t0
    fgroups: dict = {}
    for i in moved:
        s = state[i]
        key = (s["m1"].resolution, bucket_capacity(s["m1"].num_leaves), bucket_capacity(moved[i].num_leaves))
        fgroups.setdefault(key, []).append(i)
    from .fuse import default_gap_capacity, fuse

    for (res, c1, c2), members in fgroups.items():
        t0 = time.perf_counter()
        cap = bucket_capacity(max(2 * (state[i]["m1"].num_leaves + moved[i].num_leaves) for i in members))
        A = _stack([state[i]["m1"].with_capacity(c1) for i in members])
        B = _stack([moved[i].with_capacity(c2) for i in members])
        w = tuple(cfg.fuse.weights[:2])
        gcap = default_gap_capacity(cap)  # more gap cells: overflow, re-fused alone below
        out, rep = jax.vmap(lambda a, b: fuse(a, b, cfg.fuse.rule, weights=w, capacity=cap,
                                              gap_capacity=gcap, return_report=True))(A, B)
        jax.block_until_ready(out)
        dt = (time.perf_counter() - t0) / len(members)
        for j, i in enumerate(members):
            s = state[i]
            m_j, r_j = _unstack(out, j), _unstack(rep, j)
            if bool(r_j.overflow):  # rare: re-fuse alone with planned capacities
                m_j, r_j = fuse(s["m1"], moved[i], cfg.fuse.rule, weights=w, return_report=True)
            m_j = _trim(m_j)
            s["timings"]["fuse"] = dt
            s["counts"].update(leaves_2_transformed=moved[i].num_leaves, leaves_merged=m_j.num_leaves,
                               fuse=dataclasses.replace(r_j, capacity=m_j.capacity).host())
            results[i] = BatchResult("ok", merged=m_j, report=_report(s, cfg))
    return results


def _trim(m: OccupancyMap) -> OccupancyMap:
    cap = bucket_capacity(m.num_leaves)
    if cap >= m.capacity:
        return m
    return OccupancyMap(m.code[:cap], m.depth[:cap], m.log_odds[:cap], m.count, m.params,
                        m.resolution, m.tree_depth)


def _finish_icp(i, state, results, r, cfg, local=None):
    """``local``: ``_rank_and_refine``'s local step ``(result or None, info)`` for ``refine="multi"``."""
    s = state[i]
    refine = cfg.registration.refine
    info = _icp_dict(r, refine)
    best = r.best if refine == "multi" else r
    if local is not None:
        best = _with_local_step(info, best, *local)
        _fill_point_stats(info, s["q1"], s["q2"], best.T_target_source, cfg, s["m1"].resolution, s["timings"])
    T = np.asarray(best.T_target_source, np.float64)
    if info["status"] == "too_few_inliers" or not np.all(np.isfinite(T)):
        results[i] = BatchResult("error", message=f"ICP failed: {info['num_inliers']} inliers", kind="icp_failed")
        del state[i]
        return
    if not info["converged"]:
        msg = f"ICP did not converge within {info['num_iterations']} iterations"
        pol = cfg.registration.on_not_converged
        if pol == "error":
            results[i] = BatchResult("error", message=msg, kind="not_converged")
            del state[i]
            return
        if pol == "use_initial":
            T = s["T_init"]
            msg += "; merged with the initial guess"
        s["warnings"].append(msg)
    U, _, Vt = np.linalg.svd(T[:3, :3])
    T = T.copy()
    T[:3, :3] = U @ np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))]) @ Vt
    T[3] = (0, 0, 0, 1)
    s.update(T=T, info=info, result=r)


def _report(s, cfg) -> MergeReport:
    eps = (None, None, None, None)
    if s["T_true"] is not None:
        eps = (*_epsilons(s["T_init"], s["T_true"]), *_epsilons(s["T"], s["T_true"]))
    disp = _displacements(s["m2"], s["T_true"], s["T_init"], s["T"])
    timings = {**s["timings"], "total": sum(s["timings"].values())}
    info = s["info"]
    return MergeReport(
        T_1_2_init=s["T_init"], T_1_2=s["T"], refine=cfg.registration.refine, icp=info,
        epsilon_r_init=eps[0], epsilon_t_init=eps[1], epsilon_r=eps[2], epsilon_t=eps[3],
        counts=s["counts"], timings=timings, resolution=s["m1"].resolution, T_1_2_true=s["T_true"],
        warnings=tuple(s["warnings"]), status="ok" if info is None or info["converged"] else "not_converged",
        displacement_init=disp[0], displacement=disp[1],
        icp_result=s["result"], points_1=s["q1"], points_2=s["q2"])


# ----------------------------------------------------------------------------- manifests

SUMMARY_FIELDS = ["index", "map1", "map2", "output", "status", "kind", "message", "refine",
                  "icp_status", "icp_iterations", "icp_rmse", "icp_fitness", "leaves_merged",
                  "epsilon_r_init", "epsilon_t_init", "epsilon_r", "epsilon_t", "displacement_init",
                  "displacement", "seconds", "host"]

_GUESS = ("x", "y", "z", "roll", "pitch", "yaw")


@dataclasses.dataclass(frozen=True)
class ManifestRow:
    """One pair of a manifest: absolute ``map1``, ``map2``, ``output`` paths, the guess
    ``(x, y, z, roll, pitch, yaw)`` [m, rad] and optional ground truth of the same form."""

    index: int
    map1: str
    map2: str
    output: str
    guess: tuple = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    truth: tuple | None = None


def read_manifest(path, out_dir) -> list[ManifestRow]:
    """Parse a manifest CSV with a header row: required ``map1,map2,output``; optional
    ``x,y,z,roll,pitch,yaw`` (initial guess ``T_1_2``, metres/radians) and
    ``true_x,...,true_yaw`` (ground truth, for thesis errors). Inputs are relative to the
    manifest's folder, outputs to ``out_dir``. Raises ``ValueError`` naming the line."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: manifest not found")
    base, out_dir = path.parent, Path(out_dir)
    rows = []
    with open(path, newline="") as f:
        reader = csv.DictReader(f)
        missing = {"map1", "map2", "output"} - set(reader.fieldnames or [])
        if missing:
            raise ValueError(f"{path}: missing column(s) {', '.join(sorted(missing))} "
                             f"(need map1,map2,output[,x,y,z,roll,pitch,yaw])")
        outputs = set()
        for k, r in enumerate(reader):
            line = k + 2

            def num(name, default=0.0):
                v = (r.get(name) or "").strip()
                if not v:
                    return default
                try:
                    x = float(v)
                except ValueError:
                    raise ValueError(f"{path}:{line}: {name} = {v!r} is not a number") from None
                return x

            guess = tuple(num(g) for g in _GUESS)
            truth = None
            if any((r.get("true_" + g) or "").strip() for g in _GUESS):
                truth = tuple(num("true_" + g) for g in _GUESS)
            m1, m2, out = (r.get(c, "").strip() for c in ("map1", "map2", "output"))
            if not (m1 and m2 and out):
                raise ValueError(f"{path}:{line}: map1, map2 and output must not be empty")
            out_p = (out_dir / out).resolve()
            if out_p in outputs:
                raise ValueError(f"{path}:{line}: output {out} appears twice")
            outputs.add(out_p)
            rows.append(ManifestRow(k, str((base / m1).resolve()), str((base / m2).resolve()),
                                    str(out_p), guess, truth))
    return rows


def _row_result(row: ManifestRow, status, kind="", message="", report=None, seconds=0.0) -> dict:
    out = {f: "" for f in SUMMARY_FIELDS}
    out.update(index=row.index, map1=row.map1, map2=row.map2, output=row.output, status=status,
               kind=kind, message=message.replace("\n", " "), seconds=f"{seconds:.3f}",
               host=os.uname().nodename)
    if report is not None:
        out["refine"] = report.refine
        if report.icp is not None:
            out.update(icp_status=report.icp["status"], icp_iterations=report.icp["num_iterations"],
                       icp_rmse=f"{report.icp['rmse']:.6g}", icp_fitness=f"{report.icp['fitness']:.4g}")
        out["leaves_merged"] = report.counts.get("leaves_merged", "")
        for k in ("epsilon_r_init", "epsilon_t_init", "epsilon_r", "epsilon_t", "displacement_init",
                  "displacement"):
            v = getattr(report, k)
            out[k] = "" if v is None else f"{v:.6g}"
    return out


def run_pair(row: ManifestRow, config_dict: dict, write_reports: bool = True) -> dict:
    """Load, merge and save one manifest row (the Dask task; also used locally). Returns the
    summary row; never raises for a bad pair."""
    from .io import load, save
    from ._fileutil import check_not_input

    t0 = time.perf_counter()
    try:
        cfg = config_from_dict(config_dict)
        for p in (row.map1, row.map2):
            if not Path(p).is_file():
                raise FileNotFoundError(f"{p}: no such file")
        check_not_input(row.output, [row.map1, row.map2])
        m1, m2 = load(row.map1), load(row.map2)
        T_true = None if row.truth is None else transform_from_xyz_rpy(*row.truth)
        merged, report = merge(m1, m2, transform_from_xyz_rpy(*row.guess), T_1_2_true=T_true, config=cfg)
        Path(row.output).parent.mkdir(parents=True, exist_ok=True)
        save(merged, row.output)
        if write_reports:
            report.to_json(str(Path(row.output).with_suffix(".json")))
        return _row_result(row, "ok", report=report, seconds=time.perf_counter() - t0,
                           message="; ".join(report.warnings))
    except MergeError as err:
        return _row_result(row, "error", err.kind, str(err), seconds=time.perf_counter() - t0)
    except Exception as err:  # a bad pair is recorded, the batch goes on
        kind = type(err).__name__
        return _row_result(row, "error", kind, str(err), seconds=time.perf_counter() - t0)


class _Progress:
    """tqdm if installed, else a one-line counter on stderr."""

    def __init__(self, total: int, enabled: bool, desc: str = "merging"):
        self.total, self.n, self.enabled, self.bar = total, 0, enabled, None
        if enabled:
            try:
                from tqdm import tqdm

                self.bar = tqdm(total=total, desc=desc, unit="pair", file=sys.stderr)
            except ImportError:
                self.t0 = time.perf_counter()

    def update(self, status: str):
        self.n += 1
        if not self.enabled:
            return
        if self.bar is not None:
            self.bar.update(1)
            self.bar.set_postfix_str(status)
        else:
            dt = time.perf_counter() - self.t0
            sys.stderr.write(f"\rmerging {self.n}/{self.total} ({dt:.0f}s) {status:<8}")
            sys.stderr.flush()

    def close(self):
        if self.bar is not None:
            self.bar.close()
        elif self.enabled:
            sys.stderr.write("\n")


def _write_summary(path: Path, rows: dict):
    from ._fileutil import atomic_output

    with atomic_output(path) as tmp:
        with open(tmp, "w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=SUMMARY_FIELDS)
            w.writeheader()
            for k in sorted(rows):
                w.writerow(rows[k])


def run_manifest(manifest, out_dir, *, config: MergeConfig | None = None, workers: int | None = None,
                 scheduler: str | None = None, progress: bool = True, resume: bool | None = None,
                 write_reports: bool = True) -> list[dict]:
    """Run every pair of ``manifest`` into ``out_dir``; returns the summary rows (also in
    ``out_dir/summary.csv``, rewritten atomically after every pair).

    ``scheduler``: a Dask scheduler address (``tcp://host:8786``) or a ``distributed.Client``;
    ``workers > 0`` without a scheduler starts a local Dask cluster of that many single-thread
    worker processes; otherwise pairs run in this process. ``resume`` (default: config) skips
    rows whose output file exists (recorded as ``skipped``).
    """
    cfg = MergeConfig() if config is None else config
    workers = cfg.batch.workers if workers is None else int(workers)
    scheduler = cfg.batch.scheduler if scheduler is None else scheduler
    resume = cfg.batch.resume if resume is None else bool(resume)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    rows = read_manifest(manifest, out_dir)
    summary_path = out_dir / "summary.csv"
    done: dict = {}
    todo = []
    for row in rows:
        if resume and Path(row.output).is_file():
            done[row.index] = _row_result(row, "skipped", message="output exists (resume)")
        else:
            todo.append(row)
    bar = _Progress(len(rows), progress)
    for _ in done:
        bar.update("skipped")
    cfg_dict = config_to_dict(cfg)
    if todo:
        _write_summary(summary_path, done)
    try:
        if scheduler or workers > 0:
            _run_dask(todo, cfg_dict, scheduler, workers, done, bar, summary_path, write_reports)
        else:
            for row in todo:
                done[row.index] = run_pair(row, cfg_dict, write_reports)
                bar.update(done[row.index]["status"])
                _write_summary(summary_path, done)
    finally:
        bar.close()
        _write_summary(summary_path, done)
    return [done[k] for k in sorted(done)]


def _run_dask(todo, cfg_dict, scheduler, workers, done, bar, summary_path, write_reports):
    try:
        from distributed import Client, LocalCluster, as_completed
    except ImportError:
        raise RuntimeError('running on a Dask cluster needs dask.distributed: '
                           'pip install "dask[distributed]"') from None
    own_cluster = None
    if scheduler and not isinstance(scheduler, str):
        client, own_client = scheduler, False
    elif scheduler:
        client, own_client = Client(scheduler), True
    else:
        # workers keep XLA:CPU scratch memory as this process does (hostmem; the octomerge
        # command opts in), set from their environment at process start
        own_cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                                   dashboard_address=None, env=hostmem.child_env())
        client, own_client = Client(own_cluster), True
    try:
        futures = [client.submit(run_pair, row, cfg_dict, write_reports, key=f"octomerge-pair-{row.index}-"
                                 f"{abs(hash(row.output)) % 10**8}", pure=False) for row in todo]
        by_key = {f.key: row for f, row in zip(futures, todo)}
        for fut in as_completed(futures):
            row = by_key[fut.key]
            try:
                res = fut.result()
            except Exception as err:  # worker died, pickling failed, ...
                res = _row_result(row, "error", type(err).__name__, f"task failed: {err}")
            done[row.index] = res
            bar.update(res["status"])
            _write_summary(summary_path, done)
    finally:
        if own_client:
            client.close()
        if own_cluster is not None:
            own_cluster.close()
