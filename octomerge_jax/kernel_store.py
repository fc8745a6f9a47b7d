"""Compiled kernels kept on disk between processes and found without tracing.

JAX's persistent compilation cache is keyed on the lowered program, so every new process traces
and lowers each kernel again before it can find it there (~1.5 s of a 4.3 s warm ``octomerge
merge``). ``stored_jit`` is ``jax.jit`` for the few large entry kernels a merge runs; once a
store is opened (``open_store``, done by the command line, never by importing the library) it
keys each call on what decides the program without tracing it (the function, the static
arguments, the dynamic arguments' tree, shapes and dtypes, the package's source, JAX's version,
backend and settings, the host CPU) and loads the executable a previous process serialized
(``jax.experimental.serialize_executable``). With no store open it is exactly ``jax.jit``.
docs/design.md, "Compile cache and warm-up"."""

from __future__ import annotations

import contextlib
import contextvars
import functools
import hashlib
import inspect
import json
import os
import pickle
import platform
import threading
import weakref
from pathlib import Path

import jax
from jax.experimental import serialize_executable

from ._fileutil import atomic_output, remove_stale_temp_files
from ._ops import is_traced

__all__ = ["DEFAULT_MAX_BYTES", "LOAD_EVENT", "RECENT_FILE", "RECENT_MAX_PROGRAMS", "StoredJit", "stored_jit",
           "open_store", "close_store", "store_dir", "tidy_store", "prefetch_recent", "compile_listener",
           "forget_programs"]

LOAD_EVENT = "/octomerge_jax/kernel_store/loads"
"""``jax.monitoring`` event recorded for every program loaded from the store."""

DEFAULT_MAX_BYTES = 2 << 30
"""The store's default size bound [bytes] (2 GiB; a campus-size merge keeps ~5 MB)."""

_COMPILE_LOCK = threading.Lock()
_KEYS_LOCK = threading.Lock()
_KEY_LOCKS: dict[str, threading.Lock] = {}
_LISTENER: contextvars.ContextVar = contextvars.ContextVar("octomerge_compile_listener", default=None)
_STATE: dict = {"dir": None, "environment": None, "backend_ready": False}
_KERNELS: weakref.WeakSet = weakref.WeakSet()  # every StoredJit, for forget_programs
_FORMAT = 1

RECENT_FILE = "recent-programs.json"
"""The store's list of the programs the last command that closed it used, in the order it first
used them, with the environment they were made in (``prefetch_recent``)."""

RECENT_MAX_PROGRAMS = 16
"""At most this many programs are listed; a command that used more (a warm-up, a batch of many
sizes) leaves no list."""

_BACKEND_LOCK = threading.Lock()
_USED_LOCK = threading.Lock()
_USED: list[str] = []  # the store files this process took programs from or wrote, in order
_PREFETCHED: dict[str, object] = {}  # key -> executable loaded ahead by the prefetch thread
_PREFETCH: dict = {"thread": None, "stop": None}


def open_store(path: str | os.PathLike, max_bytes: int = DEFAULT_MAX_BYTES) -> Path | None:
    """Keep compiled ``stored_jit`` kernels in directory ``path`` (``~`` expanded; created) for
    this process and later ones. On opening, files a killed process left half-written are
    removed and, when the entries take more than ``max_bytes``, the least recently used are
    removed down to three quarters of it (``tidy_store``). Returns the directory, or ``None``
    when it cannot be created (the store stays closed and kernels compile as with ``jax.jit``)."""
    path = Path(path).expanduser()
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError:
        return None
    tidy_store(path, max_bytes)
    _stop_prefetch()
    with _USED_LOCK:
        _USED.clear()
    _STATE["dir"] = path
    _STATE["environment"] = None
    return path


