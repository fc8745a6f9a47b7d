"""OctoMap .bt/.ot I/O against OctoMap itself (pyoctomap 1.2.2, OctoMap 1.10 C++)."""

from __future__ import annotations

import array
import os
import struct
import types
from pathlib import Path

import jax
import numpy as np
import pytest

from octomerge_jax import morton
from octomerge_jax.io import (
    MapFormatError,
    from_bytes,
    from_message,
    load,
    max_likelihood_prune,
    num_nodes,
    read_header,
    save,
    to_bytes,
    to_message_fields,
)
from octomerge_jax.io import _preorder
from octomerge_jax.io.octree_format import format_resolution
from octomerge_jax.map import OccupancyParams, bucket_capacity, empty, from_leaves

pyoctomap = pytest.importorskip("pyoctomap")

L_MIN = np.float32(-2.0000279)  # logodds(0.1192)
L_MAX = np.float32(3.5110307)  # logodds(0.971)


# ----------------------------------------------------------------------------- references


def _voxels(rng, n, spread=64):
    keys = rng.integers(-spread, spread, size=(n, 3))
    keys = np.unique(keys, axis=0)
    return keys


def _block(origin_key, size):
    g = np.stack(np.meshgrid(*[np.arange(size)] * 3, indexing="ij"), -1).reshape(-1, 3)
    return g + np.asarray(origin_key)


def octomap_tree(kind: str, res: float, seed: int = 0):
    """A pyoctomap OcTree plus (keys, log_odds) of the finest voxels it was built from."""
    rng = np.random.default_rng(seed)
    tree = pyoctomap.OcTree(res)
    if kind == "empty":
        return tree, None
    if kind == "scattered":  # finest voxels with assorted values, lazy + updateInnerOccupancy
        keys = _voxels(rng, 1500)
        values = rng.choice(np.array([-2.0, -1.2, -0.4, 0.0, 0.4, 0.85, 2.0, 3.5], np.float32),
                            size=keys.shape[0])
        for v in np.unique(values):
            pts = (keys[values == v] + 0.5) * res
            tree.updateNodes(pts, float(v), True)
        tree.updateInnerOccupancy()
        # values are float32(0 + v) clamped: v lies inside the clamping range
        return tree, (keys, values.astype(np.float32))
    if kind == "blocks":  # aligned blocks auto-pruned by OctoMap into leaves at depths 11..15
        for size, value in [(2, -0.4054651), (4, 0.84729785), (8, -0.4054651), (16, 0.84729785),
                            (32, -0.4054651)]:
            for _ in range(2):
                origin = rng.integers(-4, 4, size=3) * 32 + (0 if size == 32 else 32 - size)
                tree.updateNodes((_block(origin, size) + 0.5) * res, float(value), False)
        keys = _voxels(rng, 300, spread=100)
        tree.updateNodes((keys + 0.5) * res, True, False)
        return tree, None
    raise ValueError(kind)


def octomap_leaves(tree):
    """Leaves as OctoMap iterates them: (centres float32 (n,3), depth, size, log-odds)."""
    rows = []
    for it in tree.begin_leafs():
        c = it.getCoordinate()
        rows.append((c[0], c[1], c[2], it.getDepth(), it.getSize(),
                     tree.search(np.asarray(c, np.float64)).getLogOdds()))
    if not rows:
        return np.zeros((0, 3), np.float32), np.zeros(0, int), np.zeros(0), np.zeros(0, np.float32)
    a = np.array(rows, dtype=np.float64)
    return a[:, :3].astype(np.float32), a[:, 3].astype(int), a[:, 4], a[:, 5].astype(np.float32)


def _sorted_rows(centers, depths, sizes, log_odds):
    order = np.lexsort((centers[:, 2], centers[:, 1], centers[:, 0], depths))
    return centers[order], depths[order], sizes[order], log_odds[order]


def assert_same_leaves(m, tree):
    ref = _sorted_rows(*octomap_leaves(tree))
    lv = m.leaves()
    ours = _sorted_rows(lv.centers.astype(np.float32), lv.depths.astype(int), lv.sizes,
                        lv.log_odds)
    assert m.num_leaves == len(ref[1]) == tree.getNumLeafNodes()
    np.testing.assert_array_equal(ours[0], ref[0])  # centre, exactly as OctoMap's float32
    np.testing.assert_array_equal(ours[1], ref[1])  # depth
    np.testing.assert_allclose(ours[2], ref[2], rtol=1e-12)  # size [m]
    np.testing.assert_array_equal(ours[3], ref[3])  # log-odds, bit for bit


