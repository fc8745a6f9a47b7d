"""The manifest runner behind ``octomerge batch``: a CSV of map pairs and groups merged into a
folder, resumable, in this process or as Dask tasks.

``run_manifest`` reads ``[group,]map1,map2,output[,x,y,z,roll,pitch,yaw]`` rows (paths relative
to the manifest); rows sharing a ``group`` id are one N-map job (``merge_many``;
``manifest_groups``), the others pairs (``merge``). It skips jobs whose output exists (resume),
writes each output atomically as soon as it is done, and keeps ``summary.csv`` in the output
folder up to date (one row per pair or group: status ``ok`` / ``skipped`` / ``error`` with the
message, thesis errors, ICP or pose-graph figures, seconds). With ``scheduler="tcp://host:8786"``
(or ``workers=N`` for a local cluster) every pair or group is one Dask task (``run_job``):
workers import this package and run the same jitted kernels; JAX on a worker with a GPU
(``pip install "jax[cuda12]"`` there) uses it automatically.
"""

from __future__ import annotations

import csv
import dataclasses
import math
import os
import time
from pathlib import Path

from .._fileutil import atomic_output
from ..pipeline import MergeConfig, config_from_dict, config_to_dict
from ..io import load, save
from ..pipeline import MergeError, merge, transform_from_xyz_rpy
from .cache import open_worker_store
from .dask_runner import map_on_dask
from .manifest_groups import ManifestGroup, assemble_groups, group_figures, merge_group
from .outputs import MAP_SUFFIXES, angle_warnings, folder_lock, inside, same_file
from .progress import Progress

__all__ = ["ManifestGroup", "ManifestRow", "SUMMARY_FIELDS", "read_manifest", "report_path", "run_group",
           "run_job", "run_manifest", "run_pair"]

# a group's row: map1 is its map 0, map2 empty, epsilons of its worst map, the group columns filled
SUMMARY_FIELDS = ["index", "map1", "map2", "output", "status", "kind", "message", "refine",
                  "icp_status", "icp_iterations", "icp_rmse", "icp_fitness", "leaves_merged",
                  "epsilon_r_init", "epsilon_t_init", "epsilon_r", "epsilon_t", "displacement_init",
                  "displacement", "seconds", "host", "group", "maps", "maps_placed", "edges_kept",
                  "edges_rejected"]

_GUESS = ("x", "y", "z", "roll", "pitch", "yaw")


@dataclasses.dataclass(frozen=True)
class ManifestRow:
    """One row of a manifest: absolute ``map1``, ``map2``, ``output`` paths, the guess
    ``(x, y, z, roll, pitch, yaw)`` [m, rad] and optional ground truth of the same form.
    ``error``: why the row cannot run (its paths are then as written), else ``""``.
    ``group``: the row's group id (``""``: a pair); a group row's ``guess`` is ``None`` when
    its x..yaw cells are all empty (a pair's empty cells are 0)."""

    index: int
    map1: str
    map2: str
    output: str
    guess: tuple | None = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    truth: tuple | None = None
    error: str = ""
    group: str = ""


class _RowError(ValueError):
    pass


def report_path(output) -> Path:
    """Where ``run_pair`` writes the JSON report of ``output``: ``OUTPUT.json`` beside it
    (``a.bt.json`` and ``a.ot.json`` stay apart; never a name an output can have)."""
    output = Path(output)
    return output.with_name(output.name + ".json")


