"""Reader limits and degenerate input: leaf / memory budgets checked before allocating, header
numbers read as OctoMap's C++ stream reads them, long headers, resolutions, directories, and the
scan readers' one-line errors."""

from __future__ import annotations

import tracemalloc

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from octomerge_jax.budget import MemoryBudgetError, memory_budget
from octomerge_jax.io import (MapFormatError, from_bytes, load, num_nodes, read_header, save,
                              to_bytes)
from octomerge_jax.io.errors import MapTooLargeError
from octomerge_jax.io.octree_format import reading_bytes
from octomerge_jax.io.scans import read_scans
from octomerge_jax.map import from_leaves

pyoctomap = pytest.importorskip("pyoctomap")

BT_HEAD = (b"# Octomap OcTree binary file\n# (feel free to add / change comments, but leave the "
           b"first line as it is!)\n#\n")


def _bt_image(words, res=b"0.1", size=None) -> bytes:
    """A .bt image from pre-order records ``words`` (uint16 child-state words)."""
    words = np.asarray(words, np.uint16)
    if size is None:
        leaves = sum(((int(w) >> (2 * j)) & 3) in (1, 2) for w in words for j in range(8))
        size = words.size + leaves
    return (BT_HEAD + b"id OcTree\nsize %d\nres %s\ndata\n" % (size, res)
            + words.astype("<u2").tobytes())


def full_tree(height: int) -> np.ndarray:
    """Records of a full subtree ``height`` levels above depth 16, its depth-16 leaves
    alternating free / occupied (nothing prunes)."""
    s = np.array([0x9999], np.uint16)
    for _ in range(height - 1):
        s = np.concatenate([[0xFFFF], np.tile(s, 8)]).astype(np.uint16)
    return s