def write_reference(tree, tmp_path: Path, name: str):
    """(.ot, .bt) written by OctoMap; .ot first since writeBinary mutates the tree."""
    ot, bt = tmp_path / f"{name}_ref.ot", tmp_path / f"{name}_ref.bt"
    tree.write(str(ot))
    tree.writeBinary(str(bt))
    return ot, bt


KINDS = ["scattered", "blocks", "empty"]


# ----------------------------------------------------------------------------- reading


@pytest.mark.parametrize("kind", KINDS)
def test_octomap_files_load_to_the_leaves_octomap_iterates(kind, tmp_path):
    res = 0.1
    tree, _ = octomap_tree(kind, res)
    ot, bt = write_reference(tree, tmp_path, kind)
    # .ot: as OctoMap reads it back (values verbatim)
    m_ot = load(ot)
    assert m_ot.resolution == res
    assert_same_leaves(m_ot, tree.read(str(ot)) if kind != "empty" else tree)
    assert num_nodes(m_ot) == read_header(ot).size
    # .bt: clamp values, as OctoMap's readBinary
    ref = pyoctomap.OcTree(res)
    assert ref.readBinary(str(bt))
    m_bt = load(bt)
    assert_same_leaves(m_bt, ref)
    assert num_nodes(m_bt) == ref.size() == read_header(bt).size


def test_multi_depth_leaves_present(tmp_path):
    tree, _ = octomap_tree("blocks", 0.1)
    ot, _ = write_reference(tree, tmp_path, "b")
    depths = set(load(ot).leaves().depths.tolist())
    assert {11, 12, 13, 14, 15, 16} <= depths


def test_bt_reader_uses_the_maps_clamping(tmp_path):
    tree, _ = octomap_tree("scattered", 0.05)
    _, bt = write_reference(tree, tmp_path, "s")
    params = OccupancyParams.from_probabilities(clamp_min=0.2, clamp_max=0.9)
    m = load(bt, params=params)
    lo = m.leaves().log_odds
    assert set(np.unique(lo).tolist()) == {np.float32(params.clamp_min_log_odds),
                                           np.float32(params.clamp_max_log_odds)}
    ref = pyoctomap.OcTree(0.05)
    ref.setClampingThresMin(0.2)
    ref.setClampingThresMax(0.9)
    ref.readBinary(str(bt))
    assert_same_leaves(m, ref)


@pytest.mark.parametrize("cls", ["ColorOcTree", "OcTreeStamped"])
def test_color_and_stamped_ot_read_occupancy(cls, tmp_path):
    tree = getattr(pyoctomap, cls)(0.1)
    rng = np.random.default_rng(3)
    keys = _voxels(rng, 400)
    for i, k in enumerate(keys):
        tree.updateNode((k + 0.5) * 0.1, bool(i % 3))
    tree.updateInnerOccupancy()
    path = tmp_path / "c.ot"
    tree.write(str(path))
    assert read_header(path).tree_id == cls
    m = load(path)
    assert_same_leaves(m, tree)
    # their .bt (id ColorOcTree / OcTreeStamped) has the OcTree body layout
    tree.writeBinary(str(tmp_path / "c.bt"))
    assert read_header(tmp_path / "c.bt").tree_id == cls
    ref = pyoctomap.OcTree(0.1)
    assert ref.readBinary(str(tmp_path / "c.bt"))
    if cls == "OcTreeStamped":
        # pyoctomap (not OctoMap) appends a timestamp trailer to stamped .bt files, which
        # OctoMap's reader ignores: strict reading refuses it, lenient reading skips it
        with pytest.raises(MapFormatError, match="unexpected bytes after the tree"):
            load(tmp_path / "c.bt")
    assert_same_leaves(load(tmp_path / "c.bt", strict=False), ref)


def test_unknown_tree_id_is_refused(tmp_path):
    counting = pyoctomap.CountingOcTree(0.1)
    counting.updateNode(np.array([0.05, 0.05, 0.05]))
    path = tmp_path / "count.ot"
    counting.write(str(path))
    with pytest.raises(MapFormatError, match="unsupported octree id 'OcTreeBase'"):
        load(path)


def test_legacy_headerless_bt(tmp_path):
    tree, _ = octomap_tree("scattered", 0.1)
    _, bt = write_reference(tree, tmp_path, "s")
    head = read_header(bt)
    body = bt.read_bytes()[head.data_offset:]
    legacy = tmp_path / "legacy.bt"
    legacy.write_bytes(struct.pack("<idI", 3, 0.1, head.size) + body)
    assert read_header(legacy).legacy
    m = load(legacy)
    assert_same_leaves(m, tree)  # writeBinary left the tree maximum-likelihood + pruned
    with pytest.raises(MapFormatError, match="legacy"):
        load(_write(tmp_path / "bad.bt", struct.pack("<idI", 7, 0.1, 3) + body))


