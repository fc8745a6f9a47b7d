"""Export of voxels as meshes/points, and ``octomerge export``."""

from __future__ import annotations

import argparse

import numpy as np
import pytest
import trimesh

from octomerge_jax import morton
from octomerge_jax.io.export import export_map, voxel_mesh, voxel_points
from octomerge_jax.map import from_leaves


@pytest.fixture
def small_map():
    keys = np.array([[32768, 32768, 32768], [32770, 32768, 32768], [32776, 32768, 32768]], np.uint16)
    codes = morton.keys_to_codes(keys)
    return from_leaves(codes, [16, 16, 13], [2.0, -1.0, 1.0], 0.1)


def test_voxel_mesh_geometry(small_map):
    mesh = voxel_mesh(small_map)  # occupied: two leaves (one 0.1 m voxel, one 0.8 m node)
    assert len(mesh.faces) == 24
    assert mesh.is_watertight
    np.testing.assert_allclose(mesh.volume, 0.1 ** 3 + 0.8 ** 3, rtol=1e-9)
    np.testing.assert_allclose(mesh.bounds, [[0.0, 0.0, 0.0], [1.6, 0.8, 0.8]], atol=1e-12)
    everything = voxel_mesh(small_map, which="all", color_by="occupancy")
    assert len(everything.faces) == 36
    cols = everything.visual.face_colors[::12]
    assert cols[0, 0] > cols[1, 0]  # more certain = redder
    pts = voxel_points(small_map)
    np.testing.assert_allclose(np.sort(pts.vertices[:, 0]), [0.05, 1.2], atol=1e-12)


@pytest.mark.parametrize("ext", [".ply", ".glb", ".obj"])
def test_export_files_round_trip(small_map, tmp_path, ext):
    path = tmp_path / f"m{ext}"
    export_map(small_map, path)
    back = trimesh.load(path, force="mesh")
    np.testing.assert_allclose(back.bounds, [[0.0, 0.0, 0.0], [1.6, 0.8, 0.8]], atol=1e-6)


def test_export_errors(small_map, tmp_path):
    with pytest.raises(ValueError, match="unsupported"):
        export_map(small_map, tmp_path / "m.stl")
    with pytest.raises(ValueError, match="color_by"):
        export_map(small_map, tmp_path / "m.ply", color_by="rainbow")
    with pytest.raises(ValueError, match=".ply"):
        export_map(small_map, tmp_path / "m.glb", points=True)


def test_export_cli(small_map, tmp_path):
    from octomerge_jax.cli import export as export_cli
    from octomerge_jax.io import save

    save(small_map, tmp_path / "m.bt")
    parser = argparse.ArgumentParser()
    export_cli.register(parser.add_subparsers())
    args = parser.parse_args(["export", str(tmp_path / "m.bt"), str(tmp_path / "m.glb")])
    assert args.func(args) == 0
    assert len(trimesh.load(tmp_path / "m.glb", force="mesh").faces) == 24
    from octomerge_jax.cli import CliError

    args = parser.parse_args(["export", str(tmp_path / "m.bt"), str(tmp_path / "m.bt")])
    with pytest.raises(CliError, match="OUT must end in"):  # never over the input map
        args.func(args)
