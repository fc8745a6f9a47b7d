"""Dense (map-to-map) alignment and gradient-based transform tuning.

ICP (Alg. 3) aligns the *occupied* voxel centres of two maps. Here the whole map takes part:
map 1 is read by trilinear interpolation (thesis eqs. 3.6-3.13) at the known voxels of map 2
moved by ``T_1_2``, and the agreement of the two signed occupancy fields is a differentiable
function of the pose, minimised coarse to fine by L-BFGS (Nocedal & Wright ch. 7).

- ``_problem``: host planning (``prepare_alignment``: the coarsened levels and map 2's
  weighted sample points), the ``AlignProblem`` pytree, ``pose_from_increment``;
- ``_loss``: the symmetric agreement loss, ``problem_loss`` / ``alignment_loss``, the status
  scores (``score_alignment``);
- ``_solve``: ``solve_alignment`` / ``align_dense``, the guard restart and the status checks;
- ``_lbfgs``, ``_jaxopt``: the two minimiser backends (``solver="lbfgs"`` / ``"jaxopt"``);
- ``_tuning``: ``transformed_occupancy`` and ``fused_log_odds`` with a traced transform.
"""

from ...tree import coarsen
from ._loss import alignment_loss, level_losses, problem_loss, score_alignment
from ._problem import AlignProblem, default_levels, pose_from_increment, prepare_alignment, stack_problems
from ._solve import AlignResult, Solver, align_dense, best_result, solve_alignment, solve_alignment_batch
from ._tuning import fused_log_odds, transformed_occupancy

__all__ = [
    "AlignProblem", "AlignResult", "Solver", "align_dense", "alignment_loss", "best_result", "coarsen",
    "default_levels", "fused_log_odds", "level_losses", "pose_from_increment", "prepare_alignment",
    "problem_loss", "score_alignment", "solve_alignment", "solve_alignment_batch", "stack_problems",
    "transformed_occupancy",
]