def _write(path, data):
    path.write_bytes(data)
    return path


def test_childless_root_reads_as_empty(tmp_path):
    # OctoMap writes this after deleting every leaf (octomap#106); see the module docstring
    tree = pyoctomap.OcTree(0.1)
    tree.updateNode(np.array([0.05, 0.05, 0.05]), True)
    tree.deleteNode(np.array([0.05, 0.05, 0.05]))
    ot, bt = write_reference(tree, tmp_path, "d")
    # OctoMap's stale size() makes the header claim 16 nodes for 1: strict refuses, like
    # OctoMap's own readBinary ("Tree size mismatch")
    with pytest.raises(MapFormatError, match="size mismatch"):
        load(bt)
    assert load(bt, strict=False).num_leaves == 0
    assert load(ot, strict=False).num_leaves == 0
    fixed = bt.read_bytes().replace(b"size 16", b"size 1")
    assert load(_write(tmp_path / "one.bt", fixed)).num_leaves == 0


# ----------------------------------------------------------------------------- writing


@pytest.mark.parametrize("kind", KINDS)
def test_rewrite_is_byte_identical_to_octomap(kind, tmp_path):
    tree, _ = octomap_tree(kind, 0.1)
    ot, bt = write_reference(tree, tmp_path, kind)
    m_ot = load(ot)
    save(m_ot, tmp_path / "ours.ot")
    assert (tmp_path / "ours.ot").read_bytes() == ot.read_bytes()
    # full log-odds -> maximum likelihood + OctoMap's prune == OctoMap's writeBinary
    save(m_ot, tmp_path / "ours.bt")
    assert (tmp_path / "ours.bt").read_bytes() == bt.read_bytes()
    save(load(bt), tmp_path / "again.bt")
    assert (tmp_path / "again.bt").read_bytes() == bt.read_bytes()


@pytest.mark.parametrize("res", [0.1, 0.05, 0.025, 0.3, 1.0])
def test_independent_map_writes_octomaps_bytes(res, tmp_path):
    """A map built from voxels (not from a file) writes what OctoMap writes for the tree it
    builds from the same voxels: header (%g resolution, node count) and body, both formats."""
    tree, (keys, values) = octomap_tree("scattered", res, seed=7)
    ot, bt = write_reference(tree, tmp_path, "s")
    codes = morton.keys_to_codes((keys + morton.KEY_OFFSET).astype(np.uint16))
    m = from_leaves(codes, np.full(codes.size, 16), values, res)
    assert to_bytes(m, binary=False, header=True) == ot.read_bytes()
    assert to_bytes(m, binary=True, header=True) == bt.read_bytes()
    assert f"res {format_resolution(res)}\n".encode() in bt.read_bytes()


def test_prune_stops_at_first_depth_without_prunes(tmp_path):
    """OctoMap's prune() stops at the first depth with nothing to collapse: 8 equal depth-14
    leaves with nothing prunable at depth 15 stay unpruned in the .bt."""
    base = np.uint64(morton.keys_to_codes(np.array([32768, 32768, 32768], np.uint16)))
    step = np.uint64(8 ** 2)  # depth-14 children of one depth-13 node
    codes = base + step * np.arange(8, dtype=np.uint64)
    m = from_leaves(codes, np.full(8, 14), np.full(8, -1.0, np.float32), 0.1)
    save(m, tmp_path / "ours.bt")
    ref = pyoctomap.OcTree(0.1)
    ref.readBinary(str(tmp_path / "ours.bt"))
    ref.writeBinary(str(tmp_path / "ref.bt"))
    assert (tmp_path / "ours.bt").read_bytes() == (tmp_path / "ref.bt").read_bytes()
    assert load(tmp_path / "ours.bt").num_leaves == 8
    c, d, v = max_likelihood_prune(codes, np.full(8, 14), np.full(8, -1.0, np.float32))
    assert d.tolist() == [14] * 8 and np.all(v == L_MIN)
    # a collapse at depth 15 only lets prune() go on to depth 14 (where nothing collapses)
    extra = np.uint64(morton.keys_to_codes(np.array([40000, 40000, 40000], np.uint16)))
    codes2 = np.concatenate([codes, (extra & _preorder.MASKS[15]) + np.arange(8, dtype=np.uint64)])
    _, d2, _ = max_likelihood_prune(codes2, np.r_[np.full(8, 14), np.full(8, 16)],
                                    np.full(16, -1.0, np.float32))
    assert sorted(d2.tolist()) == [14] * 8 + [15]
    # collapses at 15 and 14 let it reach depth 13
    codes3 = np.concatenate([codes, (extra & _preorder.MASKS[14]) + np.arange(64, dtype=np.uint64)])
    _, d3, _ = max_likelihood_prune(codes3, np.r_[np.full(8, 14), np.full(64, 16)],
                                    np.full(72, -1.0, np.float32))
    assert sorted(d3.tolist()) == [13, 14]