def tidy_store(path: Path, max_bytes: int = DEFAULT_MAX_BYTES) -> None:
    """Remove the temporary files of writers that are gone (``remove_stale_temp_files``), then,
    while the store's entries take more than ``max_bytes``, the least recently used ones (by
    modification time, which a load refreshes) down to three quarters of it. Files that vanish
    or cannot be removed meanwhile (another process) are skipped."""
    remove_stale_temp_files(path)
    entries = []
    for item in path.glob("*.pkl"):
        if item.name.startswith("."):  # a temporary of a running writer
            continue
        try:
            st = item.stat()
        except OSError:
            continue
        entries.append((st.st_mtime, st.st_size, item))
    total = sum(size for _, size, _ in entries)
    if total <= max_bytes:
        return
    for _, size, item in sorted(entries, key=lambda e: e[0]):
        try:
            item.unlink()
        except OSError:
            continue
        total -= size
        if total <= max_bytes * 3 // 4:
            return


def close_store() -> None:
    """Stop reading and writing the store; kernels already loaded in this process stay loaded.
    Waits for a prefetch (``prefetch_recent``) to stop, then lists the programs this process used
    in the store's ``RECENT_FILE`` for the next command (more than ``RECENT_MAX_PROGRAMS``: the
    file is removed; none: it is left as it is)."""
    directory = _STATE["dir"]
    _stop_prefetch()
    _STATE["dir"] = None
    if directory is None:
        return
    with _USED_LOCK:
        used = list(dict.fromkeys(_USED))
        _USED.clear()
    recent = directory / RECENT_FILE
    if not used:  # a command without kernels (info, convert) keeps the last list
        return
    with contextlib.suppress(OSError):
        if len(used) <= RECENT_MAX_PROGRAMS:
            text = json.dumps({"format": _FORMAT, "environment": _environment(), "programs": used})
            with atomic_output(recent, suffix=".json") as tmp:
                tmp.write_text(text)
        else:
            recent.unlink(missing_ok=True)


def _stop_prefetch() -> None:
    """Stop a prefetch thread (after the program it is loading) and drop what it loaded."""
    thread, stop = _PREFETCH["thread"], _PREFETCH["stop"]
    if thread is not None:
        stop.set()
        thread.join()
        _PREFETCH.update(thread=None, stop=None)
    _PREFETCHED.clear()


def prefetch_recent() -> bool:
    """Start loading, in a background thread, the programs listed in the open store's
    ``RECENT_FILE`` (the last command's, in the order it used them) when they were made in this
    environment: a command like the last one then finds them loaded instead of loading each when
    it first calls it (loading releases the GIL, so it overlaps the command's work). A program the
    command calls while the thread loads it waits for it; ``close_store`` stops the thread.
    Returns whether a thread was started. docs/design.md, "Compile cache and warm-up"."""
    directory = _STATE["dir"]
    if directory is None or _PREFETCH["thread"] is not None or jax.device_count() != 1:
        return False
    try:
        with open(directory / RECENT_FILE) as f:
            recent = json.load(f)
        names = [str(n) for n in recent["programs"]][:RECENT_MAX_PROGRAMS]
        if recent.get("format") != _FORMAT or recent.get("environment") != _environment():
            return False
        names = [n for n in names if Path(n).name == n and n.endswith(".pkl")]  # entries of the store only
    except (OSError, ValueError, KeyError, TypeError):
        return False
    stop = threading.Event()
    thread = threading.Thread(target=_prefetch, args=(directory, names, stop), name="octomerge-prefetch",
                              daemon=True)
    _PREFETCH.update(thread=thread, stop=stop)
    thread.start()
    return True


def _prefetch(directory: Path, names: list[str], stop: threading.Event) -> None:
    """The prefetch thread: load each listed program not yet taken (a failure skips it)."""
    for name in names:
        if stop.is_set():
            return
        key = name.removesuffix(".pkl").rsplit("-", 1)[-1]
        with _key_lock(key):
            if key in _PREFETCHED or any(key in k._loaded for k in list(_KERNELS)):
                continue
            compiled = _load_file(directory / name)
            if compiled is not None:
                _PREFETCHED[key] = compiled


def store_dir() -> Path | None:
    """The open store's directory, or ``None``."""
    return _STATE["dir"]


