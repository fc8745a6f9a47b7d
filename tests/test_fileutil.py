"""Saves: atomic (a new inode renamed over the old), durable (fsync of file and folder), no
temporary file left by SIGTERM / SIGINT, leftovers of killed writers removed, and failed writes
(disk full, file size limit) reported with the user's path while the old file stays intact."""

from __future__ import annotations

import errno
import os
import signal
import subprocess
import sys
import textwrap
import threading
from pathlib import Path

import numpy as np
import pytest

from octomerge_jax import _fileutil
from octomerge_jax.io import load, octree_format, save
from octomerge_jax.map import from_leaves

FILEUTIL = Path(_fileutil.__file__)


def _map(n: int):
    codes = np.arange(n, dtype=np.uint64) * np.uint64(8)
    return from_leaves(codes, np.full(n, 16), np.linspace(-2, 2, n).astype(np.float32), 0.1)


def _child(code: str, *args, **kwargs) -> subprocess.Popen:
    """A Python process with ``_fileutil`` loaded standalone (stdlib only: starts in ~50 ms)."""
    prelude = textwrap.dedent(f"""
        import importlib.util, sys
        spec = importlib.util.spec_from_file_location("fu", {str(FILEUTIL)!r})
        fu = importlib.util.module_from_spec(spec); spec.loader.exec_module(fu)
    """)
    return subprocess.Popen([sys.executable, "-c", prelude + textwrap.dedent(code), *args],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, **kwargs)


def _hidden(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir() if p.name.startswith("."))


def test_save_replaces_the_file_instead_of_writing_into_it(tmp_path):
    """A reader holding the old file, and a hard link to it, keep the old bytes: the new map
    is a new file renamed over the name (an in-place writer would change both)."""
    target = tmp_path / "m.bt"
    save(_map(8), target)
    old = target.read_bytes()
    os.link(target, tmp_path / "link.bt")
    with open(target, "rb") as reader:
        save(_map(200), target)
        assert reader.read() == old
    assert (tmp_path / "link.bt").read_bytes() == old
    assert target.read_bytes() != old and load(target).num_leaves == 200
    assert _hidden(tmp_path) == []


