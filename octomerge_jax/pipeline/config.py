"""Every parameter of the merge pipeline, as nested dataclass sections, their ranges
(``validate``) and their plain-dict form. Reading and writing them as TOML or JSON:
``config_file``.

The sections mirror the pipeline (thesis Ch. 6): ``registration`` (Alg. 1-3: occupied points,
overlap, ICP), ``transform`` (Alg. 4-7), ``fuse`` (Alg. 8), ``batch`` (many pairs) and ``demo``
(the simulated two-robot job). ``octomerge dump-config`` prints the defaults; every subcommand
takes ``--config FILE``; command-line flags override the file.

    cfg = MergeConfig()                                  # defaults
    cfg = load_config("merge.toml")                      # partial files are fine
    cfg = cfg.replace(registration={"refine": "multi"})  # functional update
    text = dumps_toml(cfg)

Unknown keys and wrong types raise ``ValueError`` naming the file and the key, so a typo never
silently falls back to a default.
"""

from __future__ import annotations

import dataclasses
import math
import types
import typing

from ..types import (COARSE_MATCHING_CHOICES, HYPOTHESES_CHOICES, ON_NOT_CONVERGED_CHOICES, OVERLAP_CHOICES,
                     POLISH_CHOICES, REFINE_CHOICES)

__all__ = [
    "RegistrationConfig",
    "TransformConfig",
    "FuseConfig",
    "BatchConfig",
    "DemoConfig",
    "MergeConfig",
    "REFINE_CHOICES",
    "OVERLAP_CHOICES",
    "ON_NOT_CONVERGED_CHOICES",
    "HYPOTHESES_CHOICES",
    "DEMO_SCENES",
    "COARSE_MATCHING_CHOICES",
    "POLISH_CHOICES",
    "config_from_dict",
    "config_to_dict",
    "validate",
]

DEMO_SCENES = ("lab", "office", "campus")


@dataclasses.dataclass(frozen=True)
class RegistrationConfig:
    """Alg. 1-3: occupied-leaf clouds, commonly mapped subsets, refinement of the guess.

    - ``refine``: ``"icp+dense"`` (the default: ICP from the guess on the commonly mapped
      subsets, then the dense alignment of the occupancy fields from ICP's result at the
      levels finer than ICP's last correspondence distance: sub-voxel, see ``docs/design.md``,
      "Dense alignment ends the default refinement"), ``"icp"`` (ICP only: faster, about a
      voxel off), ``"multi"`` (candidates from ``hypotheses``, the one whose maps agree best
      picked, then one ICP on the commonly mapped subsets from it, kept if the maps agree
      better; for poor guesses), ``"dense"`` (``registration.align_dense`` only),
      ``"none"`` (trust the guess) or ``"global"`` (no guess needed:
      ``pipeline.register_global``, then the dense alignment from its result as in
      ``"icp+dense"``; what ``merge`` uses when no guess is given and ``refine`` is left at
      its default).
    - ``overlap``: ``"bbox"`` (thesis Alg. 2: intersection of bounding boxes; the default),
      ``"voxel"`` (points near the other map's points under the guess) or ``"none"`` (all
      points).
    - ``overlap_margin``: [m] the overlap test's slack: ``radius`` of ``"voxel"`` (a point is
      kept if the other cloud has a point that close under the guess), ``margin`` of
      ``"bbox"`` (``None``: 3 voxels for ``"voxel"``, the thesis's 1 m for ``"bbox"``).
    - ``min_overlap_points``: fewer common points in either map means "no overlap" (an error).
    - ``max_correspondence_distance`` / ``min_correspondence_distance`` [m]: ICP's distance
      schedule (``None``: 10 and 2 voxels), shrunk by ``shrink_factor`` each time the change of
      the transform falls below ``transformation_epsilon`` (``None``: resolution / 60).
    - ``max_iterations``, ``min_inliers``, ``cell_capacity``: ICP limits (see ``registration.icp``).
    - ``coarse_matching``: ICP's coarse stages: ``"centroid"`` (every 4th source point, from
      8192 points up, to the target's voxel-grid centroids; the default), ``"symmetric"``
      (both clouds' centroids) or ``"nearest"`` (Open3D's fixed point). See ``registration.icp``.
    - ``hypotheses``: where ``refine="multi"`` starts: ``"yaw_grid"`` (the guess turned about
      map 2's centroid every ``yaw_step_rad``, plus +-``roll_pitch_offset_rad`` of roll and
      pitch; keeps the guess's translation), ``"correlation"`` (the ``correlation_hypotheses``
      best poses of ``registration.correlation_search``: a fine yaw grid x every translation,
      scored by the maps' occupancy agreement; the best ``correlation_dense`` of them also
      start the dense alignment, 0 turns that off; a guess tilted by more than 0.02 rad is
      also searched level) or ``"both"`` (the default). With ``"both"`` the correlation
      candidates' pick is taken over the yaw grid's when only it passes the dense status
      checks (agreement, overlap), else only when its map loss is lower by more than
      ``far_margin`` (relative).
    - ``polish``: the last step of ``"icp+dense"`` and ``"global"``: ``"gicp"`` (the default:
      ``registration.gicp`` from the dense result, plane-to-plane on the occupied voxel
      centres, kept when it moves the pose less than a voxel; ``docs/design.md``,
      "GICP polishes the default refinement") or ``"none"``.
    - ``on_not_converged``: ICP stopped at ``max_iterations``: ``"warn"`` (use its transform,
      report ``converged = false``), ``"error"`` (fail) or ``"use_initial"`` (merge with the
      guess). Too few inliers is always an error unless ``refine="none"``.
    """

    refine: str = "icp+dense"
    overlap: str = "bbox"
    overlap_margin: float | None = None
    min_overlap_points: int = 30
    max_correspondence_distance: float | None = None
    min_correspondence_distance: float | None = None
    shrink_factor: float = 0.5
    transformation_epsilon: float | None = None
    max_iterations: int = 100
    min_inliers: int = 6
    cell_capacity: int = 8
    coarse_matching: str = "centroid"
    yaw_step_rad: float = math.pi / 6
    roll_pitch_offset_rad: float = 0.1
    hypotheses: str = "both"
    correlation_hypotheses: int = 8
    correlation_dense: int = 3
    far_margin: float = 0.03
    polish: str = "gicp"
    on_not_converged: str = "warn"


