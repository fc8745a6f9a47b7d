"""The merge pipeline (thesis Ch. 6): configuration, the registration step, ``merge``,
``merge_many`` and ``merge_batch``, and what they report."""

from .batch import BatchResult, merge_batch
from .clouds import VOXEL_OVERLAP_VOXELS, overlap_margin, point_stats
from .config import (COARSE_MATCHING_CHOICES, DEMO_SCENES, HYPOTHESES_CHOICES, ON_NOT_CONVERGED_CHOICES,
                     OVERLAP_CHOICES, POLISH_CHOICES, REFINE_CHOICES, BatchConfig, DemoConfig, FuseConfig, MergeConfig,
                     RegistrationConfig, TransformConfig, config_from_dict, config_to_dict, validate)
from .config_file import dumps_toml, load_config, save_config
from .globalreg import candidate_listener, judge_local, register_global
from .many import merge_many
from .many_report import EdgeReport, ManyReport, MapReport
from .merging import (check_resolutions, fuse_in_frame_1, merge, resample_to_resolution, transform_and_fuse,
                      transform_from_xyz_rpy, transform_to_frame_1)
from .ranking import rank_by_map_agreement
from .refine import dense_after_global, polish, register
from .report import MergeError, MergeReport, Registration
from .timings import Timings, stage_listener
from .trace import icp_trace

__all__ = [
    "BatchConfig", "BatchResult", "COARSE_MATCHING_CHOICES", "DEMO_SCENES", "DemoConfig", "EdgeReport", "FuseConfig",
    "ManyReport", "MapReport",
    "HYPOTHESES_CHOICES", "MergeConfig", "MergeError", "MergeReport", "ON_NOT_CONVERGED_CHOICES",
    "OVERLAP_CHOICES", "POLISH_CHOICES", "REFINE_CHOICES", "Registration", "RegistrationConfig", "Timings", "TransformConfig",
    "VOXEL_OVERLAP_VOXELS", "check_resolutions", "config_from_dict", "config_to_dict", "dense_after_global",
    "dumps_toml", "icp_trace", "judge_local", "load_config", "merge", "merge_batch", "merge_many", "overlap_margin",
    "point_stats", "polish",
    "rank_by_map_agreement", "register", "register_global", "resample_to_resolution", "save_config",
    "transform_and_fuse", "transform_from_xyz_rpy", "validate",
    "candidate_listener", "fuse_in_frame_1", "stage_listener", "transform_to_frame_1",  # --- the command line
]
