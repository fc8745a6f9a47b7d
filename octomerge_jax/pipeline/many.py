"""``merge_many``: N maps into one globally consistent map (thesis Ch. 6 for each pair, a pose
graph over all of them).

::

    maps ──screen_pairs──> candidate pairs        (all pairs, or a coarse-descriptor pre-screen)
         ──measure_pair──> T_i_j, Omega, confidence per pair   (guess-free, or from the guesses)
         ──consensus.choose_candidates──> per pair the candidate pose the other pairs agree with
           (maps left unplaced: their next most similar maps registered, up to GROW_ROUNDS rounds)
         ──refine locally from it (the configured mode, "icp+dense")
         ──posegraph.solve_robust──> T_0_k, kept / rejected edges, covariances
         ──transform_map (each placed map)──fuse_many──> merged   (one pass, Alg. 8)

Guesses (``T_inits``: ``T_0_k``; ``pairs``: ``T_i_k``) narrow the search: only pairs whose
bounding boxes overlap under the guesses are registered, each from its guess with the
configured ``refine`` mode, and every guess enters the graph as a weak prior. With
``refine="none"`` the guesses are the measurements. A map that no kept measurement connects
to map 0 is reported unplaced and left out, not forced in
(``docs/design.md``, "Pose graph over pairwise registrations").
"""

from __future__ import annotations

import time
from typing import Sequence

import numpy as np

from .. import registration as reg
from ..fusion import fuse_many_with_report
from ..map import OccupancyMap
from ..registration import consensus, posegraph
from ..resample import transform_map
from .config import MergeConfig
from .many_report import EdgeReport, ManyReport, MapReport
from .merging import check_resolutions, check_transform, config_with_overrides
from .pairs import candidate_measurement, measure_pair, more_pairs, screen_pairs
from .report import MergeError, MergeReport
from .timings import Timings

__all__ = ["merge_many"]

_LOW = 1e-9
#: two candidate poses of a map agree within this rotation [rad] and translation (voxels, at
#: least the metres below): wrong candidates of symmetric scenes lie a half turn or a bay away
CONSENSUS_ROT_RAD, CONSENSUS_TRANS_VOXELS, CONSENSUS_TRANS_MIN_M = 0.1, 5.0, 1.0
#: rounds of more pairs for the maps the consensus leaves unplaced (from 7 maps on)
GROW_ROUNDS = 3
#: the refinements that polish a guess-free edge from its chosen pose (the others leave it)
LOCAL_REFINES = ("icp", "icp+dense", "dense")


def _guesses(n: int, T_inits, pairs) -> tuple[dict, np.ndarray | None]:
    """``({(i, k): T_i_k}, T_0_k guesses (n, 4, 4) or None)`` from ``merge_many``'s arguments;
    raises ``ValueError`` for a bad plan."""
    if T_inits is not None and pairs is not None:
        raise ValueError("give T_inits or pairs, not both")
    if T_inits is not None:
        T_inits = list(T_inits)
        if len(T_inits) != n - 1:
            raise ValueError(f"T_inits has {len(T_inits)} transforms for {n} maps (need {n - 1})")
        g = {(0, k): np.eye(4) if T is None else check_transform(T, f"T_inits[{k - 1}]")
             for k, T in enumerate(T_inits, 1)}
    elif pairs is not None:
        g = {}
        for (i, k), T in dict(pairs).items():
            i, k = int(i), int(k)
            if not (0 <= i < n and 0 <= k < n) or i == k:
                raise ValueError(f"pairs: ({i}, {k}) is not a pair of two of the {n} maps")
            g[(i, k)] = np.eye(4) if T is None else check_transform(T, f"pairs[({i}, {k})]")
    else:
        return {}, None
    keys = list(g)
    T0, placed, _ = posegraph.spanning_tree_poses(n, [a for a, _ in keys], [b for _, b in keys],
                                                  np.stack([g[e] for e in keys]), np.ones(len(keys)),
                                                  np.ones(len(keys), bool))
    if not placed.all():
        raise ValueError(f"the guesses do not connect maps {np.flatnonzero(~placed).tolist()} to map 0")
    return g, T0


