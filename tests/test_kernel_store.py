"""``kernel_store``: compiled kernels kept on disk and loaded in later processes without tracing,
with results identical to ``jax.jit``'s; a bad entry costs a compile, never a result."""

import json
import os
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from octomerge_jax import kernel_store
from octomerge_jax.kernel_store import stored_jit

from helpers import own_kernel_store


def solve_sorted(a, b, *, scale: int):
    """LAPACK (a solve), a sort and an iota: the kinds of program whose loaded copies crashed or
    missed functions before ``kernel_store`` prepared the backend and compiled fresh."""
    x = jnp.linalg.solve(a @ a.T + jnp.eye(a.shape[0]), b)
    return jnp.sort(x) * scale + jnp.arange(x.shape[0], dtype=x.dtype)


STORED = stored_jit(solve_sorted, static_argnames=("scale",))
A = np.random.default_rng(0).normal(size=(6, 6)).astype(np.float32)
B = np.arange(6, dtype=np.float32)


@pytest.fixture
def store(tmp_path):
    """A store of the test's own (the run's, tests/conftest.py, is put back after)."""
    with own_kernel_store(tmp_path / "kernels", [STORED]) as path:
        yield path


@pytest.fixture
def no_store():
    run_store = kernel_store.store_dir()
    kernel_store.close_store()
    yield
    if run_store is not None:
        kernel_store.open_store(run_store)


def test_without_a_store_it_is_jax_jit(no_store):
    np.testing.assert_array_equal(STORED(A, B, scale=2), jax.jit(solve_sorted, static_argnames="scale")(A, B, scale=2))


def test_a_call_stores_one_program_per_shape_and_static_value(store):
    ref = jax.jit(solve_sorted, static_argnames="scale")
    np.testing.assert_array_equal(STORED(A, B, scale=2), ref(A, B, scale=2))
    np.testing.assert_array_equal(STORED(A, B, scale=2), ref(A, B, scale=2))
    assert len(list(store.glob("solve_sorted-*.pkl"))) == 1
    np.testing.assert_array_equal(STORED(A, B, scale=3), ref(A, B, scale=3))
    np.testing.assert_array_equal(STORED(A[:4, :4], B[:4], scale=3), ref(A[:4, :4], B[:4], scale=3))
    assert len(list(store.glob("solve_sorted-*.pkl"))) == 3


def test_precompile_stores_the_program_a_call_then_runs(store):
    # scale 11: a program no other test compiles (XLA:CPU's second compile of a sort in one process cannot be
    # serialized, so a later test's store would stay empty)
    a, b = A[:2, :2], B[:2]
    expected = jax.jit(solve_sorted, static_argnames="scale")(a, b, scale=11)
    heard = []
    with kernel_store.compile_listener(heard.append):
        shapes = [jax.ShapeDtypeStruct(x.shape, x.dtype) for x in (a, b)]
        assert STORED.precompile(*shapes, scale=11)  # shapes suffice: nothing runs
        assert len(heard) == 1 and len(list(store.glob("solve_sorted-*.pkl"))) == 1
        np.testing.assert_array_equal(STORED(a, b, scale=11), expected)
    assert len(heard) == 1  # the call compiled nothing


def test_precompile_without_a_store_does_nothing(no_store):
    assert not STORED.precompile(A[:2, :2], B[:2], scale=11)


def test_under_a_trace_it_is_the_plain_jit(store):
    a, b = A[:5, :5], B[:5]
    out = jax.vmap(lambda b: STORED(a, b, scale=2))(np.stack([b, b + 1]))
    np.testing.assert_array_equal(out[1], STORED(a, b + 1, scale=2))
    assert len(list(store.glob("*.pkl"))) == 1  # the direct call only


def test_a_corrupt_entry_is_compiled_again(store):
    a, b = A[:3, :3], B[:3]
    expected = np.asarray(STORED(a, b, scale=5))
    (entry,) = store.glob("solve_sorted-*.pkl")
    entry.write_bytes(b"not a program")
    STORED._loaded.clear()
    np.testing.assert_array_equal(STORED(a, b, scale=5), expected)