def _package_source_digest() -> str:
    """SHA-256 of every ``.py`` file of the package (path and content): a changed kernel's source
    never meets an executable compiled from the old one."""
    h = hashlib.sha256()
    root = Path(__file__).resolve().parent
    for path in sorted(root.rglob("*.py")):
        h.update(str(path.relative_to(root)).encode())
        h.update(path.read_bytes())
    return h.hexdigest()


def _host_cpu() -> str:
    """The host CPU's model and instruction-set flags (Linux; else the platform's names): a
    program compiled for one CPU's instructions is never loaded on another that lacks them
    (a cache directory shared between machines)."""
    try:
        with open("/proc/cpuinfo", encoding="utf-8", errors="replace") as f:
            lines = [line for line in f if line.startswith(("model name", "flags", "Features", "CPU part"))]
        info = "".join(sorted(set(lines)))
    except OSError:
        info = ""
    return hashlib.sha256((info or f"{platform.machine()} {platform.processor()}").encode()).hexdigest()


def _environment() -> str:
    """What besides the arguments decides a compiled program: versions, backend, settings."""
    if _STATE["environment"] is None:
        import jaxlib

        device = jax.devices()[0]
        _STATE["environment"] = repr((
            _FORMAT, jax.__version__, jaxlib.__version__, device.platform, device.device_kind,
            device.client.platform_version, jax.device_count(), jax.config.jax_enable_x64,
            jax.config.jax_default_matmul_precision, os.environ.get("XLA_FLAGS", ""), _host_cpu(),
            _package_source_digest()))
    return _STATE["environment"]


def _prepare_backend() -> None:
    """Set up what lowering would have set up before a deserialized program runs: on the CPU,
    jaxlib binds LAPACK's routines (ICP's solves call them) only when a linear-algebra op is
    lowered, and a loaded program calling them unbound crashes the process."""
    with _BACKEND_LOCK:
        if _STATE["backend_ready"]:
            return
        try:
            from jax._src.lax.linalg import initialize_lapack  # noqa: PLC0415 - private, checked below

            initialize_lapack()
        except (ImportError, AttributeError):
            spec = jax.ShapeDtypeStruct((2, 2), "float32")
            jax.jit(jax.numpy.linalg.eigh).lower(spec)
        _STATE["backend_ready"] = True


def _cache_threshold_override():
    """A context manager that raises JAX's persistent-cache write threshold to infinity for
    this thread only (``None`` where this JAX lacks the thread-local setting)."""
    try:
        from jax._src import config as jax_config  # noqa: PLC0415 - private, checked below

        return jax_config.persistent_cache_min_compile_time_secs(float("inf"))
    except (ImportError, AttributeError, TypeError):
        return None


def _compile_fresh(lowered):
    """``lowered.compile()`` that neither reads nor writes JAX's persistent compilation cache. An
    executable read back from that cache serializes without its compiled functions on the CPU
    (the copy then fails with ``NOT_FOUND: Function ... not found``), so the store keeps only
    fresh compiles: ``lowered`` comes from the ``stored_``-named twin of the kernel (a program
    of its own name, never found in that cache), and the cache's write threshold is raised for
    the one compile so it is not written there either: for the compiling thread only, so
    threads compile side by side (where JAX lacks that, globally and one compile at a time)."""
    override = _cache_threshold_override()
    if override is not None:
        with override:
            return lowered.compile()
    with _COMPILE_LOCK:
        threshold = jax.config.jax_persistent_cache_min_compile_time_secs
        jax.config.update("jax_persistent_cache_min_compile_time_secs", float("inf"))
        try:
            return lowered.compile()
        finally:
            jax.config.update("jax_persistent_cache_min_compile_time_secs", threshold)


def _key_lock(key: str) -> threading.Lock:
    """The lock that makes one thread compile or load the program ``key`` while others wait."""
    with _KEYS_LOCK:
        return _KEY_LOCKS.setdefault(key, threading.Lock())


