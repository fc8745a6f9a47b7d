"""Map transformation by inverse mapping and trilinear resampling (thesis §3.2, §5.2.2, §6.4,
Alg. 4-7, eqs. 3.6-3.13 and 5.13), plus differentiable trilinear ``sample``.

``transform_map(m, T_dst_src)`` expresses map ``m`` (built in frame ``src``) in frame ``dst`` at
the same resolution. As in the thesis, every destination voxel centre ``x_n`` (depth 16) is
mapped back, ``x_s = T_dst_src^-1 x_n`` (eq. 5.13), and gets a value only if ``x_s`` falls
inside a known source leaf (of any depth). The value is interpolated from the 8 finest voxel
centres that enclose ``x_s`` (eqs. 3.6-3.13; a neighbour inside a pruned, coarse leaf takes
that leaf's value). Differences from the published code (Appendix A.2):

- the true rigid inverse ``(R^T, -R^T t)``: A.2 builds row 3 of ``R`` from element (0,2)
  instead of (2,1) and inverts the translation as ``-t``;
- non-rigid, NaN or non-finite transforms raise ``ValueError`` on the host;
- ``method="trilinear"`` leaves unknown neighbours out and renormalises the remaining weights,
  so unknown space is not painted free (A.2 weighs them as p = 0; that rule is kept as
  ``method="thesis"``);
- output log-odds are finite and clamped to the map's ``[clamp_min, clamp_max]``;
- where every contributing neighbour holds the same log-odds the output is that value
  exactly (no float round trip through probability), so uniform regions stay prunable and
  whole-voxel moves are exact permutations.

How: the host refines the destination top-down (``_cells.py``): a destination cell whose
interpolation stencils all read one uniform source region is one output leaf of that value
(resampled at its own scale), a cell whose stencils read nothing known is dropped, and only
cells near a change of value are split, down to *bricks* (depth-13 nodes, 8^3 voxels). The
brick plan (``_bricks.py``) gives each such brick a 3x3x3 window of source bricks in a
brick-indexed table of the source; a jitted loop (``_kernel.py``) resamples the bricks in
fixed-size chunks with the blends of ``_interp.py``, prunes each brick inside itself and
appends its leaves; coarse cells and whole-brick leaves are merged last (``_merge.py``).
Memory and time follow the output's leaves, not the volume it covers.
"""

from __future__ import annotations

import numpy as np

from .. import morton
from ..map import OccupancyMap
from ..se3 import check_rigid_transform
from ._bricks import make_plan, transformed_bounds
from ._interp import METHODS, SPACES, check_choice, sample
from ._kernel import run_kernel
from ._merge import merge_with_cells

__all__ = [
    "METHODS",
    "SPACES",
    "check_rigid_transform",
    "transformed_bounds",
    "transform_map",
    "sample",
]


def transform_map(m: OccupancyMap, T_dst_src, method: str = "trilinear", *,
                  space: str = "probability", chunk_bricks: int = 128,
                  out_capacity: int | None = None) -> OccupancyMap:
    """Alg. 7 (corrected): the map ``m`` of frame ``src`` expressed in frame ``dst``.

    Args:
      m: source map (leaves at any depth).
      T_dst_src: ``(4, 4)`` rigid transform mapping points of ``src`` into ``dst`` (metres).
      method: ``"trilinear"`` (unknown neighbours left out, weights renormalised),
        ``"nearest"`` (value of the source leaf containing ``x_s``) or ``"thesis"``
        (unknown neighbours weigh as probability 0, as Appendix A.2; bugs fixed).
      space: interpolate in ``"probability"`` (thesis) or ``"log_odds"``; ``"thesis"``
        requires ``"probability"``.
      chunk_bricks: destination bricks (8^3 voxels) per loop step (static; a step's work
        arrays take roughly ``chunk_bricks * 512 * 8 * 16`` bytes).
      out_capacity: static output capacity before the final prune; default a guess from the
        leaf and brick counts, grown (the kernel resumes where it stopped) if it fills up.

    Returns a maximally pruned map with the source's resolution and parameters: destination
    voxels (depth 16) whose centre maps back into a known source leaf, log-odds clamped.
    Raises ``ValueError`` for an invalid transform, method, space or chunk size, or when the
    transformed map would leave OctoMap's key range; ``budget.MemoryBudgetError`` before an
    allocation over the memory budget (an output of very many leaves: a coarse leaf moved by
    a fraction of its size has a boundary of finest voxels).
    """
    check_choice(method, METHODS, "method")
    check_choice(space, SPACES, "space")
    if method == "thesis" and space != "probability":
        raise ValueError('method="thesis" interpolates in probability; use space="probability"')
    if chunk_bricks < 1:
        raise ValueError(f"chunk_bricks must be positive, got {chunk_bricks}")
    T = check_rigid_transform(T_dst_src)
    res = m.resolution
    if m.num_leaves == 0:
        return m
    p_min, p_max = transformed_bounds(m, T)
    limit = morton.KEY_OFFSET * res * (1 + 1e-12)  # rounding of a map spanning the key range
    if np.any(p_min < -limit) or np.any(p_max > limit):
        raise ValueError(
            f"T_dst_src: the transformed map spans {p_min.round(3).tolist()} .. "
            f"{p_max.round(3).tolist()} m, outside OctoMap's key range +-{limit:g} m at "
            f"resolution {res:g} m")
    plan = make_plan(m, T, method, space, int(chunk_bricks), out_capacity, (p_min, p_max))
    cells = plan.cells
    kernel_out, total = run_kernel(plan) if plan.n_dest_bricks else (None, 0)
    return merge_with_cells(kernel_out, total, cells.codes, cells.depths, cells.log_odds, m).trimmed()
