"""Scan files: ScanGraph round trip and hand-made bytes, logs, PCD/PLY, malformed inputs,
and the ``octomerge build`` command."""

from __future__ import annotations

import struct

import numpy as np
import pytest
import trimesh

from octomerge_jax import se3
from octomerge_jax.io.scans import (Scan, read_point_cloud, read_scan_graph, read_scan_log, read_scans,
                                    write_scan_graph, write_scan_log)
from octomerge_jax.sim.trajectory import pose_from_xyz_rpy


def _scans(rng, n=3):
    return [Scan(rng.uniform(-3, 3, (50 + 10 * i, 3)),
                 pose_from_xyz_rpy(*rng.uniform(-1, 1, 3), *rng.uniform(-0.5, 0.5, 3)), i)
            for i in range(n)]


def test_graph_round_trip(tmp_path):
    scans = _scans(np.random.default_rng(0))
    write_scan_graph(tmp_path / "a.graph", scans)
    back, edges = read_scan_graph(tmp_path / "a.graph", with_edges=True)
    assert [s.id for s in back] == [0, 1, 2]
    for a, b in zip(scans, back):
        np.testing.assert_array_equal(a.points, b.points)
        np.testing.assert_allclose(a.pose, b.pose, atol=1e-12)
    assert [(e.first, e.second) for e in edges] == [(0, 1), (1, 2)]
    np.testing.assert_allclose(edges[0].constraint, np.linalg.inv(scans[0].pose) @ scans[1].pose, atol=1e-12)


def test_hand_made_graph(tmp_path):
    """Bytes laid out by hand as OctoMap's ScanGraph::writeBinary does."""
    q = [np.cos(np.pi / 8), 0.0, 0.0, np.sin(np.pi / 8)]  # yaw pi/4
    data = struct.pack("<I", 1)
    data += struct.pack("<I", 2) + struct.pack("<i3d", 3, 1.0, 2.0, 3.0) + struct.pack("<i3d", 3, -1.0, 0.5, 0.25)
    data += struct.pack("<i3d", 3, 10.0, 20.0, 0.5) + struct.pack("<i4d", 4, *q)
    data += struct.pack("<I", 7) + struct.pack("<I", 0)
    (tmp_path / "h.graph").write_bytes(data)
    (s,) = read_scan_graph(tmp_path / "h.graph")
    assert s.id == 7
    np.testing.assert_array_equal(s.points, [[1, 2, 3], [-1, 0.5, 0.25]])
    np.testing.assert_allclose(s.pose[:3, 3], [10, 20, 0.5])
    np.testing.assert_allclose(s.world_points()[0], [10 + np.cos(np.pi / 4) - 2 * np.sin(np.pi / 4),
                                                      20 + np.sin(np.pi / 4) + 2 * np.cos(np.pi / 4), 3.5])
    # truncations at every length name a byte offset
    for cut in (2, 6, 20, len(data) - 3):
        (tmp_path / "t.graph").write_bytes(data[:cut])
        with pytest.raises(ValueError, match="byte offset"):
            read_scan_graph(tmp_path / "t.graph")
    bad = bytearray(data)
    bad[8:12] = struct.pack("<i", 5)  # the first point's element count
    (tmp_path / "b.graph").write_bytes(bytes(bad))
    with pytest.raises(ValueError, match="byte offset 8"):
        read_scan_graph(tmp_path / "b.graph")
    (tmp_path / "x.graph").write_bytes(data + b"\0")
    with pytest.raises(ValueError, match="trailing"):
        read_scan_graph(tmp_path / "x.graph")


def test_log_files(tmp_path):
    text = ("# comment\nNODE 1 2 0.5 0 0 1.5707963267948966\n1 0 0\n0 1 0\n\n"
            "NODE 0 0 0 0 0 0\n  indented lines are skipped\n2 2 2\n")
    (tmp_path / "a.log").write_text(text)
    scans = read_scan_log(tmp_path / "a.log")
    assert [len(s.points) for s in scans] == [2, 1]
    np.testing.assert_allclose(scans[0].world_points(), [[1, 3, 0.5], [0, 2, 0.5]], atol=1e-12)
    write_scan_log(tmp_path / "b.dat", scans)
    back = read_scans(tmp_path / "b.dat")
    for a, b in zip(scans, back):
        np.testing.assert_allclose(a.pose, b.pose, atol=1e-12)
        np.testing.assert_array_equal(a.points, b.points)
    (tmp_path / "bare.txt").write_text("1 2 3\n4 5 6\n")
    (s,) = read_scans(tmp_path / "bare.txt")
    assert np.array_equal(s.pose, np.eye(4)) and s.points.shape == (2, 3)
    for bad, where in (("NODE 1 2 3\n", ":1:"), ("NODE 0 0 0 0 0 0\n1 2\n", ":2:"),
                       ("NODE 0 0 0 0 0 0\n1 x 3\n", ":2:"), ("1 2 3\nNODE 0 0 0 0 0 0\n", ":2:"),
                       ("# nothing\n", "no scans")):
        (tmp_path / "bad.log").write_text(bad)
        with pytest.raises(ValueError, match=where):
            read_scan_log(tmp_path / "bad.log")


