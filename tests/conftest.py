"""Strict test settings: promotions must be explicit and warnings are errors (pyproject),
while the library itself touches no global JAX config."""

import jax
import pytest


@pytest.fixture(autouse=True)
def _strict_promotion():
    with jax.numpy_dtype_promotion("strict"):
        yield
