"""correlation_search: the global step of refine="multi" (a yaw grid x every translation).

The scene is a corridor-like hall, 9 x 3 x 2 m with partitions and boxes, free inside (what
a ray-casting robot records); robot 1 maps x < 5.5 m, robot 2 maps x >= 3 m in its own frame,
so the maps overlap in a third of the hall. The guess is off by 1.7 rad of yaw about map 2's
origin and 1 m: the truth is metres from every hypothesis of the yaw grid.
"""

from __future__ import annotations

import math
import types
from functools import lru_cache

import numpy as np
import pytest

from octomerge_jax import registration as reg
from octomerge_jax import tree
from octomerge_jax.pipeline import MergeConfig, merge, merge_batch, transform_from_xyz_rpy
from octomerge_jax.pipeline.timings import Timings
from octomerge_jax.registration.correlation import _grid_len
from octomerge_jax.resample import transform_map

RES = 0.1
T_TRUE = transform_from_xyz_rpy(1.2, -0.7, 0.0, 0.0, 0.0, 0.6)


def _box_surface(lo, hi, res):
    axes = [np.arange(a + res / 2, b, res) for a, b in zip(lo, hi)]
    g = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    lo, hi = np.asarray(lo), np.asarray(hi)
    return g[np.any((g - lo < res) | (hi - g < res), axis=1)]


@lru_cache(maxsize=None)
def hall():
    """(occupied centres, free centres) of the hall in the world (= map 1) frame [m]."""
    occ = [_box_surface((0, 0, 0), (9.0, 3.0, 2.0), RES)]
    for lo, hi in [((1.0, 0.0, 0.0), (1.1, 1.8, 2.0)), ((2.5, 1.2, 0.0), (3.3, 2.0, 0.9)),
                   ((4.2, 0.0, 0.0), (4.3, 1.1, 2.0)), ((5.6, 2.1, 0.0), (6.4, 3.0, 1.3)),
                   ((7.1, 0.6, 0.0), (7.5, 1.5, 0.6)), ((8.0, 1.8, 0.0), (8.1, 3.0, 2.0))]:
        occ.append(_box_surface(lo, hi, RES))
    occ = np.unique(np.round(np.concatenate(occ) / RES - 0.5).astype(np.int64), axis=0)
    axes = [np.arange(0, 90), np.arange(0, 30), np.arange(0, 20)]
    cells = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    taken = np.zeros((90, 30, 20), bool)
    taken[tuple(occ.T)] = True
    free = cells[~taken[tuple(cells.T)]]
    return (occ + 0.5) * RES, (free + 0.5) * RES


def robot_map(x_lo, x_hi, T_world_map=None):
    occ, free = hall()
    o = occ[(occ[:, 0] >= x_lo) & (occ[:, 0] < x_hi)]
    f = free[(free[:, 0] >= x_lo) & (free[:, 0] < x_hi)]
    m = tree.from_voxels(np.concatenate([o, f]), np.concatenate(
        [np.full(len(o), 2.0, np.float32), np.full(len(f), -1.5, np.float32)]), RES)
    return m if T_world_map is None else transform_map(m, np.linalg.inv(T_world_map), "nearest")


@lru_cache(maxsize=None)
def pair():
    return robot_map(-1.0, 5.5), robot_map(3.0, 10.0, T_TRUE)


def bad_guess(yaw=1.7):
    """The truth turned by ``yaw`` about map 2's origin and moved 1 m."""
    return transform_from_xyz_rpy(0.8, 0.6, 0.0, 0.0, 0.0, 0.0) @ T_TRUE @ transform_from_xyz_rpy(
        0.0, 0.0, 0.0, 0.0, 0.0, yaw)


def _displacement(m2, T):
    p = np.asarray(reg.occupied_points(m2))
    return float(np.mean(np.asarray(reg.point_displacement(T, T_TRUE, p))))