def test_threshold_is_inclusive_and_uses_map_params():
    codes = np.arange(8, dtype=np.uint64)
    lo = np.array([0.0, -1e-7, 5, -5, 0.1, -0.1, 0.0, 3], np.float32)
    _, _, v = max_likelihood_prune(codes, np.full(8, 16), lo)
    np.testing.assert_array_equal(v, np.where(lo >= 0, L_MAX, L_MIN))
    params = OccupancyParams.from_probabilities(occupancy_threshold=0.7)
    _, _, v = max_likelihood_prune(codes, np.full(8, 16), lo, params)
    np.testing.assert_array_equal(v >= 0, lo >= np.float32(params.occupancy_threshold_log_odds))


def test_depth0_leaf_is_written_as_eight_children(tmp_path):
    m = from_leaves(np.zeros(1, np.uint64), np.zeros(1), np.full(1, -1.5, np.float32), 0.2)
    for ext in ("bt", "ot"):
        save(m, tmp_path / f"r.{ext}")
        assert read_header(tmp_path / f"r.{ext}").size == 9
        back = load(tmp_path / f"r.{ext}")
        assert back.num_leaves == 8 and set(back.leaves().depths.tolist()) == {1}
    ref = pyoctomap.OcTree(0.2).read(str(tmp_path / "r.ot"))
    assert ref.size() == 9 and ref.getNumLeafNodes() == 8


def test_round_trips(tmp_path):
    rng = np.random.default_rng(11)
    tree, _ = octomap_tree("blocks", 0.1, seed=5)
    ot, _ = write_reference(tree, tmp_path, "b")
    m = load(ot)
    lv = m.leaves()
    noisy = from_leaves(lv.codes, lv.depths, rng.normal(size=lv.codes.size).astype(np.float32),
                        0.1)
    save(noisy, tmp_path / "n.ot")
    back = load(tmp_path / "n.ot").leaves()
    for a, b in zip(back, noisy.leaves()):
        np.testing.assert_array_equal(a, b)
    save(noisy, tmp_path / "n.bt")
    bt_leaves = load(tmp_path / "n.bt").leaves()
    c, d, v = max_likelihood_prune(lv.codes, lv.depths, noisy.leaves().log_odds)
    np.testing.assert_array_equal(bt_leaves.codes, c)
    np.testing.assert_array_equal(bt_leaves.depths, d)
    np.testing.assert_array_equal(bt_leaves.log_odds, v)


def test_empty_map_matches_octomap_empty_files(tmp_path):
    ot, bt = write_reference(pyoctomap.OcTree(0.2), tmp_path, "e")
    m = empty(0.2)
    assert to_bytes(m, binary=True, header=True) == bt.read_bytes()
    assert to_bytes(m, binary=False, header=True) == ot.read_bytes()
    assert to_bytes(m, binary=True) == b"" == to_bytes(m, binary=False)
    assert load(bt).num_leaves == 0 and load(ot).resolution == 0.2


def test_num_nodes_counts_inner_nodes_and_root():
    # one finest leaf: root + 15 inner + leaf
    one = from_leaves(np.zeros(1, np.uint64), np.full(1, 16), np.ones(1, np.float32), 0.1)
    assert num_nodes(one) == 17
    assert num_nodes(empty(0.1)) == 0
    two = from_leaves(np.array([0, 1], np.uint64), np.full(2, 16), np.ones(2, np.float32), 0.1)
    assert num_nodes(two) == 18


def test_num_nodes_agrees_with_tree_module(tmp_path):
    tree_mod = pytest.importorskip("octomerge_jax.tree")
    tree, _ = octomap_tree("blocks", 0.1, seed=4)
    ot, bt = write_reference(tree, tmp_path, "b")
    for path in (ot, bt):
        m = load(path)
        assert tree_mod.num_nodes(m) == num_nodes(m) == read_header(path).size


def test_writers_refuse_invalid_maps():
    # overlapping leaves (a depth-15 leaf containing a depth-16 one), bypassing the check
    bad = from_leaves(np.array([0, 1], np.uint64), np.array([15, 16]),
                      np.ones(2, np.float32), 0.1, check=False)
    for binary in (True, False):
        with pytest.raises(ValueError, match="overlap"):
            to_bytes(bad, binary=binary)
    misaligned = from_leaves(np.array([3], np.uint64), np.array([15]), np.ones(1, np.float32),
                             0.1, check=False)
    with pytest.raises(ValueError, match="aligned"):
        to_bytes(misaligned)


