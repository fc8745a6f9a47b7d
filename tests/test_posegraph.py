"""registration.posegraph: the robust pose-graph solve on synthetic measurements (no maps): a
wrong measurement is rejected and leaves the result unchanged, a loop whose spanning-tree
chaining accumulates error ends closer to the truth after the solve, an isolated node is
reported unplaced, and the covariance and priors behave."""

import numpy as np
import pytest

from octomerge_jax import se3
from octomerge_jax.registration.posegraph import cycle_chi2, make_graph, solve_pose_graph, solve_robust, \
    spanning_tree_poses, triangles

SIGMA_T, SIGMA_R = 0.05, 0.01  # [m], [rad]
INFO = np.diag([SIGMA_T ** -2] * 3 + [SIGMA_R ** -2] * 3)


def _truth(n, seed=3):
    rng = np.random.default_rng(seed)
    return np.stack([np.eye(4)] + [se3.from_xyz_rpy(*rng.uniform(-6, 6, 2), rng.uniform(-0.3, 0.3),
                                                     *rng.uniform(-0.05, 0.05, 2), rng.uniform(-np.pi, np.pi), xp=np)
                                    for _ in range(n - 1)])


def _measure(T, edges, rng, noise=(0.01, 0.002)):
    Z = []
    for a, b in edges:
        xi = np.concatenate([rng.normal(0, noise[0], 3), rng.normal(0, noise[1], 3)])
        Z.append(np.linalg.inv(T[a]) @ T[b] @ se3.se3_exp(xi, xp=np))
    return np.stack(Z)


def _errors(T_est, T_true):
    """(rotation angle [rad], translation [m]) of each pose against the truth."""
    d = np.linalg.inv(T_true) @ T_est
    ang = np.arccos(np.clip((np.trace(d[:, :3, :3], axis1=1, axis2=2) - 1) / 2, -1, 1))
    return ang, np.linalg.norm(d[:, :3, 3], axis=1)


# a ring with chords: every edge lies in at least one triangle
EDGES = [(0, 1), (1, 2), (2, 3), (3, 4), (4, 5), (5, 0), (0, 2), (1, 3), (2, 4), (3, 5), (4, 0)]


def _solve(edges, Z, **kw):
    info = np.broadcast_to(INFO, (len(edges), 6, 6))
    i, j = np.array(edges).T
    return solve_robust(6, i, j, Z, info, **kw)


def test_wrong_edge_rejected_and_result_unchanged():
    rng = np.random.default_rng(0)
    T = _truth(6)
    Z = _measure(T, EDGES, rng)
    wrong = EDGES.index((1, 3))
    Z_bad = Z.copy()
    Z_bad[wrong] = Z[wrong] @ se3.from_xyz_rpy(1.5, -0.8, 0.0, 0.0, 0.0, 0.7, xp=np)  # 1.7 m, 0.7 rad off
    clean = _solve(EDGES, Z)
    without = _solve(EDGES, Z, usable=np.arange(len(EDGES)) != wrong)
    bad = _solve(EDGES, Z_bad)
    assert clean.kept.all() and not any(clean.why), clean.why
    assert not bad.kept[wrong] and bad.why[wrong] == "cycle", bad.why
    assert bad.kept.sum() == len(EDGES) - 1
    # unchanged: the same poses as without the wrong edge, and as good as with the right one
    np.testing.assert_allclose(bad.T_0_k, without.T_0_k, atol=1e-6)
    ang_b, t_b = _errors(bad.T_0_k, T)
    ang_c, t_c = _errors(clean.T_0_k, T)
    assert ang_b.max() < 0.005 and t_b.max() < 0.03, (ang_b, t_b)
    assert abs(ang_b.max() - ang_c.max()) < 0.002 and abs(t_b.max() - t_c.max()) < 0.01
    assert bad.chi2[wrong] > 1e3 and bad.chi2[bad.kept].max() < 22.46
    # its triangles are the inconsistent ones
    assert np.all(bad.cycle_chi2[np.any(bad.cycles == wrong, axis=1)] > 1e3)


def test_wrong_edge_without_triangles_is_rejected_by_its_residual():
    rng = np.random.default_rng(1)
    T = _truth(5)
    edges = [(0, 1), (1, 2), (2, 3), (3, 4), (4, 0), (0, 2), (2, 4)]  # (1, 2) and (3, 4) close triangles,
    Z = _measure(T, edges, rng)
    # a second measurement of pair (0, 1), wrong: it closes no triangle (one edge per pair is checked)
    Z_bad = np.concatenate([Z, (Z[0] @ se3.from_xyz_rpy(0.0, 2.0, 0.0, 0.0, 0.0, -0.5, xp=np))[None]])
    i, j = np.array(edges + [(0, 1)]).T
    info = np.broadcast_to(INFO, (len(i), 6, 6))
    score = np.r_[np.ones(len(edges)), 0.5]
    r = solve_robust(5, i, j, Z_bad, info, score=score)
    assert r.why[-1] == "residual" and r.kept[:-1].all(), r.why
    ang, t = _errors(r.T_0_k, T)
    assert ang.max() < 0.005 and t.max() < 0.03