@dataclasses.dataclass(frozen=True)
class TransformConfig:
    """Alg. 4-7: resampling map 2 into map 1's frame (``resample.transform_map``).

    - ``interpolation``: ``"trilinear"`` (unknown neighbours left out), ``"nearest"`` or
      ``"thesis"`` (unknown neighbours weigh as p = 0, Appendix A.2).
    - ``space``: interpolate in ``"probability"`` (thesis) or ``"log_odds"``.
    - ``chunk_bricks``: destination bricks (8^3 voxels) per scan step (memory/speed trade-off).
    - ``resample_resolution``: maps of different resolutions are an error unless this is true;
      then map 2 is resampled onto map 1's voxel grid (trilinear samples at map 1's voxel
      centres).
    """

    interpolation: str = "trilinear"
    space: str = "probability"
    chunk_bricks: int = 64
    resample_resolution: bool = False


@dataclasses.dataclass(frozen=True)
class FuseConfig:
    """Alg. 8 (``fuse.fuse`` / ``fuse.fuse_many``).

    - ``rule``: ``"sum"`` (eq. 5.15, independent maps), ``"max"`` (maps sharing data) or
      ``"weighted"`` (with ``weights``).
    - ``weights``: one per map, for ``rule = "weighted"``.
    """

    rule: str = "sum"
    weights: tuple[float, ...] = (1.0, 1.0)


@dataclasses.dataclass(frozen=True)
class BatchConfig:
    """``octomerge batch``.

    - ``workers``: local processes / threads (0: run in this process).
    - ``scheduler``: a Dask address (``tcp://host:8786``) or ``""``.
    - ``resume``: skip pairs whose output exists.
    - ``group_by_bucket``: run pairs of one capacity bucket through one jitted ``vmap`` call
      (``merge_batch``) instead of one by one.
    - ``timeout_s`` [s]: how long to wait for the scheduler to answer and, once every worker
      is gone, for one to come back before the pending pairs fail.
    """

    workers: int = 0
    scheduler: str = ""
    resume: bool = True
    group_by_bucket: bool = True
    timeout_s: float = 60.0  # wait for a scheduler to answer / for a worker when none is left


@dataclasses.dataclass(frozen=True)
class DemoConfig:
    """``octomerge demo``: the simulated two-robot job (``sim.make_two_robot_maps``).

    - ``scene``: ``"lab"``, ``"office"`` or ``"campus"`` (outdoor, lidar: use resolution 0.2).
    - ``resolution``: voxel edge [m].
    - ``spacing``: between scans [m]; 0: the scene's own (lab / office 0.5, campus 2).
    - ``seed``: of the simulated robots' paths and noise.
    - ``error_xyz`` [m] / ``error_rpy_rad``: perturb the true ``T_1_2`` to make the erroneous
      initial guess (thesis eqs. 7.2/7.3 give its eps_r / eps_t).
    """

    scene: str = "lab"
    resolution: float = 0.1
    spacing: float = 0.0
    seed: int = 0
    error_xyz: tuple[float, float, float] = (0.4, -0.3, 0.0)
    error_rpy_rad: tuple[float, float, float] = (0.0, 0.0, 0.05)