def dense_bt(height: int) -> bytes:
    """A valid .bt: a chain from the root down to a full subtree of 8^height leaves."""
    return _bt_image(np.concatenate([np.full(16 - height, 3, np.uint16), full_tree(height)]),
                     size=16 - height + (8 ** height - 1) // 7 + 8 ** height)


def coarse_free_bt(depth: int) -> bytes:
    """A valid .bt of 8 free leaves at ``depth`` (1..16): the coarsest free space."""
    return _bt_image(np.concatenate([np.full(depth - 1, 3, np.uint16), [0x5555]]))


# ----------------------------------------------------------------------------- budgets


def test_max_leaves_and_memory_budget_refuse_before_allocating(tmp_path):
    path = tmp_path / "dense.bt"
    path.write_bytes(dense_bt(6))  # 262,144 leaves, 75 KB
    with pytest.raises(MapTooLargeError, match="262,144 leaves, over the limit of 1,000"):
        load(path, max_leaves=1000)
    need = reading_bytes((8 ** 6 - 1) // 7 + 10, 8 ** 6)
    tracemalloc.start()
    try:
        with memory_budget(need // 2), pytest.raises(MemoryBudgetError, match="dense.bt"):
            load(path)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak < need // 8  # refused after reading the structure, before the leaves
    with memory_budget(need):
        assert load(path).num_leaves == 8 ** 6
    with pytest.raises(MapTooLargeError, match="<bytes>"):
        from_bytes(dense_bt(6), max_leaves=10)


@pytest.mark.slow
def test_crafted_40mb_file_is_refused_by_default(tmp_path):
    """8^9 = 134M leaves in a 38 MB .bt: refused by the default leaf limit, quickly."""
    path = tmp_path / "bomb.bt"
    path.write_bytes(dense_bt(9))
    assert path.stat().st_size < 40e6
    with pytest.raises(MapTooLargeError, match="134,217,728 leaves"):
        load(path)


@settings(max_examples=12, deadline=None)
@given(kind=st.sampled_from(["coarse", "dense"]), depth=st.integers(1, 16),
       height=st.integers(1, 4))
def test_adversarial_valid_maps_stay_within_the_reading_estimate(kind, depth, height):
    """Coarse free leaves at every depth and dense full trees: the host memory reading takes
    is within ``reading_bytes`` (the figure checked against the budget), and a budget just
    below it refuses the map before reading the leaves."""
    data = coarse_free_bt(depth) if kind == "coarse" else dense_bt(height)
    m = from_bytes(data)
    records = (len(data) - data.index(b"data\n") - 5) // 2
    need = reading_bytes(records, m.num_leaves)
    tracemalloc.start()
    try:
        from_bytes(data)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak <= need + 64 * 1024  # + fixed-size temporaries (lookup tables, headers)
    with memory_budget(need - 1), pytest.raises(MemoryBudgetError):
        from_bytes(data)
    ot = to_bytes(m, binary=False, header=True)  # the same tree as .ot
    need_ot = reading_bytes(num_nodes(m), m.num_leaves)
    tracemalloc.start()
    try:
        assert from_bytes(ot).num_leaves == m.num_leaves
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak <= need_ot + 64 * 1024
    if kind == "coarse":  # free space of a depth-d cube, as free leaves of that depth
        lv = m.leaves()
        assert m.num_leaves == 8 and set(lv.depths.tolist()) == {depth}
        assert np.all(lv.log_odds < 0)


# ----------------------------------------------------------------------------- headers


def _octomap_bt(tmp_path):
    tree = pyoctomap.OcTree(0.5)
    tree.updateNode(np.array([0.1, 0.2, 0.3]), True)
    path = tmp_path / "ref.bt"
    tree.writeBinary(str(path))
    return path.read_bytes()


def _with_res_line(data: bytes, new: bytes) -> bytes:
    i = data.index(b"res ")
    return data[:i] + new + data[data.index(b"\n", i):]


@pytest.mark.parametrize("edit, res", [
    (lambda d: _with_res_line(d, b"res 1_0"), 1.0),  # C++ reads 1, then skips "_0 ..."
    (lambda d: _with_res_line(d, b"res 0.25abc"), 0.25),
    (lambda d: _with_res_line(d, b"res +2.5e-1"), 0.25),
    (lambda d: d.replace(b"res ", b"#" + b"c" * 70000 + b"\nres "), 0.5),  # > 64 KiB
    (lambda d: d.replace(b"res ", b"x" * 5000 + b" unknown keyword\nres "), 0.5),  # long token
])
def test_headers_read_like_octomap(tmp_path, edit, res):
    data = edit(_octomap_bt(tmp_path))
    path = tmp_path / "h.bt"
    path.write_bytes(data)
    ref = pyoctomap.OcTree(0.1)
    assert ref.readBinary(str(path)) and ref.getResolution() == res
    m = load(path)
    assert m.resolution == res and m.num_leaves == ref.getNumLeafNodes()
    assert read_header(path).resolution == res


@pytest.mark.parametrize("res", [b"1e-300", b"5e-324", b"1e39", b"1e300", b"1e400", b"inf",
                                 b"nan", b"0", b"-1"])
def test_degenerate_resolutions_are_refused(tmp_path, res):
    path = tmp_path / "r.bt"
    path.write_bytes(_bt_image([0x0002], res=res))
    with pytest.raises(MapFormatError) as info:
        load(path)
    msg = str(info.value)
    assert msg.startswith(str(path)) and "\n" not in msg and "res" in msg


def test_degenerate_payload_resolution_is_refused():
    with pytest.raises(ValueError, match="outside the supported"):
        from_bytes(b"\x02\x00", binary=True, resolution=1e-300)


def test_directory_input_is_reported_as_a_directory(tmp_path):
    folder = tmp_path / "maps.bt"
    folder.mkdir()
    for reader in (load, read_header, read_scans):
        with pytest.raises(IsADirectoryError, match="is a directory"):
            reader(folder)
    with pytest.raises(FileNotFoundError, match="no such file"):
        load(tmp_path / "missing.bt")


def test_cli_info_on_a_directory(tmp_path, capsys):
    from octomerge_jax.cli import main

    (tmp_path / "d.bt").mkdir()
    assert main(["info", str(tmp_path / "d.bt")]) == 1
    err = capsys.readouterr().err.strip()
    assert err.endswith("is a directory, not a map file") and "\n" not in err


# ----------------------------------------------------------------------------- scans

PCD = ("VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 1\nHEIGHT 1\n"
       "POINTS 1\nDATA binary\n")


@pytest.mark.parametrize("name, text, match", [
    ("q.pcd", PCD.replace("TYPE F F F", "TYPE Q Q Q"), r"q.pcd:4: PCD TYPE"),
    ("s0.pcd", PCD.replace("SIZE 4 4 4", "SIZE 0 4 4"), r"s0.pcd:3: PCD SIZE"),
    ("s3.pcd", PCD.replace("SIZE 4 4 4", "SIZE 3 4 4"), r"s3.pcd: PCD field 'x'"),
    ("p.pcd", PCD.replace("POINTS 1", "POINTS"), r"p.pcd:8: PCD POINTS needs one value"),
    ("n.pcd", PCD.replace("POINTS 1", "POINTS -5"), r"n.pcd:8: PCD POINTS needs integers"),
    ("c.pcd", PCD.replace("COUNT 1 1 1", "COUNT 1 1"), r"c.pcd: PCD COUNT has 2 entries"),
    ("a.pcd", PCD.replace("binary", "ascii") + "1 2 x\n", r"a.pcd:10: non-numeric"),
    ("big.dat", "NODE 0 0 0 0 0 0\n1 2 3\n1e30 0 0\n", r"big.dat:3: point coordinate 1e\+30"),
    ("nan.dat", "NODE 0 0 nan 0 0 0\n1 2 3\n", r"nan.dat:1: NODE position nan is not finite"),
    ("ang.dat", "NODE 0 0 0 0 inf 0\n1 2 3\n", r"ang.dat:1: non-finite NODE angles"),
])
def test_scan_readers_give_one_line_errors(tmp_path, name, text, match):
    path = tmp_path / name
    path.write_bytes(text.encode() + (b"\0" * 12 if "binary" in text else b""))
    with pytest.raises(ValueError, match=match) as info:
        read_scans(path)
    assert "\n" not in str(info.value)


def test_graph_with_a_nan_pose_names_the_byte_offset(tmp_path):
    from octomerge_jax.io.scans import write_scan_graph

    path = tmp_path / "g.graph"
    write_scan_graph(path, [(np.zeros((2, 3)), np.eye(4))])
    data = bytearray(path.read_bytes())
    at = 4 + 4 + 2 * 28 + 4  # node count, point count, 2 points, translation tag
    data[at:at + 8] = np.float64(np.nan).tobytes()
    path.write_bytes(bytes(data))
    with pytest.raises(ValueError, match=rf"g.graph: byte offset {at}: node 0 pose translation"):
        read_scans(path)


def test_save_round_trip_still_exact(tmp_path):
    m = from_leaves(np.arange(0, 64, 8, dtype=np.uint64), np.full(8, 15), np.ones(8, np.float32),
                    0.1)
    save(m, tmp_path / "m.ot")
    back = load(tmp_path / "m.ot")
    assert back.leaves().codes.tolist() == m.leaves().codes.tolist()
