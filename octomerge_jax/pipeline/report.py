"""What a merge reports: ``Registration`` (the registration step's outcome), ``MergeReport``
(host values, JSON) and ``MergeError`` (an input the user must fix, with a ``kind`` that says
which)."""

from __future__ import annotations

import dataclasses
import json
import math
import re

import jax
import numpy as np

from .._fileutil import atomic_write_bytes

__all__ = ["MergeError", "MergeReport", "Registration"]

_NUM_LIST = re.compile(r"\[\s*((?:-?[0-9.eE+-]+|null)(?:,\s*(?:-?[0-9.eE+-]+|null))*)\s*\]")



class MergeError(ValueError):
    """A merge the pipeline refuses, with ``kind`` one of ``"resolution"``, ``"transform"``,
    ``"empty"``, ``"no_overlap"``, ``"icp_failed"``, ``"not_converged"`` (the CLI maps kinds
    to exit codes). ``report`` holds the partial ``MergeReport`` when there is one."""

    def __init__(self, message: str, kind: str, report: "MergeReport | None" = None):
        super().__init__(message)
        self.kind = kind
        self.report = report


@dataclasses.dataclass(frozen=True)
class Registration:
    """The registration step's outcome (``register``; thesis Alg. 1-3), host values.

    - ``T_1_2``: ``(4, 4)`` float64, the transform to merge with (map 2's frame into map 1's
      [m]), rigid (``se3.project_to_rigid``).
    - ``converged``: whether the solver whose transform is used converged (``True`` for
      ``refine="none"``).
    - ``info``: the solver's figures, JSON-ready (``MergeReport.icp``); ``None`` for
      ``refine="none"``.
    - ``result``: the solver's own result (``IcpResult``, ``IcpMultiResult``, ``AlignResult``)
      or ``None``.
    - ``counts``: point counts: ``occupied_1`` / ``occupied_2`` and, when subsets were cut,
      ``overlap_1`` / ``overlap_2``.
    - ``points_1`` ``(n1, 3)``, ``points_2`` ``(n2, 3)``: float32 [m], the clouds registered
      (the overlap subsets, or the occupied clouds), each in its own map's frame.
    - ``warnings``: human-readable lines (ICP not converged, dense alignment failed, ...).
    - ``confidence``: in [0, 1], how much the transform is to be trusted (``refine="global"``:
      the margin of the best over the second-best distinct pose and the overlap explained;
      ``None`` where not assessed). The merge's status is ``info["verdict"]`` when present.
    - ``candidates``: the top distinct poses, best first, each a dict with at least
      ``"T_1_2"`` (4x4 nested list) and ``"score"`` (share of the smaller map explained).
    """

    T_1_2: np.ndarray
    converged: bool
    info: dict | None
    result: object
    counts: dict
    points_1: np.ndarray
    points_2: np.ndarray
    warnings: tuple[str, ...] = ()
    # --- global
    confidence: float | None = None
    candidates: tuple = ()