def test_forget_programs_drops_them_and_the_store_gives_them_back(store):
    # scale 13: a program no other test compiles (see test_precompile_stores_the_program_a_call_then_runs)
    a, b = A[:3, :3], B[:3]
    expected = np.asarray(STORED(a, b, scale=13))
    plain = jax.jit(lambda x: x * 3.0)
    plain(b)
    assert STORED.programs() >= 1 and plain._cache_size() == 1
    kernel_store.forget_programs()
    assert STORED.programs() == 0 and plain._cache_size() == 0
    heard = []
    with kernel_store.compile_listener(heard.append):
        np.testing.assert_array_equal(STORED(a, b, scale=13), expected)
    assert heard == [] and STORED.programs() == 1  # loaded from the store, not compiled


def test_dynamic_parameters_after_static_ones_are_refused():
    def f(n, x):
        return x * n

    with pytest.raises(TypeError, match="must be positional and come before"):
        stored_jit(f, static_argnames=("n",))


PROCESS = textwrap.dedent("""
    import json, sys
    import jax, numpy as np
    from octomerge_jax import kernel_store
    sys.path.insert(0, {tests!r})
    from test_kernel_store import STORED, A, B, solve_sorted
    jax.config.update("jax_compilation_cache_dir", {xla!r})
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    events = []
    jax.monitoring.register_event_listener(lambda e, **k: events.append(e))
    if {use_store}:
        kernel_store.open_store({store!r})
        out = STORED(A, B, scale=2)
    else:
        out = jax.jit(solve_sorted, static_argnames="scale")(A, B, scale=2)
    print(json.dumps({{"out": np.asarray(out).tolist(),
                       "loads": events.count(kernel_store.LOAD_EVENT),
                       "cache_hits": events.count("/jax/compilation_cache/cache_hits")}}))
""")


def _process(tmp_path, use_store: bool) -> dict:
    code = PROCESS.format(tests=str(Path(__file__).parent), xla=str(tmp_path / "xla"),
                          store=str(tmp_path / "kernels"), use_store=use_store)
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    return json.loads(done.stdout.strip().splitlines()[-1])


def test_a_later_process_loads_the_program_and_gets_the_same_result(tmp_path):
    # the plain program first, into JAX's persistent cache: the store must not copy it from
    # there (an executable read from that cache serializes without its compiled functions)
    plain = _process(tmp_path, use_store=False)
    first = _process(tmp_path, use_store=True)
    assert first["loads"] == 0 and first["cache_hits"] == 0
    later = _process(tmp_path, use_store=True)
    assert later["loads"] == 1
    assert later["out"] == first["out"] == plain["out"]
    (entry,) = (tmp_path / "kernels").glob("solve_sorted-*.pkl")
    entry.write_bytes(b"not a program")
    again = _process(tmp_path, use_store=True)
    assert again["loads"] == 0 and again["out"] == plain["out"]
    assert _process(tmp_path, use_store=True)["loads"] == 1  # the entry was written anew


def test_opening_removes_stale_temporaries_and_the_least_recently_used(tmp_path):
    now = time.time()
    for i, age in enumerate((50, 40, 30, 20, 10)):  # 5 entries of 100 bytes, entry-0 the oldest
        entry = tmp_path / f"k-{i}.pkl"
        entry.write_bytes(b"x" * 100)
        os.utime(entry, (now - age, now - age))
    gone = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    # temporaries named as atomic_output names them: of this running process, and of one that is gone
    fresh = tmp_path / f".k-5.pkl.omj{os.getpid()}-abcd1234.pkl"
    stale = tmp_path / f".k-6.pkl.omj{int(gone.stdout)}-abcd1234.pkl"
    fresh.write_bytes(b"partial")
    stale.write_bytes(b"partial")
    kernel_store.tidy_store(tmp_path, max_bytes=500)
    assert fresh.exists() and not stale.exists()
    assert len(list(tmp_path.glob("k-*.pkl"))) == 5  # within the bound: nothing removed
    kernel_store.tidy_store(tmp_path, max_bytes=400)  # over: down to 300 bytes, oldest first
    assert sorted(p.name for p in tmp_path.glob("k-*.pkl")) == ["k-2.pkl", "k-3.pkl", "k-4.pkl"]


