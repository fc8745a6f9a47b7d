"""The ``--reuse-host-memory`` option shared by the benchmark scripts (``octomerge_jax.hostmem``)."""

from __future__ import annotations

import argparse


def add_flag(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--reuse-host-memory", action="store_true",
                        help="keep XLA:CPU scratch memory between calls (octomerge_jax.reuse_host_memory, "
                             "as the octomerge CLI does)")


def apply(args) -> str:
    """Apply the option (before the first JAX computation); returns ``"on"`` or ``"off"``."""
    if not args.reuse_host_memory:
        return "off"
    from octomerge_jax.hostmem import reuse_host_memory

    if not reuse_host_memory():
        raise SystemExit("--reuse-host-memory: not applied (needs Linux with glibc, before JAX starts)")
    return "on"