def read_manifest(path, out_dir) -> list[ManifestRow | ManifestGroup]:
    """Parse a manifest CSV (UTF-8, a byte-order mark allowed) with a header row: required
    ``map1,map2,output``; optional ``x,y,z,roll,pitch,yaw`` (initial guess ``T_1_2``,
    metres/radians), ``true_x,...,true_yaw`` (ground truth, for thesis errors) and ``group``
    (rows sharing a non-empty id, all with the same output, are one ``ManifestGroup``, at the
    place of its first row; ``manifest_groups``). Inputs are relative to the manifest's
    folder, outputs to ``out_dir`` and must stay inside it.

    A bad row (wrong number of fields, a bad number, an empty path, an output outside
    ``out_dir``, not ``.bt``/``.ot``, listed twice or equal to an input; in a group, an
    output other than the group's or a map paired with itself) comes back with ``error`` set
    (naming ``path:line``), and makes its whole group an error; the other rows are
    unaffected. Raises ``ValueError`` only for a manifest that cannot be read as a whole (not
    UTF-8, no header, a required column missing)."""
    path = Path(path)
    if path.is_dir():
        raise IsADirectoryError(f"{path}: is a directory, not a manifest")
    if not path.is_file():
        raise FileNotFoundError(f"{path}: manifest not found")
    base, out_dir = path.parent, Path(out_dir)
    rows: list[ManifestRow] = []
    outputs: dict = {}  # output path -> group id of its row ("" for a pair)
    group_outputs: dict = {}  # group id -> output path of its first row
    try:
        with open(path, newline="", encoding="utf-8-sig") as f:
            reader = csv.DictReader(f)
            fields = [c.strip() for c in reader.fieldnames or []]
            reader.fieldnames = fields
            missing = {"map1", "map2", "output"} - set(fields)
            if missing:
                raise ValueError(f"{path}: missing column(s) {', '.join(sorted(missing))} "
                                 f"(need [group,]map1,map2,output[,x,y,z,roll,pitch,yaw])")
            for k, r in enumerate(reader):
                where = f"{path}:{reader.line_num}"
                try:
                    rows.append(_parse_row(k, r, len(fields), base, out_dir, outputs, group_outputs, where))
                except _RowError as err:
                    raw = [(r.get(c) or "").strip() if isinstance(r.get(c), str) else "" for c in
                           ("map1", "map2", "output", "group")]
                    rows.append(ManifestRow(k, *raw[:3], error=f"{where}: {err}", group=raw[3]))
    except UnicodeDecodeError as err:
        raise ValueError(f"{path}: not UTF-8 text ({err.reason} at byte {err.start})") from None
    except csv.Error as err:
        raise ValueError(f"{path}: not a readable CSV file: {err}") from None
    return assemble_groups(rows, path)


def _parse_row(k, r, n_fields, base, out_dir, outputs, group_outputs, where) -> ManifestRow:
    extra = r.get(None) or []
    given = [v for key, v in r.items() if key is not None and v is not None]
    if extra or len(given) != n_fields:
        raise _RowError(f"{len(given) + len(extra)} fields, the header has {n_fields}")

    def num(name):
        v = (r.get(name) or "").strip()
        if not v:
            return 0.0
        try:
            x = float(v)
        except ValueError:
            raise _RowError(f"{name} = {v!r} is not a number") from None
        if not math.isfinite(x) or "_" in v:
            raise _RowError(f"{name} = {v!r} is not a finite number")
        return x

    gid = (r.get("group") or "").strip()
    guess = tuple(num(g) for g in _GUESS)
    if gid and not any((r.get(g) or "").strip() for g in _GUESS):
        guess = None
    truth = None
    if any((r.get("true_" + g) or "").strip() for g in _GUESS):
        truth = tuple(num("true_" + g) for g in _GUESS)
    m1, m2, out = (r[c].strip() for c in ("map1", "map2", "output"))
    if not (m1 and m2 and out):
        raise _RowError("map1, map2 and output must not be empty")
    if Path(out).suffix.lower() not in MAP_SUFFIXES:
        raise _RowError(f"output {out} must end in .bt or .ot")
    if Path(out).is_absolute() or not inside(out_dir / out, out_dir):
        raise _RowError(f"output {out} is outside --out-dir {out_dir} (give a path inside it)")
    out_p = (out_dir / out).resolve()
    if gid and group_outputs.setdefault(gid, out_p) != out_p:
        raise _RowError(f"output {out} is not the output of the earlier rows of group {gid}")
    if out_p in outputs and (not gid or outputs[out_p] != gid):
        raise _RowError(f"output {out} appears twice")
    outputs[out_p] = gid
    p1, p2 = (base / m1).resolve(), (base / m2).resolve()
    if gid and p1 == p2:
        raise _RowError(f"map1 and map2 are the same map {m1} (a group row pairs two maps)")
    for written in (out_p, report_path(out_p)):
        if same_file(written, p1) or same_file(written, p2):
            raise _RowError(f"output {written.name} is also an input; refusing to overwrite it")
    return ManifestRow(k, str(p1), str(p2), str(out_p), guess, truth, group=gid)