@dataclasses.dataclass(frozen=True)
class MergeConfig:
    """All parameters (one section per pipeline stage)."""

    registration: RegistrationConfig = RegistrationConfig()
    transform: TransformConfig = TransformConfig()
    fuse: FuseConfig = FuseConfig()
    batch: BatchConfig = BatchConfig()
    demo: DemoConfig = DemoConfig()

    def replace(self, **sections) -> "MergeConfig":
        """Copy with sections updated: ``cfg.replace(registration={"refine": "none"})`` (a dict
        updates only the named keys; a section dataclass replaces the section)."""
        changes = {}
        for name, value in sections.items():
            current = getattr(self, name, None)
            if not dataclasses.is_dataclass(current):
                raise ValueError(f"MergeConfig has no section {name!r}")
            if isinstance(value, dict):
                value = _section_from_dict(type(current), {**config_to_dict(current), **value}, name)
            changes[name] = value
        out = dataclasses.replace(self, **changes)
        validate(out)
        return out


def validate(cfg: MergeConfig) -> None:
    """Raise ``ValueError`` naming the key for out-of-range or unknown choices."""
    r, t, f = cfg.registration, cfg.transform, cfg.fuse
    _choice(r.refine, REFINE_CHOICES, "registration.refine")
    _choice(r.overlap, OVERLAP_CHOICES, "registration.overlap")
    _choice(r.on_not_converged, ON_NOT_CONVERGED_CHOICES, "registration.on_not_converged")
    _choice(r.coarse_matching, COARSE_MATCHING_CHOICES, "registration.coarse_matching")
    _choice(r.hypotheses, HYPOTHESES_CHOICES, "registration.hypotheses")
    _choice(r.polish, POLISH_CHOICES, "registration.polish")
    _choice(t.interpolation, ("trilinear", "nearest", "thesis"), "transform.interpolation")
    _choice(t.space, ("probability", "log_odds"), "transform.space")
    _choice(f.rule, ("sum", "max", "weighted"), "fuse.rule")
    for key, (lo, hi, lo_open) in _RANGES.items():
        section, name = key.split(".")
        value = getattr(getattr(cfg, section), name)
        if value is not None:
            _check_range(key, value, lo, hi, lo_open)
    if (r.min_correspondence_distance is not None and r.max_correspondence_distance is not None
            and r.min_correspondence_distance > r.max_correspondence_distance):
        raise ValueError("registration.min_correspondence_distance must not exceed "
                         f"registration.max_correspondence_distance, got {r.min_correspondence_distance} > "
                         f"{r.max_correspondence_distance}")
    if not 0.0 < r.shrink_factor < 1.0:
        raise ValueError(f"registration.shrink_factor must lie in (0, 1), got {r.shrink_factor}")
    _check_weights(f.weights)
    _choice(cfg.demo.scene, DEMO_SCENES, "demo.scene")
    if not (math.isfinite(cfg.demo.spacing) and cfg.demo.spacing >= 0):
        raise ValueError(f"demo.spacing must be >= 0 metres (0: the scene's own), got {cfg.demo.spacing}")
    if cfg.demo.spacing != 0:
        _check_range("demo.spacing", cfg.demo.spacing, *_DEMO_SPACING, False)
    for key in ("error_xyz", "error_rpy_rad"):
        for v in getattr(cfg.demo, key):
            _check_range(f"demo.{key}", v, -_DEMO_ERROR[key], _DEMO_ERROR[key], False)


def _choice(value, choices, key):
    if value not in choices:
        raise ValueError(f"{key} must be one of {', '.join(map(repr, choices))}, got {value!r}")


# ----------------------------------------------------------------------------- dict <-> dataclass


def config_to_dict(obj) -> dict:
    """A config (or section) as a plain nested dict; ``None`` values are left out (TOML has no
    null, and a missing key means the default)."""
    out = {}
    for f in dataclasses.fields(obj):
        v = getattr(obj, f.name)
        if dataclasses.is_dataclass(v):
            out[f.name] = config_to_dict(v)
        elif v is None:
            continue
        elif isinstance(v, tuple):
            out[f.name] = list(v)
        else:
            out[f.name] = v
    return out


