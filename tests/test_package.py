import subprocess
import sys

import octomerge_jax as om
from octomerge_jax import examples, tree


def test_import_changes_no_global_jax_config():
    code = (
        "import jax; before = (jax.config.jax_enable_x64, jax.config.jax_default_matmul_precision,"
        " str(jax.config.jax_explicit_x64_dtypes));"
        "import octomerge_jax, octomerge_jax.tree, octomerge_jax.io;"
        "after = (jax.config.jax_enable_x64, jax.config.jax_default_matmul_precision,"
        " str(jax.config.jax_explicit_x64_dtypes));"
        "import jax.numpy as jnp; assert jnp.zeros(1).dtype == jnp.float32, jnp.zeros(1).dtype;"
        "assert before == after, (before, after); print('ok')"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "ok"


def test_public_names_exist():
    for name in om.__all__:
        assert hasattr(om, name), name


def test_shipped_example_map_is_the_generated_room():
    shipped = om.example_map()
    assert shipped.resolution == 0.1
    assert tree.equal(shipped, examples.make_example_room())
    occupied = int(shipped.is_occupied().sum())
    assert 0 < occupied < shipped.num_leaves
