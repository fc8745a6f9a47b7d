"""The live viewer (``octomerge_jax.viewer``, ``octomerge view``): scene data on the host, and
the page rendered by headless Chromium with pixels checked (skipped, with the reason, where no
Chromium is installed; ``.ci/run`` installs Debian's ``chromium``)."""

from __future__ import annotations

import io
import json

import numpy as np
import pytest

import octomerge_jax as om
from octomerge_jax.cli import main
from octomerge_jax.viewer import MAP_COLORS, height_colors, voxel_boxes

from browser import Browser, find_chromium


@pytest.fixture(scope="module")
def room():
    return om.example_map()


def test_voxel_boxes_are_the_occupied_leaves(room):
    lv = room.leaves()
    occ = lv.log_odds > room.params.occupancy_threshold_log_odds
    b = voxel_boxes(room)
    assert b.coarsened == 0
    np.testing.assert_allclose(b.centers, lv.centers[occ], atol=1e-6)
    np.testing.assert_allclose(b.sizes, lv.sizes[occ], atol=1e-7)
    free = voxel_boxes(room, occupied=False)
    assert len(free.sizes) == int((~occ).sum())


def test_voxel_boxes_coarsen_to_the_budget_and_cover_every_leaf(room):
    full = voxel_boxes(room)
    b = voxel_boxes(room, max_boxes=len(full.sizes) // 5)
    assert b.coarsened >= 1 and len(b.sizes) <= len(full.sizes) // 5
    # every occupied leaf centre lies inside some drawn cell
    lo, hi = b.centers - b.sizes[:, None] / 2, b.centers + b.sizes[:, None] / 2
    p = full.centers[:: max(1, len(full.centers) // 500)]
    inside = ((p[:, None, :] >= lo[None] - 1e-6) & (p[:, None, :] <= hi[None] + 1e-6)).all(-1).any(1)
    assert inside.all()
    with pytest.raises(ValueError, match="max_boxes"):
        voxel_boxes(room, max_boxes=0)


def test_height_colors_run_low_to_high():
    c = height_colors(np.array([0.0, 0.5, 1.0]), 0.0, 1.0)
    assert c.dtype == np.uint8 and c.shape == (3, 3)
    assert tuple(c[0]) == (68, 1, 84) and tuple(c[-1]) == (253, 231, 37)


def test_view_report_errors_name_the_file(tmp_path, room, capsys):
    pytest.importorskip("viser")
    om.save(room, tmp_path / "a.bt")
    bad = tmp_path / "r.json"
    bad.write_text(json.dumps({"T_1_2": [[1, 0], [0, 1]]}))
    assert main(["view", str(tmp_path / "a.bt"), str(tmp_path / "a.bt"), "--report", str(bad)]) == 1
    assert f"{bad}: T_1_2 is not a finite 4x4 matrix" in capsys.readouterr().err
    assert main(["view", str(tmp_path)]) == 1
    assert "is a directory" in capsys.readouterr().err


def _fractions(png: bytes) -> tuple[float, float]:
    """Shares of map 1's (teal, ``MAP_COLORS[0]``) and map 2's (orange, ``MAP_COLORS[1]``)
    pixels below the page's notices and panel, right of the axes gizmo. Shading changes
    brightness and tint, so pixels are told apart by channel order, not by exact colour."""
    from PIL import Image

    a = np.asarray(Image.open(io.BytesIO(png)).convert("RGB")).astype(np.int32)[210:-70, 70:]
    r, g, b = a[..., 0], a[..., 1], a[..., 2]
    teal = (g - r > 40) & (b - r > 40)
    orange = (r - b > 80) & (r > g + 20)
    return float(teal.mean()), float(orange.mean())


def test_browser_shows_the_voxels_and_the_map_toggle(room, tmp_path):
    pytest.importorskip("viser")
    pytest.importorskip("PIL")
    if find_chromium() is None:
        pytest.skip("Chromium not installed (apt install chromium; .ci/run installs it)")
    from octomerge_jax.viewer import view

    T = om.from_xyz_rpy(3.0, 0.5, 0.0, 0.0, 0.0, 0.6)
    v = view([room, room], transforms=[None, T], color_by="map")
    try:
        assert tuple(MAP_COLORS[0]) == (27, 158, 119) and tuple(MAP_COLORS[1]) == (217, 95, 2)
        with Browser() as b:
            b.open(v.url)
            png = b.screenshot(until=lambda p: min(_fractions(p)) > 0.01)
            (tmp_path / "both.png").write_bytes(png)
            teal, orange = _fractions(png)
            assert teal > 0.01, "map 1's voxels are not on the page"
            assert orange > 0.01, "map 2's voxels are not on the page"
            v.frames[1].visible = False  # what the page's "map 2" toggle does
            png = b.screenshot(until=lambda p: _fractions(p)[1] < 0.0005, timeout_s=30)
            (tmp_path / "map1.png").write_bytes(png)
            teal, orange = _fractions(png)
            assert orange < 0.0005, "map 2 still drawn after hiding it"
            assert teal > 0.01
    finally:
        v.close()
