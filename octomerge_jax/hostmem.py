"""Opt-in reuse of host memory between XLA:CPU calls (a process-wide glibc malloc setting).

XLA:CPU allocates each call's scratch buffer with ``malloc`` and frees it afterwards (hundreds
of MB for a fuse of millions of leaves). glibc serves blocks above 32 MB with a fresh ``mmap``
and unmaps them on ``free``, and XLA's worker threads allocate from arenas of their own that do
the same, so every call faults its scratch pages in again (figures: ``docs/design.md``,
"Host-memory reuse").

``reuse_host_memory()`` makes glibc serve every thread from the main heap (one arena), never
``mmap`` and never trim it, so freed scratch stays in the process and the next call of the same
size reuses it. The costs: the process keeps its peak heap until it exits (it is reused, not
returned to the system), and threads share one malloc arena: XLA's compiler threads queue for
its lock, so compiling takes longer (figures: ``docs/design.md``). Worth it where large kernels
run many times in one process (``octomerge batch``), not for one merge. Arenas are
bound to threads when JAX's backend starts, so call it once at startup, before the first JAX
computation (``octomerge batch`` does); later it changes nothing and warns. The same from
outside Python:
``GLIBC_TUNABLES=glibc.malloc.arena_max=1:glibc.malloc.mmap_max=0:glibc.malloc.trim_threshold=2147483647``;
``child_env()`` gives that variable to child processes (``octomerge batch``'s local Dask workers).
Importing the package never does this.
"""

from __future__ import annotations

import ctypes
import os
import sys
import warnings

__all__ = ["reuse_host_memory", "child_env", "GLIBC_TUNABLES"]

# the same setting for a process started with it in its environment
GLIBC_TUNABLES = "glibc.malloc.arena_max=1:glibc.malloc.mmap_max=0:glibc.malloc.trim_threshold=2147483647"

# glibc <malloc.h>
_M_TRIM_THRESHOLD, _M_MMAP_MAX, _M_ARENA_MAX = -1, -4, -8
_SETTINGS = ((_M_ARENA_MAX, 1), (_M_MMAP_MAX, 0), (_M_TRIM_THRESHOLD, 2**31 - 1))
_applied = False


def _jax_backend_started() -> bool:
    xb = sys.modules.get("jax._src.xla_bridge")
    return bool(getattr(xb, "_backends", None)) if xb is not None else False


def reuse_host_memory() -> bool:
    """Keep freed XLA:CPU scratch memory in the process for the next call (see the module
    docstring for what it changes and costs). Process-wide; call once at startup.

    Returns ``True`` when the setting is in effect, ``False`` when nothing was changed: not
    Linux with glibc, or a JAX backend has already started (a ``RuntimeWarning`` says so).
    """
    global _applied
    if _applied:
        return True
    if not sys.platform.startswith("linux"):
        return False
    try:
        mallopt = ctypes.CDLL("libc.so.6").mallopt
    except (OSError, AttributeError):
        return False
    if _jax_backend_started():
        warnings.warn("reuse_host_memory(): a JAX backend is already running, its threads keep "
                      "their malloc arenas; call it before the first JAX computation (nothing "
                      "was changed)", RuntimeWarning, stacklevel=2)
        return False
    mallopt.argtypes, mallopt.restype = (ctypes.c_int, ctypes.c_int), ctypes.c_int
    _applied = all(mallopt(option, value) == 1 for option, value in _SETTINGS)
    return _applied


def child_env(environ=os.environ) -> dict[str, str]:
    """Environment variables that give child processes (e.g. Dask workers) this process's host
    memory reuse: ``{"GLIBC_TUNABLES": ...}`` (appended to an existing value) when
    ``reuse_host_memory()`` is in effect here, else ``{}``."""
    if not _applied:
        return {}
    old = environ.get("GLIBC_TUNABLES", "")
    return {"GLIBC_TUNABLES": f"{old}:{GLIBC_TUNABLES}" if old else GLIBC_TUNABLES}