@pytest.mark.parametrize("yaw", [1.7, -2.6])
def test_finds_the_pose_the_yaw_grid_starts_metres_from(yaw):
    m1, m2 = pair()
    G = bad_guess(yaw)
    center = G[:3, :3] @ np.asarray(reg.occupied_points(m2)).mean(0) + G[:3, 3]
    grid = np.asarray(reg.default_hypotheses(G, center), np.float64)
    assert min(_displacement(m2, T) for T in grid) > 1.0  # the need: no grid start is near

    r = reg.correlation_search(m1, m2, G)
    assert r.hypotheses.shape == (12, 4, 4) and r.scores.shape == (12,)
    assert np.all(np.diff(r.scores) <= 0)  # best first
    d = [_displacement(m2, T) for T in r.hypotheses]
    assert d[0] < 0.3, d[:4]  # the best one is within ~1 cell (0.2 m) of the truth
    assert float(reg.rotation_angle_error(r.hypotheses[0], T_TRUE)) < 0.05
    for T in r.hypotheses:
        reg.check_rigid(T)


def test_points_only_recover_a_shift_and_keep_the_guess_tilt():
    """With clouds (no free space) the score is surface overlap; a pure shift of the cloud
    is found to within a cell, and roll / pitch come from the guess."""
    occ, _ = hall()
    p1 = occ[occ[:, 0] < 6.0]
    shift = np.asarray([1.0, -0.4, 0.2])
    p2 = p1 - shift  # T_1_2 = translation by shift
    tilt = transform_from_xyz_rpy(0, 0, 0, 0.02, -0.01, 0.0)
    r = reg.correlation_search(p1, p2, tilt, cell=0.2, yaw_step_rad=2 * math.pi, num_hypotheses=3)
    assert np.linalg.norm(r.hypotheses[0, :3, 3] - shift) < 0.2 + 0.05  # tilt moves it a little
    np.testing.assert_allclose(r.hypotheses[0, :3, :3], tilt[:3, :3], atol=1e-9)
    r0 = reg.correlation_search(p1, p2, np.eye(4), cell=0.2, yaw_step_rad=2 * math.pi)
    np.testing.assert_allclose(r0.hypotheses[0, :3, 3], shift, atol=0.2 / 2 + 1e-6)


def test_bad_arguments_name_what_was_wrong():
    m1, m2 = pair()
    with pytest.raises(ValueError, match="T_1_2_init"):
        reg.correlation_search(m1, m2, np.ones((4, 4)))
    with pytest.raises(ValueError, match="source"):
        reg.correlation_search(m1, np.zeros((0, 3)), np.eye(4))
    with pytest.raises(ValueError, match="target"):
        reg.correlation_search(np.full((5, 3), np.nan), m2, np.eye(4))
    with pytest.raises(ValueError, match="cell"):
        reg.correlation_search(m1, m2, np.eye(4), cell=-1.0)
    with pytest.raises(ValueError, match="free_weight"):
        reg.correlation_search(m1, m2, np.eye(4), free_weight=-1.0)
    with pytest.raises(ValueError, match="resolutions differ"):
        reg.correlation_search(m1, tree.from_voxels(np.zeros((1, 3)), np.ones(1, np.float32), 0.2),
                               np.eye(4))


def test_grid_lengths_are_few_and_cover():
    lens = {_grid_len(n) for n in range(1, 600)}
    assert all(_grid_len(n) >= n for n in range(1, 600))
    assert all(_grid_len(n) <= 1.5 * n for n in range(1, 600))  # at most half again
    assert lens == {2 ** a for a in range(10)} | {3 * 2 ** a for a in range(9)}  # 19 shapes up to 768


# refine="multi" is no longer the default guess-free mode (refine="global", tests/test_global.py)
@pytest.mark.slow
def test_merge_multi_with_correlation_hypotheses_recovers_the_truth():
    """refine="multi" from the bad guess (no yaw-grid start within 1 m of the truth, see
    above; the yaw grid alone ends 3.2 m off: ICP slides the right yaw along the hall); from
    the correlation poses (ICP on the commonly mapped subsets from each) the merge lands on
    the truth, and merge_batch takes the same steps."""
    m1, m2 = pair()
    cfg = MergeConfig().replace(registration={"refine": "multi", "hypotheses": "correlation"})
    _, rep = merge(m1, m2, bad_guess(), config=cfg, T_1_2_true=T_TRUE)
    assert rep.displacement < 0.1, rep.displacement
    assert {"correlation", "icp_correlation", "dense_correlation"} <= set(rep.timings)
    rc = cfg.registration
    assert len(rep.icp["map_loss"]) == rc.correlation_hypotheses + rc.correlation_dense
    assert rep.icp["local"]["pick_origin"] in ("correlation+icp", "correlation+dense")
    # the point statistics describe the result whichever step made it (a dense-born pick has
    # none of its own: measured at its transform)
    assert rep.icp["num_inliers"] > 0 and 0 < rep.icp["rmse"] < 2 * RES, rep.icp
    assert "rmse" in rep.summary()
    (b,) = merge_batch([(m1, m2, bad_guess(), T_TRUE)], config=cfg)
    assert b.status == "ok", b.message
    np.testing.assert_allclose(b.report.T_1_2, rep.T_1_2, atol=1e-3)
    assert b.report.icp["rmse"] == pytest.approx(rep.icp["rmse"], rel=1e-3)