def _boxes_overlap(m_i: OccupancyMap, m_j: OccupancyMap, T_i_j, margin: float) -> bool:
    """Whether map j's leaf bounding box, placed by ``T_i_j``, meets map i's (grown by ``margin``)."""
    def box(m):
        lv = m.leaves()
        return lv.centers.min(0), lv.centers.max(0)
    (lo_i, hi_i), (lo_j, hi_j) = box(m_i), box(m_j)
    corners = np.array([[x, y, z] for x in (lo_j[0], hi_j[0]) for y in (lo_j[1], hi_j[1]) for z in (lo_j[2], hi_j[2])])
    c = corners @ np.asarray(T_i_j)[:3, :3].T + np.asarray(T_i_j)[:3, 3]
    return bool(np.all(c.min(0) <= hi_i + margin) and np.all(c.max(0) >= lo_i - margin))


def _sigmas(cov) -> tuple[float | None, float | None]:
    if cov is None or not np.all(np.isfinite(cov)):
        return None, None
    return (float(np.sqrt(max(np.linalg.eigvalsh(cov[:3, :3]).max(), 0.0))),
            float(np.sqrt(max(np.linalg.eigvalsh(cov[3:, 3:]).max(), 0.0))))


def _consensus(maps, edges: list[dict], min_confidence: float):
    """``(pool, Consensus or None)``: the guess-free edges whose ``"ok"`` or ``"ambiguous"``
    registration has candidate poses, and ``consensus.choose_candidates`` over them (``None``
    without any)."""
    pool = [e for e in edges if e.get("meas") is not None and e["meas"].verdict in ("ok", "ambiguous")
            and e["conf"] >= min_confidence and e["reg"].candidates]
    if not pool:
        return pool, None
    res = float(maps[0].resolution)
    return pool, consensus.choose_candidates(
        len(maps), [e["i"] for e in pool], [e["j"] for e in pool],
        [[np.asarray(c["T_1_2"], np.float64) for c in e["reg"].candidates] for e in pool],
        [[float(c["score"]) for c in e["reg"].candidates] for e in pool],
        [e["meas"].verdict == "ok" for e in pool], rot_tol=CONSENSUS_ROT_RAD,
        trans_tol=max(CONSENSUS_TRANS_VOXELS * res, CONSENSUS_TRANS_MIN_M))


def _choose_by_consensus(maps, edges: list[dict], min_confidence: float) -> list[dict]:
    """Guess-free edges: each ``"ok"`` or ``"ambiguous"`` registration's candidate poses go to
    ``consensus.choose_candidates``; an edge keeps the candidate the other pairs agree with
    (``figures["candidate"]``: its rank; ambiguous registrations become usable that way), or
    is set aside as ``"inconsistent"`` when its maps are placed and no candidate agrees, or as
    ``"undecided"`` when one of its maps is left unplaced (its pairs disagree: it is not placed
    by one of them). In place; returns the edges that kept a candidate."""
    pool, cons = _consensus(maps, edges, min_confidence)
    if cons is None:
        return []
    chosen = []
    for e, c in zip(pool, cons.choice):
        if c >= 0:
            meas = candidate_measurement(maps[e["i"]], maps[e["j"]], e["meas"], int(c))
            e.update(T=meas.T_i_j, info=meas.information, why="", meas=meas,
                     figures={**(e["figures"] or {}), "candidate": int(c)})
            chosen.append(e)
        elif cons.placed[e["i"]] and cons.placed[e["j"]]:
            e["why"] = "inconsistent: none of its candidate poses agrees with the other pairs"
        elif not e["why"]:  # an "ok" pair of a map the pairs disagree on: not placed by it alone
            k = e["j"] if cons.placed[e["i"]] else e["i"]
            e["why"] = f"undecided: the pairs of map {k} disagree on where it lies"
    return chosen


def _register_pairs(maps, pairs, T0_guess, cfg: MergeConfig, min_confidence: float, timings: Timings) -> list[dict]:
    """One edge per pair ``(i, j)``: map j registered to map i, guess-free without ``T0_guess``
    (its candidate poses kept under ``figures["candidates"]``, best first: what the consensus
    chooses from), else from the guesses' ``T_i_j``. An edge that is not ``"ok"`` or below
    ``min_confidence`` says why."""
    edges = []
    for i, j in pairs:
        t0 = time.perf_counter()
        T_init = np.eye(4) if T0_guess is None else np.linalg.inv(T0_guess[i]) @ T0_guess[j]
        try:
            meas = measure_pair(maps[i], maps[j], T_init, cfg, T0_guess is None, timings)
        except MergeError as err:
            edges.append(dict(i=i, j=j, kind="registration", T=None, info=None, conf=None, figures=None,
                              why=f"registration: {err.kind}: {err}", seconds=time.perf_counter() - t0, reg=None))
            continue
        figures = dict(meas.registration.info or {})
        if T0_guess is None:
            figures["candidates"] = list(meas.registration.candidates)
        edges.append(dict(i=i, j=j, kind="registration", T=meas.T_i_j, info=meas.information,
                          conf=meas.confidence, figures=figures,
                          why=("" if meas.verdict == "ok" else f"registration {meas.verdict}")
                          or ("" if meas.confidence >= min_confidence else "low_confidence"),
                          seconds=time.perf_counter() - t0, reg=meas.registration, meas=meas))
    return edges