def test_point_cloud_files(tmp_path):
    pts = np.random.default_rng(1).uniform(-1, 1, (20, 3)).astype(np.float32)
    trimesh.PointCloud(pts).export(tmp_path / "c.ply")
    np.testing.assert_allclose(read_point_cloud(tmp_path / "c.ply"), pts, atol=1e-7)
    header = "VERSION 0.7\nFIELDS x y z intensity\nSIZE 4 4 4 4\nTYPE F F F F\nCOUNT 1 1 1 1\n" \
             f"WIDTH {len(pts)}\nHEIGHT 1\nPOINTS {len(pts)}\n"
    body = "\n".join(" ".join(f"{v!r}" for v in (*map(float, p), 1.0)) for p in pts)
    (tmp_path / "a.pcd").write_text(header + "DATA ascii\n" + body + "\n")
    np.testing.assert_allclose(read_point_cloud(tmp_path / "a.pcd"), pts, atol=1e-7)
    rec = np.c_[pts, np.ones(len(pts), np.float32)].astype("<f4").tobytes()
    (tmp_path / "b.pcd").write_bytes((header + "DATA binary\n").encode() + rec)
    np.testing.assert_array_equal(read_point_cloud(tmp_path / "b.pcd"), pts)
    (tmp_path / "t.pcd").write_bytes((header + "DATA binary\n").encode() + rec[:-8])
    with pytest.raises(ValueError, match="truncated"):
        read_point_cloud(tmp_path / "t.pcd")
    (tmp_path / "z.pcd").write_text(header.replace("x y z", "a b c") + "DATA ascii\n")
    with pytest.raises(ValueError, match="'x'"):
        read_point_cloud(tmp_path / "z.pcd")


def test_rotation_helpers():
    rng = np.random.default_rng(2)
    for _ in range(20):
        r, p, y = rng.uniform(-1.2, 1.2, 3)
        R = pose_from_xyz_rpy(0, 0, 0, r, p, y)[:3, :3]
        q = se3.to_quaternion(R, xp=np)
        np.testing.assert_allclose(se3.from_quaternion(q, xp=np)[:3, :3], R, atol=1e-12)
        np.testing.assert_allclose(se3.to_xyz_rpy(pose_from_xyz_rpy(0, 0, 0, r, p, y), xp=np)[3:], (r, p, y), atol=1e-12)


def test_build_cli_matches_octomap(tmp_path):
    """``octomerge build`` on a .graph equals pyoctomap inserting the same scans."""
    pyoctomap = pytest.importorskip("pyoctomap")
    from octomerge_jax.cli import build as build_cli
    from octomerge_jax.io import load
    import argparse

    rng = np.random.default_rng(3)
    scans = [Scan(rng.uniform(-2, 2, (300, 3)), pose_from_xyz_rpy(0.3 * i, 0.1, 0.4, 0, 0, 0.5 * i), i)
             for i in range(2)]
    write_scan_graph(tmp_path / "s.graph", scans)
    parser = argparse.ArgumentParser()
    build_cli.register(parser.add_subparsers())
    args = parser.parse_args(["build", str(tmp_path / "s.graph"), str(tmp_path / "o.bt"), "--res", "0.2"])
    assert args.func(args) == 0
    ours = load(tmp_path / "o.bt")
    t = pyoctomap.OcTree(0.2)
    for s in scans:
        t.insertPointCloud(s.world_points().astype(np.float32).astype(np.float64), s.sensor_origin)
    t.writeBinary(str(tmp_path / "ref.bt"))
    ref = load(tmp_path / "ref.bt")
    occ = lambda m: set(m.leaves().codes[np.asarray(m.is_occupied())[: m.num_leaves]].tolist())
    agree = len(occ(ours) & occ(ref)) / len(occ(ours) | occ(ref))
    assert agree >= 0.99, agree
    with pytest.raises(Exception, match="must end in"):
        build_cli.run(parser.parse_args(["build", str(tmp_path / "s.graph"), str(tmp_path / "o.txt")]))
