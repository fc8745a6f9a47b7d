"""Dense (map-to-map) alignment and gradient-based transform tuning: the public names of
``registration._dense`` under the module path ``octomerge_jax.registration.dense``."""

from ._dense import (AlignProblem, AlignResult, Solver, align_dense, alignment_loss, best_result, coarsen,
                     default_levels, fused_log_odds, level_losses, pose_from_increment, prepare_alignment,
                     problem_loss, score_alignment, solve_alignment, solve_alignment_batch, stack_problems,
                     transformed_occupancy)

__all__ = [
    "AlignProblem", "AlignResult", "Solver", "align_dense", "alignment_loss", "best_result", "coarsen",
    "default_levels", "fused_log_odds", "level_losses", "pose_from_increment", "prepare_alignment",
    "problem_loss", "score_alignment", "solve_alignment", "solve_alignment_batch", "stack_problems",
    "transformed_occupancy",
]