def test_save_is_atomic_and_checks_extension(tmp_path):
    m = from_leaves(np.zeros(1, np.uint64), np.full(1, 16), np.ones(1, np.float32), 0.1)
    target = tmp_path / "m.bt"
    save(m, target)
    before = target.read_bytes()
    with pytest.raises(TypeError):
        save("not a map", target)
    assert target.read_bytes() == before
    assert sorted(os.listdir(tmp_path)) == ["m.bt"]  # no temp file left behind
    with pytest.raises(ValueError, match="unknown map format '.pcd'"):
        save(m, tmp_path / "m.pcd")
    with pytest.raises(ValueError, match="unknown map format"):
        load(tmp_path / "m.txt")
    save(m, tmp_path / "UPPER.BT")
    assert load(tmp_path / "UPPER.BT").num_leaves == 1


def test_loaded_maps_of_one_bucket_share_a_compiled_function(tmp_path):
    traces = []

    @jax.jit
    def occupied_count(m):
        traces.append(1)
        return m.is_occupied().sum()

    for seed in (1, 2):
        tree, _ = octomap_tree("scattered", 0.1, seed=seed)
        ot, bt = write_reference(tree, tmp_path, f"s{seed}")
        for path in (ot, bt):
            m = load(path)
            assert m.capacity == bucket_capacity(m.num_leaves) == 2048
            occupied_count(m).block_until_ready()
    assert len(traces) == 1


# ----------------------------------------------------------------------------- messages


@pytest.mark.parametrize("binary", [True, False])
def test_message_payload_round_trip(binary, tmp_path):
    tree, _ = octomap_tree("blocks", 0.1, seed=2)
    ot, bt = write_reference(tree, tmp_path, "b")
    m = load(ot)
    payload = to_bytes(m, binary=binary)
    image = (bt if binary else ot).read_bytes()
    assert image.endswith(payload) and len(payload) == len(image) - read_header(
        bt if binary else ot).data_offset
    back = from_bytes(payload, binary=binary, resolution=0.1)
    expect = load(bt if binary else ot)
    for a, b in zip(back.leaves(), expect.leaves()):
        np.testing.assert_array_equal(a, b)
    # a message object as rclpy would deliver it: int8[] as array('b')
    fields = to_message_fields(m, binary=binary)
    assert fields["id"] == "OcTree" and fields["binary"] is binary
    assert isinstance(fields["data"], array.array) and fields["data"].typecode == "b"
    msg = types.SimpleNamespace(**fields)
    for a, b in zip(from_message(msg).leaves(), expect.leaves()):
        np.testing.assert_array_equal(a, b)
    # ROS1 python gives a list of ints in -128..127
    as_list = from_bytes(list(fields["data"]), binary=binary, resolution=0.1)
    assert as_list.num_leaves == expect.num_leaves


def test_from_bytes_accepts_file_images_and_checks_arguments(tmp_path):
    tree, _ = octomap_tree("scattered", 0.1)
    ot, bt = write_reference(tree, tmp_path, "s")
    assert from_bytes(bt.read_bytes()).num_leaves == load(bt).num_leaves
    assert from_bytes(np.frombuffer(ot.read_bytes(), np.int8)).num_leaves == load(ot).num_leaves
    with pytest.raises(ValueError, match="binary=False but the data is a binary"):
        from_bytes(bt.read_bytes(), binary=False)
    with pytest.raises(ValueError, match="resolution"):
        from_bytes(bt.read_bytes(), resolution=0.2)
    with pytest.raises(ValueError, match="binary must be given"):
        from_bytes(b"\x00\x00")
    with pytest.raises(ValueError, match="resolution must be given"):
        from_bytes(b"\x00\x00", binary=True)
    assert from_bytes(b"", binary=True, resolution=0.1).num_leaves == 0


def test_color_payload_layout(tmp_path):
    tree = pyoctomap.ColorOcTree(0.1)
    for i, k in enumerate(_voxels(np.random.default_rng(0), 50)):
        tree.updateNode((k + 0.5) * 0.1, bool(i % 2))
    tree.updateInnerOccupancy()
    tree.write(str(tmp_path / "c.ot"))
    body = (tmp_path / "c.ot").read_bytes()[read_header(tmp_path / "c.ot").data_offset:]
    m = from_bytes(body, binary=False, resolution=0.1, id="ColorOcTree")
    assert_same_leaves(m, tree)
    with pytest.raises(MapFormatError):  # the OcTree layout does not fit these bytes
        from_bytes(body, binary=False, resolution=0.1, id="OcTree")


