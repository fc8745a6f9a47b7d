"""Registration of two occupancy maps (thesis §5.2.1, §6.1-6.3): occupied-voxel clouds,
overlap extraction, jitted/differentiable point-to-point ICP, rendezvous initial estimates,
error metrics and rigid-transform helpers."""

from .correlation import CorrelationResult, correlation_search
from . import dense
from .dense import (AlignProblem, AlignResult, align_dense, alignment_loss, best_result,
                     default_levels, fused_log_odds, level_losses, pose_from_increment, prepare_alignment,
                     problem_loss, score_alignment, solve_alignment, solve_alignment_batch, stack_problems,
                     transformed_occupancy)
from .evaluate import RegistrationStats, evaluate_registration
from ._icp import (COARSE_MATCHING, IcpMultiResult, IcpResult, default_hypotheses, icp, icp_multi, icp_padded,
                   icp_padded_stack, invert_result, kabsch, pad_points, pad_points_host, sequential_default,
                   stage_distances)
from .metrics import (point_displacement, rotation_angle_error, rotation_error, translation_distance,
                      translation_error)
from .neighbors import HashGrid, any_within, build_grid, build_grids, nearest
from .status import Status
from .overlap import Overlap, overlap
from .points import occupied_points
from .rendezvous import (lift_2d, relative_pose_2d, relative_pose_3d, rendezvous_transform,
                         rendezvous_transform_2d)
from ..se3 import check_rigid, from_quaternion, from_xyz_rpy, inverse, to_quaternion, to_xyz_rpy, transform_points

__all__ = [
    "CorrelationResult", "correlation_search",
    "AlignProblem", "AlignResult", "align_dense", "alignment_loss", "best_result", "default_levels",
    "fused_log_odds", "level_losses", "pose_from_increment", "prepare_alignment", "problem_loss",
    "score_alignment", "solve_alignment", "solve_alignment_batch", "stack_problems", "transformed_occupancy",
    "RegistrationStats", "evaluate_registration", "COARSE_MATCHING", "IcpMultiResult", "IcpResult", "default_hypotheses", "icp", "icp_multi", "icp_padded", "icp_padded_stack",
    "invert_result", "kabsch", "pad_points_host", "sequential_default",
    "pad_points", "stage_distances", "rotation_angle_error", "rotation_error",
    "translation_distance", "translation_error", "point_displacement", "Status", "HashGrid", "any_within", "build_grid",
    "build_grids", "nearest", "Overlap", "overlap", "occupied_points", "lift_2d",
    "relative_pose_2d", "relative_pose_3d", "rendezvous_transform", "rendezvous_transform_2d",
    "check_rigid", "from_quaternion", "from_xyz_rpy", "inverse", "to_quaternion", "to_xyz_rpy",
    "transform_points",
]
