"""Start-up: ``import octomerge_jax`` and ``octomerge --help`` load neither JAX nor any optional
dependency; each command loads only its own module; the command line's compilation cache is
handed to worker processes (docs/design.md, "Start-up: lazy imports", "Compile cache and
warm-up")."""

import json
import subprocess
import sys

import pytest

import octomerge_jax as om
from octomerge_jax import cli
from octomerge_jax.cli import cache

HEAVY = ("jax", "numpy", "scipy", "trimesh", "matplotlib", "dask", "distributed", "tqdm")


def _modules_after(code: str) -> set[str]:
    probe = code + "; import sys, json; print(json.dumps(sorted(sys.modules)))"
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True)
    return set(json.loads(out.stdout.strip().splitlines()[-1]))


def _heavy(mods: set[str]) -> set[str]:
    return {m for m in mods if m.split(".")[0] in HEAVY}


def test_import_loads_no_heavy_module():
    assert not _heavy(_modules_after("import octomerge_jax"))


def test_help_and_version_load_no_heavy_module():
    code = ("import sys; from octomerge_jax.cli import main\n"
            "for argv in (['--help'], ['--version']):\n"
            "    try: main(argv)\n"
            "    except SystemExit: pass")
    mods = _modules_after(code)
    assert not _heavy(mods)
    assert not {m for m in mods if m.startswith("octomerge_jax.cli.") and m != "octomerge_jax.cli._common"
                and m != "octomerge_jax.cli.cache"}


def test_help_lists_every_command_with_its_own_summary():
    """``COMMANDS``'s summaries are the ones each module registers (the full parser)."""
    full = next(a for a in cli.build_parser()._actions if a.dest == "command")
    lazy = next(a for a in cli.build_parser("")._actions if a.dest == "command")
    assert list(full.choices) == list(lazy.choices) == list(cli.COMMANDS)
    helps = {c.dest: c.help for c in full._choices_actions}
    assert helps == {name: summary for name, (_, summary) in cli.COMMANDS.items()}


def test_public_names_resolve_lazily_and_list_in_dir():
    assert set(om.__all__) <= set(dir(om))
    assert om.merge is om.pipeline.merge and om.load is om.io.load
    with pytest.raises(AttributeError, match="no_such_name"):
        om.no_such_name  # noqa: B018


def test_cache_dir_setting(tmp_path):
    assert cache.cache_dir({"OCTOMERGE_CACHE_DIR": "off"}) is None
    assert cache.cache_dir({"OCTOMERGE_CACHE_DIR": str(tmp_path)}) == str(tmp_path)
    assert cache.cache_dir({"XDG_CACHE_HOME": str(tmp_path)}) == str(tmp_path / "octomerge_jax" / "xla")


def test_worker_env_hands_over_the_cache_in_use():
    """tests/conftest.py turns the run's cache on (unless OCTOMERGE_TEST_CACHE_DIR=off), so
    workers get it and keep every program; without a cache they get nothing."""
    import jax

    env = cache.worker_env()
    if not jax.config.jax_compilation_cache_dir:
        assert env == {}
        return
    assert env["JAX_COMPILATION_CACHE_DIR"] == jax.config.jax_compilation_cache_dir
    assert float(env["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"]) == 0.0


def test_warmup_rejects_bad_arguments(tmp_path, capsys):
    assert cli.main(["warmup", str(tmp_path / "a.bt")]) == 2
    assert "two maps" in capsys.readouterr().err
    assert cli.main(["warmup", "--res", "-1"]) == 2
    with pytest.raises(SystemExit) as exc:  # argparse: a mode merge does not have
        cli.main(["warmup", "--refine", "icp+gicp"])
    assert exc.value.code == 2 and "invalid choice: 'icp+gicp'" in capsys.readouterr().err


@pytest.mark.slow  # compiles a merge's programs (~30 s on 2 idle cores unless the run's cache has them)
def test_warmup_merges_the_room_pair_into_the_cache(capsys):
    """The smallest built-in size, ``refine none``: one merge, reported with its program count."""
    assert cli.main(["warmup", "--res", "0.2", "--refine", "none"]) == 0
    out = capsys.readouterr().out
    assert "room at 0.2 m" in out and "refine none" in out and "programs compiled" in out
    assert f"cache: {cache.worker_env()['JAX_COMPILATION_CACHE_DIR']}" in out


@pytest.mark.slow  # compiles the default merges' programs for one size (~1 min on 2 idle cores)
def test_warmup_readies_what_the_default_merge_commands_run(tmp_path, capsys):
    """After ``octomerge warmup`` of a size, ``octomerge merge`` of a pair of that size compiles
    nothing, without a guess (global) and from one (icp+dense): its default modes."""
    import jax

    from octomerge_jax.cli.warmup import _XYZ_RPY_TRUE
    from octomerge_jax.io import save
    from octomerge_jax.pipeline import transform_from_xyz_rpy
    from octomerge_jax.sim import small_room_map, small_room_voxels

    assert cli.main(["warmup", "--res", "0.2"]) == 0
    voxels = small_room_voxels(0.2)
    save(small_room_map((-1.0, 3.0), 0.2, voxels=voxels), tmp_path / "a.bt")
    save(small_room_map((0.8, 9.0), 0.2, transform_from_xyz_rpy(*_XYZ_RPY_TRUE), voxels=voxels), tmp_path / "b.bt")
    compiles = []

    def on_compile(event, secs, **kw):
        if event == "/jax/core/compile/backend_compile_duration":
            compiles.append(secs)

    jax.monitoring.register_event_duration_secs_listener(on_compile)
    try:
        for guess in ([], ["--xyz", "0.4", "-0.2", "0", "--rpy", "0", "0", "0.8"]):
            cli.main(["merge", str(tmp_path / "a.bt"), str(tmp_path / "b.bt"), str(tmp_path / "out.bt"), "--force",
                      "-q", *guess])
            assert (tmp_path / "out.bt").is_file()
    finally:
        jax.monitoring.unregister_event_duration_listener(on_compile)
    assert not compiles, f"{len(compiles)} programs compiled after the warm-up"


def test_a_batch_worker_opens_the_kernel_store_its_parent_handed_over(tmp_path):
    from octomerge_jax import kernel_store

    run_store = kernel_store.store_dir()  # tests/conftest.py opens the run's
    kernel_store.close_store()
    try:
        cache.open_worker_store({})
        assert kernel_store.store_dir() is None and cache.STORE_VARIABLE not in cache.worker_env()
        cache.open_worker_store({cache.STORE_VARIABLE: str(tmp_path / "kernels")})
        assert kernel_store.store_dir() == tmp_path / "kernels"
        assert cache.worker_env()[cache.STORE_VARIABLE] == str(tmp_path / "kernels")
    finally:
        kernel_store.close_store()
        if run_store is not None:
            kernel_store.open_store(run_store)
