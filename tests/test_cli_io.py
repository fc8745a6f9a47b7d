"""``octomerge info`` and ``octomerge convert`` against OctoMap (pyoctomap)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from octomerge_jax.cli import main

pyoctomap = pytest.importorskip("pyoctomap")


@pytest.fixture()
def octomap_files(tmp_path):
    rng = np.random.default_rng(0)
    tree = pyoctomap.OcTree(0.05)
    keys = np.unique(rng.integers(-50, 50, size=(800, 3)), axis=0)
    occ = rng.random(keys.shape[0]) < 0.4
    tree.updateNodes((keys[occ] + 0.5) * 0.05, True, True)
    tree.updateNodes((keys[~occ] + 0.5) * 0.05, False, True)
    block = np.stack(np.meshgrid(*[np.arange(8)] * 3, indexing="ij"), -1).reshape(-1, 3) + 64
    tree.updateNodes((block + 0.5) * 0.05, False, True)
    tree.updateInnerOccupancy()
    ot, bt = tmp_path / "map.ot", tmp_path / "map.bt"
    tree.write(str(ot))
    tree.writeBinary(str(bt))  # ML + prune
    return tree, ot, bt


def test_info_json_matches_octomap(octomap_files, capsys):
    tree, ot, bt = octomap_files
    assert main(["info", str(bt), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    ref = pyoctomap.OcTree(0.05)
    ref.readBinary(str(bt))
    assert info["nodes"] == info["header_size"] == ref.size()
    assert info["leaves"] == ref.getNumLeafNodes()
    assert info["resolution_m"] == 0.05 and info["file_bytes"] == bt.stat().st_size
    n_occ = sum(ref.isNodeOccupied(ref.search(np.asarray(it.getCoordinate(), np.float64)))
                for it in ref.begin_leafs())
    assert info["occupied_leaves"] == n_occ
    assert info["free_leaves"] == info["leaves"] - n_occ
    depths = {}
    for it in ref.begin_leafs():
        depths[str(it.getDepth())] = depths.get(str(it.getDepth()), 0) + 1
    assert info["leaves_per_depth"] == depths and "13" in depths
    np.testing.assert_allclose(info["bounds_min_m"], ref.getMetricMin(), atol=1e-6)
    np.testing.assert_allclose(info["bounds_max_m"], ref.getMetricMax(), atol=1e-6)


def test_info_text(octomap_files, capsys):
    _, ot, _ = octomap_files
    assert main(["info", str(ot)]) == 0
    out = capsys.readouterr().out
    assert "resolution: 0.05 m" in out and "ot (full log-odds)" in out
    assert "depth 16 (0.05 m):" in out and "nodes:" in out


def test_convert_both_ways_byte_identical(octomap_files, tmp_path, capsys):
    tree, ot, bt = octomap_files
    out_bt = tmp_path / "conv.bt"
    assert main(["convert", str(ot), str(out_bt)]) == 0
    assert out_bt.read_bytes() == bt.read_bytes()
    out_ot = tmp_path / "conv.ot"
    assert main(["convert", str(bt), str(out_ot)]) == 0
    ref = pyoctomap.OcTree(0.05)
    ref.readBinary(str(bt))
    ref.updateInnerOccupancy()  # OctoMap leaves the root at clamp max after readBinary
    ref.write(str(tmp_path / "ref.ot"))
    assert out_ot.read_bytes() == (tmp_path / "ref.ot").read_bytes()
    assert "conv.ot" in capsys.readouterr().out


def test_convert_refuses_overwriting_its_input(octomap_files, capsys):
    _, ot, bt = octomap_files
    before = bt.read_bytes()
    assert main(["convert", str(bt), str(bt)]) == 1
    assert "is also an input" in capsys.readouterr().err
    assert main(["convert", str(bt), str(bt), "--force"]) == 0
    assert bt.read_bytes() == before  # OctoMap's own .bt is a fixed point


def test_cli_errors(octomap_files, tmp_path, capsys):
    _, ot, _ = octomap_files
    assert main(["convert", str(ot), str(tmp_path / "x.pcd")]) == 1
    assert "must end in .bt or .ot" in capsys.readouterr().err
    assert main(["info", str(tmp_path / "missing.bt")]) == 1
    assert "no such file" in capsys.readouterr().err
    broken = tmp_path / "broken.ot"
    broken.write_bytes(ot.read_bytes()[:-7])
    assert main(["info", str(broken)]) == 1
    err = capsys.readouterr().err
    assert str(broken) in err and "byte" in err and "truncated" in err
    assert main(["convert", str(broken), str(tmp_path / "out.bt")]) == 1
    assert not (tmp_path / "out.bt").exists()


def test_cli_keeps_compiled_kernels_in_a_persistent_cache(tmp_path):
    """The console script (not the library import) turns on JAX's persistent compilation cache
    in ``$OCTOMERGE_CACHE_DIR``; ``off`` disables it."""
    import os
    import subprocess
    import sys

    from octomerge_jax.examples import example_map_path

    cache = tmp_path / "xla"
    code = "import sys; from octomerge_jax.cli import main; sys.exit(main(sys.argv[1:]))"
    env = {**os.environ, "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS": "0", "JAX_PLATFORMS": "cpu"}
    for setting, expect in ((str(tmp_path / "none"), None), (str(cache), True)):
        env["OCTOMERGE_CACHE_DIR"] = "off" if expect is None else setting
        out = subprocess.run([sys.executable, "-c", code, "info", str(example_map_path())], env=env,
                             capture_output=True, text=True, timeout=120)
        assert out.returncode == 0, out.stderr
    assert not (tmp_path / "none").exists()
    assert len(list(cache.iterdir())) > 0
