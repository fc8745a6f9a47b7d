"""ROS bags: Octomap maps round-tripped through ROS 1 / ROS 2 (sqlite3, MCAP) bags written by
rosbags, PointCloud2 scans placed by Odometry / PoseStamped / tf, malformed bags, and the CLI
(info / convert / merge / build with bags)."""

from __future__ import annotations

import math

import numpy as np
import pytest

import octomerge_jax as om
from octomerge_jax import se3
from octomerge_jax.cli import main
from octomerge_jax.io import MapFormatError, to_bytes
from octomerge_jax.io.bags import (BagError, TransformBuffer, decode_point_cloud2, read_bag, read_bag_scans,
                                   select_map, write_bag)
from octomerge_jax.io.bags.scans import nearest
from octomerge_jax.io.scans import Scan

pytest.importorskip("rosbags")
from bagtools import KINDS, BagWriter, bag_path  # noqa: E402

S = 1_000_000_000  # ns per s


def same_leaves(a, b):
    la, lb = a.leaves(), b.leaves()
    return (np.array_equal(la.codes, lb.codes) and np.array_equal(la.depths, lb.depths)
            and np.array_equal(la.log_odds, lb.log_odds))


@pytest.fixture(scope="module")
def room(tmp_path_factory):
    d = tmp_path_factory.mktemp("room")
    m = om.example_map()
    om.save(m, d / "room.bt")
    om.save(m, d / "room.ot")
    return m, om.load(d / "room.bt"), om.load(d / "room.ot"), d


@pytest.mark.parametrize("kind", KINDS)
def test_map_round_trip(room, tmp_path, kind):
    m, bt, ot, d = room
    for binary, ref, file in ((True, bt, d / "room.bt"), (False, ot, d / "room.ot")):
        path = bag_path(tmp_path, kind, f"m{int(binary)}")
        write_bag(path, [m, m], binary=binary, frame_id="world", stamps_ns=[5 * S + 7, 6 * S],
                  storage=None if kind == "ros1" else kind)
        maps = list(read_bag(path))
        assert [b.stamp_ns for b in maps] == [5 * S + 7, 6 * S]
        assert {(b.frame_id, b.topic, b.binary, b.tree_id) for b in maps} == \
            {("world", "/octomap_binary" if binary else "/octomap_full", binary, "OcTree")}
        body = to_bytes(m, binary=binary)
        assert file.read_bytes().endswith(body) and maps[0].payload_bytes == len(body)
        assert all(same_leaves(b.map, ref) for b in maps)  # bit-identical to the file's leaves
        assert select_map(path).stamp_ns == 6 * S
        assert select_map(path, stamp=5.9).stamp_ns == 5 * S + 7
        assert select_map(path, stamp=6.0).stamp_ns == 6 * S
        with pytest.raises(BagError, match=r"at or before --stamp 5\.000000000 s \(2 maps from 5\.000000007"):
            select_map(path, stamp=5.0)
        with pytest.raises(BagError, match="not a finite time"):
            select_map(path, stamp=math.nan)
        with pytest.raises(BagError, match=r"no topic /x in the bag \(topics: /octomap_"):
            select_map(path, "/x")
    if kind != "ros1":  # a ROS 2 bag's storage file opens the bag folder
        (f,) = [p for p in path.iterdir() if p.suffix in (".db3", ".mcap")]
        assert same_leaves(select_map(f).map, ot)