@dataclasses.dataclass(frozen=True)
class MergeReport:
    """What a merge did (host values; ``to_json()`` writes the fields below by these names).

    - ``T_1_2_init``, ``T_1_2``: ``(4, 4)`` float64, the initial guess and the transform used
      (after refinement), mapping map 2's frame into map 1's [m].
    - ``T_1_2_true``: ground truth if given, else ``None``.
    - ``refine``: ``"icp"``, ``"multi"``, ``"dense"``, ``"icp+dense"``, ``"none"`` or ``"global"``
      (then ``icp`` also holds ``verdict`` and ``global``: ``register_global``'s figures).
    - ``icp``: the ICP result as a dict (``converged``, ``status``, ``num_iterations``,
      ``num_inliers``, ``rmse`` [m], ``fitness``, ``correspondence_distance`` [m], ...; for
      ``"dense"`` the same keys for the dense alignment (status names ``str(Status)``,
      the point statistics measured at its transform by ``point_stats``) and its own figures
      under ``dense`` (for ``"icp+dense"``: ICP's fields, and under ``dense`` the dense
      alignment's with the point statistics at the transform used; ``start_level``, the index
      of the first level solved, and ``restarted``, ``AlignResult.restarted``; and under ``gicp``
      the polish's: ``used``, ``converged``, ``num_iterations``, ``num_inliers``, ``num_samples``,
      ``rmse`` [m], ``shift`` [m], the samples' mean move); for
      ``"multi"`` also ``best_index`` (the candidate chosen by map agreement,
      ``rank_by_map_agreement``), ``point_best_index`` (``icp_multi``'s own choice),
      ``map_loss`` per candidate, ``num_hypotheses``, ``num_basins``: the ICP runs left after
      merging hypotheses that reached one basin, and ``local``: the local ICP on the commonly
      mapped subsets from the chosen candidate, ``used`` when it lowered the map loss (or, under
      ``dense``, the dense alignment from it when neither passed the dense status checks), whose
      convergence, iterations, inliers and rmse the top-level fields then report; a pick
      from the dense alignment has its point statistics measured at its transform,
      ``stats_evaluated``),
      ``None`` for ``refine="none"``.
    - ``epsilon_r_init``, ``epsilon_t_init``, ``epsilon_r``, ``epsilon_t``: thesis eqs. 7.2 /
      7.3 before / after refinement when ``T_1_2_true`` is given (else ``None``).
    - ``displacement_init``, ``displacement``: mean distance [m] between map 2's occupied leaf
      centres placed by the guess / the result and by ``T_1_2_true`` (else ``None``). Unlike
      eps_t it does not grow with the distance of the map from its frame's origin.
    - ``counts``: leaves of both inputs and of the result, occupied and overlap points, fuse
      case counts (``FuseReport.host()``).
    - ``timings``: seconds per stage (``occupied_points``, ``overlap``, ``icp``, ``transform``,
      ``fuse``, ``total``; the CLI adds ``load`` and ``save``).
    - ``resolution`` [m], ``warnings`` (human-readable), ``status`` (``"ok"`` or
      ``"not_converged"``).
    Not serialised: ``icp_result`` (the ``IcpResult`` / ``IcpMultiResult`` pytree) and the
    overlap clouds ``points_1`` / ``points_2`` (``(n, 3)`` float32, each map's frame) used
    for figures.
    """

    T_1_2_init: np.ndarray
    T_1_2: np.ndarray
    refine: str
    icp: dict | None
    epsilon_r_init: float | None
    epsilon_t_init: float | None
    epsilon_r: float | None
    epsilon_t: float | None
    counts: dict
    timings: dict
    resolution: float
    T_1_2_true: np.ndarray | None = None
    warnings: tuple[str, ...] = ()
    status: str = "ok"
    displacement_init: float | None = None
    displacement: float | None = None
    icp_result: object = dataclasses.field(default=None, repr=False, compare=False)
    points_1: np.ndarray | None = dataclasses.field(default=None, repr=False, compare=False)
    points_2: np.ndarray | None = dataclasses.field(default=None, repr=False, compare=False)
    # --- global
    confidence: float | None = None
    candidates: tuple = ()

    _JSON_FIELDS = ("status", "refine", "resolution", "T_1_2_init", "T_1_2", "T_1_2_true", "icp",
                    "epsilon_r_init", "epsilon_t_init", "epsilon_r", "epsilon_t", "displacement_init",
                    "displacement", "counts", "timings", "warnings", "confidence", "candidates")

    def to_dict(self) -> dict:
        """JSON-ready dict (matrices as nested lists, row-major)."""
        out = {}
        for name in self._JSON_FIELDS:
            out[name] = _jsonable(getattr(self, name))
        return out

    def to_json(self, path=None, indent: int = 2) -> str:
        """The report as JSON text; also written (atomically) to ``path`` if given."""
        text = json.dumps(self.to_dict(), indent=indent)
        # one line per matrix row / short number list, instead of one line per number
        text = _NUM_LIST.sub(lambda m: "[" + ", ".join(x.strip() for x in m.group(1).split(",")) + "]",
                             text) + "\n"
        if path is not None:
            atomic_write_bytes(path, text.encode())
        return text

    def with_timings(self, **extra) -> "MergeReport":
        return dataclasses.replace(self, timings={**self.timings, **extra})

    def summary(self) -> str:
        """A few human-readable lines (what the CLI prints)."""
        lines = []
        if self.status != "ok" or self.confidence is not None:
            conf = "" if self.confidence is None else f", confidence {self.confidence:.2f}"
            lines.append(f"status: {self.status}{conf}")
        if self.icp is not None:
            i = self.icp
            what = "dense alignment" if self.refine == "dense" else f"ICP ({self.refine})"
            lines.append(f"{what}: {i['status']} after {i['num_iterations']} iterations, "
                         f"{i['num_inliers']} inliers, rmse {i['rmse']:.4f} m, fitness {i['fitness']:.2f}")
        if self.epsilon_r_init is not None:
            lines.append(f"epsilon_r {self.epsilon_r_init:.4f} -> {self.epsilon_r:.4f}   "
                         f"epsilon_t {self.epsilon_t_init:.4f} -> {self.epsilon_t:.4f} m  (thesis eqs. 7.2/7.3)")
        if self.displacement_init is not None:
            lines.append(f"map 2 occupied voxels off the truth by {self.displacement_init:.4f} -> "
                         f"{self.displacement:.4f} m (mean)")
        c = self.counts
        lines.append(f"leaves: map1 {c.get('leaves_1', 0):,} + map2 {c.get('leaves_2', 0):,} "
                     f"-> merged {c.get('leaves_merged', 0):,}")
        lines.append("time: " + ", ".join(f"{k} {v:.2f}s" for k, v in self.timings.items()))
        lines.extend(f"warning: {w}" for w in self.warnings)
        return "\n".join(lines)


def _jsonable(v):
    if v is None or isinstance(v, (bool, str)):
        return v
    if isinstance(v, dict):
        return {str(k): _jsonable(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_jsonable(x) for x in v]
    if isinstance(v, (np.ndarray, jax.Array)):
        return _jsonable(np.asarray(v).tolist())
    if isinstance(v, (np.integer,)):
        return int(v)
    if isinstance(v, (float, np.floating)):
        f = float(v)
        return f if math.isfinite(f) else None
    return v


# --- many


def jsonable(v):
    """``v`` with NumPy / JAX arrays and scalars turned into JSON types (lists, floats; a
    non-finite float as ``None``), dicts and sequences converted recursively."""
    return _jsonable(v)
