"""Literal aliases for the string options shared by the kernels, the solvers, the merge
configuration and the command line, and the tuples of their values (for validation and
``--help``): one definition of each choice."""

from __future__ import annotations

from typing import Literal, get_args

__all__ = [
    "Rule", "RULES",
    "Method", "METHODS",
    "Space", "SPACES",
    "Refine", "REFINE_CHOICES",
    "OverlapMethod", "OVERLAP_CHOICES",
    "OnNotConverged", "ON_NOT_CONVERGED_CHOICES",
    "CoarseMatching", "COARSE_MATCHING_CHOICES",
    "Hypotheses", "HYPOTHESES_CHOICES",
    "Polish", "POLISH_CHOICES",
]

#: How ``fuse`` combines two log-odds where both maps know a voxel (thesis eq. 5.15 for "sum").
Rule = Literal["sum", "max", "weighted"]
#: How ``transform_map`` / ``sample`` interpolate (thesis Alg. 4-7 for "thesis").
Method = Literal["trilinear", "nearest", "thesis"]
#: Which quantity ``sample`` / ``transform_map`` interpolates.
Space = Literal["probability", "log_odds"]
#: The registration step of a merge.
Refine = Literal["icp", "multi", "none", "dense", "icp+dense", "global"]
#: How the commonly mapped subsets are selected before ICP (thesis Alg. 2).
OverlapMethod = Literal["voxel", "bbox", "none"]
#: What a merge does when ICP stops at its iteration limit.
OnNotConverged = Literal["warn", "error", "use_initial"]
#: How ICP's coarse stages match points.
CoarseMatching = Literal["centroid", "symmetric", "nearest"]
#: Where the guess-free search takes its starting poses.
Hypotheses = Literal["yaw_grid", "correlation", "both"]
#: The last step of the dense-ending refinements ("icp+dense", "global").
Polish = Literal["gicp", "none"]

RULES = get_args(Rule)
METHODS = get_args(Method)
SPACES = get_args(Space)
REFINE_CHOICES = get_args(Refine)
OVERLAP_CHOICES = get_args(OverlapMethod)
ON_NOT_CONVERGED_CHOICES = get_args(OnNotConverged)
COARSE_MATCHING_CHOICES = get_args(CoarseMatching)
HYPOTHESES_CHOICES = get_args(Hypotheses)
POLISH_CHOICES = get_args(Polish)
