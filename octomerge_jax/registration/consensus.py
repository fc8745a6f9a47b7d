"""Which of each pair's candidate poses is the right one: the choice the other pairs agree with.

A guess-free pairwise registration returns its best few distinct poses (``candidates``, best
first). In a symmetric scene the best can be wrong (an office floor turned by pi, a corridor
shifted by one bay) while the right pose is among the others; a second opinion comes from the
other maps: if maps i, j and k overlap, the right ``T_i_k`` equals ``T_i_j T_j_k``. Here the
maps are placed relative to map 0 one at a time by the pose the paths of one or two pairwise
candidates agree on, then each pair keeps the candidate that agrees with the placed poses (or
none).

A map's hypotheses are its paths from placed maps: one candidate of a pair with a placed map,
or two through one unplaced map. A path weighs its weakest candidate's score; paths leaving
the map over the same pair count once (they are not independent). A map is placed where its
best pose has ``MIN_MARGIN`` times the support of its next best, from two pairs or from an
unambiguous pair's own best candidate (``trusted``; its other candidates do not compete: that
pair ranked them); the map with the largest margin goes first. Equal evidence for two poses
(a map whose own content is symmetric) leaves the map unplaced. Cost: ``O(n * d^2 * c^2)``
hypotheses per placement (``d`` pairs per map, ``c`` candidates per pair); the pose graph
(``posegraph.solve_robust``) then refines the chosen measurements.
Reference: the pairwise-consistency selection of loop closures in multi-robot SLAM (PCM,
Mangelson et al. 2018) on triangles instead of odometry; why and its limits:
``docs/design.md``, "Choosing among a pair's candidate poses".
"""

from __future__ import annotations

from typing import NamedTuple, Sequence

import numpy as np

__all__ = ["Consensus", "MIN_MARGIN", "choose_candidates"]

#: a map is placed only where its best pose has this many times the support of its next best
MIN_MARGIN = 1.5


class Consensus(NamedTuple):
    """``choose_candidates``' result (host values)."""

    T_0_k: np.ndarray  # (n, 4, 4) float64 poses of the placed maps (identity where unplaced)
    placed: np.ndarray  # (n,) bool
    choice: np.ndarray  # (m,) int: the candidate each edge keeps, -1: none agrees with the poses
    support: np.ndarray  # (n,) int: paths that agreed on each map's pose (0 for map 0 / unplaced)


def _close(A, B, rot_tol: float, trans_tol: float) -> bool:
    """Rotation angle of ``A^T B`` within ``rot_tol`` [rad] and translations within
    ``trans_tol`` [m] (host, float64)."""
    if np.linalg.norm(A[:3, 3] - B[:3, 3]) > trans_tol:
        return False
    cos = (np.trace(A[:3, :3].T @ B[:3, :3]) - 1.0) / 2.0
    return bool(np.arccos(np.clip(cos, -1.0, 1.0)) <= rot_tol)