def _row_result(row: ManifestRow | ManifestGroup, status, kind="", message="", report=None, seconds=0.0) -> dict:
    out = {f: "" for f in SUMMARY_FIELDS}
    out.update(index=row.index, map1=row.map1, map2=row.map2, output=row.output, status=status,
               kind=kind, message=message.replace("\n", " "), seconds=f"{seconds:.3f}",
               host=os.uname().nodename, group=row.group)
    if isinstance(row, ManifestGroup):
        out["maps"] = len(row.maps)
        if report is not None:
            out.update(group_figures(report), refine=report.merge_reports[0].refine if row.guessed else "multi")
        return out
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
    """Load, merge and save one manifest row (the Dask task; also used locally). The map is
    saved, then its report (``report_path``): the pair counts as finished only when both
    exist. Returns the summary row; never raises for a bad pair."""
    t0 = time.perf_counter()
    try:
        if row.error:
            return _row_result(row, "error", "manifest", row.error)
        cfg = config_from_dict(config_dict)
        for p in (row.map1, row.map2):
            if not Path(p).is_file():
                raise FileNotFoundError(f"{p}: {'is a directory' if Path(p).is_dir() else 'no such file'}")
        m1, m2 = load(row.map1), load(row.map2)
        T_true = None if row.truth is None else transform_from_xyz_rpy(*row.truth)
        merged, report = merge(m1, m2, transform_from_xyz_rpy(*row.guess), T_1_2_true=T_true, config=cfg)
        Path(row.output).parent.mkdir(parents=True, exist_ok=True)
        save(merged, row.output)
        if write_reports:
            report.to_json(str(report_path(row.output)))
        notes = angle_warnings(("roll", "pitch", "yaw"), row.guess[3:], False, "",
                               " (manifest angles are radians)") + list(report.warnings)
        return _row_result(row, "ok", report=report, seconds=time.perf_counter() - t0, message="; ".join(notes))
    except MergeError as err:
        return _row_result(row, "error", err.kind, str(err), seconds=time.perf_counter() - t0)
    except Exception as err:  # a bad pair is recorded, the batch goes on
        kind = type(err).__name__
        return _row_result(row, "error", kind, str(err), seconds=time.perf_counter() - t0)


def run_group(group: ManifestGroup, config_dict: dict, write_reports: bool = True) -> dict:
    """Load, merge (``merge_many``) and save one manifest group, as ``run_pair`` does a pair:
    the map, then its report (``ManyReport.to_json``, with the map paths as ``inputs``). A
    group whose maps could not be placed next to map 0 is an error (``no_overlap``), as is
    one with a missing or unreadable map. Returns the summary row; never raises for a bad
    group."""
    t0 = time.perf_counter()
    try:
        if group.error:
            return _row_result(group, "error", "manifest", group.error)
        cfg = config_from_dict(config_dict)
        for p in group.maps:
            if not Path(p).is_file():
                raise FileNotFoundError(f"{p}: {'is a directory' if Path(p).is_dir() else 'no such file'}")
        maps = [load(p) for p in group.maps]
        t_load = time.perf_counter() - t0
        merged, report = merge_group(group, maps, cfg)
        if report.figures["maps_placed"] < 2:
            why = ", ".join(f"({e.i}, {e.j}) {e.why}" for e in report.edges if not e.kept and e.kind != "prior")
            raise MergeError(f"group {group.group}: no map could be placed next to {group.maps[0]}"
                             + (f"; edges rejected: {why}" if why else ""), "no_overlap")
        t1 = time.perf_counter()
        Path(group.output).parent.mkdir(parents=True, exist_ok=True)
        save(merged, group.output)
        if write_reports:
            report = dataclasses.replace(report, timings={**report.timings, "load": t_load,
                                                          "save": time.perf_counter() - t1})
            report.to_json(str(report_path(group.output)))
        notes = [w for p in group.pairs if p.guess is not None
                 for w in angle_warnings(("roll", "pitch", "yaw"), p.guess[3:], False, "",
                                         " (manifest angles are radians)")]
        return _row_result(group, "ok", report=report, seconds=time.perf_counter() - t0,
                           message="; ".join(dict.fromkeys(notes + list(report.warnings))))
    except MergeError as err:
        return _row_result(group, "error", err.kind, str(err), seconds=time.perf_counter() - t0)
    except Exception as err:  # a bad group is recorded, the batch goes on
        return _row_result(group, "error", type(err).__name__, str(err), seconds=time.perf_counter() - t0)


def run_job(job: ManifestRow | ManifestGroup, config_dict: dict, write_reports: bool = True) -> dict:
    """``run_group`` for a group, ``run_pair`` for a pair (the Dask task; on a worker it opens
    the kernel store its parent handed over)."""
    open_worker_store()
    if isinstance(job, ManifestGroup):
        return run_group(job, config_dict, write_reports)
    return run_pair(job, config_dict, write_reports)


