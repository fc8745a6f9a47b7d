"""Point clouds and poses for other tools: ``.pcd`` read back by an independent PCD reader,
``.ply`` by trimesh, TUM poses by NumPy + SciPy, and ``octomerge export`` for each."""

from __future__ import annotations

import json

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

import octomerge_jax as om
from octomerge_jax import se3
from octomerge_jax.cli import main
from octomerge_jax.io.export import export_map, pcd_bytes, write_tum


def read_pcd(data: bytes):
    """A minimal PCD v0.7 reader written from PCL's format description (not ours): header
    lines up to DATA, then ascii rows or packed little-endian records."""
    head, fields = {}, None
    pos = 0
    while True:
        end = data.index(b"\n", pos)
        line = data[pos:end].decode()
        pos = end + 1
        if line.startswith("#"):
            continue
        key, *vals = line.split()
        head[key] = vals
        if key == "DATA":
            break
    fields = head["FIELDS"]
    kinds = {("F", "4"): "<f4", ("U", "4"): "<u4", ("F", "8"): "<f8", ("I", "4"): "<i4"}
    dt = np.dtype([(f, kinds[(t, s)]) for f, t, s in zip(fields, head["TYPE"], head["SIZE"])])
    n = int(head["POINTS"][0])
    assert int(head["WIDTH"][0]) * int(head["HEIGHT"][0]) == n
    if head["DATA"][0] == "binary":
        assert len(data) - pos == n * dt.itemsize
        return np.frombuffer(data, dt, count=n, offset=pos)
    rows = [r.split() for r in data[pos:].decode().splitlines() if r.strip()]
    out = np.zeros(n, dt)
    for j, f in enumerate(fields):
        out[f] = [float(r[j]) if dt[f].kind == "f" else int(r[j]) for r in rows]
    return out


@pytest.fixture(scope="module")
def room():
    m = om.example_map()
    L = m.leaves()
    occ = np.asarray(m.is_occupied())[: m.num_leaves]
    return m, L.centers[occ]


@pytest.mark.parametrize("ascii", [False, True])
def test_pcd_occupied_centres(room, tmp_path, ascii):
    m, centres = room
    path = tmp_path / "room.pcd"
    export_map(m, path, ascii=ascii)
    rec = read_pcd(path.read_bytes())
    got = np.stack([rec["x"], rec["y"], rec["z"]], axis=1)
    np.testing.assert_array_equal(got, centres.astype(np.float32))
    rgb = rec["rgb"].astype(np.uint32)
    r, b = rgb >> 16 & 255, rgb & 255
    low, high = np.argmin(centres[:, 2]), np.argmax(centres[:, 2])
    assert rgb.max() < 1 << 24 and (r[high], b[high]) != (r[low], b[low])  # viridis by height
    empty = read_pcd(pcd_bytes(np.zeros((0, 3)), ascii=ascii))
    assert len(empty) == 0 and empty.dtype.names == ("x", "y", "z")


def test_ply_points_read_by_trimesh(room, tmp_path):
    m, centres = room
    export_map(m, tmp_path / "room.ply", points=True)
    back = trimesh.load(tmp_path / "room.ply")
    assert isinstance(back, trimesh.PointCloud)
    np.testing.assert_allclose(back.vertices, centres, atol=1e-6)


def test_tum_round_trip(tmp_path):
    rng = np.random.default_rng(0)
    Ts = np.stack([se3.from_xyz_rpy(*rng.uniform(-5, 5, 3), *rng.uniform(-3, 3, 3), xp=np) for _ in range(5)])
    stamps = 1712345678.0 + np.arange(5) * 0.1
    write_tum(tmp_path / "p.tum", stamps, Ts)
    rows = np.loadtxt(tmp_path / "p.tum", comments="#")
    np.testing.assert_allclose(rows[:, 0], stamps, rtol=0, atol=1e-9)
    np.testing.assert_allclose(rows[:, 1:4], Ts[:, :3, 3], rtol=0, atol=1e-15)
    R = Rotation.from_quat(rows[:, 4:8]).as_matrix()  # scalar-last (x, y, z, w), as TUM
    np.testing.assert_allclose(R, Ts[:, :3, :3], atol=1e-14)
    assert np.all(rows[:, 7] >= 0)
    bad = Ts.copy()
    bad[2, 0, 0] = 2.0
    with pytest.raises(ValueError, match="transform 2"):
        write_tum(tmp_path / "b.tum", stamps, bad)
    with pytest.raises(ValueError, match="5 stamps but 4 transforms"):
        write_tum(tmp_path / "b.tum", stamps, Ts[:4])
    assert not (tmp_path / "b.tum").exists()


def test_export_cli_pcd_and_tum(room, tmp_path, capsys):
    m, centres = room
    om.save(m, tmp_path / "room.bt")
    assert main(["export", str(tmp_path / "room.bt"), str(tmp_path / "room.pcd"), "--ascii", "-q"]) == 0
    assert len(read_pcd((tmp_path / "room.pcd").read_bytes())) == len(centres)
    T = se3.from_xyz_rpy(1.5, -0.8, 0.0, 0.0, 0.0, 0.785, xp=np)
    (tmp_path / "r.json").write_text(json.dumps({"T_1_2": T.tolist(), "status": "converged"}))
    assert main(["export", str(tmp_path / "r.json"), str(tmp_path / "t.tum")]) == 0
    row = np.loadtxt(tmp_path / "t.tum", comments="#")
    assert row[0] == 0.0
    np.testing.assert_allclose(Rotation.from_quat(row[4:]).as_matrix(), T[:3, :3], atol=1e-14)
    capsys.readouterr()
    assert main(["export", str(tmp_path / "r.json"), str(tmp_path / "t.pcd")]) == 1
    assert main(["export", str(tmp_path / "room.bt"), str(tmp_path / "x.ply"), "--ascii"]) == 2
    (tmp_path / "bad.json").write_text("{}")
    assert main(["export", str(tmp_path / "bad.json"), str(tmp_path / "t2.tum")]) == 1
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 3 and "no T_1_2" in err[2], err
