"""Registration of two occupancy maps (thesis §5.2.1, §6.1-6.3): occupied-voxel clouds, overlap
extraction, point-to-point ICP (jitted, differentiable), dense alignment of the occupancy fields,
GICP on occupied voxel centres (the sub-voxel polish),
the correlation search over poses, rendezvous initial estimates, error metrics and one status
vocabulary. The rigid-transform helpers are ``octomerge_jax.se3``'s, re-exported here.

Submodules: ``points``, ``common_region`` (the function ``overlap``), ``neighbors``, ``features``
and ``global_search`` (pose candidates without a guess), ``_icp`` (private: the function ``icp``
is its public face), ``dense``, ``correlation``, ``evaluate``, ``metrics``, ``rendezvous``,
``status``, ``generalized_icp`` (the function ``gicp``).
"""

from ..se3 import check_rigid, from_quaternion, from_xyz_rpy, inverse, to_quaternion, to_xyz_rpy, transform_points
from ._icp import (COARSE_MATCHING, IcpMultiResult, IcpResult, default_hypotheses, icp, icp_multi, icp_padded,
                   icp_padded_stack, invert_result, kabsch, pad_points, pad_points_host, sequential_default,
                   stage_distances, IcpPath, icp_with_path)
from .correlation import CorrelationResult, correlation_search
from .dense import (AlignProblem, AlignResult, align_dense, alignment_loss, best_result, default_levels,
                    fused_log_odds, level_losses, pose_from_increment, prepare_alignment, problem_loss,
                    score_alignment, solve_alignment, solve_alignment_batch, stack_problems, transformed_occupancy)
from .evaluate import RegistrationStats, evaluate_registration
from .generalized_icp import GICP_MIN_POINTS, GicpResult, gicp, precompile_gicp
from .metrics import point_displacement, rotation_angle_error, rotation_error, translation_distance, translation_error
from .neighbors import HashGrid, any_within, build_grid, build_grids, nearest
from .common_region import Overlap, overlap
from .points import occupied_points
from .rendezvous import lift_2d, relative_pose_2d, relative_pose_3d, rendezvous_transform, rendezvous_transform_2d
from .status import Status, usable_mask

__all__ = [
    # status
    "Status", "usable_mask",
    # clouds and overlap (Alg. 1, 2)
    "occupied_points", "Overlap", "overlap",
    # ICP (Alg. 3)
    "COARSE_MATCHING", "IcpMultiResult", "IcpResult", "default_hypotheses", "icp", "icp_multi", "icp_padded",
    "icp_padded_stack", "invert_result", "kabsch", "pad_points", "pad_points_host", "sequential_default",
    "stage_distances", "IcpPath", "icp_with_path",
    "HashGrid", "any_within", "build_grid", "build_grids", "nearest",
    # dense alignment and the correlation search
    "AlignProblem", "AlignResult", "align_dense", "alignment_loss", "best_result", "default_levels",
    "fused_log_odds", "level_losses", "pose_from_increment", "prepare_alignment", "problem_loss",
    "score_alignment", "solve_alignment", "solve_alignment_batch", "stack_problems", "transformed_occupancy",
    "CorrelationResult", "correlation_search",
    # the GICP polish
    "GICP_MIN_POINTS", "GicpResult", "gicp", "precompile_gicp",
    # evaluation and errors
    "RegistrationStats", "evaluate_registration", "point_displacement", "rotation_angle_error", "rotation_error",
    "translation_distance", "translation_error",
    # initial estimates
    "lift_2d", "relative_pose_2d", "relative_pose_3d", "rendezvous_transform", "rendezvous_transform_2d",
    # rigid transforms (octomerge_jax.se3)
    "check_rigid", "from_quaternion", "from_xyz_rpy", "inverse", "to_quaternion", "to_xyz_rpy", "transform_points",
]
