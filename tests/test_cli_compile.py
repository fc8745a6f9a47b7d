"""How a cold ``octomerge`` command compiles: with ``cli.cache.FAST_COMPILE_FLAGS`` (the user's
``XLA_FLAGS`` kept), and with the merge's later kernels compiled in a second thread while the
registration compiles (``cli.compile_ahead``)."""

import contextlib
import logging
import os
import subprocess
import sys
import threading
from types import SimpleNamespace

import jax
import numpy as np
import pytest

from octomerge_jax import kernel_store
from octomerge_jax.budget import memory_budget
from octomerge_jax.cli import compile_ahead as ahead
from octomerge_jax.cli.cache import FAST_COMPILE_FLAGS, FAST_COMPILE_JAXLIB, fast_compile_flags, use_fast_compile
from octomerge_jax.kernel_store import stored_jit
from octomerge_jax.pipeline import MergeConfig
from octomerge_jax.pipeline.clouds import select_overlap
from octomerge_jax.registration.global_search import free_space
from octomerge_jax.sim import small_room_map

from helpers import own_kernel_store


def test_fast_compile_flags_are_added_and_the_users_own_setting_wins():
    (flag,) = FAST_COMPILE_FLAGS
    assert fast_compile_flags(None) == fast_compile_flags("") == flag
    assert fast_compile_flags("--xla_force_host_platform_device_count=2") == \
        f"--xla_force_host_platform_device_count=2 {flag}"
    name = flag.split("=")[0]
    assert fast_compile_flags(f"{name}=true") == f"{name}=true"


def test_a_subcommand_sets_xla_flags_for_itself_and_its_children():
    code = ("import os, sys\nfrom octomerge_jax.cli import console_main\nsys.argv = ['octomerge'] + sys.argv[1:]\n"
            "try:\n    console_main()\nexcept SystemExit:\n    pass\nprint(os.environ.get('XLA_FLAGS'))")
    env = {**os.environ, "XLA_FLAGS": "--xla_dump_disable_metadata=true"}

    def flags(*argv):
        out = subprocess.run([sys.executable, "-c", code, *argv], capture_output=True, text=True, check=True, env=env)
        return out.stdout.strip().splitlines()[-1]

    assert flags("info", "--help") == fast_compile_flags("--xla_dump_disable_metadata=true")
    assert flags("--version") == "--xla_dump_disable_metadata=true"  # loads no JAX


def test_only_a_jaxlib_known_to_have_the_flags_gets_them():
    """XLA aborts on a flag it does not know: an untested jaxlib runs without them."""
    environ = {}
    assert not use_fast_compile(environ, jaxlib_version="0.99.0") and environ == {}
    assert use_fast_compile(environ, jaxlib_version=FAST_COMPILE_JAXLIB[0] + "1")
    assert environ == {"XLA_FLAGS": fast_compile_flags(None)}


def _twice(x):
    return x * 2


def _thrice(x):
    return x * 3


_twice.__module__ = "octomerge_jax.registration.probe"  # compiled as the registration's kernels are
REGISTRATION_KERNEL = stored_jit(_twice)
OTHER_KERNEL = stored_jit(_thrice)


@pytest.fixture
def store(tmp_path):
    """A store of the test's own (the run's, tests/conftest.py, is put back after)."""
    with own_kernel_store(tmp_path / "kernels", [REGISTRATION_KERNEL, OTHER_KERNEL]) as path:
        yield path


@pytest.fixture
def calls(monkeypatch):
    """The work ahead's calls: ``(thread name, T_1_2)`` each."""
    seen = []

    def transform_to_frame_1(m2, T_1_2, config, timings):
        seen.append((threading.current_thread().name, np.asarray(T_1_2)))
        return m2

    monkeypatch.setattr(ahead, "transform_to_frame_1", transform_to_frame_1)
    monkeypatch.setattr(ahead, "fuse_in_frame_1", lambda m1, m2_in_1, config, timings: (np.zeros(1), None))
    return seen


@pytest.fixture
def beside(monkeypatch):
    """The threads that compiled the fusion's second program ahead (``fusion.precompile_fuse``)."""
    seen = []
    monkeypatch.setattr(ahead, "fuse_plan_shapes", lambda m1, m2_in_1: None)
    monkeypatch.setattr(ahead, "precompile_fuse",
                        lambda m1, m2_in_1, shapes: seen.append(threading.current_thread().name))
    return seen


