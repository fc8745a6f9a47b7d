"""merge_many without guesses on simulated teams (slow: guess-free pairwise registrations),
the descriptor pre-screen, ManyReport's TUM / JSON output, and the merge-many command's input
checks (cheap)."""

from __future__ import annotations

import numpy as np
import pytest

from octomerge_jax.registration import rotation_angle_error, translation_distance
from octomerge_jax.cli import main
from octomerge_jax.pipeline import ManyReport, MapReport, merge_many
from octomerge_jax.pipeline.many_report import tum_lines
from octomerge_jax.pipeline.pairs import alignment_information, more_pairs, screen_pairs
from octomerge_jax.sim import small_room_map, team_maps, tile_grid
from octomerge_jax import se3


def test_tile_grid_and_screen_pairs_cost():
    tiles = tile_grid([[0, 0], [16, 8]], 8, 1.0)
    assert tiles.shape == (8, 2, 2)
    np.testing.assert_allclose(tiles[0], [[-1, -1], [5, 5]])  # 4 x 2 cells of 4 m, grown by 1 m
    maps = [small_room_map((x, x + 2.0), 0.2) for x in (-1.0, 0.5, 2.0)]
    pairs, sim = screen_pairs(maps, 1, all_below=7)
    assert pairs == [(0, 1), (0, 2), (1, 2)] and sim.shape == (3, 3)  # few maps: every pair
    pairs, _ = screen_pairs(maps, 1, all_below=2)  # each map's most similar one only
    assert 2 <= len(pairs) <= 3 and all(i < j for i, j in pairs)
    np.testing.assert_allclose(np.diag(sim), 1.0)


def test_more_pairs_offers_an_unplaced_maps_next_most_similar_maps():
    sim = np.array([[1.0, 0.9, 0.5, 0.1],
                    [0.9, 1.0, 0.2, 0.3],
                    [0.5, 0.2, 1.0, 0.8],
                    [0.1, 0.3, 0.8, 1.0]])
    # map 3 tried with 2 already: its next are 1, then 0
    assert more_pairs(sim, [3], [(2, 3), (0, 1)], 1) == [(1, 3)]
    assert more_pairs(sim, [3], [(2, 3), (0, 1)], 2) == [(0, 3), (1, 3)]
    assert more_pairs(sim, [2, 3], [(2, 3), (3, 1)], 1) == [(0, 2), (0, 3)]
    assert more_pairs(sim, [3], [(0, 3), (1, 3), (2, 3)], 4) == []  # every pair of it tried
    assert more_pairs(sim, [], [], 4) == []


def test_alignment_information_is_the_point_to_point_hessian():
    rng = np.random.default_rng(0)
    p = rng.uniform(-2, 2, (200, 3))
    T = se3.from_xyz_rpy(0.3, -0.2, 0.1, 0.0, 0.0, 0.4, xp=np)
    q = p @ T[:3, :3].T + T[:3, 3]
    Omega, n = alignment_information(q, p, T, 0.05, sigma_m=0.1)
    assert n == 200
    H = np.zeros((6, 6))
    for x in p:  # brute force: J = [I, -[p]x] per point, right perturbation
        J = np.hstack([np.eye(3), -se3.skew(x, xp=np)])
        H += J.T @ J
    np.testing.assert_allclose(Omega, H / (200 * 0.1 ** 2), rtol=1e-5, atol=1e-6)
    # no points on a side (a registration that found no common region): no information, no error
    for a, b in ((q, p[:0]), (q[:0], p)):
        Omega, n = alignment_information(a, b, T, 0.05, sigma_m=0.1)
        assert n == 0 and not Omega.any()


def test_tum_and_json_of_a_report(tmp_path):
    T1 = se3.from_xyz_rpy(1.0, 2.0, 0.5, 0.0, 0.0, np.pi / 2, xp=np)
    lines = tum_lines([np.eye(4), None, T1])
    assert len(lines) == 2
    vals = [float(v) for v in lines[1].split()]
    assert vals[0] == 2.0 and vals[1:4] == [1.0, 2.0, 0.5]
    np.testing.assert_allclose(vals[4:], [0, 0, np.sin(np.pi / 4), np.cos(np.pi / 4)], atol=1e-9)  # x y z w
    maps = tuple(MapReport(k, s, T, None, None, None, (), 10) for k, (s, T) in
                 enumerate([("root", np.eye(4)), ("unplaced", None), ("placed", T1)]))
    rep = ManyReport(transforms=(np.eye(4), None, T1), maps=maps, edges=(), figures={}, timings={}, resolution=0.1)
    assert rep.placed.tolist() == [True, False, True] and len(rep) == 0
    assert '"transforms"' in rep.to_json(tmp_path / "r.json") and (tmp_path / "r.json").exists()


def test_merge_many_command_input_errors(tmp_path, capsys):
    a = tmp_path / "a.bt"
    a.write_bytes(b"")
    assert main(["merge-many", str(tmp_path / "o.bt"), str(a)]) == 2
    assert main(["merge-many", str(tmp_path / "o.bt"), str(a), str(tmp_path / "missing.bt")]) == 1
    assert main(["merge-many", str(tmp_path / "o.txt"), str(a), str(a)]) == 1
    assert main(["merge-many", str(a), str(a), str(a)]) == 1  # OUT is an input
    err = capsys.readouterr().err
    assert "missing.bt: no such file" in err and "must end in .bt or .ot" in err and "also an input" in err


@pytest.mark.slow  # N guess-free registrations of every pair: minutes on 2 cores
@pytest.mark.parametrize("scene, n, resolution", [
    # the office floor is nearly symmetric under a half turn and its corridor repeats: two pairs'
    # best poses are wrong (one called "ok"), the right ones are among their candidates, and the
    # other pairs' agreement picks them (consensus.choose_candidates)
    ("office", 4, 0.2),
    ("campus", 5, 0.5)])
def test_team_without_guesses(scene, n, resolution):
    """N robots in random frames (fixed seed): every transform within a voxel and 0.01 rad of the
    truth, every pairwise result either kept or rejected with a reason."""
    team = team_maps(scene, n, resolution, seed=0, overlap_m=3.0 if scene == "office" else 10.0)
    merged, rep = merge_many(list(team.maps), T_trues=list(team.T_0_k[1:]))
    assert rep.placed.all(), rep.summary()
    for k in range(1, n):
        r = float(rotation_angle_error(rep.transforms[k], team.T_0_k[k]))
        t = float(translation_distance(rep.transforms[k], team.T_0_k[k]))
        assert r < 0.01 and t < resolution, (k, r, t, rep.summary())
    assert all(e.kept or e.why for e in rep.edges)
    assert merged.num_leaves > max(m.num_leaves for m in team.maps)