@pytest.mark.slow
def test_merge_multi_default_takes_both_sources():
    """refine="multi" with its default hypotheses ("both"): the yaw grid's and the correlation
    poses' candidates; from the bad guess (the yaw grid alone ends 3.2 m off on this hall) the
    correlation pick is taken and the merge lands on the truth."""
    m1, m2 = pair()
    assert MergeConfig().registration.hypotheses == "both"
    _, rep = merge(m1, m2, bad_guess(), refine="multi", T_1_2_true=T_TRUE)
    assert rep.displacement < 0.1, rep.displacement
    assert {"icp", "correlation", "icp_correlation"} <= set(rep.timings)
    loc = rep.icp["local"]
    assert loc["chosen"] == "far" and loc["pick_origin"].startswith("correlation"), loc
    assert loc["plausible_far"], loc
    r = rep.icp_result  # both sources' candidates in one result, every per-candidate field as long
    k = np.asarray(r.scores).shape[0]
    assert np.asarray(r.num_iterations_run).shape == np.asarray(r.basin).shape == (k,)
    assert np.asarray(r.candidates.num_iterations).shape == (k,)


@pytest.mark.parametrize("loss_near, loss_far, plausible, chosen", [
    (-0.29, -0.304, (True, True), "far"), (-0.271, -0.276, (True, True), "near"),
    (-0.30, -0.28, (True, True), "near"), (-0.30, -0.28, (False, False), "near"),
    (-0.19, -0.32, (True, False), "near"), (-0.32, -0.19, (False, True), "far")])