def test_the_rest_of_the_merge_runs_ahead_when_the_registration_compiles(store, calls, beside):
    m = SimpleNamespace(resolution=0.1, capacity=1024)
    T = np.eye(4)
    T[0, 3] = 2.0
    with ahead.compile_ahead(m, m, T, MergeConfig()):
        OTHER_KERNEL(np.arange(3.0))  # not the registration's: nothing starts
        assert calls == []
        REGISTRATION_KERNEL(np.arange(3.0))
        REGISTRATION_KERNEL(np.arange(4.0))  # started once
    assert len(calls) == 1 and calls[0][0] == "octomerge-compile-ahead"
    assert beside == ["octomerge-compile-beside"]  # the fusion's two programs side by side
    np.testing.assert_array_equal(calls[0][1], T)
    REGISTRATION_KERNEL._loaded.clear()
    with ahead.compile_ahead(m, m, None, MergeConfig()):
        REGISTRATION_KERNEL(np.arange(3.0))  # loaded from the store: warm, nothing starts
    assert len(calls) == 1
    with ahead.compile_ahead(m, SimpleNamespace(resolution=0.2, capacity=1024), T, MergeConfig()):
        REGISTRATION_KERNEL(np.arange(5.0))  # map 2 is resampled first: not worked ahead
    assert len(calls) == 1
    with memory_budget(4 * 2 * 1024 * ahead.BYTES_PER_ROW - 1):
        with ahead.compile_ahead(m, m, T, MergeConfig()):
            REGISTRATION_KERNEL(np.arange(6.0))  # would need more than its share of the budget
    assert len(calls) == 1


def test_without_a_guess_the_work_ahead_runs_from_the_searchs_first_candidate(store, calls, monkeypatch):
    heard = []

    @contextlib.contextmanager
    def candidate_listener(callback):  # register_global's hook, called here by hand
        heard.append(callback)
        yield

    monkeypatch.setattr(ahead, "candidate_listener", candidate_listener)
    REGISTRATION_KERNEL._loaded.clear()
    m = SimpleNamespace(resolution=0.1, capacity=1024)
    T = np.eye(4)
    T[1, 3] = 3.0
    with ahead.compile_ahead(m, m, None, MergeConfig()):
        REGISTRATION_KERNEL(np.arange(7.0))  # compiling, but no pose to work from yet
        assert calls == []
        heard[0](T)
        heard[0](np.eye(4))  # the first candidate counts
    assert len(calls) == 1 and calls[0][0] == "octomerge-compile-ahead"
    np.testing.assert_array_equal(calls[0][1], T)


def test_work_ahead_that_fails_is_dropped(store, monkeypatch):
    def fail(*args):
        raise MemoryError("over the budget")

    monkeypatch.setattr(ahead, "transform_to_frame_1", fail)
    m = SimpleNamespace(resolution=0.1, capacity=1024)
    with ahead.compile_ahead(m, m, np.eye(4), MergeConfig()):
        assert int(REGISTRATION_KERNEL(np.arange(3.0))[1]) == 2


def test_threads_compile_a_kernel_once_and_the_listener_hears_only_fresh_compiles(store):
    heard, outs = [], []
    barrier = threading.Barrier(3)

    def call():
        with kernel_store.compile_listener(heard.append):
            barrier.wait()
            outs.append(np.asarray(OTHER_KERNEL(np.arange(6.0))))

    threads = [threading.Thread(target=call) for _ in range(3)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert heard == [f"{__name__}._thrice"] and len(outs) == 3
    assert all(np.array_equal(o, np.arange(6.0) * 3) for o in outs)
    OTHER_KERNEL._loaded.clear()
    with kernel_store.compile_listener(heard.append):
        OTHER_KERNEL(np.arange(6.0))  # from the store
    assert len(heard) == 1 and len(list(store.glob("_thrice-*.pkl"))) == 1


class _Compiles(logging.Handler):
    """Counts JAX's "Compiling ..." log records while installed."""

    def __init__(self):
        super().__init__()
        self.names: list[str] = []

    def emit(self, record):
        msg = record.getMessage()
        if msg.startswith("Compiling "):
            self.names.append(msg.split(" ")[1])


def test_a_new_map_size_in_the_same_bucket_compiles_nothing_new():
    """The registration's host steps hand the jitted kernels padded clouds and host scalars:
    a pair of another size (same capacity bucket) must not compile a program per size; in a
    long run of many pairs (``merge_many``) that exhausted the process's memory maps."""
    rng = np.random.default_rng(0)
    rooms = {res: small_room_map((0.0, 3.0), res) for res in (0.2, 0.1)}

    def run(n1, n2, res):
        p1 = rng.uniform(0, 4, (n1, 3)).astype(np.float32)
        select_overlap(p1, p1[:n2] + 0.01, np.eye(4), "voxel", 0.3)
        select_overlap(p1, p1[:n2] + 0.01, np.eye(4), "bbox", None)
        free_space(rooms[res], 0.6)

    run(700, 600, 0.2)  # compiles
    seen = _Compiles()
    logger = logging.getLogger("jax")
    logger.addHandler(seen)
    try:
        with jax.log_compiles(True):
            run(900, 650, 0.1)  # other sizes, same buckets (1024) and another map size
    finally:
        logger.removeHandler(seen)
    assert seen.names == [], seen.names