def _register_until_placed(maps, pairs, sim, max_pairs_per_map, cfg: MergeConfig, min_confidence: float,
                           timings: Timings) -> list[dict]:
    """Guess-free edges of the screened ``pairs``, then, while the consensus leaves maps
    unplaced, of each such map's next ``max_pairs_per_map`` most similar maps
    (``pairs.more_pairs``; at most ``GROW_ROUNDS`` rounds): the descriptor ranks the right
    neighbours of a repetitive building low, so a map none of its first pairs places gets more
    (``docs/design.md``, "Pose graph over pairwise registrations")."""
    edges = _register_pairs(maps, pairs, None, cfg, min_confidence, timings)
    tried = list(pairs)
    for _ in range(GROW_ROUNDS if max_pairs_per_map else 0):
        _, cons = _consensus(maps, edges, min_confidence)
        unplaced = np.flatnonzero(np.ones(len(maps), bool) if cons is None else ~cons.placed)
        new = more_pairs(sim, unplaced, tried, max_pairs_per_map) if len(unplaced) else []
        if not new:
            break
        edges += _register_pairs(maps, new, None, cfg, min_confidence, timings)
        tried += new
    return edges


def _polish(maps, chosen: list[dict], cfg: MergeConfig, timings: Timings) -> None:
    """Each chosen edge registered again locally from its pose with the configured refinement
    (``"icp+dense"`` by default: ICP alone keeps a voxel-lattice bias, ``docs/design.md``); the
    local result replaces the candidate when its own verdict is ``"ok"``. In place."""
    for e in chosen:
        try:
            local = measure_pair(maps[e["i"]], maps[e["j"]], e["T"], cfg, False, timings)
        except MergeError:
            continue
        if local.verdict == "ok":
            e.update(T=local.T_i_j, info=local.information, reg=local.registration,
                     figures={**e["figures"], "polish": {"refine": cfg.registration.refine,
                                                         **(local.registration.info or {})}})