def test_both_sources_take_the_far_pick_only_by_the_margin(monkeypatch, loss_near, loss_far, plausible, chosen):
    """hypotheses="both": each group's pick gets its local step; a pick that passes the dense
    status checks (overlap, agreement) beats one that does not, whatever the losses (the
    simulated lab with a tilted guess: the pose turned by pi -0.32 / agreement 0.78, the yaw
    grid's -0.19 / 0.89 after its local step); else the correlation (far) pick wins only
    when its map loss is lower by more than far_margin (3 %) of the near one's (the hall:
    -0.304 vs -0.291, far; the simulated lab: a wrong pose -0.276 vs -0.271)."""
    from octomerge_jax.pipeline import ranking as pl

    class Pose:
        def __init__(self, i):
            self.T_target_source = i

    class Picked:
        def __init__(self, i):
            self.best, self.best_index = Pose(i), np.int32(i)

    losses = np.asarray([loss_near, 0.0, loss_far, 0.0])
    monkeypatch.setattr(reg, "prepare_alignment", lambda m1, m2: None)

    def rank(m1, m2, result, *, problem=None, among=None):
        i = int(np.argmin(np.where(among, losses, np.inf)))
        return Picked(i), losses

    monkeypatch.setattr(pl, "rank_by_map_agreement", rank)
    monkeypatch.setattr(pl, "scores_and_plausible", lambda problem, ids: (
        losses[list(ids)], np.asarray([plausible[i // 2] for i in ids])))
    monkeypatch.setattr(pl, "local_step",
                        lambda p1, p2, pick, *a: (f"local from {pick.T_target_source}", {"used": False}))
    near = np.asarray([True, True, False, False])
    m = types.SimpleNamespace(resolution=RES)
    r, _, local, info = pl.rank_and_refine(m, m, None, None, None, near, MergeConfig(), {}, Timings())
    assert info["chosen"] == chosen
    assert int(r.best_index) == (2 if chosen == "far" else 0) and local == f"local from {r.best_index}"
    assert info["loss_near"] == pytest.approx(loss_near) and info["loss_far"] == pytest.approx(loss_far)


def test_cli_flag_selects_the_hypotheses():
    from octomerge_jax.cli import build_parser
    from octomerge_jax.cli.merge import config_from_args

    args = build_parser().parse_args(["merge", "a.bt", "b.bt", "out.bt", "--refine", "multi",
                                      "--hypotheses", "correlation"])
    rc = config_from_args(args).registration
    assert (rc.refine, rc.hypotheses) == ("multi", "correlation")
    default = config_from_args(build_parser().parse_args(["merge", "a.bt", "b.bt", "o.bt"])).registration
    assert default.hypotheses == "both"
    grid = build_parser().parse_args(["merge", "a.bt", "b.bt", "o.bt", "--hypotheses", "yaw_grid"])
    assert config_from_args(grid).registration.hypotheses == "yaw_grid"
    with pytest.raises(SystemExit):
        build_parser().parse_args(["merge", "a.bt", "b.bt", "o.bt", "--hypotheses", "ransac"])
    with pytest.raises(ValueError, match="registration.hypotheses"):
        MergeConfig().replace(registration={"hypotheses": "ransac"})


def test_local_candidates_keep_one_row_per_pose_and_mark_poses_without_overlap():
    """A correlation pose with too little common space keeps its row (status too few inliers,
    so ranking cannot pick it): rows stay aligned with the hypotheses they came from."""
    from octomerge_jax.pipeline.candidates import local_candidates
    from octomerge_jax.pipeline.clouds import icp_kwargs

    m1, m2 = pair()
    p1 = np.asarray(reg.occupied_points(m1), np.float32)
    p2 = np.asarray(reg.occupied_points(m2), np.float32)
    far = T_TRUE.copy()
    far[:3, 3] += (200.0, 0.0, 0.0)
    cfg = MergeConfig()
    r = local_candidates(p1, p2, np.stack([far, T_TRUE]), cfg, RES, icp_kwargs(cfg, RES), Timings())
    assert np.asarray(r.candidates.status).tolist()[0] == 2 and int(r.candidates.status[1]) in (0, 1)
    np.testing.assert_allclose(r.candidates.T_target_source[0], far, atol=1e-5)
    assert int(r.best_index) == 1 and r.hypotheses.shape == (2, 4, 4)


def test_a_tilted_guess_is_also_searched_level():
    """``refine="multi"``'s search turns the guess about +z, keeping its roll and pitch; a guess
    tilted by more than 0.02 rad is also searched level (its yaw and translation kept), for
    z-up maps whose guess carries a tilt error."""
    from octomerge_jax.pipeline.candidates import search_tilts

    flat = transform_from_xyz_rpy(1.0, -2.0, 0.3, 0.0, 0.0, -2.6)
    (only,) = search_tilts(flat)
    np.testing.assert_array_equal(only, flat)
    assert len(search_tilts(transform_from_xyz_rpy(0, 0, 0, 0.01, -0.01, 1.0))) == 1  # 0.014 rad
    tilted = transform_from_xyz_rpy(1.0, -2.0, 0.3, 0.05, 0.1, -2.6)
    same, level = search_tilts(tilted)
    np.testing.assert_array_equal(same, tilted)
    np.testing.assert_allclose(level, flat, atol=1e-12)
    reg.check_rigid(level)


@pytest.mark.slow
def test_merge_multi_from_a_tilted_far_guess(tmp_path):
    """The simulated lab read back from ``.bt``, guesses turned by -2.6 / 2.8 rad, tilted by
    0.11 / 0.12 rad and 1.6-1.8 m off: the search at the guess's tilt cannot reach the truth
    and the yaw grid's ICP ends turned by pi (6.6 m off before the level search); with it the
    merge lands on the truth."""
    from octomerge_jax.io import load, save
    from octomerge_jax.sim import make_two_robot_maps

    m1, m2, T = make_two_robot_maps("lab", 0.05)
    save(m1, tmp_path / "a.bt")
    save(m2, tmp_path / "b.bt")
    m1, m2 = load(tmp_path / "a.bt"), load(tmp_path / "b.bt")
    for off, rpy in (((1.5, 1.0, 0.0), (0.05, 0.1, -2.6)), ((0.5, -1.5, 0.3), (0.0, -0.12, 2.8))):
        guess = transform_from_xyz_rpy(*off, *rpy) @ T
        _, rep = merge(m1, m2, guess, refine="multi", T_1_2_true=T)
        assert rep.displacement_init > 5.0 and rep.displacement < 0.05, (rpy, rep.displacement, rep.icp["local"])
