"""merge_many on a team of N robots (tiles of a simulated scene, random frames): time per
stage and accuracy per map, against the same pairwise registrations chained along a
maximum-confidence spanning tree (map_merge_3d's way) in the same run.

    timeout 900 python benchmarks/bench_many.py --scene office --sizes 4 8 16 --resolution 0.2
    timeout 900 python benchmarks/bench_many.py --guess-noise 0.3 0.1   # rough guesses: ICP per pair
    timeout 900 python benchmarks/bench_many.py --synthetic             # pre-screen and solve only

Prints one row per N: seconds for the pre-screen, the pairwise registrations, the graph solve,
transform + fuse; pairs registered; maps placed; the worst rotation [rad] and translation [m]
error of a placed map with the graph and with the spanning tree. Without ``--guess-noise`` every
candidate pair is registered guess-free (``register_global``), each pair's pose chosen among its
candidates by the other pairs' agreement and refined locally (``icp+dense``); the tree chains
each "ok" pair's own best pose. With ``--guess-noise`` the robots have guesses ``T_0_k``
off by up to that many metres / radians (uniform in x, y, yaw), so only pairs that overlap under
the guesses are registered, with ICP from them. ``--budget-s`` stops before a
size whose registrations would not fit (estimated from the previous size's seconds per pair).
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from octomerge_jax import merge_many, se3
from octomerge_jax.registration import rotation_angle_error, translation_distance
from octomerge_jax.pipeline.pairs import screen_pairs
from octomerge_jax.registration.posegraph import solve_robust, spanning_tree_poses
from octomerge_jax.sim import team_maps


def _worst(T_est, T_true):
    errs = [(rotation_angle_error(T, Tt), translation_distance(T, Tt)) for T, Tt in zip(T_est, T_true) if T is not None]
    if not errs:
        return float("nan"), float("nan")
    r, t = np.array(errs, np.float64).T
    return float(r.max()), float(t.max())


def run(scene: str, n: int, resolution: float, seed: int, overlap_m: float, guess_noise=None) -> dict:
    team = team_maps(scene, n, resolution, seed=seed, overlap_m=overlap_m)
    guesses = None
    if guess_noise is not None:
        rng = np.random.default_rng(seed + 1)
        t, r = guess_noise
        guesses = [T @ se3.from_xyz_rpy(*rng.uniform(-t, t, 2), 0.0, 0.0, 0.0, rng.uniform(-r, r), xp=np)
                   for T in team.T_0_k[1:]]
    t0 = time.perf_counter()
    _, rep = merge_many(list(team.maps), guesses, T_trues=list(team.T_0_k[1:]))
    wall = time.perf_counter() - t0
    # map_merge_3d's way: each pair's own best pose, pairs its registration called "ok"
    reg = [e for e in rep.edges if e.kind == "registration" and e.T_i_j is not None
           and (e.figures or {}).get("verdict", "ok") == "ok"]
    best = [np.asarray(e.figures["candidates"][0]["T_1_2"]) if e.figures.get("candidates") else e.T_i_j for e in reg]
    T_tree, placed, _ = spanning_tree_poses(n, [e.i for e in reg], [e.j for e in reg],
                                            np.stack(best) if reg else np.zeros((0, 4, 4)),
                                            [e.confidence for e in reg], np.ones(len(reg), bool))
    tree = [T_tree[k] if placed[k] else None for k in range(n)]
    tm = rep.timings
    return dict(n=n, screen=tm["screen"], register=tm["register"] + tm.get("consensus", 0.0) + tm.get("polish", 0.0),
                solve=tm["solve"],
                fuse=tm["transform"] + tm["fuse"], wall=wall, pairs=rep.figures["pairs_registered"],
                kept=rep.figures["edges_kept"], placed=rep.figures["maps_placed"], placed_tree=int(placed.sum()),
                graph=_worst(rep.transforms, team.T_0_k), tree=_worst(tree, team.T_0_k))


def run_synthetic(scene: str, n: int, resolution: float, seed: int, overlap_m: float) -> dict:
    """The pre-screen on the real maps, then measurements made from the truth (0.02 m, 0.003 rad
    noise, on every screened pair whose tiles overlap) with one of them replaced by a wrong one
    (1.5 m, 0.7 rad off): the graph solve's cost and robustness against the spanning tree,
    without the registrations' minutes."""
    team = team_maps(scene, n, resolution, seed=seed, overlap_m=overlap_m)
    t0 = time.perf_counter()
    cand, _ = screen_pairs(list(team.maps), 4)
    t_screen = time.perf_counter() - t0
    tl = team.tiles
    cand = [(i, j) for i, j in cand if np.all(tl[i, 0] < tl[j, 1]) and np.all(tl[j, 0] < tl[i, 1])]
    rng = np.random.default_rng(seed)
    Z = np.stack([np.linalg.inv(team.T_0_k[i]) @ team.T_0_k[j]
                  @ se3.se3_exp(np.r_[rng.normal(0, 0.02, 3), rng.normal(0, 0.003, 3)], xp=np) for i, j in cand])
    wrong = len(cand) // 2
    Z[wrong] = Z[wrong] @ se3.from_xyz_rpy(1.5, -0.8, 0.0, 0.0, 0.0, 0.7, xp=np)
    info = np.broadcast_to(np.diag([0.05 ** -2] * 3 + [0.01 ** -2] * 3), (len(cand), 6, 6))
    conf = np.ones(len(cand))
    conf[wrong] = 2.0  # the wrong one looks best, so the tree uses it
    i, j = np.array(cand).T
    t0 = time.perf_counter()
    sol = solve_robust(n, i, j, Z, info, score=conf)
    t_solve = time.perf_counter() - t0
    T_tree, placed, _ = spanning_tree_poses(n, i, j, Z, conf, np.ones(len(cand), bool))
    return dict(n=n, screen=t_screen, pairs=len(cand), solve=t_solve, kept=int(sol.kept.sum()),
                placed=int(sol.placed.sum()), placed_tree=int(placed.sum()),
                rejected=[sol.why[e] for e in range(len(cand)) if not sol.kept[e]],
                graph=_worst([T if p else None for T, p in zip(sol.T_0_k, sol.placed)], team.T_0_k),
                tree=_worst([T if p else None for T, p in zip(T_tree, placed)], team.T_0_k))


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scene", default="office", choices=("lab", "office", "campus"))
    ap.add_argument("--sizes", type=int, nargs="+", default=[4, 8, 16])
    ap.add_argument("--resolution", type=float, default=0.2)
    ap.add_argument("--overlap", type=float, default=2.0, help="tile growth on each side [m]")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--guess-noise", type=float, nargs=2, metavar=("M", "RAD"),
                    help="give the robots guesses this far off (default: no guesses, guess-free registration)")
    ap.add_argument("--budget-s", type=float, default=800.0)
    ap.add_argument("--synthetic", action="store_true",
                    help="pre-screen and graph solve only, measurements from the truth with one wrong one")
    args = ap.parse_args(argv)
    if args.synthetic:
        print(f"scene {args.scene}, resolution {args.resolution} m, overlap +-{args.overlap} m, seed {args.seed}, "
              "synthetic measurements (one wrong)")
        print("| N | pre-screen s | pairs | solve s | kept | rejected | placed graph / tree | "
              "worst rot graph / tree [rad] | worst trans graph / tree [m] |")
        print("|---|---|---|---|---|---|---|---|---|")
        for n in args.sizes:
            r = run_synthetic(args.scene, n, args.resolution, args.seed, args.overlap)
            print(f"| {n} | {r['screen']:.2f} | {r['pairs']} | {r['solve']:.2f} | {r['kept']} | {r['rejected']} | "
                  f"{r['placed']} / {r['placed_tree']} | "
                  f"{r['graph'][0]:.4f} / {r['tree'][0]:.4f} | {r['graph'][1]:.3f} / {r['tree'][1]:.3f} |", flush=True)
        return
    mode = "guess-free"
    if args.guess_noise is not None:
        mode = f"guesses off by <= {args.guess_noise[0]} m, {args.guess_noise[1]} rad"
    print(f"scene {args.scene}, resolution {args.resolution} m, overlap +-{args.overlap} m, seed {args.seed}, {mode}")
    print("| N | pre-screen s | pairs | registration s | solve s | transform+fuse s | placed graph / tree | "
          "kept | worst rot graph / tree [rad] | worst trans graph / tree [m] |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    t_start, per_pair = time.perf_counter(), None
    for n in args.sizes:
        if per_pair is not None:
            guess = per_pair * min(n * (n - 1) / 2, n * 4)
            if time.perf_counter() - t_start + guess > args.budget_s:
                print(f"| {n} | skipped: about {guess:.0f} s of registrations would exceed --budget-s |")
                continue
        r = run(args.scene, n, args.resolution, args.seed, args.overlap, args.guess_noise)
        per_pair = r["register"] / max(r["pairs"], 1)
        print(f"| {n} | {r['screen']:.2f} | {r['pairs']} | {r['register']:.1f} | {r['solve']:.2f} | {r['fuse']:.1f} | "
              f"{r['placed']} / {r['placed_tree']} | {r['kept']} | {r['graph'][0]:.4f} / {r['tree'][0]:.4f} | "
              f"{r['graph'][1]:.3f} / {r['tree'][1]:.3f} |", flush=True)


if __name__ == "__main__":
    main()
