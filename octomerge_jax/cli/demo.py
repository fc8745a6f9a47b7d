"""``octomerge demo [--out-dir DIR]``: the main job on simulated data, end to end.

Two robots map the simulated lab (boxes + fence, thesis §7.2) in frames rotated by pi/4; the
maps are merged from an erroneous initial guess (0.5 m and 0.05 rad off), and the demo writes both input maps, ``merged.bt``, ``report.json`` and the
figures, and prints the thesis's errors eps_r / eps_t before and after ICP.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from .. import se3
from ..pipeline import DEMO_SCENES, REFINE_CHOICES, MergeConfig, load_config
from ..io import save
from ..pipeline import merge, transform_from_xyz_rpy
from ._common import CliError
from .compile_ahead import compile_ahead
from .outputs import check_writable_folder
from .merge import write_figures
from .plots import plot_merge_comparison
from .progress import StageBar, show_bars

EPILOG = """examples:
  octomerge demo                                  # writes ./octomerge-demo/
  octomerge demo --out-dir /tmp/demo --scene office --resolution 0.1
  octomerge demo --yaw-error 0.5 --refine multi   # a guess plain ICP cannot fix
  octomerge demo --scene campus --resolution 0.2  # outdoor, 100 x 60 m, lidar (~2 min)

Outputs (files of these names in DIR are replaced): map1.bt, map2.bt (the robots' maps; rerun the merge with the printed command),
merged.bt, merged_no_icp.bt, report.json, overlap_before_after.png (Fig. 7.6),
merged_map.png (Fig. 7.7), merge_with_without_icp.png (Fig. 7.8), icp_convergence.png.
"""


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "demo", help="simulate two robots, merge their maps from a wrong guess, write figures",
        description="The README's main job: simulate the two-robot lab scene, merge the maps "
                    "with an erroneous initial guess, write the merged map, a report and "
                    "before/after figures, and print the thesis's errors before and after ICP.",
        epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out-dir", type=Path, default=Path("octomerge-demo"), metavar="DIR",
                   help="output folder (created; default ./octomerge-demo)")
    p.add_argument("--scene", choices=DEMO_SCENES, help="simulated scene (default lab; campus: outdoor, "
                   "a 16-beam lidar, use --resolution 0.2)")
    p.add_argument("--resolution", type=float, help="voxel size [m] (default 0.1)")
    p.add_argument("--spacing", type=float, help="distance between scans [m] (default the scene's: 0.5 indoors, "
                   "2 on the campus)")
    p.add_argument("--seed", type=int, help="scene/noise seed")
    p.add_argument("--yaw-error", type=float, metavar="RAD", help="yaw error of the guess (default 0.05)")
    p.add_argument("--xyz-error", type=float, nargs=3, metavar=("X", "Y", "Z"),
                   help="translation error of the guess [m] (default 0.4 -0.3 0)")
    p.add_argument("--refine", choices=REFINE_CHOICES, help="refinement (default icp+dense)")
    p.add_argument("--no-figures", action="store_true", help="skip the figures (faster)")
    p.add_argument("--config", type=Path, metavar="FILE", help="TOML/JSON settings (octomerge dump-config)")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def _config(args):
    cfg = load_config(args.config) if args.config else MergeConfig()
    demo = {}
    for key in ("scene", "resolution", "spacing", "seed"):
        v = getattr(args, key)
        if v is not None:
            demo[key] = v
    if args.yaw_error is not None:
        demo["error_rpy_rad"] = (cfg.demo.error_rpy_rad[0], cfg.demo.error_rpy_rad[1], args.yaw_error)
    if args.xyz_error is not None:
        demo["error_xyz"] = tuple(args.xyz_error)
    reg = {"refine": args.refine} if args.refine else {}
    return cfg.replace(demo=demo, registration=reg)


def perturbed_guess(T_true, error_xyz, error_rpy_rad) -> np.ndarray:
    """The erroneous guess: ``T_true``'s xyz / rpy plus the errors (host, float64)."""
    x, y, z, roll, pitch, yaw = se3.to_xyz_rpy(np.asarray(T_true, np.float64), xp=np)
    x, y, z = np.array([x, y, z]) + np.asarray(error_xyz, np.float64)
    return transform_from_xyz_rpy(x, y, z, roll + error_rpy_rad[0], pitch + error_rpy_rad[1],
                                  yaw + error_rpy_rad[2])


def run(args) -> int:
    from ..sim import make_two_robot_maps  # trimesh and scipy: loaded by this command only

    try:
        cfg = _config(args)
    except (ValueError, FileNotFoundError) as err:
        raise CliError(str(err)) from None
    d = cfg.demo
    out = args.out_dir
    if out.exists() and not out.is_dir():
        raise CliError(f"{out}: --out-dir is not a directory")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise CliError(f"{out}: cannot create --out-dir: {err.strerror or err}") from None
    check_writable_folder(out)
    t0 = time.perf_counter()
    print(f"simulating two robots in the {d.scene} scene at {d.resolution:g} m ...", flush=True)
    bar = StageBar(show_bars(args.quiet), "demo")
    with bar.stage("simulate"):
        m1, m2, T_true = make_two_robot_maps(d.scene, d.resolution, spacing=d.spacing or None, seed=d.seed)
    bar.close()
    t_sim = time.perf_counter() - t0
    print(f"  map 1: {m1.num_leaves:,} leaves, map 2: {m2.num_leaves:,} leaves ({t_sim:.1f} s)")
    save(m1, out / "map1.bt")
    save(m2, out / "map2.bt")
    T_init = perturbed_guess(T_true, d.error_xyz, d.error_rpy_rad)
    print(f"merging from a guess off by {list(d.error_xyz)} m and rpy {list(d.error_rpy_rad)} rad "
          f"({cfg.registration.refine}) ...", flush=True)
    bar = StageBar(show_bars(args.quiet), "merge")
    with bar.watch(), compile_ahead(m1, m2, T_init, cfg):
        merged, report = merge(m1, m2, T_init, T_1_2_true=T_true, config=cfg)
    bar.close()
    save(merged, out / "merged.bt")
    report = report.with_timings(simulate=t_sim)
    report.to_json(out / "report.json")
    print(report.summary())
    written = ["map1.bt", "map2.bt", "merged.bt", "report.json"]
    if not args.no_figures:
        write_figures(report, merged, out / "overlap_before_after.png", out / "merged_map.png",
                      out / "icp_convergence.png" if report.icp is not None else None, cfg, T_true)
        written += ["overlap_before_after.png", "merged_map.png"]
        if report.icp is not None:
            written.append("icp_convergence.png")
            unrefined, _ = merge(m1, m2, T_init, refine="none", config=cfg)
            save(unrefined, out / "merged_no_icp.bt")
            # walls between floor and ceiling, from above: a misregistration doubles them
            z = merged.leaves().centers[:, 2]
            zlo, zhi = float(z.min()), float(z.max())
            zmin, zmax = zlo + 0.2 * (zhi - zlo), zhi - 0.2 * (zhi - zlo)
            plot_merge_comparison(
                [unrefined, merged], [f"initial guess (eps_r {report.epsilon_r_init:.3f})",
                                      f"after ICP (eps_r {report.epsilon_r:.3f})"],
                out / "merge_with_without_icp.png", zmin=zmin, zmax=zmax,
                suptitle="merged maps without / with ICP refinement, walls from above (Fig. 7.8)")
            written += ["merged_no_icp.bt", "merge_with_without_icp.png"]
    print()
    print(f"epsilon before ICP: eps_r = {report.epsilon_r_init:.4f}, eps_t = {report.epsilon_t_init:.4f} m")
    print(f"epsilon after  ICP: eps_r = {report.epsilon_r:.4f}, eps_t = {report.epsilon_t:.4f} m"
          "   (thesis: coherent below 0.25 / 0.9)")
    print(f"wrote {out}/: {', '.join(written)}  ({time.perf_counter() - t0:.1f} s)")
    x, y, z, *rpy = se3.to_xyz_rpy(T_init, xp=np)
    print("same merge from the files:\n  octomerge merge "
          f"{out / 'map1.bt'} {out / 'map2.bt'} {out / 'merged_again.bt'} "
          f"--xyz {x:.4f} {y:.4f} {z:.4f} --rpy {rpy[0]:.4f} {rpy[1]:.4f} {rpy[2]:.4f}")
    return 0
