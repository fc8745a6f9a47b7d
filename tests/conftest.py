"""Strict test settings: promotions must be explicit and warnings are errors (pyproject),
while the library itself touches no global JAX config.

One JAX persistent compilation cache per test run, shared by the xdist workers and by the CLI
subprocesses the tests start: a kernel compiled by one worker is loaded, not compiled again, by
the others (docs/design.md, "Compile cache and warm-up"). ``OCTOMERGE_TEST_CACHE_DIR`` names a
directory to keep it in across runs (``off``: no cache); by default it is a temporary directory
removed at the end of the run. The kernel store (``kernel_store``) lives in it too and is open
in every test process, as in a command. The suite compiles with the command's XLA flags
(``cli.cache.use_fast_compile``): a quarter less compile time."""

import gc
import os
import shutil
import tempfile

from octomerge_jax.cli.cache import use_fast_compile

use_fast_compile()  # before the first JAX computation of this process and of the ones it starts

import jax  # noqa: E402
import pytest  # noqa: E402

from octomerge_jax import kernel_store  # noqa: E402

_KEY = "octomerge_test_xla_cache"


def _cache_dir(config) -> str | None:
    """The run's cache directory: made by the controller (or a run without xdist), handed to
    the workers through ``workerinput``."""
    if hasattr(config, "workerinput"):
        return config.workerinput.get(_KEY)
    wanted = os.environ.get("OCTOMERGE_TEST_CACHE_DIR")
    if wanted is not None:
        if wanted.strip().lower() in ("", "off", "0", "none"):
            return None
        os.makedirs(wanted, exist_ok=True)
        return wanted
    path = tempfile.mkdtemp(prefix="octomerge-test-xla-")
    config.add_cleanup(lambda: shutil.rmtree(path, ignore_errors=True))
    return path


def pytest_configure(config):
    path = _cache_dir(config)
    config._octomerge_xla_cache = path
    if path:
        jax.config.update("jax_compilation_cache_dir", path)
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
        kernel_store.open_store(os.path.join(path, "kernels"))
    # CLI subprocesses use the same cache; in-process CLI calls find JAX's cache already set and
    # change nothing (tests/test_cli_io.py checks the CLI's own cache setting in a subprocess)
    os.environ["OCTOMERGE_CACHE_DIR"] = path or "off"


@pytest.hookimpl(optionalhook=True)
def pytest_configure_node(node):
    """xdist controller: give each worker the run's cache directory."""
    node.workerinput[_KEY] = node.config._octomerge_xla_cache


def _memory_maps() -> tuple[int, int]:
    """``(memory mappings of this process, the kernel's limit)``; ``(0, 1)`` off Linux."""
    try:
        with open("/proc/self/maps") as maps, open("/proc/sys/vm/max_map_count") as limit:
            return sum(1 for _ in maps), int(limit.read())
    except (OSError, ValueError):
        return 0, 1


@pytest.fixture(autouse=True)
def _forget_programs():
    """After a test, once the process holds over half of Linux's limit of memory mappings,
    drop the compiled programs (later tests reload theirs from the run's cache): a worker that
    kept all of a run's thousands of programs reached the limit, at which XLA crashes
    (``kernel_store.forget_programs``)."""
    yield
    used, limit = _memory_maps()
    if used > limit // 2:
        kernel_store.forget_programs()
        gc.collect()


@pytest.fixture(autouse=True)
def _strict_promotion():
    with jax.numpy_dtype_promotion("strict"):
        yield
