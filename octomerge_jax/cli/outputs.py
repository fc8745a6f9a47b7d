"""The command line's input and output policy, one copy for every subcommand.

- An input must be an existing regular file (a folder is reported as one, not as missing).
- An output is checked before any compute: its extension, its folder (exists, writable: a
  file is created and removed there), and that it does not already exist, unless ``--force``.
  ``--force`` also lets a command's main output replace one of its inputs (read completely
  before the atomic rename); a side output (report, figure) never replaces an input or
  another output of the same command.
- A failed write names the user's path, not the hidden temporary file beside it.
- An angle beyond a full turn is warned about (radians that look like degrees).

See ``docs/design.md``, "Output policy of the command line".
"""

from __future__ import annotations

import contextlib
import fcntl
import math
import os
import socket
import tempfile
from pathlib import Path
from typing import Iterable, Iterator, Sequence

from ._common import CliError

__all__ = ["FIGURE_SUFFIXES", "MAP_SUFFIXES", "angle_warnings", "check_input", "check_output",
           "check_writable_folder", "folder_lock", "inside", "same_file", "writing"]

MAP_SUFFIXES = (".bt", ".ot")
# formats matplotlib's Agg canvas writes (checked without importing matplotlib)
FIGURE_SUFFIXES = (".png", ".pdf", ".svg", ".svgz", ".jpg", ".jpeg", ".tif", ".tiff", ".webp", ".eps", ".ps")


def check_input(path, what: str = "input") -> None:
    """Raise ``CliError`` (exit 1) unless ``path`` is an existing regular file."""
    path = Path(path)
    if path.is_dir():
        raise CliError(f"{path}: is a directory, not a {what} file")
    if not path.exists():
        raise CliError(f"{path}: no such file")
    if not path.is_file():
        raise CliError(f"{path}: not a regular file")


def same_file(a, b) -> bool:
    """Whether paths ``a`` and ``b`` name one file (through symlinks and hard links)."""
    a, b = Path(a), Path(b)
    if a.resolve() == b.resolve():
        return True
    try:
        return a.exists() and b.exists() and os.path.samefile(a, b)
    except OSError:
        return False


def check_writable_folder(folder, for_path=None) -> None:
    """Raise ``CliError`` naming ``for_path`` (or ``folder``) unless ``folder`` exists and a
    file can be created in it (a probe file is created and removed: permissions, read-only
    file systems and ACLs all show)."""
    folder = Path(folder) if str(folder) else Path(".")
    name = for_path if for_path is not None else folder
    if not folder.is_dir():
        raise CliError(f"{name}: folder {folder} does not exist")
    try:
        fd, probe = tempfile.mkstemp(prefix=".octomerge-probe.", dir=folder)
    except OSError as err:
        raise CliError(f"{name}: cannot write in {folder}: {err.strerror or err}") from None
    os.close(fd)
    os.unlink(probe)


def check_output(path, *, inputs: Iterable = (), force: bool = False, suffixes: Sequence[str] | None = None,
                 what: str = "OUT", side: bool = False, others: Iterable = ()) -> None:
    """Check an output path before any compute; raise ``CliError`` (exit 1) naming it.

    Args:
      path: the output the user named.
      inputs: the command's input files.
      force: ``--force``: an existing file may be overwritten (for a main output, an input too).
      suffixes: allowed extensions (lower case, with the dot), or ``None`` for any.
      what: the argument's name in messages (``OUT``, ``--report``).
      side: a side output (report, figure): never an input, even with ``force``.
      others: the command's other outputs (none may share this path).
    """
    path = Path(path)
    if suffixes is not None and path.suffix.lower() not in suffixes:
        names = ", ".join(suffixes[:-1]) + " or " + suffixes[-1] if len(suffixes) > 1 else suffixes[0]
        raise CliError(f"{path}: {what} must end in {names}")
    if path.is_dir():
        raise CliError(f"{path}: {what} is a directory")
    for other in others:
        if other is not None and same_file(path, other):
            raise CliError(f"{path}: {what} is also another output of this command")
    for src in inputs:
        if same_file(path, src):
            if side:
                raise CliError(f"{path}: {what} is also an input; refusing to overwrite it")
            if not force:
                raise CliError(f"{path}: {what} is also an input; pass --force to overwrite it")
            break
    else:
        if path.exists() and not force:
            raise CliError(f"{path} exists; pass --force to overwrite it")
    check_writable_folder(path.parent, path)


@contextlib.contextmanager
def writing(path) -> Iterator[None]:
    """Turn an ``OSError`` raised while writing ``path`` (permission, full disk, file size
    limit) into a one-line ``CliError`` naming ``path``, not the temporary file beside it."""
    try:
        yield
    except OSError as err:
        raise CliError(f"{path}: cannot write: {err.strerror or err}") from None


def angle_warnings(names: Sequence[str], values: Sequence[float], degrees: bool, flag: str = "--rpy",
                   hint: str = "; if it is in degrees, add --degrees") -> list[str]:
    """One warning per angle beyond a full turn (2 pi rad, or 360 with ``degrees``): in
    radians such a value usually is degrees given without ``--degrees``. The angles are still
    used (ROS and OctoMap take radians; a multi-turn angle is a valid rotation)."""
    full = 360.0 if degrees else 2 * math.pi
    out = []
    for name, v in zip(names, values):
        if abs(v) > full:
            out.append(f"{flag} {name}".strip() + f" = {v:g} {'degrees' if degrees else 'rad'} is more than a "
                       "full turn" + ("" if degrees else hint))
    return out


def inside(path, folder) -> bool:
    """Whether ``path``, with every symlink resolved, lies inside ``folder`` (resolved)."""
    return Path(path).resolve().is_relative_to(Path(folder).resolve())


@contextlib.contextmanager
def folder_lock(folder, name: str = ".octomerge-batch.lock") -> Iterator[Path]:
    """Hold an exclusive lock on ``folder/name`` while the block runs; raise ``CliError``
    naming the holder (pid, host) if another process holds it.

    ``flock`` locks are released by the kernel when their process dies, so a lock file left
    by a killed run (a dead pid) is simply taken over. The file is removed on exit."""
    path = Path(folder) / name
    while True:
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.read(fd, 200).decode(errors="replace").strip() or "another process"
            os.close(fd)
            raise CliError(f"{folder}: another octomerge batch ({holder}) is running on this folder "
                           f"(lock file {path})") from None
        try:  # the file may have been removed by its last holder between open and flock
            same = os.path.samestat(os.fstat(fd), os.stat(path))
        except FileNotFoundError:
            same = False
        if same:
            break
        os.close(fd)
    try:
        os.ftruncate(fd, 0)
        os.write(fd, f"pid {os.getpid()} on {socket.gethostname()}\n".encode())
        yield path
    finally:
        with contextlib.suppress(OSError):
            os.unlink(path)
        os.close(fd)
