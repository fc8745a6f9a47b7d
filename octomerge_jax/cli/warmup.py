"""``octomerge warmup [MAP1 MAP2]``: compile the merge kernels into the persistent cache ahead of
the first real merge. docs/design.md, "Compile cache and warm-up"."""

from __future__ import annotations

import argparse
import math
import time
from collections import Counter
from pathlib import Path

from ..types import REFINE_CHOICES
from ._common import CliError

EPILOG = """examples:
  octomerge warmup                       # the built-in room pair, 0.1 to 0.025 m
  octomerge warmup --res 0.0125          # large maps (~0.5M leaves)
  octomerge warmup robot1.bt robot2.bt   # exactly the programs merging these two maps needs
  octomerge warmup --refine icp none     # only what merges with --refine icp / none need

A merge's first call is mostly XLA compilation of a few dozen programs, one set per capacity
bucket (array sizes padded to powers of two). The command line keeps compiled programs in a
persistent cache ($OCTOMERGE_CACHE_DIR, default ~/.cache/octomerge_jax/xla); this command fills
it by merging pairs of the sizes given, in each mode of --refine (by default what
`octomerge merge` runs from a guess, icp+dense, and without one, global, then icp and none),
and writes nothing else. With your own pair, global runs first and the transform it finds is
the other modes' guess; a mode whose registration fails there is reported and skipped.
"""

#: ``MergeError.kind`` of a registration that ended badly: the warm-up goes on with the next mode
_REGISTRATION_FAILURES = ("icp_failed", "not_converged", "no_overlap")
#: ``--refine``'s default: ``merge``'s default from a guess and without one, then the lighter modes
DEFAULT_MODES = ("icp+dense", "global", "icp", "none")

# the built-in room pair: robot 2's frame turned pi/4 and shifted (sim.small_room)
_XYZ_RPY_TRUE = (0.35, -0.25, 0.0, 0.0, 0.0, math.pi / 4)
_GUESS_ERROR = (0.05, -0.05, 0.0, 0.0, 0.0, -0.04)


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "warmup", help="compile the merge kernels for common map sizes into the persistent cache",
        description="Merge pairs of common sizes (or MAP1 and MAP2) once, discarding the result, "
                    "so that later `octomerge merge` / `demo` / `batch` runs load their compiled "
                    "kernels from the persistent cache instead of compiling them.",
        epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("maps", type=Path, nargs="*", metavar="MAP",
                   help="two .bt/.ot maps to compile for (default: the built-in room pair)")
    p.add_argument("--res", type=float, nargs="+", default=[0.1, 0.07, 0.05, 0.035, 0.025], metavar="M",
                   help="resolutions [m] of the built-in room pair (default 0.1 0.07 0.05 0.035 0.025: "
                        "about 5k to 105k leaves per map, doubling)")
    p.add_argument("--refine", nargs="+", default=list(DEFAULT_MODES), choices=REFINE_CHOICES, metavar="MODE",
                   help=f"refinement modes to compile, of {', '.join(REFINE_CHOICES)} (default: "
                        f"{' '.join(DEFAULT_MODES)}; global runs without a guess, as `octomerge merge` "
                        "does when given none)")
    p.set_defaults(func=run)


def _pairs(args):
    """``(label, m1, m2, T_1_2 guess)`` for each pair to merge (your pair: the identity, replaced
    by the ``global`` mode's result when that runs)."""
    import numpy as np

    from ..io import load
    from ..pipeline import transform_from_xyz_rpy
    from ..sim import small_room_map, small_room_voxels

    if args.maps:
        yield f"{args.maps[0].name} + {args.maps[1].name}", load(args.maps[0]), load(args.maps[1]), np.eye(4)
        return
    T_true = transform_from_xyz_rpy(*_XYZ_RPY_TRUE)
    guess = transform_from_xyz_rpy(*(a + b for a, b in zip(_XYZ_RPY_TRUE, _GUESS_ERROR)))
    for res in args.res:
        voxels = small_room_voxels(res)
        m1 = small_room_map((-1.0, 3.0), res, voxels=voxels)
        m2 = small_room_map((0.8, 9.0), res, T_true, voxels=voxels)
        yield f"room at {res:g} m", m1, m2, guess


def _check(args) -> None:
    """Raise ``CliError`` for arguments that cannot work, before anything heavy is imported."""
    if args.maps:
        if len(args.maps) != 2:
            raise CliError(f"give two maps (MAP1 MAP2), got {len(args.maps)}", exit_code=2)
        for path in args.maps:
            if not path.is_file():
                raise CliError(f"{path}: no such file")
    for res in args.res:
        if not (res > 0 and math.isfinite(res)):
            raise CliError(f"--res {res}: a resolution must be a positive number of metres", exit_code=2)


def run(args) -> int:
    _check(args)
    import jax

    from ..kernel_store import LOAD_EVENT, store_dir
    from ..pipeline import MergeConfig, MergeError, merge

    compiled, loaded = Counter(), Counter()

    def on_compile(event, secs, **kw):
        if event == "/jax/core/compile/backend_compile_duration":
            compiled["programs"] += 1
            compiled["seconds"] += secs

    def on_event(event, **kw):
        if event == "/jax/compilation_cache/cache_hits":  # also counted as a backend compile
            loaded["programs"] += 1
        elif event == LOAD_EVENT:  # loaded from the kernel store, no backend compile
            loaded["stored"] += 1

    cache = jax.config.jax_compilation_cache_dir
    if not cache:
        print("warning: the persistent compilation cache is off ($OCTOMERGE_CACHE_DIR): "
              "nothing is kept for later runs")
    failed: list[str] = []
    merged = 0  # merges that ran to the end
    jax.monitoring.register_event_duration_secs_listener(on_compile)
    jax.monitoring.register_event_listener(on_event)
    try:
        for label, m1, m2, guess in _pairs(args):
            # your own pair: global first, and its transform is the other modes' guess
            modes = sorted(args.refine, key=lambda r: r != "global") if args.maps else args.refine
            for refine in modes:
                before_c, before_l = dict(compiled), dict(loaded)
                t0 = time.perf_counter()
                try:
                    _, report = merge(m1, m2, None if refine == "global" else guess, config=MergeConfig(),
                                      refine=refine)
                except MergeError as err:
                    if err.kind not in _REGISTRATION_FAILURES:
                        raise CliError(f"{label}: {err}") from err
                    # e.g. your pair from the identity: what ran is compiled, the other modes run
                    failed.append(f"{label}, refine {refine}: {err}")
                    print(f"warning: {failed[-1]}")
                    continue
                merged += 1
                if refine == "global" and args.maps:
                    guess = report.T_1_2
                n = compiled["programs"] - before_c.get("programs", 0)
                hits = loaded["programs"] - before_l.get("programs", 0)
                stored = loaded["stored"] - before_l.get("stored", 0)
                print(f"{label} ({m1.num_leaves:,} + {m2.num_leaves:,} leaves), refine {refine}: "
                      f"{time.perf_counter() - t0:.1f} s, {n - hits} programs compiled, {hits + stored} loaded")
    finally:
        jax.monitoring.unregister_event_duration_listener(on_compile)
        jax.monitoring.unregister_event_listener(on_event)
    if failed and not merged:
        raise CliError(failed[0])
    if cache:
        print(f"cache: {cache}")
    if store_dir() is not None:
        print(f"kernel store: {store_dir()}")
    return 0
