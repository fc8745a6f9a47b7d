import subprocess
import sys

import pytest

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


# minor faults while writing a freed-then-fresh 96 MB block (printed); no JAX, no octomerge_jax
_FAULT_PROBE = """
import ctypes, resource
libc = ctypes.CDLL("libc.so.6")
libc.malloc.restype, libc.malloc.argtypes = ctypes.c_void_p, [ctypes.c_size_t]
libc.free.argtypes = [ctypes.c_void_p]
def touch_faults(n=96 << 20):
    p = libc.malloc(n)
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    ctypes.memset(p, 1, n)
    faults = resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before
    libc.free(p)
    return faults
touch_faults()
print(touch_faults())
"""

_REUSE_PROBE = """
import sys, warnings
import octomerge_jax
if sys.argv[1] == "on":
    assert octomerge_jax.reuse_host_memory() is True
""" + _FAULT_PROBE + """
import jax.numpy as jnp
jnp.zeros(3).block_until_ready()
with warnings.catch_warnings(record=True) as w:
    warnings.simplefilter("always")
    late = octomerge_jax.reuse_host_memory()
print(late, [str(x.category.__name__) for x in w])
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc malloc setting")
def test_reuse_host_memory_keeps_freed_blocks_and_is_opt_in():
    def probe(mode):
        out = subprocess.run([sys.executable, "-c", _REUSE_PROBE, mode], capture_output=True,
                             text=True, check=True)
        faults, late = out.stdout.strip().splitlines()
        return int(faults), late
    # default (import only): a freed 96 MB block goes back to the system, re-faulted next time
    faults, late = probe("off")
    assert faults > 10_000
    assert late == "False ['RuntimeWarning']"  # too late once JAX runs: nothing changed
    # opted in before JAX starts: the block stays in the heap and is reused
    faults, late = probe("on")
    assert faults < 1_000
    assert late == "True []"


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc malloc setting")
@pytest.mark.parametrize("command,value,applied", [
    ("dump-config", None, False), ("dump-config", "on", True), ("batch", None, True), ("batch", "0", False)])
def test_octomerge_command_reuses_host_memory_for_batch_or_when_asked(command, value, applied):
    """``batch`` keeps XLA:CPU's scratch memory by default, a single command does not (its
    compilation would slow); ``OCTOMERGE_REUSE_HOST_MEMORY`` turns it on or off for all."""
    import os

    argv = ["octomerge", command] + (["--help"] if command == "batch" else [])  # batch needs a manifest
    code = ("import sys, octomerge_jax.hostmem as h; from octomerge_jax.cli import console_main\n"
            f"sys.argv = {argv!r}\n"
            "try:\n    console_main()\nexcept SystemExit:\n    pass\n"
            "print(h._applied, file=sys.stderr)")
    env = {k: v for k, v in os.environ.items() if k != "OCTOMERGE_REUSE_HOST_MEMORY"}
    if value is not None:
        env["OCTOMERGE_REUSE_HOST_MEMORY"] = value
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, env=env)
    assert out.stderr.strip().splitlines()[-1] == str(applied)
    assert ("[registration]" if command == "dump-config" else "manifest") in out.stdout  # the command itself ran


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc malloc setting")
def test_child_env_gives_workers_the_reuse(monkeypatch):
    """``child_env`` (what ``octomerge batch`` gives its local Dask workers) carries the setting
    into a new process: a freed 96 MB block is reused there, as in the parent; empty when the
    parent did not opt in."""
    import os

    from octomerge_jax import hostmem
    from octomerge_jax.cli.cache import worker_env
    from octomerge_jax.cli.dask_runner import map_on_dask

    def faults(env):
        base = {k: v for k, v in os.environ.items() if k != "GLIBC_TUNABLES"}
        out = subprocess.run([sys.executable, "-c", _FAULT_PROBE], capture_output=True, text=True,
                             check=True, env={**base, **env})
        return int(out.stdout)

    monkeypatch.setattr(hostmem, "_applied", False)
    assert hostmem.child_env() == {}
    assert faults(hostmem.child_env()) > 10_000
    monkeypatch.setattr(hostmem, "_applied", True)
    env = hostmem.child_env({"GLIBC_TUNABLES": "glibc.malloc.tcache_count=0"})
    assert env == {"GLIBC_TUNABLES": "glibc.malloc.tcache_count=0:" + hostmem.GLIBC_TUNABLES}
    assert faults(hostmem.child_env({})) < 1_000
    # the batch runner's own cluster is started with it
    distributed = pytest.importorskip("distributed")
    seen = {}

    class Stop(Exception):
        pass

    def fake_cluster(**kw):
        seen.update(kw)
        raise Stop

    monkeypatch.setattr(distributed, "LocalCluster", fake_cluster)
    with pytest.raises(Stop):
        list(map_on_dask(len, [], workers=2, key=str))
    assert seen["env"] == {**hostmem.child_env(), **worker_env()} and seen["processes"]