@contextlib.contextmanager
def compile_listener(callback):
    """Within the block, call ``callback(kernel)`` (``kernel``: the kernel's ``module.name``)
    in this thread before each stored kernel it compiles afresh (a program neither held by the
    process nor in the open store). Threads started inside the block do not inherit it."""
    token = _LISTENER.set(callback)
    try:
        yield
    finally:
        _LISTENER.reset(token)


def forget_programs() -> None:
    """Drop every compiled program this process holds, the stored kernels' and ``jax.jit``'s
    (``jax.clear_caches``); the store on disk is untouched, so a later call loads its program
    from there. Each compiled program keeps a few memory mappings of its code until dropped, and
    Linux allows a process 65,530 (``vm.max_map_count``): a process that compiles programs by
    the thousand, such as a test run, crashes in XLA once it reaches that limit. Call it between
    independent pieces of such work (``tests/conftest.py`` does, after a test, near the limit)."""
    for kernel in list(_KERNELS):
        kernel._loaded.clear()
    jax.clear_caches()


def _renamed(fun):
    """``fun`` under the name ``stored_<name>`` (its signature kept), so its programs have their
    own names and keys."""
    @functools.wraps(fun)
    def twin(*args, **kwargs):
        return fun(*args, **kwargs)

    twin.__name__ = f"stored_{fun.__name__}"
    twin.__qualname__ = f"stored_{fun.__qualname__}"
    return twin