def test_a_load_marks_the_entry_recently_used(store):
    a, b = A[:2, :2], B[:2]
    expected = np.asarray(STORED(a, b, scale=7))
    (entry,) = store.glob("solve_sorted-*.pkl")
    os.utime(entry, (0, 0))
    STORED._loaded.clear()
    np.testing.assert_array_equal(STORED(a, b, scale=7), expected)
    assert entry.stat().st_mtime > 0


def test_the_readme_path_opens_under_home(tmp_path, monkeypatch):
    monkeypatch.setenv("HOME", str(tmp_path))
    run_store = kernel_store.store_dir()
    try:
        opened = kernel_store.open_store("~/.cache/octomerge_jax/xla/kernels")
        assert opened == tmp_path / ".cache" / "octomerge_jax" / "xla" / "kernels"
        assert kernel_store.store_dir().is_dir()
    finally:
        kernel_store.close_store()
        if run_store is not None:
            kernel_store.open_store(run_store)


def _recent(path: Path) -> dict:
    return json.loads((path / kernel_store.RECENT_FILE).read_text())


def test_a_command_lists_its_programs_and_the_next_loads_them_ahead(tmp_path):
    a, b = A[:4, :4], B[:4]
    with own_kernel_store(tmp_path / "kernels", [STORED]) as path:
        expected = np.asarray(STORED(a, b, scale=21))
    listed = _recent(path)["programs"]
    assert len(listed) == 1 and listed[0].startswith("solve_sorted-") and (path / listed[0]).exists()
    # the next command: the program is loaded by the prefetch thread, then taken by the call
    with own_kernel_store(path, [STORED]):
        assert kernel_store.prefetch_recent()
        kernel_store._PREFETCH["thread"].join()
        assert len(kernel_store._PREFETCHED) == 1
        heard = []
        with kernel_store.compile_listener(heard.append):
            np.testing.assert_array_equal(STORED(a, b, scale=21), expected)
        assert heard == [] and not kernel_store._PREFETCHED and STORED.programs() == 1
    assert _recent(path)["programs"] == listed


def test_no_prefetch_from_another_environment_or_a_bad_list(tmp_path):
    with own_kernel_store(tmp_path / "kernels", [STORED]) as path:
        STORED(A[:2, :2], B[:2], scale=22)
    recent = path / kernel_store.RECENT_FILE
    good = recent.read_text()
    for text in (good.replace('"environment": "', '"environment": "other '), "{not json", '{"format": 1}', ""):
        recent.write_text(text)
        with own_kernel_store(path, [STORED]):
            assert not kernel_store.prefetch_recent()
    # names outside the store are not read (a loadable copy there would be a second program)
    stored = next(path.glob("solve_sorted-*.pkl"))
    (path.parent / "copy-outside.pkl").write_bytes(stored.read_bytes())
    recent.write_text(good.replace('"programs": ["', '"programs": ["../copy-outside.pkl", "'))
    with own_kernel_store(path, [STORED]):
        assert kernel_store.prefetch_recent()
        kernel_store._PREFETCH["thread"].join()
        assert len(kernel_store._PREFETCHED) == 1
    recent.unlink()
    with own_kernel_store(path, [STORED]):
        assert not kernel_store.prefetch_recent()  # no list: nothing to load


def test_a_command_of_many_programs_leaves_no_list(tmp_path, monkeypatch):
    with own_kernel_store(tmp_path / "kernels", [STORED]) as path:
        STORED(A[:2, :2], B[:2], scale=23)
    assert (path / kernel_store.RECENT_FILE).exists()
    monkeypatch.setattr(kernel_store, "RECENT_MAX_PROGRAMS", 1)
    with own_kernel_store(path, [STORED]):
        STORED(A[:2, :2], B[:2], scale=23)
        STORED(A[:2, :2], B[:2], scale=24)
    assert not (path / kernel_store.RECENT_FILE).exists()