def _coerce(value, annotation, key: str):
    """Check/convert one value against its field annotation (str, int, float, bool, tuples,
    ``X | None``)."""
    origin = typing.get_origin(annotation)
    if origin in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(annotation) if a is not type(None)]
        if value is None:
            return None
        return _coerce(value, args[0], key)
    if origin is tuple:
        if not isinstance(value, (list, tuple)):
            raise ValueError(f"{key}: expected a list, got {value!r}")
        args = typing.get_args(annotation)
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_coerce(v, args[0], key) for v in value)
        if len(value) != len(args):
            raise ValueError(f"{key}: expected {len(args)} values, got {len(value)}")
        return tuple(_coerce(v, a, key) for v, a in zip(value, args))
    if annotation is bool:
        if not isinstance(value, bool):
            raise ValueError(f"{key}: expected true or false, got {value!r}")
        return value
    if annotation is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ValueError(f"{key}: expected an integer, got {value!r}")
        return value
    if annotation is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ValueError(f"{key}: expected a number, got {value!r}")
        return float(value)
    if annotation is str:
        if not isinstance(value, str):
            raise ValueError(f"{key}: expected a string, got {value!r}")
        return value
    raise TypeError(f"{key}: unsupported annotation {annotation!r}")  # pragma: no cover


def _section_from_dict(cls, data: dict, prefix: str):
    if not isinstance(data, dict):
        raise ValueError(f"{prefix}: expected a table of settings, got {data!r}")
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(data) - names)
    if unknown:
        raise ValueError(f"unknown setting {prefix + '.' if prefix else ''}{unknown[0]} "
                         f"(known: {', '.join(sorted(names))})")
    kwargs = {}
    for name, value in data.items():
        key = f"{prefix}.{name}" if prefix else name
        ann = hints[name]
        if dataclasses.is_dataclass(ann):
            kwargs[name] = _section_from_dict(ann, value, key)
        else:
            kwargs[name] = _coerce(value, ann, key)
    return cls(**kwargs)


def config_from_dict(data: dict) -> MergeConfig:
    """A ``MergeConfig`` from a (possibly partial) nested dict; missing keys keep defaults."""
    cfg = _section_from_dict(MergeConfig, data, "")
    validate(cfg)
    return cfg


# --- cli
# Ranges of the numeric settings, [lo, hi] (``lo_open``: (lo, hi]): beyond them a value crashes
# a stage or makes it run away (a 1e-9 yaw step is 6e9 ICP starts, 1e8 chunk bricks 10 GiB).
_RANGES = {
    "registration.overlap_margin": (0.0, 1e4, True),
    "registration.min_overlap_points": (0, 2**31 - 1, False),
    "registration.max_correspondence_distance": (0.0, 1e4, True),
    "registration.min_correspondence_distance": (0.0, 1e4, True),
    "registration.transformation_epsilon": (0.0, 1e4, True),
    "registration.max_iterations": (1, 100_000, False),
    "registration.min_inliers": (1, 2**31 - 1, False),
    "registration.cell_capacity": (1, 1024, False),
    "registration.yaw_step_rad": (2 * math.pi / 720, 2 * math.pi, False),  # at most 720 yaw starts
    "registration.roll_pitch_offset_rad": (0.0, math.pi, False),
    "registration.correlation_hypotheses": (1, 1024, False),
    "registration.correlation_dense": (0, 1024, False),
    "registration.far_margin": (0.0, 1e3, False),
    "transform.chunk_bricks": (1, 1 << 16, False),
    "batch.workers": (0, 1024, False),
    "batch.timeout_s": (0.0, 1e6, True),
    "demo.resolution": (0.02, 5.0, False),
    "demo.seed": (0, 2**32 - 1, False),
}
_DEMO_SPACING = (0.1, 100.0)  # metres between scans, when not 0 (the scene's own)
_DEMO_ERROR = {"error_xyz": 1e3, "error_rpy_rad": 2 * math.pi}  # |error| bound, metres / radians
_MAX_WEIGHT = 1e6  # a larger fusion weight turns float32 log-odds into inf / nan


def _check_range(key: str, value, lo, hi, lo_open: bool) -> None:
    """Raise ``ValueError`` naming ``key`` unless ``value`` is a finite number in ``[lo, hi]``
    (``(lo, hi]`` when ``lo_open``)."""
    finite = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
    if not (finite and (value > lo if lo_open else value >= lo) and value <= hi):
        raise ValueError(f"{key} must lie in {'(' if lo_open else '['}{lo:g}, {hi:g}], got {value!r}")


def _check_weights(weights) -> None:
    """``fuse.weights``: one finite weight in ``[0, 1e6]`` per map (at least 2), not all 0."""
    if len(weights) < 2:
        raise ValueError(f"fuse.weights must hold one weight per map (at least 2), got {list(weights)}")
    if not all(math.isfinite(w) and 0 <= w <= _MAX_WEIGHT for w in weights):
        raise ValueError(f"fuse.weights must be finite numbers in [0, {_MAX_WEIGHT:g}], got {list(weights)}")
    if not any(w > 0 for w in weights):
        raise ValueError(f"fuse.weights must not all be 0 (that erases every voxel), got {list(weights)}")
