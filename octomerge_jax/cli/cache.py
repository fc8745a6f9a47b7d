"""JAX's persistent compilation cache and the kernel store for the command line (never turned on
by importing the library): where they live, turning them on in this process, and handing them to
worker processes.
docs/design.md, "Compile cache and warm-up"."""

from __future__ import annotations

import contextlib
import os
from pathlib import Path

__all__ = ["cache_dir", "enable_compilation_cache", "command_caches", "worker_env", "open_worker_store",
           "STORE_VARIABLE", "FAST_COMPILE_FLAGS", "FAST_COMPILE_JAXLIB", "fast_compile_flags", "use_fast_compile"]

STORE_VARIABLE = "OCTOMERGE_KERNEL_STORE"
"""Environment variable that hands the kernel store to ``batch``'s worker processes."""

_OFF = ("", "off", "0", "none")

FAST_COMPILE_FLAGS = ("--xla_cpu_use_fusion_emitters=false",)
"""XLA flags every ``octomerge`` process compiles with: XLA:CPU's classic fusion emitters, which
compile a merge's programs faster than the MLIR ones at the same run time (docs/design.md,
"XLA flags of the command line"). Ignored on other backends."""

FAST_COMPILE_JAXLIB = ("0.10.",)
"""Prefixes of the jaxlib versions whose XLA is known to have ``FAST_COMPILE_FLAGS``: XLA aborts
the process on a flag it does not know, so with any other jaxlib the flags are left out."""


def cache_dir(environ=os.environ) -> str | None:
    """The cache directory the command line uses: ``$OCTOMERGE_CACHE_DIR`` if set (``""``,
    ``off``, ``0`` or ``none`` disable it: ``None``), else ``$XDG_CACHE_HOME/octomerge_jax/xla``
    (``~/.cache/octomerge_jax/xla``)."""
    path = environ.get("OCTOMERGE_CACHE_DIR")
    if path is None:
        base = environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
        path = str(Path(base) / "octomerge_jax" / "xla")
    return None if path.strip().lower() in _OFF else path


def enable_compilation_cache() -> str | None:
    """Turn on JAX's persistent compilation cache for this process (the command line only:
    importing the library changes no JAX setting). Compiled kernels are reused by later runs,
    which cuts a merge's first call (mostly XLA compilation) on the next invocation. Every
    program is kept, however fast it compiled: a merge compiles dozens of small programs whose
    compile times add up (JAX's default keeps only those over 1 s).

    Directory: ``cache_dir()``. A cache directory the user already gave JAX
    (``JAX_COMPILATION_CACHE_DIR``) is left alone. Returns the directory in use or ``None``; a
    directory that cannot be created disables the cache silently."""
    import jax

    if jax.config.jax_compilation_cache_dir:
        return jax.config.jax_compilation_cache_dir
    path = cache_dir()
    if path is None:
        return None
    try:
        Path(path).mkdir(parents=True, exist_ok=True)
    except OSError:
        return None
    jax.config.update("jax_compilation_cache_dir", path)
    if "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS" not in os.environ:
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    return path


@contextlib.contextmanager
def command_caches():
    """What one ``octomerge`` command runs inside: JAX's persistent compilation cache turned on
    (``enable_compilation_cache``; it stays on) and the merge's large kernels kept, ready to
    load without tracing, in the kernel store ``cache_dir()/kernels`` (``kernel_store``; closed
    again at the end unless it was open before), the programs the last command used loaded ahead
    in a background thread (``kernel_store.prefetch_recent``). ``$OCTOMERGE_CACHE_DIR=off``
    turns both off."""
    from ..kernel_store import close_store, open_store, prefetch_recent, store_dir

    enable_compilation_cache()
    path = cache_dir()
    opened = path is not None and store_dir() is None and open_store(Path(path) / "kernels") is not None
    if opened:
        prefetch_recent()
    try:
        yield
    finally:
        if opened:
            close_store()


def fast_compile_flags(xla_flags: str | None) -> str:
    """``xla_flags`` (the value of ``$XLA_FLAGS``, or ``None``) with each of
    ``FAST_COMPILE_FLAGS`` appended unless it already names that flag (the user's setting wins)."""
    flags = (xla_flags or "").split()
    for flag in FAST_COMPILE_FLAGS:
        name = flag.split("=", 1)[0]
        if not any(f.split("=", 1)[0] == name for f in flags):
            flags.append(flag)
    return " ".join(flags)


def use_fast_compile(environ=os.environ, jaxlib_version: str | None = None) -> bool:
    """Set ``$XLA_FLAGS`` in ``environ`` to ``fast_compile_flags`` of its value: for this process
    (call it before its first JAX computation, when XLA reads the variable) and the processes it
    starts. Only with a jaxlib of ``FAST_COMPILE_JAXLIB`` (``jaxlib_version``: the installed
    one's by default); returns whether the flags were set. The ``octomerge`` command does this;
    importing the library never does."""
    if jaxlib_version is None:
        from jaxlib import version

        jaxlib_version = version.__version__
    if not jaxlib_version.startswith(FAST_COMPILE_JAXLIB):
        return False
    environ["XLA_FLAGS"] = fast_compile_flags(environ.get("XLA_FLAGS"))
    return True


def worker_env() -> dict[str, str]:
    """Environment variables that give worker processes (``octomerge batch --workers N``) this
    process's compilation cache and kernel store, so a program compiled by one worker (or an
    earlier run) is loaded, not compiled again, by the others: ``{}`` when no cache is on here."""
    import jax

    from ..kernel_store import store_dir

    env = {}
    path = jax.config.jax_compilation_cache_dir
    if path:
        env.update({"JAX_COMPILATION_CACHE_DIR": str(path),
                    "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS":
                        str(jax.config.jax_persistent_cache_min_compile_time_secs)})
    if store_dir() is not None:
        env[STORE_VARIABLE] = str(store_dir())
    return env


def open_worker_store(environ=os.environ) -> None:
    """In a worker process of ``batch``: open the kernel store its parent handed over in
    ``$OCTOMERGE_KERNEL_STORE`` (nothing when unset or already open)."""
    from ..kernel_store import open_store, store_dir

    path = environ.get(STORE_VARIABLE)
    if path and store_dir() is None:
        open_store(path)