def test_topics_and_bad_payloads(room, tmp_path):
    m, bt, _, _ = room
    path = tmp_path / "two.bag"
    with BagWriter(path, "ros1") as w:
        Octomap = w.T("octomap_msgs/msg/Octomap")
        good = np.frombuffer(to_bytes(m), np.int8)
        for topic, data in (("/a", good), ("/b", good[:-5])):
            w.write(topic, "octomap_msgs/msg/Octomap", Octomap(header=w.header(3 * S, "map"), binary=True, id="OcTree",
                                                               resolution=0.1, data=data), 3 * S)
        w.write("/odom", "nav_msgs/msg/Odometry", w.odometry(np.eye(4), 3 * S), 3 * S)
    with pytest.raises(BagError, match="several octomap_msgs/Octomap topics"):
        select_map(path)
    assert same_leaves(select_map(path, "/a").map, bt)
    with pytest.raises(MapFormatError, match=r"two.bag /b @ 3\.000000000 s"):
        select_map(path, "/b")
    with pytest.raises(BagError, match="topic /odom carries nav_msgs/Odometry, not octomap_msgs/Octomap"):
        select_map(path, "/odom")


def test_malformed_bags(room, tmp_path, capsys):
    m = room[0]
    ok = tmp_path / "ok.bag"
    write_bag(ok, m)
    (tmp_path / "junk.bag").write_bytes(b"#ROSBAG V2.0\n" + bytes(range(256)) * 4)
    (tmp_path / "cut.bag").write_bytes(ok.read_bytes()[: ok.stat().st_size // 2])
    r2 = tmp_path / "r2"
    write_bag(r2, m, storage="sqlite3")
    (r2 / "metadata.yaml").write_text("rosbag2_bagfile_information: [\n")
    for bad in ("junk.bag", "cut.bag", "r2", "missing.bag"):
        assert main(["info", str(tmp_path / bad)]) == 1
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and err.startswith(f"octomerge info: error: {tmp_path / bad}"), err
    for args, code, text in ((["--topic", "/nope"], 1, "no topic /nope"), (["--stamp", "1"], 1, "at or before"),
                             (["--stamp", "nan"], 1, "not a finite time"), (["--stamp", "x"], 2, "invalid float")):
        assert main(["info", str(ok), *args]) == code if code == 1 else True
        if code == 2:
            with pytest.raises(SystemExit) as e:
                main(["info", str(ok), *args])
            assert e.value.code == 2
        err = capsys.readouterr().err
        assert text in err


def test_point_cloud2_layouts(tmp_path):
    rng = np.random.default_rng(0)
    pts = rng.uniform(-5, 5, (40, 3))
    with BagWriter(tmp_path / "c.bag", "ros1") as w:
        for kw in ({}, {"dtype": ">f8", "row_pad": 3, "nan_rows": 2}, {"extra_field": False, "dtype": "<f8"}):
            msg = w.cloud(pts, S, "lidar", **kw)
            got = decode_point_cloud2(msg)
            dt = np.dtype(kw.get("dtype", "<f4"))
            np.testing.assert_array_equal(got, pts.astype(dt).astype(np.float64))
        msg.fields = msg.fields[:1]
        with pytest.raises(BagError, match="no 'y' field"):
            decode_point_cloud2(msg, "cloud 3")


def test_transform_buffer_chain():
    rng = np.random.default_rng(1)
    Ts = [se3.from_xyz_rpy(*rng.uniform(-1, 1, 6), xp=np) for _ in range(4)]
    tf = TransformBuffer()
    tf.add("map", "odom", 0, Ts[0], static=True)
    for k in range(3):
        tf.add("odom", "base", k * S, Ts[1] @ se3.from_xyz_rpy(k, 0, 0, 0, 0, 0, xp=np))
    tf.add("base", "laser", 0, Ts[2], static=True)
    tf.add("base", "camera", 0, Ts[3], static=True)
    T_odom_base = Ts[1] @ se3.from_xyz_rpy(1, 0, 0, 0, 0, 0, xp=np)
    np.testing.assert_allclose(tf.lookup("map", "laser", S + S // 10, S // 5), Ts[0] @ T_odom_base @ Ts[2], atol=1e-12)
    np.testing.assert_allclose(tf.lookup("camera", "laser", 5 * S, 0), np.linalg.inv(Ts[3]) @ Ts[2], atol=1e-12)
    assert tf.lookup("map", "laser", S // 2 + 1, S // 10) is None  # no base sample within 0.1 s
    assert tf.root_of("camera") == "map"
    stamps = np.array([10, 20, 30])
    assert [nearest(stamps, t) for t in (0, 14, 15, 16, 25, 99)] == [0, 0, 0, 1, 1, 2]
    with pytest.raises(BagError, match="does not connect frame laser to frame elsewhere"):
        tf.lookup("elsewhere", "laser", S, S)


def _scene(n_scans=4, n_points=300, seed=0):
    """Scans of a 6 x 4 x 2.5 m box: ``(clouds in the sensor frame (float32), T_odom_base (n, 4, 4),
    T_base_sensor)``."""
    rng = np.random.default_rng(seed)
    lo, hi = np.array([-3.0, -2.0, 0.0]), np.array([3.0, 2.0, 2.5])
    T_base_sensor = se3.from_xyz_rpy(0.2, 0.0, 0.4, 0.0, 0.1, 0.0, xp=np)
    poses, clouds = [], []
    for i in range(n_scans):
        T_ob = se3.from_xyz_rpy(-1.0 + 0.6 * i, 0.3 * np.sin(i), 0.0, 0.0, 0.0, 0.4 * i, xp=np)
        world = rng.uniform(lo, hi, (n_points, 3))
        axis = rng.integers(0, 3, n_points)
        world[np.arange(n_points), axis] = np.where(rng.random(n_points) < 0.5, lo[axis], hi[axis])
        T_ws = T_ob @ T_base_sensor
        clouds.append(((world - T_ws[:3, 3]) @ T_ws[:3, :3]).astype(np.float32))
        poses.append(T_ob)
    return clouds, np.stack(poses), T_base_sensor


def _as_read(T):
    """``T`` as it comes back from a message (quaternion + translation in float64)."""
    return np.asarray(se3.from_quaternion(np.asarray(se3.to_quaternion(T, xp=np)), T[:3, 3], xp=np))


def _reference(clouds, T_world_sensors, res=0.2):
    scans = [Scan(c.astype(np.float64), T) for c, T in zip(clouds, T_world_sensors)]
    return om.insert_point_clouds(om.empty(res), [s.world_points().astype(np.float32) for s in scans],
                                  np.array([s.sensor_origin for s in scans]), -1.0)


def _scan_bag(tmp_path, kind, source):
    """A bag of ``_scene``'s clouds on /points (frame laser, two NaN points each, a fifth cloud
    long after the last pose) with their poses as ``source`` says; returns ``(path, pose topic,
    T_world_sensor as read back (4, 4, 4), clouds)``."""
    clouds, T_ob, T_bs = _scene()
    path = bag_path(tmp_path, kind)
    with BagWriter(path, kind) as w:
        w.write("/tf_static", "tf2_msgs/msg/TFMessage", w.tf([("base_link", "laser", T_bs, 0)]), S)
        for i, (c, T) in enumerate(zip(clouds, T_ob)):
            t = (10 + i) * S
            if source == "odometry":  # 20 ms late: nearest stamp within the 50 ms default
                w.write("/odom", "nav_msgs/msg/Odometry", w.odometry(T, t + 20_000_000), t + 20_000_000)
            elif source == "pose_stamped":
                w.write("/pose", "geometry_msgs/msg/PoseStamped", w.pose_stamped(T @ T_bs, t), t)
            else:
                w.write("/tf", "tf2_msgs/msg/TFMessage", w.tf([("odom", "base_link", T, t - 10_000_000)]), t)
            w.write("/points", "sensor_msgs/msg/PointCloud2", w.cloud(c, t, "laser", nan_rows=2), t)
        w.write("/points", "sensor_msgs/msg/PointCloud2", w.cloud(clouds[0], 20 * S, "laser"), 20 * S)
    if source == "pose_stamped":
        T_ws = [_as_read(T @ T_bs) for T in T_ob]
    else:
        T_ws = [_as_read(T) @ _as_read(T_bs) for T in T_ob]
    return path, {"odometry": "/odom", "pose_stamped": "/pose", "tf": None}[source], np.stack(T_ws), clouds


@pytest.mark.parametrize("kind,source", [("ros1", "odometry"), ("mcap", "pose_stamped"), ("sqlite3", "tf")])
def test_scans_from_bag(tmp_path, kind, source):
    path, pose_topic, T_ws, clouds = _scan_bag(tmp_path, kind, source)
    got = read_bag_scans(path, "/points", pose_topic)
    assert got.skipped == 1 and len(got.scans) == 4 and got.stamps_ns.tolist() == [(10 + i) * S for i in range(4)]
    assert got.fixed_frame == ("map" if source == "pose_stamped" else "odom")
    for s, T, c in zip(got.scans, T_ws, clouds):
        np.testing.assert_array_equal(s.pose, T)  # the same float64 products as the reference
        np.testing.assert_array_equal(s.points, c.astype(np.float64))  # NaN rows dropped
    if source == "tf":  # nothing within 5 ms: every cloud skipped -> one-line error
        with pytest.raises(BagError, match=r"none of the 5 clouds on /points has a pose on /tf within "
                                           r"--max-pose-gap 0\.005"):
            read_bag_scans(path, "/points", max_gap_s=0.005)
        with pytest.raises(BagError, match="topic /tf_static carries tf2_msgs/TFMessage, not sensor_msgs/PointCloud2"):
            read_bag_scans(path, "/tf_static")
        with pytest.raises(BagError, match="does not connect frame laser to frame world"):
            read_bag_scans(path, "/points", fixed_frame="world")


@pytest.mark.slow
@pytest.mark.parametrize("kind,source", [("ros1", "odometry"), ("sqlite3", "tf")])
def test_build_from_bag_cli(tmp_path, kind, source):
    """``octomerge build BAG`` writes the .bt that inserting the same scans at the same poses
    writes (insertion compiles for ~30 s on 2 cores, hence slow)."""
    path, pose_topic, T_ws, clouds = _scan_bag(tmp_path, kind, source)
    out = tmp_path / "built.bt"
    args = ["build", str(path), str(out), "--res", "0.2", "--cloud-topic", "/points", "-q"]
    assert main(args + (["--pose-topic", pose_topic] if pose_topic else [])) == 0
    om.save(_reference(clouds, T_ws), tmp_path / "ref.bt")
    assert (tmp_path / "ref.bt").read_bytes() == out.read_bytes()


def test_written_bags_as_ros_tools_see_them(room, tmp_path):
    """Without rosbags' reader: the ROS 1 connection header names octomap_msgs/Octomap with the
    md5sum rosmsg gives, and the ROS 2 sqlite3 bag's tables (what ros2 bag reads) hold the type and
    a CDR message whose int8[] is the .bt body."""
    import sqlite3

    m = room[0]
    body = to_bytes(m)
    write_bag(tmp_path / "a.bag", m)
    raw = (tmp_path / "a.bag").read_bytes()
    assert raw.startswith(b"#ROSBAG V2.0\n") and b"type=octomap_msgs/Octomap" in raw
    assert b"md5sum=9a45536b45c5e409cd49f04bb2d9999f" in raw and body in raw
    write_bag(tmp_path / "b", m, storage="sqlite3", frame_id="map", stamps_ns=[3 * S])
    with sqlite3.connect(tmp_path / "b" / "b.db3") as db:
        (name, typ, fmt), = db.execute("select name, type, serialization_format from topics")
        (t, blob), = db.execute("select timestamp, data from messages")
    assert (name, typ, fmt, t) == ("/octomap_binary", "octomap_msgs/msg/Octomap", "cdr", 3 * S)
    n = len(body)
    assert blob[:4] == b"\x00\x01\x00\x00"  # CDR little-endian encapsulation
    assert blob[-n:] == body and int.from_bytes(blob[-n - 4:-n], "little") == n  # int8[]: length + bytes
