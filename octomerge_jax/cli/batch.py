"""``octomerge batch MANIFEST.csv --out-dir DIR``: many merges of pairs and groups, resumable,
optionally on Dask."""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

from ..pipeline import REFINE_CHOICES, MergeConfig, load_config
from ._common import CliError
from .manifest import run_manifest
from .outputs import check_input, check_writable_folder
from .progress import show_bars

EPILOG = """manifest (CSV with a header; inputs relative to the manifest, outputs to --out-dir):
  map1,map2,output,x,y,z,roll,pitch,yaw
  run1/robotA.bt,run1/robotB.bt,run1_merged.bt,1.5,-0.8,0,0,0,0.785
  run2/robotA.ot,run2/robotB.ot,run2_merged.ot,0,0,0,0,0,0
Optional true_x..true_yaw columns add the thesis errors eps_r/eps_t to the summary.

groups of N maps: add a group column; rows sharing a group id (and their output) are merged as
one job by merge_many (pairwise registrations, a robust pose graph, one fusion; as merge-many)
into the frame of the group's first map1. Each row is a pair as above; its guess T_1_2 becomes
a guessed edge of the pose graph (a chain, a star or a loop; with --refine none the guesses are
used as they are). A group with no guess on any row is merged without guesses. Rows with an
empty group are pairs:
  group,map1,map2,output,x,y,z,roll,pitch,yaw
  site1,s1/robotA.bt,s1/robotB.bt,site1.bt,1.5,-0.8,0,0,0,0.785
  site1,s1/robotB.bt,s1/robotC.bt,site1.bt,2.0,0.1,0,0,0,-0.3
  team2,t2/a.ot,t2/b.ot,team2.ot,,,,,,
  team2,t2/a.ot,t2/c.ot,team2.ot,,,,,,
  ,run2/robotA.ot,run2/robotB.ot,run2_merged.ot,0,0,0,0,0,0
A group's report OUT.json is merge-many's (every map's T_0_k, every edge kept or rejected, the
map paths as "inputs"); its summary row has the group columns (maps, maps placed, edges kept
and rejected) and the largest eps_r/eps_t of its maps. A bad row, a missing or unreadable map
or no map placed next to the first makes the whole group an error row; the rest run.

examples:
  octomerge batch pairs.csv --out-dir merged/                 # in this process
  octomerge batch pairs.csv --out-dir merged/ --workers 4     # local Dask cluster, 4 processes
  octomerge batch pairs.csv --out-dir merged/ --scheduler tcp://10.0.0.5:8786

A Dask cluster: on the scheduler machine run `dask scheduler`, on each worker machine
`dask worker tcp://10.0.0.5:8786 --nthreads 1` in an environment with octomerge_jax installed
(same version) and the map files at the same paths (shared filesystem). Workers with a GPU and
jax[cuda12] installed run the kernels on the GPU automatically. Re-running the same command
skips finished pairs and groups (output and report both exist; --no-resume redoes them); the
status of each is in DIR/summary.csv (pending until it ends; earlier rows are kept), each merged
map OUT gets its report OUT.json next to it. Outputs must lie inside DIR; a bad row (too few
fields, a bad number, an output outside DIR or equal to an input) is an error for that row
only. A lock file (DIR/.octomerge-batch.lock) refuses a second run on DIR while one runs.
If every Dask worker is gone for batch.timeout_s (60 s), the pending pairs fail (kind
no_workers). Exit code 0 if every pair and group merged or was skipped, 6 if some failed (the
others are complete), 1 for an unreadable manifest, an unreachable scheduler or a locked DIR.
"""

EXIT_SOME_FAILED = 6


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "batch", help="merge many pairs or groups of maps from a CSV manifest (resumable, Dask optional)",
        description="Merge every pair (and every group of N maps) listed in MANIFEST (CSV) into "
                    "--out-dir. Finished outputs are written atomically and skipped on a re-run; "
                    "bad pairs and groups are recorded in summary.csv while the rest complete.",
        epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("manifest", type=Path, metavar="MANIFEST.csv")
    p.add_argument("--out-dir", type=Path, required=True, metavar="DIR")
    p.add_argument("--workers", type=int, metavar="N", help="local Dask worker processes (0: in this process)")
    p.add_argument("--scheduler", metavar="ADDRESS", help="Dask scheduler, e.g. tcp://host:8786")
    p.add_argument("--no-resume", action="store_true", help="redo pairs and groups whose output exists")
    p.add_argument("--refine", choices=REFINE_CHOICES)
    p.add_argument("--config", type=Path, metavar="FILE", help="TOML/JSON settings (octomerge dump-config)")
    p.add_argument("--no-progress", "-q", "--quiet", action="store_true", dest="no_progress",
                   help="no progress bar (there is none when stderr is not a terminal)")
    p.set_defaults(func=run)


def run(args) -> int:
    check_input(args.manifest, "manifest")
    if args.workers is not None and args.workers < 0:
        raise CliError(f"--workers must be >= 0, got {args.workers}", 2)
    try:
        cfg = load_config(args.config) if args.config else MergeConfig()
        if args.refine:
            cfg = cfg.replace(registration={"refine": args.refine})
    except (ValueError, FileNotFoundError) as err:
        raise CliError(str(err)) from None
    workers = cfg.batch.workers if args.workers is None else args.workers
    cpus = os.cpu_count() or 1
    if workers > cpus and not (args.scheduler or cfg.batch.scheduler):
        print(f"octomerge batch: warning: --workers {workers} is more than this machine's {cpus} CPUs; "
              f"using {cpus}", file=sys.stderr)
        workers = cpus
    if args.out_dir.exists() and not args.out_dir.is_dir():
        raise CliError(f"{args.out_dir}: --out-dir is not a directory")
    try:
        args.out_dir.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise CliError(f"{args.out_dir}: cannot create --out-dir: {err.strerror or err}") from None
    check_writable_folder(args.out_dir)
    try:
        rows = run_manifest(args.manifest, args.out_dir, config=cfg, workers=workers,
                            scheduler=args.scheduler, progress=show_bars(args.no_progress),
                            resume=False if args.no_resume else None)
    except (ValueError, FileNotFoundError, RuntimeError) as err:
        raise CliError(str(err)) from None
    counts: dict = {}
    for r in rows:
        counts[r["status"]] = counts.get(r["status"], 0) + 1
    groups = sum(bool(r["group"]) for r in rows)
    jobs = f"{len(rows)} pairs" if not groups else (f"{len(rows) - groups} pairs and " * (groups < len(rows))
                                                     + f"{groups} groups")
    print(f"{jobs}: " + ", ".join(f"{v} {k}" for k, v in sorted(counts.items()))
          + f"; summary in {args.out_dir / 'summary.csv'}")
    for r in rows:
        if r["status"] == "error" and r["group"]:
            print(f"  failed: group {r['group']} ({r['maps']} maps): {r['message']}")
        elif r["status"] == "error":
            print(f"  failed: {Path(r['map1']).name} + {Path(r['map2']).name}: {r['message']}")
    return EXIT_SOME_FAILED if counts.get("error") else 0
