"""The manifest runner behind ``octomerge batch``: a CSV of map pairs merged into a folder,
resumable, in this process or as Dask tasks.

``run_manifest`` reads ``map1,map2,output[,x,y,z,roll,pitch,yaw]`` rows (paths relative to the
manifest), skips pairs whose output exists (resume), writes each output atomically as soon as
it is done, and keeps ``summary.csv`` in the output folder up to date (one row per pair:
status ``ok`` / ``skipped`` / ``error`` with the message, thesis errors, ICP figures, seconds).
With ``scheduler="tcp://host:8786"`` (or ``workers=N`` for a local cluster) every pair is one
Dask task (``run_pair``): workers import this package and run the same jitted kernels; JAX on a
worker with a GPU (``pip install "jax[cuda12]"`` there) uses it automatically.
"""

from __future__ import annotations

import csv
import dataclasses
import os
import time
from pathlib import Path

from .._fileutil import atomic_output, check_not_input
from ..pipeline import MergeConfig, config_from_dict, config_to_dict
from ..io import load, save
from ..pipeline import MergeError, merge, transform_from_xyz_rpy
from .dask_runner import map_on_dask
from .progress import Progress

__all__ = ["ManifestRow", "SUMMARY_FIELDS", "read_manifest", "run_manifest", "run_pair"]

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


def _write_summary(path: Path, rows: dict):
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
    bar = Progress(len(rows), progress)
    for _ in done:
        bar.update("skipped")
    cfg_dict = config_to_dict(cfg)
    if todo:
        _write_summary(summary_path, done)
    try:
        if scheduler or workers > 0:
            for row, res, err in map_on_dask(run_pair, todo, cfg_dict, write_reports, scheduler=scheduler,
                                             workers=workers, key=_task_key):
                if err is not None:
                    res = _row_result(row, "error", type(err).__name__, f"task failed: {err}")
                done[row.index] = res
                bar.update(res["status"])
                _write_summary(summary_path, done)
        else:
            for row in todo:
                done[row.index] = run_pair(row, cfg_dict, write_reports)
                bar.update(done[row.index]["status"])
                _write_summary(summary_path, done)
    finally:
        bar.close()
        _write_summary(summary_path, done)
    return [done[k] for k in sorted(done)]


def _task_key(row: ManifestRow) -> str:
    return f"octomerge-pair-{row.index}-{abs(hash(row.output)) % 10**8}"
