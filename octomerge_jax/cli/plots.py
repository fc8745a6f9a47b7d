"""Figures users expect from a map merger (matplotlib, imported lazily here, never at package
import): the overlap clouds before/after ICP in two colours (thesis Fig. 7.6 / 7.12), a map as
occupancy-shaded voxels (Fig. 7.7 / 7.13), merges with and without refinement side by side
(Fig. 7.8 / 7.14) and the ICP convergence (rmse, inliers and the thesis's epsilons per
iteration, from ``pipeline.icp_trace``).

Every function returns a ``matplotlib.figure.Figure`` built without pyplot (no global state,
safe in threads and Dask workers; rendered with the Agg canvas) and saves it when ``path`` is
given (atomically). In Jupyter the returned figure displays inline.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .._fileutil import atomic_output
from ..map import probability

__all__ = ["plot_overlap", "plot_map", "plot_merge_comparison", "plot_icp_convergence", "plot_pose_graph", "save_figure"]

MAP1_COLOR = "#d62728"  # thesis: first map red
MAP2_COLOR = "#2ca02c"  # second map green
_MAX_POINTS = 30_000


def _figure(figsize):
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=figsize, layout="constrained")
    FigureCanvasAgg(fig)
    return fig


def save_figure(fig, path, dpi: int = 110) -> None:
    """Save ``fig`` to ``path`` (format by extension: .png, .pdf, .svg), atomically."""
    path = Path(path)
    with atomic_output(path, suffix=path.suffix or ".png") as tmp:
        fig.savefig(tmp, dpi=dpi, format=(path.suffix[1:] or "png"))


def _subsample(p, n=_MAX_POINTS, seed=0):
    p = np.asarray(p, np.float64).reshape(-1, 3)
    if p.shape[0] <= n:
        return p
    return p[np.random.default_rng(seed).choice(p.shape[0], n, replace=False)]


def _apply(T, p):
    T = np.asarray(T, np.float64)
    return p @ T[:3, :3].T + T[:3, 3]


def _equal_3d(ax, pts):
    lo, hi = pts.min(0), pts.max(0)
    c, r = (lo + hi) / 2, max(float((hi - lo).max()) / 2, 1e-3)
    ax.set_xlim(c[0] - r, c[0] + r)
    ax.set_ylim(c[1] - r, c[1] + r)
    ax.set_zlim(c[2] - r, c[2] + r)
    try:
        ax.set_box_aspect((1, 1, 1), zoom=0.85)  # room for the z label
    except (AttributeError, TypeError):  # pragma: no cover - old matplotlib
        pass
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_zlabel("z [m]")


def plot_overlap(points_1, points_2, T_1_2_init, T_1_2, path=None, *, view: str = "3d",
                 title: str | None = None, epsilons=None):
    """Thesis Fig. 7.6: the common-territory clouds before (map 2 under ``T_1_2_init``) and after
    (under the refined ``T_1_2``) registration, map 1 red, map 2 green.

    ``points_1 (n, 3)``, ``points_2 (m, 3)`` [m] in their own frames (``MergeReport.points_1`` /
    ``points_2``); ``view`` ``"3d"`` or ``"top"`` (x-y plane); ``epsilons`` an optional
    ``((eps_r, eps_t) before, (eps_r, eps_t) after)`` for the panel titles.
    """
    p1 = _subsample(points_1)
    p2 = _subsample(points_2, seed=1)
    fig = _figure((11, 5))
    panels = [("initial guess", T_1_2_init), ("after ICP", T_1_2)]
    all_pts = np.concatenate([p1, _apply(T_1_2_init, p2), _apply(T_1_2, p2)]) if p1.size + p2.size else np.zeros((1, 3))
    for k, (name, T) in enumerate(panels):
        q2 = _apply(T, p2)
        if view == "3d":
            ax = fig.add_subplot(1, 2, k + 1, projection="3d")
            ax.scatter(p1[:, 0], p1[:, 1], p1[:, 2], s=1, c=MAP1_COLOR, label="map 1", depthshade=False)
            ax.scatter(q2[:, 0], q2[:, 1], q2[:, 2], s=1, c=MAP2_COLOR, label="map 2", depthshade=False)
            _equal_3d(ax, all_pts)
            ax.view_init(elev=40, azim=-60)
        else:
            ax = fig.add_subplot(1, 2, k + 1)
            ax.scatter(p1[:, 0], p1[:, 1], s=1, c=MAP1_COLOR, label="map 1", linewidths=0)
            ax.scatter(q2[:, 0], q2[:, 1], s=1, c=MAP2_COLOR, label="map 2", linewidths=0)
            ax.set_aspect("equal")
            ax.set_xlabel("x [m]")
            ax.set_ylabel("y [m]")
        sub = name
        if epsilons is not None and epsilons[k] is not None and epsilons[k][0] is not None:
            sub += f"\n$\\epsilon_r$ = {epsilons[k][0]:.3f}, $\\epsilon_t$ = {epsilons[k][1]:.3f} m"
        ax.set_title(sub)
        ax.legend(loc="upper right", markerscale=6, fontsize=8)
    fig.suptitle(title or "Commonly mapped territory (map 1 frame)")
    if path is not None:
        save_figure(fig, path)
    return fig


def _occupied(m, max_points: int):
    lv = m.leaves()
    thr = float(np.asarray(m.params.occupancy_threshold_log_odds))
    occ = lv.log_odds >= thr
    c, s, p = lv.centers[occ], lv.sizes[occ], probability(lv.log_odds[occ].astype(np.float64))
    if c.shape[0] > max_points:
        idx = np.random.default_rng(0).choice(c.shape[0], max_points, replace=False)
        c, s, p = c[idx], s[idx], p[idx]
    return c, s, p


def _draw_map(fig, pos, m, title, max_points, zmax=None, lims=None):
    c, s, p = _occupied(m, max_points)
    ax = fig.add_subplot(*pos, projection="3d")
    if zmax is not None:
        keep = c[:, 2] <= zmax
        c, s, p = c[keep], s[keep], p[keep]
    if c.shape[0]:
        # marker area ~ leaf size (pruned leaves drawn bigger), colour = occupancy (Fig. 7.7)
        area = np.clip((s / s.min()) ** 2 * 2.0, 1.0, 60.0)
        sc = ax.scatter(c[:, 0], c[:, 1], c[:, 2], s=area, c=p, cmap="Blues", vmin=0.3, vmax=1.0,
                        marker="s", depthshade=False, linewidths=0)
        _equal_3d(ax, c if lims is None else lims)
    else:
        sc = None
    ax.view_init(elev=45, azim=-60)
    ax.set_title(title)
    return ax, sc


def plot_map(m, path=None, *, title: str | None = None, max_points: int = 40_000,
             zmax: float | None = None):
    """Thesis Fig. 7.7: the occupied leaves of ``m`` as voxels shaded by occupancy probability
    (dark blue = high, light = low); ``zmax`` [m] cuts the ceiling off to see inside rooms."""
    fig = _figure((7, 6))
    ax, sc = _draw_map(fig, (1, 1, 1), m, title or f"{m.num_leaves:,} leaves at {m.resolution:g} m",
                       max_points, zmax)
    if sc is not None:
        fig.colorbar(sc, ax=ax, shrink=0.6, label="occupancy probability")
    if path is not None:
        save_figure(fig, path)
    return fig


def _draw_map_top(fig, pos, m, title, max_points, zmin, zmax, lims):
    """Occupied leaves with centres in ``[zmin, zmax]`` seen from above (a floor plan)."""
    c, s, p = _occupied(m, max_points * 4)
    keep = (c[:, 2] >= (-np.inf if zmin is None else zmin)) & (c[:, 2] <= (np.inf if zmax is None else zmax))
    c, s, p = c[keep], s[keep], p[keep]
    order = np.argsort(p)  # most certain on top
    ax = fig.add_subplot(*pos)
    sc = None
    if c.shape[0]:
        span = float(np.ptp((lims if lims is not None else c)[:, :2], axis=0).max()) or 1.0
        points_per_m = 4.5 * 72 / span  # a panel is about 4.5 inches wide
        area = np.clip(s[order] * points_per_m, 0.5, 30.0) ** 2
        sc = ax.scatter(c[order, 0], c[order, 1], s=area, c=p[order], cmap="Blues", vmin=0.3, vmax=1.0,
                        marker="s", linewidths=0)
    if lims is not None:
        pad = 0.02 * float((lims.max(0) - lims.min(0))[:2].max())
        ax.set_xlim(lims[:, 0].min() - pad, lims[:, 0].max() + pad)
        ax.set_ylim(lims[:, 1].min() - pad, lims[:, 1].max() + pad)
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_title(title)
    return ax, sc


def plot_merge_comparison(maps, titles, path=None, *, max_points: int = 30_000, zmax: float | None = None,
                          zmin: float | None = None, view: str = "top", suptitle: str | None = None):
    """Thesis Fig. 7.8 / 7.14: maps side by side with one colour scale and one box, e.g. the
    merge with the initial guess next to the merge with the ICP-refined transform.

    ``view="top"`` (default): the occupied leaves with centres between ``zmin`` and ``zmax``
    [m] from above, a floor plan in which a misregistration shows as doubled walls;
    ``view="3d"``: a 3-D scatter with the ceiling above ``zmax`` cut off. Raises
    ``ValueError`` for another ``view``."""
    if view not in ("top", "3d"):
        raise ValueError(f"view must be 'top' or '3d', got {view!r}")
    fig = _figure((5.5 * len(maps), 5.5))
    pts = [_occupied(m, max_points)[0] for m in maps]
    nonempty = [p for p in pts if p.shape[0]]
    lims = np.concatenate(nonempty) if nonempty else None
    sc = None
    axes = []
    for k, (m, t) in enumerate(zip(maps, titles)):
        if view == "top":
            ax, s = _draw_map_top(fig, (1, len(maps), k + 1), m, t, max_points, zmin, zmax, lims)
        else:
            ax, s = _draw_map(fig, (1, len(maps), k + 1), m, t, max_points, zmax, lims)
        sc = s if s is not None else sc
        axes.append(ax)
    if sc is not None:
        fig.colorbar(sc, ax=axes, shrink=0.6, label="occupancy probability")
    if suptitle:
        fig.suptitle(suptitle)
    if path is not None:
        save_figure(fig, path)
    return fig


def plot_icp_convergence(trace: dict, path=None, *, title: str | None = None):
    """ICP per iteration (``pipeline.icp_trace``: the reported run): inlier rmse [m] and the
    correspondence distance on the left axis, inliers on the right; with a ground truth a
    second panel shows the thesis's eps_r and eps_t (eqs. 7.2 / 7.3) per iteration, and the
    errors of the transform used after a dense alignment (``epsilon_used``) as stars."""
    it = np.arange(1, len(trace["rmse"]) + 1)
    has_eps = "epsilon_r" in trace
    fig = _figure((10 if has_eps else 6, 4))
    ax = fig.add_subplot(1, 2 if has_eps else 1, 1)
    ax.plot(it, trace["rmse"], "o-", ms=3, label="inlier rmse")
    ax.step(it, trace["distance"], where="post", ls="--", c="gray", label="correspondence distance")
    ax.set_xlabel("iteration")
    ax.set_ylabel("metres")
    ax.set_yscale("log")
    ax2 = ax.twinx()
    ax2.plot(it, trace["num_inliers"], "s-", ms=2, c="tab:orange", label="inliers")
    ax2.set_ylabel("inliers")
    lines = ax.get_legend_handles_labels()
    l2 = ax2.get_legend_handles_labels()
    ax.legend(lines[0] + l2[0], lines[1] + l2[1], fontsize=8, loc="upper right")
    ax.set_title("ICP convergence")
    if has_eps:
        bx = fig.add_subplot(1, 2, 2)
        k = np.arange(len(trace["epsilon_r"]))
        bx.plot(k, trace["epsilon_r"], "o-", ms=3, label=r"$\epsilon_r$ (eq. 7.2)")
        bx.plot(k, trace["epsilon_t"], "s-", ms=3, label=r"$\epsilon_t$ [m] (eq. 7.3)")
        if "epsilon_used" in trace:  # the transform used after ICP (dense alignment)
            er, et = trace["epsilon_used"]
            bx.plot([k[-1] + 1] * 2, [er, et], "*", ms=9, c="k", label="after dense alignment")
        bx.axhline(0.25, c="C0", ls=":", lw=1)
        bx.axhline(0.9, c="C1", ls=":", lw=1)
        bx.set_xlabel("iteration (0 = initial guess)")
        bx.set_yscale("log")
        bx.set_title("error to ground truth\n(dotted: thesis 'coherent' limits 0.25 / 0.9)")
        bx.legend(fontsize=8)
    if title:
        fig.suptitle(title)
    if path is not None:
        save_figure(fig, path)
    return fig


# --- many


def plot_pose_graph(maps, report, path=None, *, max_points: int = 4000, title: str | None = None):
    """Top view of a team merge (``merge_many``): every placed map's occupied voxels in map 0's
    frame (one colour per map, at most ``max_points`` each) with its index at its centroid, and
    the pose graph's measurement edges between the centroids: solid green kept, dashed red
    rejected (labelled with why). Unplaced maps are named in the title. Saved to ``path`` if
    given; returns the figure."""
    fig = _figure((8, 6))
    ax = fig.add_subplot(1, 1, 1)
    colours = [f"C{k % 10}" for k in range(len(maps))]
    centre = {}
    for k, (m, T) in enumerate(zip(maps, report.transforms)):
        if T is None:
            continue
        p = _apply(T, _occupied(m, max_points)[0])
        if len(p) == 0:
            continue
        ax.scatter(p[:, 0], p[:, 1], s=3, color=colours[k], alpha=0.4, linewidths=0)
        centre[k] = p[:, :2].mean(0)
    for e in report.edges:
        if e.kind == "prior" or e.i not in centre or e.j not in centre:
            continue
        (x0, y0), (x1, y1) = centre[e.i], centre[e.j]
        if e.kept:
            ax.plot([x0, x1], [y0, y1], "-", color="#2ca02c", lw=2)
        else:
            ax.plot([x0, x1], [y0, y1], "--", color="#d62728", lw=1.5)
            ax.annotate(e.why.split(":")[0], ((x0 + x1) / 2, (y0 + y1) / 2), color="#d62728", fontsize=8)
    for k, c in centre.items():
        ax.annotate(str(k), c, fontsize=12, weight="bold", ha="center", va="center",
                    bbox=dict(boxstyle="circle", fc="white", ec=colours[k]))
    unplaced = [k for k, T in enumerate(report.transforms) if T is None]
    ax.set_title((title or "maps in map 0's frame; edges: kept (green), rejected (red)")
                 + (f"\nunplaced: {unplaced}" if unplaced else ""))
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_aspect("equal", adjustable="datalim")
    if path is not None:
        save_figure(fig, path)
    return fig