def test_loop_ends_closer_to_truth_than_the_spanning_tree():
    """A ring 0-1-...-5-0 whose steps each carry a 0.02 rad yaw and 3 cm bias (odometry-like
    drift of the pairwise registrations); the closing measurement (5, 0) is exact. Chaining
    along the tree (map_merge_3d's way) adds the biases up; the solve spreads them over the loop."""
    n = 6
    T = _truth(n, seed=5)
    edges = [(k, k + 1) for k in range(n - 1)] + [(n - 1, 0)]
    bias = se3.from_xyz_rpy(0.03, 0.0, 0.0, 0.0, 0.0, 0.02, xp=np)
    Z = np.stack([np.linalg.inv(T[a]) @ T[b] @ (bias if b else np.eye(4)) for a, b in edges])
    i, j = np.array(edges).T
    info = np.broadcast_to(INFO, (n, 6, 6))
    score = np.r_[np.ones(n - 1), 0.1]  # the tree takes the chain, not the closure
    T_tree, placed, tree = spanning_tree_poses(n, i, j, Z, score, np.ones(n, bool))
    assert placed.all() and sorted(tree) == list(range(n - 1))
    r = solve_robust(n, i, j, Z, info, score=score)
    assert r.kept.all(), r.why
    ang_tree, t_tree = _errors(T_tree, T)
    ang, t = _errors(r.T_0_k, T)
    # the tree's last map is off by 5 biases (0.1 rad); after the solve every map is within ~half
    assert ang_tree.max() > 0.09
    assert ang.max() < 0.6 * ang_tree.max() and ang.mean() < 0.6 * ang_tree.mean(), (ang, ang_tree)
    assert np.abs(t).mean() < np.abs(t_tree).mean(), (t, t_tree)
    # the residual is spread: every edge carries part of the loop's error
    assert np.all(r.chi2 > 0.1) and np.all(r.chi2 < 22.46), r.chi2


def test_isolated_node_is_unplaced_and_covariance_grows_along_a_chain():
    rng = np.random.default_rng(2)
    T = _truth(5)
    edges = [(0, 1), (1, 2), (2, 3)]  # node 4 has no measurement
    Z = _measure(T, edges, rng)
    i, j = np.array(edges).T
    r = solve_robust(5, i, j, Z, np.broadcast_to(INFO, (3, 6, 6)))
    assert r.placed.tolist() == [True, True, True, True, False]
    # a chain closes no loop: its poses are the measurements chained in float64
    np.testing.assert_allclose(r.T_0_k[3], Z[0] @ Z[1] @ Z[2], atol=1e-12)
    np.testing.assert_array_equal(r.T_0_k[4], np.eye(4))
    assert np.all(np.isnan(r.covariance[4])) and np.all(r.covariance[0] == 0)
    sd = [np.sqrt(np.trace(c[:3, :3])) for c in r.covariance[1:4]]
    assert sd[0] < sd[1] < sd[2], sd  # uncertainty accumulates away from map 0
    # a measurement-free prior (a user's guess) does not place node 4
    Zp = np.concatenate([Z, (np.linalg.inv(T[2]) @ T[4])[None]])
    rp = solve_robust(5, np.r_[i, 2], np.r_[j, 4], Zp, np.broadcast_to(INFO, (4, 6, 6)),
                      prior=np.r_[False, False, False, True])
    assert not rp.placed[4] and rp.kept[3]
    np.testing.assert_allclose(rp.T_0_k, r.T_0_k, atol=1e-9)  # and pulls on no placed map


def test_prior_pulls_a_weak_direction_and_cycle_chi2_is_frame_invariant():
    rng = np.random.default_rng(4)
    T = _truth(3)
    # cycle check: a consistent triangle has a small chi2 whatever the frames' rotations
    edges = [(0, 1), (1, 2), (0, 2)]
    Z = _measure(T, edges, rng)
    cyc, flip = triangles(*np.array(edges).T, np.ones(3, bool))
    assert cyc.tolist() == [[0, 1, 2]] and flip.tolist() == [[False, False, True]]
    cov = np.broadcast_to(np.linalg.inv(INFO), (1, 3, 6, 6))
    chi_ok = float(cycle_chi2(Z[cyc], cov, flip)[0])
    Z[2] = Z[2] @ se3.from_xyz_rpy(0.0, 0.0, 0.0, 0.0, 0.0, 0.1, xp=np)
    chi_bad = float(cycle_chi2(Z[cyc], cov, flip)[0])
    assert chi_ok < 22.46 < chi_bad, (chi_ok, chi_bad)
    # the jitted LM reaches the truth from a perturbed start on an exact graph
    Z = _measure(T, edges, rng, noise=(0.0, 0.0))
    g = make_graph(*np.array(edges).T, Z, np.broadcast_to(INFO, (3, 6, 6)))
    assert g.i.shape == (16,)
    # 8 nodes, 16 edges: the bucket solve_robust used above, so nothing recompiles
    T0 = np.concatenate([T @ se3.se3_exp(np.r_[0.2, -0.1, 0.05, 0.02, -0.02, 0.15], xp=np),
                         np.broadcast_to(np.eye(4), (5, 4, 4))])
    T0[0] = np.eye(4)
    sol = solve_pose_graph(T0.astype(np.float32), g, np.array([False, True, True] + [False] * 5), 3.0,
                           max_iterations=50, kernel="cauchy")
    ang, t = _errors(np.asarray(sol.T_0_k, np.float64)[:3], T)
    assert bool(sol.converged) and ang.max() < 5e-4 and t.max() < 1e-3, (ang, t)


def test_bad_input_raises():
    with pytest.raises(ValueError, match="itself"):
        make_graph([0, 1], [1, 1], np.broadcast_to(np.eye(4), (2, 4, 4)), np.broadcast_to(INFO, (2, 6, 6)))
    with pytest.raises(ValueError, match="kernel"):
        solve_robust(2, [0], [1], np.eye(4)[None], INFO[None], kernel="huber")