def test_failed_write_keeps_the_old_file_and_names_the_users_path(tmp_path, monkeypatch):
    """Disk full half-way through the body: the old map is intact, no temp file is left, and
    the one-line error names ``m.bt``, not the hidden temp file."""
    target = tmp_path / "m.bt"
    save(_map(8), target)
    old = target.read_bytes()
    real_open = open

    class Full:
        def __init__(self, f):
            self.f = f

        def write(self, data):
            self.f.write(data[: len(data) // 2])
            self.f.flush()
            raise OSError(errno.ENOSPC, "No space left on device")

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            self.f.close()

    monkeypatch.setattr(octree_format, "open", lambda p, mode="r", *a, **k:
                        Full(real_open(p, mode, *a, **k)), raising=False)
    with pytest.raises(OSError) as info:
        save(_map(200), target)
    msg = str(info.value)
    assert str(target) in msg and "No space left" in msg and ".omj" not in msg and "\n" not in msg
    assert info.value.errno == errno.ENOSPC
    assert target.read_bytes() == old and _hidden(tmp_path) == []


def test_file_size_limit_in_a_real_process(tmp_path):
    """RLIMIT_FSIZE (what a full disk looks like to ``write``): EFBIG, old file intact."""
    target = tmp_path / "out.bin"
    target.write_bytes(b"old")
    p = _child("""
        import resource, signal
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (1000, 1000))
        try:
            fu.atomic_write_bytes(sys.argv[1], b"x" * 5000)
        except OSError as err:
            print(type(err).__name__, err.errno, err)
    """, str(target))
    out, err = p.communicate(timeout=60)
    assert p.returncode == 0, err
    assert out.startswith("OSError 27 ") and str(target) in out and ".omj" not in out
    assert target.read_bytes() == b"old" and _hidden(tmp_path) == []


def test_save_fsyncs_the_file_before_the_rename_and_the_folder_after(tmp_path, monkeypatch):
    events = []
    real_fsync, real_replace = os.fsync, os.replace

    def fsync(fd):
        events.append(("fsync", os.readlink(f"/proc/self/fd/{fd}")))
        real_fsync(fd)

    def replace(src, dst):
        events.append(("replace", str(dst)))
        real_replace(src, dst)

    monkeypatch.setattr(os, "fsync", fsync)
    monkeypatch.setattr(os, "replace", replace)
    target = tmp_path / "m.ot"
    save(_map(8), target)
    kinds = [e[0] for e in events]
    assert kinds == ["fsync", "replace", "fsync"], events
    assert Path(events[0][1]).name.startswith(".m.ot.omj")  # the temp file, whole
    assert events[1][1] == str(target)
    assert events[2][1] == str(tmp_path)  # the folder, so the rename survives a crash


def _stalled_writer(target, disposition: str, seconds: float = 30.0):
    """A child process in the middle of a save to ``target`` (its temp file written, the
    rename not yet done), returned once it says so. ``disposition`` sets SIGINT and SIGTERM
    first: ``"default"`` (Ctrl-C raises KeyboardInterrupt, SIGTERM kills, whatever the process
    that runs the tests ignores: a background job of a shell ignores SIGINT) or ``"ignored"``."""
    p = _child(f"""
        import signal, time
        ignored = {disposition == "ignored"!r}
        signal.signal(signal.SIGINT, signal.SIG_IGN if ignored else signal.default_int_handler)
        signal.signal(signal.SIGTERM, signal.SIG_IGN if ignored else signal.SIG_DFL)
        with fu.atomic_output(sys.argv[1]) as tmp:
            open(tmp, "wb").write(b"partial")
            print("writing", flush=True)
            time.sleep({seconds!r})
    """, str(target))
    assert p.stdout.readline().strip() == "writing"
    return p


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_signal_during_a_save_leaves_no_temp_file(tmp_path, sig):
    target = tmp_path / "m.bt"
    target.write_bytes(b"old")
    p = _stalled_writer(target, "default")
    assert len(_hidden(tmp_path)) == 1
    p.send_signal(sig)
    p.communicate(timeout=30)
    assert p.returncode in (-sig, 1)  # killed by the signal / KeyboardInterrupt
    assert _hidden(tmp_path) == [] and target.read_bytes() == b"old"


def test_an_ignored_signal_stays_ignored_during_a_save(tmp_path):
    """A process that ignores SIGINT / SIGTERM (started by ``nohup`` or as a background job)
    is not made to stop by a save: the save completes."""
    target = tmp_path / "m.bt"
    target.write_bytes(b"old")
    p = _stalled_writer(target, "ignored", seconds=1.0)
    p.send_signal(signal.SIGTERM)
    p.send_signal(signal.SIGINT)
    _, err = p.communicate(timeout=30)
    assert p.returncode == 0, err
    assert _hidden(tmp_path) == [] and target.read_bytes() == b"partial"


def test_no_signal_handler_outside_a_save_or_off_the_main_thread(tmp_path):
    before = signal.getsignal(signal.SIGTERM)
    seen = {}
    with _fileutil.atomic_output(tmp_path / "a.txt") as tmp:
        tmp.write_text("a")
        seen["main"] = signal.getsignal(signal.SIGTERM)

    def worker():
        with _fileutil.atomic_output(tmp_path / "b.txt") as tmp:
            tmp.write_text("b")
            seen["thread"] = signal.getsignal(signal.SIGTERM)

    t = threading.Thread(target=worker)
    t.start()
    t.join()
    assert seen["main"] is not before and seen["thread"] is before
    assert signal.getsignal(signal.SIGTERM) is before
    assert (tmp_path / "a.txt").read_text() == "a" and (tmp_path / "b.txt").read_text() == "b"


def test_leftover_of_a_killed_writer_is_removed_by_the_next_save(tmp_path):
    target = tmp_path / "m.bt"
    p = _stalled_writer(target, "default")
    p.kill()  # kill -9: no cleanup can run
    p.communicate(timeout=30)
    leftover = _hidden(tmp_path)
    assert len(leftover) == 1 and leftover[0].startswith(".m.bt.omj")
    # not ours or not stale: another tool's hidden file, an old-style name, a live writer
    live = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(30)"])
    try:
        keep = [".other.tmp", ".m.bt.abcdefgh.tmp", f".x.bt.omj{live.pid}-abcdefgh.tmp",
                f".x.bt.omj{os.getpid()}-abcdefgh.tmp"]
        for name in keep:
            (tmp_path / name).write_bytes(b"keep")
        save(_map(8), tmp_path / "other.bt")  # any save to the folder
        assert _hidden(tmp_path) == sorted(keep)
    finally:
        live.kill()
        live.wait()


def test_unwritable_folder_names_the_users_path(tmp_path):
    if os.geteuid() == 0:
        pytest.skip("root writes into read-only folders")
    folder = tmp_path / "ro"
    folder.mkdir()
    folder.chmod(0o500)
    try:
        with pytest.raises(PermissionError, match=r"ro/m.bt: cannot write"):
            save(_map(8), folder / "m.bt")
    finally:
        folder.chmod(0o700)


def test_an_exception_in_the_writer_removes_the_temp_file(tmp_path):
    before = signal.getsignal(signal.SIGTERM)
    with pytest.raises(RuntimeError):
        with _fileutil.atomic_output(tmp_path / "x.bin") as tmp:
            tmp.write_bytes(b"half")
            raise RuntimeError("boom")
    assert list(tmp_path.iterdir()) == []
    assert signal.getsignal(signal.SIGTERM) is before  # nothing outlives the save