def choose_candidates(n: int, i: Sequence[int], j: Sequence[int], candidates: Sequence[Sequence[np.ndarray]],
                      scores: Sequence[Sequence[float]], trusted: Sequence[bool], *, rot_tol: float = 0.1,
                      trans_tol: float = 1.0, min_margin: float = MIN_MARGIN) -> Consensus:
    """Place maps ``0..n-1`` and pick one candidate per edge by agreement (module docstring).

    Args:
      n: maps; map 0 is the reference (identity).
      i, j: ``(m,)`` edge ends: edge e's candidates are ``T_i_j`` (map j's frame into map i's).
      candidates: per edge a list of ``(4, 4)`` candidate poses [m], best first (may be empty).
      scores: per edge the candidates' scores (higher is better): their weights in the vote
        (a negative score counts nothing).
      trusted: ``(m,)``: the edge's first candidate may place a map on its own (an ``"ok"``
        registration).
      rot_tol, trans_tol: two poses agree within this rotation [rad] and translation [m].

    Returns a ``Consensus``. Raises ``ValueError`` when the lists' lengths differ."""
    m = len(i)
    if not (len(j) == len(candidates) == len(scores) == len(trusted) == m):
        raise ValueError("i, j, candidates, scores and trusted need one entry per edge")
    # directed adjacency: (neighbour, edge, candidate poses T_from_to)
    adj: list[list[tuple[int, int, list[np.ndarray]]]] = [[] for _ in range(n)]
    for e in range(m):
        Ts = [np.asarray(T, np.float64) for T in candidates[e]]
        adj[int(i[e])].append((int(j[e]), e, Ts))
        adj[int(j[e])].append((int(i[e]), e, [np.linalg.inv(T) for T in Ts]))
    T0 = np.tile(np.eye(4), (n, 1, 1))
    placed = np.zeros(n, bool)
    placed[0] = True
    support = np.zeros(n, int)
    while True:
        best = None  # (margin, support, k, pose, paths)
        for k in np.flatnonzero(~placed):
            hyps = _hypotheses(int(k), adj, T0, placed, scores)
            groups = sorted(_clusters(hyps, rot_tol, trans_tol), key=lambda g: g[1], reverse=True)
            if not groups:
                continue
            paths, top, pose, _ = groups[0]
            vouch = _trusted(hyps, pose, rot_tol, trans_tol, trusted)
            # a trusted pair has ranked its own candidates already: its others do not compete
            runner = max((sum(w for e, w in g[3].items() if e not in vouch) for g in groups[1:]), default=0.0)
            margin = top / max(runner, 1e-9)
            # clearly more support than any other pose of this map, from two independent paths
            # or a trusted pair's own best candidate
            if top <= 0 or margin < min_margin or not (paths >= 2 or vouch):
                continue
            if best is None or (margin, top) > best[:2]:
                best = (margin, top, int(k), pose, paths)
        if best is None:
            break
        _, _, k, pose, paths = best
        T0[k], placed[k], support[k] = pose, True, paths
    choice = np.full(m, -1)
    for e in range(m):
        a, b = int(i[e]), int(j[e])
        if not (placed[a] and placed[b]):
            continue
        want = np.linalg.inv(T0[a]) @ T0[b]
        for c, T in enumerate(candidates[e]):
            if _close(np.asarray(T, np.float64), want, rot_tol, trans_tol):
                choice[e] = c
                break
    return Consensus(T0, placed, choice, support)


def _hypotheses(k: int, adj, T0, placed, scores) -> list[tuple[np.ndarray, float, tuple]]:
    """Poses of map k in map 0's frame by every path of one edge from a placed map, or of two
    through an unplaced map: ``(pose, weight, ((edge, candidate), ...))``, the weight that of
    the path's weakest candidate."""
    out = []
    for a, e, Ts in adj[k]:  # T_k_a per candidate
        if placed[a]:
            for c, T_k_a in enumerate(Ts):
                out.append((T0[a] @ np.linalg.inv(T_k_a), _weight(scores[e][c]), ((e, c),)))
            continue
        for b, f, Us in adj[a]:  # through the unplaced map a: T_a_b
            if b == k or not placed[b]:
                continue
            for c, T_k_a in enumerate(Ts):
                for d, T_a_b in enumerate(Us):
                    pose = T0[b] @ np.linalg.inv(T_k_a @ T_a_b)
                    out.append((pose, min(_weight(scores[e][c]), _weight(scores[f][d])), ((e, c), (f, d))))
    return out


def _weight(score) -> float:
    """A candidate's weight in the vote: its score, negative scores counting nothing."""
    return max(float(score), 0.0)


def _clusters(hyps, rot_tol: float, trans_tol: float):
    """Groups of agreeing hypotheses: ``(paths, support, pose, {edge: weight})`` per group.
    A path's weight is its weakest candidate's; paths leaving map k over the same edge are not
    independent, so
    each such edge adds its best path's weight once (``support``) and counts once
    (``paths``). The pose is that of the group's best direct path (else its best path)."""
    order = sorted(range(len(hyps)), key=lambda h: -hyps[h][1])
    used = np.zeros(len(hyps), bool)
    for h in order:
        if used[h]:
            continue
        members = [g for g in range(len(hyps)) if not used[g] and _close(hyps[g][0], hyps[h][0], rot_tol, trans_tol)]
        used[members] = True
        per_edge: dict[int, float] = {}
        for g in members:
            e = hyps[g][2][0][0]
            per_edge[e] = max(per_edge.get(e, 0.0), hyps[g][1])
        direct = [g for g in members if len(hyps[g][2]) == 1]
        anchor = max(direct or members, key=lambda g: hyps[g][1])
        yield len(per_edge), float(sum(per_edge.values())), hyps[anchor][0], per_edge


def _trusted(hyps, pose, rot_tol: float, trans_tol: float, trusted) -> set:
    """The trusted edges whose first candidate, as a direct path, agrees with ``pose``."""
    return {path[0][0] for T, _, path in hyps
            if len(path) == 1 and path[0][1] == 0 and trusted[path[0][0]] and _close(T, pose, rot_tol, trans_tol)}
