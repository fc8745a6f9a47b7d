"""Strict test settings: promotions must be explicit and warnings are errors (pyproject),
while the library itself touches no global JAX config."""

import os

import jax
import pytest

# the CLI turns on JAX's persistent compilation cache; in-process CLI tests must not change the
# test process's JAX config or write to the home directory (tests/test_cli_io.py checks the cache)
os.environ["OCTOMERGE_CACHE_DIR"] = "off"


@pytest.fixture(autouse=True)
def _strict_promotion():
    with jax.numpy_dtype_promotion("strict"):
        yield
