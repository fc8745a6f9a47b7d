"""Atomic file output: write to a temp file in the destination folder, then rename."""

from __future__ import annotations

import contextlib
import os
import re
import signal
import tempfile
import threading
from pathlib import Path

__all__ = ["atomic_write_bytes", "atomic_output", "check_not_input", "check_input_file",
           "remove_stale_temp_files", "TEMP_FILE_PATTERN"]


@contextlib.contextmanager
def atomic_output(path, suffix: str | None = None):
    """Yield a temporary path next to ``path``; on success make it durable and rename it
    over ``path``.

    The caller writes the temporary file; then it is fsynced, renamed over ``path`` and the
    folder fsynced, so after a crash or power loss ``path`` holds the old or the new file,
    whole. On an exception the temp file is removed and ``path`` is left untouched. While
    the save runs in the main thread, SIGTERM / SIGINT / SIGHUP with their default action remove the
    temp file before the process dies (other handlers are called as before; SIGINT's
    ``KeyboardInterrupt`` unwinds through the cleanup). A temp file left by a killed process
    (``kill -9``) is removed by the next save to that folder (``remove_stale_temp_files``).

    Raises ``OSError`` (``PermissionError``, ...) whose message names ``path`` and the
    reason (disk full, file too large, read-only folder), never the temp name.
    """
    path = Path(path)
    folder = path.parent if str(path.parent) else Path(".")
    if not folder.is_dir():
        raise FileNotFoundError(f"{path}: output folder {folder} does not exist")
    remove_stale_temp_files(folder)
    try:
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.{_TMP_MARK}{os.getpid()}-",
                                   suffix=suffix or ".tmp", dir=folder)
    except OSError as err:
        raise _write_error(path, err) from None
    os.close(fd)
    guard = _SignalCleanup(tmp)
    try:
        with guard:
            yield Path(tmp)
            umask = os.umask(0)
            os.umask(umask)
            os.chmod(tmp, 0o666 & ~umask)  # mkstemp creates 0600; give outputs normal permissions
            _fsync_path(tmp)
            os.replace(tmp, path)
    except BaseException as err:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        if isinstance(err, OSError) and not isinstance(err, FileNotFoundError):
            raise _write_error(path, err) from None
        raise
    _fsync_dir(folder)


def atomic_write_bytes(path, data: bytes) -> None:
    """Write ``data`` to ``path`` atomically (temp file in the same folder + rename)."""
    with atomic_output(path) as tmp:
        with open(tmp, "wb") as f:
            f.write(data)


def check_not_input(output, inputs, force: bool = False) -> None:
    """Raise ``ValueError`` if ``output`` is one of ``inputs`` (same file), unless ``force``."""
    if force:
        return
    out = Path(output)
    for item in inputs:
        src = Path(item)
        same = out.resolve() == src.resolve()
        if not same and out.exists() and src.exists():
            same = os.path.samefile(out, src)
        if same:
            raise ValueError(f"output {output} is also an input; refusing to overwrite it "
                             "(pass --force to allow)")


# --- io
#: Marker in our temp names: ``.NAME.omj<pid>-<8 random>.tmp`` (or the output's suffix).
_TMP_MARK = "omj"
#: Our temp files, with the writer's pid: what ``remove_stale_temp_files`` may delete.
TEMP_FILE_PATTERN = re.compile(r"^\..+\." + _TMP_MARK + r"(?P<pid>[0-9]+)-[a-z0-9_]{8}\.[A-Za-z0-9]{1,16}$")


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except (PermissionError, OverflowError, ValueError):
        return True
    return True


def remove_stale_temp_files(folder) -> list[Path]:
    """Remove this package's temp files in ``folder`` (``TEMP_FILE_PATTERN``) whose writer
    process is gone on this machine (a save killed by ``kill -9`` or a power loss), owned by
    this user. Other files, and temp files of running processes, are left alone. Returns the
    paths removed; errors (a folder that cannot be listed) are ignored."""
    removed = []
    try:
        entries = list(os.scandir(folder))
    except OSError:
        return removed
    me, uid = os.getpid(), os.geteuid()
    for entry in entries:
        m = TEMP_FILE_PATTERN.match(entry.name)
        if not m:
            continue
        pid = int(m["pid"])
        try:
            if pid == me or _pid_alive(pid) or not entry.is_file(follow_symlinks=False) \
                    or entry.stat(follow_symlinks=False).st_uid != uid:
                continue
            os.unlink(entry.path)
        except OSError:
            continue
        removed.append(Path(entry.path))
    return removed


def check_input_file(path) -> None:
    """Raise ``IsADirectoryError`` / ``FileNotFoundError`` naming ``path`` unless it is an
    existing file (or a link to one)."""
    p = Path(path)
    if p.is_dir():
        raise IsADirectoryError(f"{p}: is a directory, not a file")
    if not p.exists():
        raise FileNotFoundError(f"{p}: no such file")


def _write_error(path: Path, err: OSError) -> OSError:
    """``err`` re-raised with a message naming the user's ``path`` (not the temp file)."""
    reason = err.strerror or str(err)
    if err.errno is None:
        return OSError(f"{path}: cannot write ({reason})")
    return OSError(err.errno, f"{path}: cannot write ({reason})")  # PermissionError, ...


def _fsync_path(path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _fsync_dir(folder: Path) -> None:
    """fsync a folder so a rename in it is durable (ignored where not supported)."""
    with contextlib.suppress(OSError):
        fd = os.open(folder, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


_CLEANUP_SIGNALS = tuple(getattr(signal, n) for n in ("SIGTERM", "SIGINT", "SIGHUP") if hasattr(signal, n))
_active_temps: set[str] = set()  # main thread's saves in progress
_previous_handlers: dict = {}


def _on_signal(signum, frame):
    previous = _previous_handlers.get(signum, signal.SIG_DFL)
    if callable(previous):  # someone else's handler: theirs decides (an exception unwinds)
        previous(signum, frame)
        return
    for tmp in list(_active_temps):  # default action: the process dies; remove temps first
        with contextlib.suppress(OSError):
            os.unlink(tmp)
    _active_temps.clear()
    _restore_handlers()
    os.kill(os.getpid(), signum)


def _restore_handlers() -> None:
    for signum, previous in _previous_handlers.items():
        with contextlib.suppress(ValueError, OSError):
            if signal.getsignal(signum) is _on_signal:
                signal.signal(signum, previous)
    _previous_handlers.clear()


class _SignalCleanup:
    """While a save runs in the main thread: SIGTERM / SIGINT / SIGHUP remove its temp file before
    the default action kills the process. Nothing is installed outside a save or in other
    threads (a leftover there is removed by the next save's ``remove_stale_temp_files``)."""

    def __init__(self, tmp: str):
        self.tmp = str(tmp)
        self.installed = False

    def __enter__(self):
        if threading.current_thread() is not threading.main_thread():
            return self
        if not _active_temps:
            for signum in _CLEANUP_SIGNALS:
                previous = signal.getsignal(signum)
                if previous in (signal.SIG_IGN, None):
                    continue
                _previous_handlers[signum] = previous
                signal.signal(signum, _on_signal)
        _active_temps.add(self.tmp)
        self.installed = True
        return self

    def __exit__(self, *exc):
        if self.installed:
            _active_temps.discard(self.tmp)
            if not _active_temps:
                _restore_handlers()
        return False