class StoredJit:
    """``jax.jit(fun, static_argnames=..., donate_argnums=...)`` whose compiled programs go to and
    come from the open store (see the module). Dynamic parameters must be positional and come
    before the static ones (else ``TypeError``). Calls under a trace (inside another ``jit`` or
    ``vmap``) and on a machine with more than one device use the plain ``jax.jit``. Other
    attributes (``lower``, ``eval_shape``, ...) are the jitted function's."""

    def __init__(self, fun, static_argnames: tuple[str, ...] = (), donate_argnums: tuple[int, ...] = ()):
        self.jitted = jax.jit(fun, static_argnames=static_argnames, donate_argnums=donate_argnums)
        self._for_store = jax.jit(_renamed(fun), static_argnames=static_argnames, donate_argnums=donate_argnums)
        self._signature = inspect.signature(fun)
        kinds = [(p.name in static_argnames, p.kind) for p in self._signature.parameters.values()]
        positional = (inspect.Parameter.POSITIONAL_ONLY, inspect.Parameter.POSITIONAL_OR_KEYWORD)
        if any(not is_static and kind not in positional for is_static, kind in kinds) or \
                any(a and not b for (a, _), (b, _) in zip(kinds, kinds[1:])):
            raise TypeError(f"stored_jit: {fun.__qualname__}'s dynamic parameters must be positional and come "
                            "before its static ones")
        self._static = frozenset(static_argnames)
        self._name = f"{fun.__module__}.{fun.__qualname__}"
        self._loaded: dict[str, object] = {}
        functools.update_wrapper(self, fun)
        _KERNELS.add(self)

    def programs(self) -> int:
        """How many compiled programs this process holds for the kernel (``jax.jit``'s own and
        those taken from the store): a call that does not raise it compiled nothing."""
        return self.jitted._cache_size() + len(self._loaded)

    def eval_shape(self, *args, **kwargs):
        """``jax.ShapeDtypeStruct``s of a call's result (arrays may be given as
        ``jax.ShapeDtypeStruct``), by the trace the store's programs compile from: compiling
        these shapes afterwards does not trace the function again."""
        return self._for_store.eval_shape(*args, **kwargs)

    def __getattr__(self, name):
        if name == "jitted":
            raise AttributeError(name)
        return getattr(self.jitted, name)

    def __call__(self, *args, **kwargs):
        directory = _STATE["dir"]
        if directory is None or jax.device_count() != 1:
            return self.jitted(*args, **kwargs)
        dynamic, static = self._split(args, kwargs)
        if is_traced(*jax.tree_util.tree_leaves(dynamic)):
            return self.jitted(*args, **kwargs)
        return self._program(directory, dynamic, static)(*dynamic)

    def precompile(self, *args, **kwargs) -> bool:
        """Make the program a call with these arguments would run ready (loaded from the open
        store, or compiled and stored) without running it; arrays may be given as
        ``jax.ShapeDtypeStruct``. Returns ``False`` (nothing done) with no store open or more
        than one device."""
        directory = _STATE["dir"]
        if directory is None or jax.device_count() != 1:
            return False
        self._program(directory, *self._split(args, kwargs))
        return True

    def _split(self, args, kwargs) -> tuple[tuple, dict]:
        """A call's ``(dynamic arguments, {static name: value})``."""
        bound = self._signature.bind(*args, **kwargs)
        bound.apply_defaults()
        dynamic = tuple(v for k, v in bound.arguments.items() if k not in self._static)
        return dynamic, {k: v for k, v in bound.arguments.items() if k in self._static}

    def _program(self, directory: Path, dynamic: tuple, static: dict):
        """The executable for these arguments: this process's, the store's, or compiled and
        stored."""
        leaves, tree = jax.tree_util.tree_flatten(dynamic)
        key = hashlib.sha256(repr((self._name, sorted(static.items()), str(tree),
                                   [str(jax.typeof(x)) for x in leaves], _environment())).encode()).hexdigest()[:32]
        compiled = self._loaded.get(key)
        if compiled is None:
            with _key_lock(key):  # another thread compiling it: wait and take its program
                compiled = self._loaded.get(key)
                if compiled is None:
                    compiled = _PREFETCHED.pop(key, None)
                    if compiled is None:
                        compiled = self._load(directory, key)
                    if compiled is None:
                        listener = _LISTENER.get()
                        if listener is not None:
                            listener(self._name)
                        compiled = _compile_fresh(self._for_store.lower(*dynamic, **static))
                        self._save(directory, key, compiled)
                    with _USED_LOCK:
                        _USED.append(self._path(directory, key).name)
                self._loaded[key] = compiled
        return compiled

    def _path(self, directory: Path, key: str) -> Path:
        return directory / f"{self._name.rsplit('.', 1)[-1]}-{key}.pkl"

    def _load(self, directory: Path, key: str):
        """The stored executable for ``key``, or ``None`` (absent, unreadable or not loadable
        here: it is then compiled and stored again)."""
        return _load_file(self._path(directory, key))

    def _save(self, directory: Path, key: str, compiled) -> None:
        """Write ``compiled`` under ``key`` (``atomic_output``); a program that cannot be
        serialized or a store that cannot be written is skipped (the next process compiles it
        again)."""
        try:
            blob = pickle.dumps(serialize_executable.serialize(compiled))
            with atomic_output(self._path(directory, key), suffix=".pkl") as tmp:
                tmp.write_bytes(blob)
        except Exception:  # noqa: BLE001 - storing is an optimisation
            return


def _load_file(path: Path):
    """The executable stored in ``path``, or ``None`` (absent, unreadable or not loadable here)."""
    try:
        with open(path, "rb") as f:
            payload, in_tree, out_tree = pickle.load(f)
        _prepare_backend()
        compiled = serialize_executable.deserialize_and_load(payload, in_tree, out_tree)
    except Exception:  # noqa: BLE001 - a bad entry costs a compile, never the merge
        return None
    with contextlib.suppress(OSError):
        os.utime(path)  # recently used: kept by tidy_store
    jax.monitoring.record_event(LOAD_EVENT)
    return compiled


def stored_jit(fun=None, *, static_argnames: tuple[str, ...] = (), donate_argnums: tuple[int, ...] = ()):
    """Decorator: ``StoredJit`` of ``fun`` (``@stored_jit(static_argnames=(...))`` or
    ``@stored_jit``)."""
    if fun is None:
        return functools.partial(stored_jit, static_argnames=static_argnames, donate_argnums=donate_argnums)
    return StoredJit(fun, tuple(static_argnames), tuple(donate_argnums))