def merge_many(maps: Sequence[OccupancyMap], T_inits=None, *, pairs=None, refine: str | None = None,
               rule: str | None = None, T_trues=None, config: MergeConfig | None = None,
               max_pairs_per_map: int | None = 4, min_confidence: float = 0.1, prior_sigma_m: float = 1.0,
               prior_sigma_rad: float = 0.2, kernel: str = "cauchy", max_chi2: float = posegraph.CHI2_6DOF_999):
    """Merge N maps into map 0's frame: pairwise measurements, a robust pose graph, one fusion.

    Args:
      maps: ``[m_0, m_1, ...]`` of one resolution (else ``MergeError("resolution")``).
      T_inits: optional ``n - 1`` guesses ``T_0_k`` (k = 1..n-1, map k's frame into map 0's).
      pairs: optional pairwise guesses ``{(i, k): T_i_k}`` that connect every map to map 0
        (a spanning tree such as a chain, or any graph). Without guesses (the default) every
        candidate pair is registered guess-free (``refine="multi"`` from the identity).
      refine: the registration mode used from the guesses (``"none"``: the guesses are the
        measurements); ignored without guesses.
      rule: ``fuse_many`` rule.
      T_trues: optional true ``T_0_k`` (``n - 1``) for the thesis errors per map.
      config: all other parameters (``MergeConfig``).
      max_pairs_per_map: without guesses and from 7 maps on, each map's this many most similar
        maps (coarse descriptor) are registered (``None``: every pair); a map the measurements
        do not place then gets its next this many, for up to ``GROW_ROUNDS`` rounds.
      min_confidence: measurements below it are not used (``why="low_confidence"``), nor those
        whose registration ended other than ``"ok"`` (``why="registration ambiguous"``, ...),
        except that without guesses a pair keeps the candidate pose the other pairs agree with
        (``consensus.choose_candidates``; an ``"ambiguous"`` pair too, a best pose they
        contradict is replaced or set aside as ``"inconsistent"``).
      prior_sigma_m, prior_sigma_rad: standard deviations of a guess as a prior [m], [rad].
      kernel, max_chi2: the pose graph's robust kernel and rejection threshold
        (``registration.posegraph.solve_robust``).

    Returns ``(merged, ManyReport)``; ``merged`` fuses the placed maps in one pass
    (``fuse_many``) in map 0's frame. Raises ``ValueError`` for a bad plan and ``MergeError``
    for mixed resolutions.
    """
    maps = list(maps)
    n = len(maps)
    if n < 2:
        raise ValueError("merge_many needs at least two maps")
    cfg = config_with_overrides(config, refine, None, None, rule, None)
    check_resolutions(maps, [f"maps[{i}]" for i in range(n)], False)
    guesses, T0_guess = _guesses(n, T_inits, pairs)
    T_trues = None if T_trues is None else [np.eye(4)] + [check_transform(T, f"T_trues[{k}]")
                                                        for k, T in enumerate(T_trues)]
    t_start = time.perf_counter()
    timings, reg_timings = Timings(), Timings()
    res = maps[0].resolution
    with timings.stage("screen"):
        if T0_guess is None:
            cand, sim = screen_pairs(maps, max_pairs_per_map)
        else:
            near = [(i, j) for i in range(n) for j in range(i + 1, n)
                    if _boxes_overlap(maps[i], maps[j], np.linalg.inv(T0_guess[i]) @ T0_guess[j], 2 * res)]
            cand = sorted(set(near) | {(min(e), max(e)) for e in guesses})
    edges: list[dict] = []
    with timings.stage("register"):
        if T0_guess is not None and cfg.registration.refine == "none":
            pass  # the guesses are the measurements
        elif T0_guess is not None:
            edges = _register_pairs(maps, cand, T0_guess, cfg, min_confidence, reg_timings)
        else:
            edges = _register_until_placed(maps, cand, sim, max_pairs_per_map, cfg, min_confidence, reg_timings)
    if T0_guess is None:
        with timings.stage("consensus"):
            chosen = _choose_by_consensus(maps, edges, min_confidence)
        if cfg.registration.refine in LOCAL_REFINES:
            with timings.stage("polish"):
                _polish(maps, chosen, cfg, reg_timings)
    guess_kind = "guess" if cfg.registration.refine == "none" else "prior"
    prior_info = np.diag([prior_sigma_m ** -2.0] * 3 + [prior_sigma_rad ** -2.0] * 3)
    for (i, k), T in guesses.items():
        edges.append(dict(i=i, j=k, kind=guess_kind, T=T, info=prior_info, conf=None, figures=None, why="",
                          seconds=0.0, reg=None))
    usable = np.array([e["T"] is not None and e["why"] == "" for e in edges], bool)
    with timings.stage("solve"):
        if len(edges):
            Z = np.stack([np.eye(4) if e["T"] is None else e["T"] for e in edges])
            info = np.stack([np.zeros((6, 6)) if e["info"] is None else e["info"] for e in edges])
            score = np.array([2.0 if e["kind"] == "guess" else (e["conf"] or 0.0) for e in edges])
            sol = posegraph.solve_robust(n, [e["i"] for e in edges], [e["j"] for e in edges], Z, info,
                                         score=score, usable=usable,
                                         prior=np.array([e["kind"] == "prior" for e in edges]),
                                         kernel=kernel, max_chi2=max_chi2)
        else:
            sol = posegraph.solve_robust(n, [0], [1], np.eye(4)[None], np.zeros((1, 6, 6)), usable=np.zeros(1, bool))
    transforms = tuple(sol.T_0_k[k] if sol.placed[k] else None for k in range(n))
    tc = cfg.transform
    moved, order = [maps[0]], [0]
    with timings.stage("transform"):
        for k in range(1, n):
            if sol.placed[k]:
                moved.append(transform_map(maps[k], sol.T_0_k[k], tc.interpolation, space=tc.space,
                                           chunk_bricks=tc.chunk_bricks))
                order.append(k)
    weights = None
    if cfg.fuse.rule == "weighted":
        if len(cfg.fuse.weights) != n:
            raise ValueError(f"fuse.weights has {len(cfg.fuse.weights)} entries for {n} maps")
        weights = [cfg.fuse.weights[k] for k in order]
    with timings.stage("fuse") as stage:
        merged, frep = stage.ready(fuse_many_with_report(moved, cfg.fuse.rule, weights=weights))
    timings["total"] = time.perf_counter() - t_start
    return merged, _report(maps, edges, sol, transforms, T_trues, T0_guess, cfg, timings, reg_timings, cand,
                           merged, frep)