def _write_summary(path: Path, rows: dict, earlier: list):
    with atomic_output(path) as tmp:
        with open(tmp, "w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=SUMMARY_FIELDS, extrasaction="ignore")
            w.writeheader()
            for k in sorted(rows):
                w.writerow(rows[k])
            w.writerows(earlier)


def _read_summary(path: Path) -> dict:
    """Rows of an earlier ``summary.csv`` by output path (an unreadable file gives none)."""
    try:
        with open(path, newline="", encoding="utf-8-sig") as f:
            return {r.get("output") or "": r for r in csv.DictReader(f)}
    except (OSError, UnicodeDecodeError, csv.Error):
        return {}


def _finished(row: ManifestRow | ManifestGroup, write_reports: bool) -> bool:
    return Path(row.output).is_file() and (not write_reports or report_path(row.output).is_file())


def run_manifest(manifest, out_dir, *, config: MergeConfig | None = None, workers: int | None = None,
                 scheduler: str | None = None, progress: bool = True, resume: bool | None = None,
                 write_reports: bool = True) -> list[dict]:
    """Run every pair and group of ``manifest`` into ``out_dir``; returns the summary rows
    (one per pair or group; also in ``out_dir/summary.csv``, rewritten atomically after each).

    ``scheduler``: a Dask scheduler address (``tcp://host:8786``) or a ``distributed.Client``;
    ``workers > 0`` without a scheduler starts a local Dask cluster of that many single-thread
    worker processes (at most one per job; a group is one task); otherwise jobs run in this
    process. ``resume`` (default: config) skips a pair or group that is finished: its output
    and its report exist (status ``skipped``, the earlier summary row's figures kept). Jobs not
    yet run are ``pending`` in the summary until they end; if every Dask worker is gone for
    ``config.batch.timeout_s`` they end as errors of kind ``no_workers``. Rows of an earlier
    ``summary.csv`` whose output is not in this manifest are kept at its end.

    A bad row is an error row (a bad row of a group: the group's); the others run. Raises ``ValueError`` for a manifest that
    cannot be read, ``cli.CliError`` if another run holds ``out_dir``'s lock file,
    ``dask_runner.SchedulerError`` if the scheduler cannot be reached.
    """
    cfg = MergeConfig() if config is None else config
    workers = cfg.batch.workers if workers is None else int(workers)
    scheduler = cfg.batch.scheduler if scheduler is None else scheduler
    resume = cfg.batch.resume if resume is None else bool(resume)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    rows = read_manifest(manifest, out_dir)
    summary_path = out_dir / "summary.csv"
    with folder_lock(out_dir):
        earlier = _read_summary(summary_path)
        done: dict = {}
        todo = []
        skipped = 0
        for row in rows:
            if row.error:
                done[row.index] = _row_result(row, "error", "manifest", row.error)
            elif resume and _finished(row, write_reports):
                before = earlier.get(row.output, {})
                done[row.index] = {**_row_result(row, "skipped", message="output exists (resume)"),
                                   **{k: before[k] for k in _KEPT if before.get(k)}}
                skipped += 1
            else:
                todo.append(row)
                done[row.index] = _row_result(row, "pending", message="not finished")
        current = {r["output"] for r in done.values()}
        kept = [r for out, r in earlier.items() if out not in current]
        bar = Progress(len(rows), progress)
        for k in sorted(done):
            if done[k]["status"] != "pending":
                bar.update(done[k]["status"])
        cfg_dict = config_to_dict(cfg)
        _write_summary(summary_path, done, kept)
        try:
            if todo and (scheduler or workers > 0):
                for row, res, err in map_on_dask(run_job, todo, cfg_dict, write_reports, scheduler=scheduler,
                                                 workers=min(workers, len(todo)), key=_task_key,
                                                 timeout_s=cfg.batch.timeout_s):
                    if err is not None:
                        res = _row_result(row, "error", getattr(err, "kind", type(err).__name__),
                                          f"task failed: {err}")
                    done[row.index] = res
                    bar.update(res["status"])
                    _write_summary(summary_path, done, kept)
            else:
                for row in todo:
                    done[row.index] = run_job(row, cfg_dict, write_reports)
                    bar.update(done[row.index]["status"])
                    _write_summary(summary_path, done, kept)
        finally:
            bar.close()
            _write_summary(summary_path, done, kept)
    return [done[k] for k in sorted(done)]


# figures of an earlier run kept in the row of a pair or group skipped on resume
_KEPT = ("seconds", "refine", "icp_status", "icp_iterations", "icp_rmse", "icp_fitness", "leaves_merged", "epsilon_r_init",
         "epsilon_t_init", "epsilon_r", "epsilon_t", "displacement_init", "displacement", "host", "maps_placed",
         "edges_kept", "edges_rejected")


def _task_key(row: ManifestRow | ManifestGroup) -> str:
    what = "group" if isinstance(row, ManifestGroup) else "pair"
    return f"octomerge-{what}-{row.index}-{abs(hash(row.output)) % 10**8}"
