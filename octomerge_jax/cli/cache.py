"""JAX's persistent compilation cache for the command line (never turned on by importing the
library): where it lives, turning it on in this process, and handing it to worker processes.
docs/design.md, "Compile cache and warm-up"."""

from __future__ import annotations

import os
from pathlib import Path

__all__ = ["cache_dir", "enable_compilation_cache", "worker_env"]

_OFF = ("", "off", "0", "none")


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


def worker_env() -> dict[str, str]:
    """Environment variables that give worker processes (``octomerge batch --workers N``) this
    process's compilation cache, so a program compiled by one worker (or an earlier run) is
    loaded, not compiled again, by the others: ``{}`` when no cache is on here."""
    import jax

    path = jax.config.jax_compilation_cache_dir
    if not path:
        return {}
    return {"JAX_COMPILATION_CACHE_DIR": str(path),
            "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS":
                str(jax.config.jax_persistent_cache_min_compile_time_secs)}