def _report(maps, edges, sol, transforms, T_trues, T0_guess, cfg, timings, reg_timings, cand, merged, frep):
    n = len(maps)
    m = len(edges)
    kept = np.asarray(sol.kept)[:m] if m else np.zeros(0, bool)
    edge_reports = []
    for e, ed in enumerate(edges):
        why = ed["why"] or ("" if kept[e] else sol.why[e])
        measured = ed["T"] is not None and transforms[ed["i"]] is not None and transforms[ed["j"]] is not None
        edge_reports.append(EdgeReport(
            i=ed["i"], j=ed["j"], kind=ed["kind"], T_i_j=ed["T"], confidence=ed["conf"], information=ed["info"],
            residual=sol.residual[e] if measured else None, chi2=float(sol.chi2[e]) if measured else None,
            kept=bool(kept[e]), why=why, figures=ed["figures"], seconds=ed["seconds"]))
    map_reports, merge_reports = [], []
    for k in range(n):
        touching = tuple(e for e in range(m)
                         if kept[e] and edges[e]["kind"] != "prior" and k in (edges[e]["i"], edges[e]["j"]))
        placed = transforms[k] is not None
        cov = sol.covariance[k] if placed and k else None
        s_m, s_r = _sigmas(cov)
        eps = (None, None)
        if T_trues is not None and placed and k:
            eps = (float(reg.rotation_error(transforms[k], T_trues[k])),
                   float(reg.translation_error(transforms[k], T_trues[k])))
        map_reports.append(MapReport(index=k, status="root" if k == 0 else ("placed" if placed else "unplaced"),
                                     T_0_k=transforms[k], covariance=cov, sigma_m=s_m, sigma_rad=s_r, edges=touching,
                                     leaves=maps[k].num_leaves, epsilon_r=eps[0], epsilon_t=eps[1]))
        if k == 0:
            continue
        best = max(touching, key=lambda e: edges[e]["conf"] or 0.0, default=None)
        figs = None if best is None else edges[best]["figures"]
        placing = None if best is None else edges[best]["reg"]
        T_init = np.eye(4) if T0_guess is None else T0_guess[k]
        T_used = transforms[k] if placed else T_init
        e_r = e_t = e_r0 = e_t0 = None
        if T_trues is not None:
            e_r0, e_t0 = float(reg.rotation_error(T_init, T_trues[k])), float(reg.translation_error(T_init, T_trues[k]))
            e_r, e_t = float(reg.rotation_error(T_used, T_trues[k])), float(reg.translation_error(T_used, T_trues[k]))
        merge_reports.append(MergeReport(
            T_1_2_init=T_init, T_1_2=T_used, refine=cfg.registration.refine, icp=figs, epsilon_r_init=e_r0,
            epsilon_t_init=e_t0, epsilon_r=e_r, epsilon_t=e_t, counts={"leaves_1": maps[0].num_leaves,
                                                                        "leaves_2": maps[k].num_leaves,
                                                                        "leaves_merged": merged.num_leaves},
            timings={}, resolution=maps[0].resolution, T_1_2_true=None if T_trues is None else T_trues[k],
            status="ok" if placed else "unplaced", icp_result=None if placing is None else placing.result,
            points_1=None if placing is None else placing.points_1,
            points_2=None if placing is None else placing.points_2))
    reg_edges = [e for e in edge_reports if e.kind != "prior"]
    figures = {"maps_placed": int(sum(t is not None for t in transforms)), "pairs_possible": n * (n - 1) // 2,
               "pairs_registered": sum(e.kind == "registration" for e in edge_reports),
               "pairs_added": len({(e.i, e.j) for e in reg_edges} - set(cand)),
               "edges_kept": sum(e.kept for e in reg_edges), "edges_rejected": sum(not e.kept for e in reg_edges),
               "candidate_pairs": [list(c) for c in cand], "solver_iterations": sol.num_iterations,
               "solver_rounds": sol.rounds, "solver_cost": sol.cost, "solver_converged": sol.converged,
               "cycles_checked": int(len(sol.cycles)), "leaves_merged": merged.num_leaves, "fuse": frep.host(),
               "registration_stages": dict(reg_timings)}
    warnings = tuple(f"map {k} overlaps no other map it could be registered to: left out of the merged map"
                     for k in range(n) if transforms[k] is None)
    return ManyReport(transforms=transforms, maps=tuple(map_reports), edges=tuple(edge_reports), figures=figures,
                      timings=dict(timings), resolution=maps[0].resolution, warnings=warnings,
                      merge_reports=tuple(merge_reports))