# ----------------------------------------------------------------------------- bad input


@pytest.fixture(scope="module")
def ref_files(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("ref")
    tree, _ = octomap_tree("blocks", 0.1, seed=9)
    return write_reference(tree, tmp, "b")


@pytest.mark.parametrize("fmt", ["ot", "bt"])
def test_truncated_files_raise_with_path_and_offset(fmt, ref_files, tmp_path):
    path = ref_files[0] if fmt == "ot" else ref_files[1]
    data = path.read_bytes()
    head = read_header(path).data_offset
    for cut in [0, 10, head - 3, head, head + 1, (head + len(data)) // 2, len(data) - 1]:
        bad = _write(tmp_path / f"cut.{fmt}", data[:cut])
        with pytest.raises(MapFormatError) as info:
            load(bad)
        assert str(bad) in str(info.value) and "byte" in str(info.value)
        assert 0 <= info.value.offset <= cut


@pytest.mark.parametrize("fmt", ["ot", "bt"])
def test_trailing_bytes_and_size_mismatch(fmt, ref_files, tmp_path):
    path = ref_files[0] if fmt == "ot" else ref_files[1]
    data = path.read_bytes()
    bad = _write(tmp_path / f"t.{fmt}", data + b"\x00\x07junk")
    with pytest.raises(MapFormatError, match="6 unexpected bytes after the tree") as info:
        load(bad)
    assert info.value.offset == len(data)
    assert load(bad, strict=False).num_leaves == load(path).num_leaves
    size = read_header(path).size
    wrong = _write(tmp_path / f"w.{fmt}", data.replace(f"size {size}".encode(),
                                                        f"size {size + 1}".encode()))
    with pytest.raises(MapFormatError, match="size mismatch"):
        load(wrong)


@pytest.mark.parametrize("header, match", [
    (b"# Octomap OcTree binary file\nid OcTree\nsize 1\nres -0.1\ndata\n\x00\x00", "positive"),
    (b"# Octomap OcTree binary file\nid OcTree\nsize 1\nres 0.1\n", "without a 'data' line"),
    (b"# Octomap OcTree binary file\nsize 1\nres 0.1\ndata\n\x00\x00", "no 'id'"),
    (b"# Octomap OcTree binary file\nid OcTree\nsize x1\nres 0.1\ndata\n", "not a node count"),
    (b"# Octomap OcTree binary file\nid OcTree\nsize 1\nres abc\ndata\n", "not a number"),
    (b"# Octomap OcTree binary file\nid OcTree\nsize 99999999999999\nres 0.1\ndata\n\x00\x00",
     "not a node count"),
    (b"# Octomap OcTree file\nid SemanticOcTree\nsize 1\nres 0.1\ndata\n\x00", "unsupported"),
])
def test_bad_headers(header, match):
    with pytest.raises(MapFormatError, match=match) as info:
        from_bytes(header)
    assert str(info.value).startswith("<bytes>")


def test_not_an_octomap_file(tmp_path):
    for ext in ("bt", "ot"):
        with pytest.raises(MapFormatError, match="not an OctoMap") as info:
            load(_write(tmp_path / f"g.{ext}", b"GARBAGE that is long enough to be read\n"))
        assert info.value.offset == 0 and str(tmp_path) in str(info.value)


def test_header_tolerances_like_octomap():
    # comments, unknown keywords, reordered keys, deprecated id "1" and CRLF-free whitespace
    body = b"\x00\x02"  # root with one occupied depth-1 child (slot 4)
    data = (b"# Octomap OcTree binary file\n# my comment\nres 0.5 \nfoo bar baz\nid 1\n"
            b"size 2\ndata   \n" + body)
    m = from_bytes(data)
    assert m.resolution == 0.5 and m.num_leaves == 1
    assert m.leaves().depths.tolist() == [1] and m.leaves().log_odds[0] == L_MAX


def test_corrupt_structure():
    # .bt root announcing inner children that never come: truncated
    with pytest.raises(MapFormatError, match="truncated"):
        from_bytes(b"\xff\xff", binary=True, resolution=0.1)
    # an inner node without children
    with pytest.raises(MapFormatError, match="no children") as info:
        from_bytes(b"\x03\x00\x00\x00", binary=True, resolution=0.1)
    assert info.value.offset == 2
    # a chain of 17 inner levels: deeper than OctoMap's 16
    chain = b"\x03\x00" * 16 + b"\x02\x00"
    with pytest.raises(MapFormatError, match="deeper"):
        from_bytes(chain, binary=True, resolution=0.1)
    # .ot: NaN leaf value
    nan = struct.pack("<fB", 0.0, 1) + struct.pack("<fB", float("nan"), 0)
    with pytest.raises(MapFormatError, match="NaN") as info:
        from_bytes(nan, binary=False, resolution=0.1)
    assert info.value.offset == 5
    ok = struct.pack("<fB", 0.0, 1) + struct.pack("<fB", 1.5, 0)
    m = from_bytes(ok, binary=False, resolution=0.1)
    assert m.num_leaves == 1 and m.leaves().depths.tolist() == [1]


def test_huge_claimed_size_does_not_allocate():
    data = b"# Octomap OcTree file\nid OcTree\nsize 4000000000\nres 0.1\ndata\n" + \
        struct.pack("<fB", 0.0, 0)
    with pytest.raises(MapFormatError, match="size mismatch"):
        from_bytes(data)


def test_reader_matches_brute_force_recursive_parser():
    """The vectorised stream parser against a plain recursive reader (OctoMap's algorithm)."""
    rng = np.random.default_rng(4)
    for trial in range(20):
        n = int(rng.integers(1, 300))
        depth = rng.integers(1, 17, size=n)
        keys = rng.integers(0, 1 << 16, size=(n, 3)).astype(np.uint16)
        codes = morton.keys_to_codes(keys) & _preorder.MASKS[depth]
        codes, first = np.unique(codes, return_index=True)
        depth = depth[first]
        # drop leaves inside others
        keep, last_end = [], -1
        for i, (c, d) in enumerate(zip(codes.tolist(), depth.tolist())):
            if c > last_end:
                keep.append(i)
                last_end = c + 8 ** (16 - d) - 1
        codes, depth = codes[keep], depth[keep]
        values = rng.normal(size=codes.size).astype(np.float32)
        body, _ = _preorder.encode_ot(codes, depth, values)
        got = from_bytes(body.tobytes(), binary=False, resolution=0.1)
        n = got.num_leaves
        ref = _recursive_ot(body.tobytes())
        np.testing.assert_array_equal(morton.join_codes(np.asarray(got.code)[:n]),
                                      [r[0] for r in ref])
        np.testing.assert_array_equal(np.asarray(got.depth)[:n], [r[1] for r in ref])
        np.testing.assert_array_equal(np.asarray(got.log_odds)[:n],
                                      np.array([r[2] for r in ref], np.float32))


def test_fused_bt_writer_matches_prune_then_encode():
    """The one-pass .bt writer equals max_likelihood_prune + the plain record encoder."""
    rng = np.random.default_rng(8)
    for trial in range(40):
        n = int(rng.integers(1, 500))
        span = int(rng.choice([2, 4, 8, 32]))
        keys = rng.integers(0, span, size=(n, 3)) + int(rng.integers(0, 1 << 15))
        if trial % 4 == 3:  # dense aligned cubes, one raw value per 2^3 block: depth-15
            # leaves that differ raw (0 vs 2) but agree after maximum likelihood
            side = int(rng.choice([4, 8]))
            keys = _block(rng.integers(0, 1 << 10, size=3) * 8, side)
            lo = rng.choice(np.array([0.0, 2.0], np.float32), size=(side // 2,) * 3)[
                keys[:, 0] % side // 2, keys[:, 1] % side // 2, keys[:, 2] % side // 2]
        else:
            lo = rng.choice(np.array([-1.0, 0.0, 2.0], np.float32), size=keys.shape[0])
        codes, first = np.unique(morton.keys_to_codes(keys.astype(np.uint16)), return_index=True)
        codes, depths, lo = tree_prune_host(codes, lo[first])
        if trial % 2 and np.any(depths < 16):  # only coarse leaves: empty finest levels
            keep = depths < 16
            codes, depths, lo = codes[keep], depths[keep], lo[keep]
        m = from_leaves(codes, depths, lo, 0.1)
        c, d, v = max_likelihood_prune(codes, depths, lo)
        body, nodes = encode_bt_reference(c, d.astype(np.uint8), v >= 0)
        assert to_bytes(m, binary=True) == body.tobytes()
        assert read_header_size(to_bytes(m, binary=True, header=True)) == nodes


def encode_bt_reference(codes, depths, occupied) -> tuple[np.ndarray, int]:
    """``.bt`` body of the tree over the given leaves (``depth >= 1``), as is (no maximum
    likelihood, no pruning): per *inner* node in pre-order two bytes of 2-bit child states
    (``writeBinaryNode``: 0 unknown, 1 free leaf, 2 occupied leaf, 3 inner; child j at bits
    2(j%4) of byte j//4). Returns (bytes, nodes). The reference for the writer's fused
    ``_preorder.encode_bt_pruned``."""
    if codes.size == 0:
        return np.zeros(0, np.uint8), 0
    lay = _preorder.layout(codes, depths)
    total = lay.depth.size
    state = np.full(total, 3, dtype=np.uint16)
    state[lay.leaf_record] = np.where(occupied, 2, 1).astype(np.uint16)
    word = np.zeros(total, dtype=np.uint16)
    for kids, starts, parents, ci in _preorder.levels(lay):
        contrib = state[kids] << (2 * ci.astype(np.uint16))
        word[parents] = np.bitwise_or.reduceat(contrib, starts)
    is_leaf = np.zeros(total, dtype=bool)
    is_leaf[lay.leaf_record] = True
    inner = word[~is_leaf]
    return inner.astype("<u2").view(np.uint8), total


def tree_prune_host(codes, log_odds):
    """Maximal prune (8 equal sibling leaves -> parent, bottom-up) in plain NumPy (host
    arrays: ``OccupancyMap.leaves()`` compiles a slice per leaf count)."""
    depths = np.full(codes.size, 16)
    for d in range(15, -1, -1):
        idx = np.flatnonzero(depths == d + 1)
        parent = codes[idx] & _preorder.MASKS[d]
        starts = np.flatnonzero(np.r_[True, parent[1:] != parent[:-1]]) if idx.size else idx
        run = np.diff(np.r_[starts, idx.size])
        block = idx[starts[run == 8][:, None] + np.arange(8)]
        block = block[np.all(log_odds[block] == log_odds[block[:, :1]], axis=1)]
        depths[block[:, 0]] = d
        keep = np.ones(codes.size, bool)
        keep[block[:, 1:]] = False
        codes, depths, log_odds = codes[keep], depths[keep], log_odds[keep]
    return codes, depths, log_odds


def read_header_size(image: bytes) -> int:
    return int(image.split(b"\nsize ")[1].split(b"\n")[0])


def _recursive_ot(data: bytes):
    out, pos = [], 0

    def node(code, depth):
        nonlocal pos
        value, mask = struct.unpack_from("<fB", data, pos)
        pos += 5
        if mask == 0:
            out.append((code, depth, value))
        for j in range(8):
            if mask >> j & 1:
                node(code | (j << 3 * (15 - depth)), depth + 1)

    node(0, 0)
    assert pos == len(data)
    return out


@pytest.mark.slow
def test_real_size_map_round_trips_through_octomap(tmp_path):
    """~0.5M leaves at several depths: OctoMap reads our files and re-writes them byte for
    byte; we read OctoMap's files back to the same leaves."""
    rng = np.random.default_rng(12)
    side = 128
    grid = np.stack(np.meshgrid(*[np.arange(side)] * 3, indexing="ij"), -1).reshape(-1, 3)
    keys = (grid + morton.KEY_OFFSET - side // 2).astype(np.uint16)
    # values constant on random 4^3 blocks, 2% noisy voxels: pruning yields depths 14..16
    coarse = rng.choice(np.array([-2.0, -0.4, 0.85, 3.5], np.float32), size=(side // 4,) * 3)
    values = coarse[grid[:, 0] // 4, grid[:, 1] // 4, grid[:, 2] // 4]
    noisy = rng.random(values.size) < 0.02
    values = np.where(noisy, rng.normal(size=values.size).astype(np.float32), values)
    codes = morton.keys_to_codes(keys)
    order = np.argsort(codes)
    codes, values = codes[order], values[order].astype(np.float32)
    full = from_leaves(codes, np.full(codes.size, 16), values, 0.05)
    import octomerge_jax.tree as tree_mod

    m = tree_mod.prune(full)
    assert m.num_leaves > 400_000 and len(set(m.leaves().depths.tolist())) >= 3
    save(m, tmp_path / "ours.ot")
    save(m, tmp_path / "ours.bt")
    ref = pyoctomap.OcTree(0.05).read(str(tmp_path / "ours.ot"))
    assert ref.size() == num_nodes(m) and ref.getNumLeafNodes() == m.num_leaves
    ref.write(str(tmp_path / "ref.ot"))
    assert (tmp_path / "ref.ot").read_bytes() == (tmp_path / "ours.ot").read_bytes()
    ref.writeBinary(str(tmp_path / "ref.bt"))  # ML + prune in OctoMap
    assert (tmp_path / "ref.bt").read_bytes() == (tmp_path / "ours.bt").read_bytes()
    back = load(tmp_path / "ref.ot").leaves()
    for a, b in zip(back, m.leaves()):
        np.testing.assert_array_equal(a, b)
