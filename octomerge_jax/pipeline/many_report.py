"""What ``merge_many`` reports: ``ManyReport`` with one ``MapReport`` per map and one
``EdgeReport`` per pairwise measurement or guess, as JSON and as TUM poses."""

from __future__ import annotations

import dataclasses
import json
import re

import numpy as np

from .. import se3
from .._fileutil import atomic_write_bytes
from .report import MergeReport, jsonable

__all__ = ["EdgeReport", "ManyReport", "MapReport", "tum_lines"]

# a list of numbers (a matrix row) on one line
_NUM_LIST = re.compile(r"\[\s*((?:-?[0-9.eE+-]+|null)(?:,\s*(?:-?[0-9.eE+-]+|null))*)\s*\]")


@dataclasses.dataclass(frozen=True)
class EdgeReport:
    """One edge of the pose graph.

    - ``i``, ``j``: the maps; the measurement maps j's frame into i's.
    - ``kind``: ``"registration"`` (a pairwise registration), ``"guess"`` (a user guess used as
      the measurement, ``refine="none"``) or ``"prior"`` (a user guess entering the graph as a
      weak prior next to the registrations).
    - ``T_i_j``: ``(4, 4)`` float64 measurement [m], or ``None`` when the registration failed.
    - ``confidence``: in [0, 1] (``None`` for priors and failures).
    - ``information``: ``(6, 6)`` float64 (v [1/m^2], omega [1/rad^2]) or ``None``.
    - ``residual``: ``(6,)`` float64 ``log(Z^-1 T_0_i^-1 T_0_j)`` after the solve (v [m],
      omega [rad]); ``chi2``: its squared Mahalanobis norm; ``None`` when not measured or a map
      of the edge is unplaced.
    - ``kept``: used in the final solve; ``why``: ``""`` when kept, else why not
      (``"cycle"``, ``"residual"``, ``"low_confidence"``, ``"registration: <error>"``).
    - ``figures``: the registration's figures (``MergeReport.icp``'s keys), ``seconds``.
    """

    i: int
    j: int
    kind: str
    T_i_j: np.ndarray | None
    confidence: float | None
    information: np.ndarray | None
    residual: np.ndarray | None
    chi2: float | None
    kept: bool
    why: str
    figures: dict | None
    seconds: float


@dataclasses.dataclass(frozen=True)
class MapReport:
    """One map: ``status`` ``"root"`` (map 0), ``"placed"`` or ``"unplaced"`` (no kept
    measurement connects it to map 0; left out of the merged map); ``T_0_k`` ``(4, 4)`` or
    ``None``; ``covariance`` ``(6, 6)`` marginal covariance of ``T_0_k`` (v [m^2], omega
    [rad^2], right perturbation) or ``None``; ``sigma_m`` / ``sigma_rad``: square roots of
    the largest eigenvalues of its translation / rotation blocks; ``edges``: indices of the kept
    edges that touch it; ``epsilon_r`` / ``epsilon_t``: thesis eqs. 7.2 / 7.3 against the truth
    when given; ``leaves``."""

    index: int
    status: str
    T_0_k: np.ndarray | None
    covariance: np.ndarray | None
    sigma_m: float | None
    sigma_rad: float | None
    edges: tuple[int, ...]
    leaves: int
    epsilon_r: float | None = None
    epsilon_t: float | None = None


@dataclasses.dataclass(frozen=True)
class ManyReport:
    """What ``merge_many`` did (host values; ``to_json()`` writes all but ``merge_reports``).

    - ``transforms``: per map ``T_0_k`` ``(4, 4)`` float64 (map k's frame into map 0's [m];
      identity for map 0) or ``None`` for a map left unplaced.
    - ``maps``: ``MapReport`` per map; ``edges``: ``EdgeReport`` per edge.
    - ``figures``: global figures (maps placed, pairs possible, the candidate pairs, pairs
      registered / kept / rejected, solver iterations, rounds and cost, leaves merged, fuse counts).
    - ``timings``: seconds per stage (``screen``, ``register``, ``solve``, ``transform``,
      ``fuse``, ``total``); ``resolution`` [m]; ``warnings``.
    - ``merge_reports``: one ``MergeReport`` per map 1..n-1 (its ``T_1_2`` is ``T_0_k``, its
      ``icp`` the figures of the kept registration of map k with the most confidence); the report
      also reads as this sequence (``len``, indexing, iteration), as ``merge_many``'s
      earlier list of reports did.
    - ``inputs``: the maps' file paths when the caller knows them (``octomerge batch``), else ``()``.
    """

    transforms: tuple
    maps: tuple[MapReport, ...]
    edges: tuple[EdgeReport, ...]
    figures: dict
    timings: dict
    resolution: float
    warnings: tuple[str, ...] = ()
    merge_reports: tuple[MergeReport, ...] = dataclasses.field(default=(), repr=False, compare=False)
    inputs: tuple[str, ...] = ()

    def __len__(self) -> int:
        return len(self.merge_reports)

    def __getitem__(self, k):
        return self.merge_reports[k]

    def __iter__(self):
        return iter(self.merge_reports)

    @property
    def placed(self) -> np.ndarray:
        """``(n,)`` bool: maps in the merged map."""
        return np.array([t is not None for t in self.transforms])

    def to_dict(self) -> dict:
        """JSON-ready dict (matrices as nested lists, row-major)."""
        return jsonable({"resolution": self.resolution, "transforms": list(self.transforms),
                         "maps": [dataclasses.asdict(m) for m in self.maps],
                         "edges": [dataclasses.asdict(e) for e in self.edges],
                         "figures": self.figures, "timings": self.timings, "warnings": list(self.warnings),
                         **({"inputs": list(self.inputs)} if self.inputs else {})})

    def to_json(self, path=None, indent: int = 2) -> str:
        """The report as JSON text; also written (atomically) to ``path`` if given."""
        text = json.dumps(self.to_dict(), indent=indent)
        text = _NUM_LIST.sub(lambda m: "[" + ", ".join(x.strip() for x in m.group(1).split(",")) + "]", text) + "\n"
        if path is not None:
            atomic_write_bytes(path, text.encode())
        return text

    def write_tum(self, path, timestamps=None) -> str:
        """The placed maps' poses ``T_0_k`` in TUM format (``timestamp tx ty tz qx qy qz qw``,
        one line per placed map; ``timestamps`` default: the map index), as read by evo.
        Written atomically to ``path`` (``None``: only returned)."""
        text = "".join(tum_lines(self.transforms, timestamps))
        if path is not None:
            atomic_write_bytes(path, text.encode())
        return text

    def summary(self) -> str:
        """A few human-readable lines (what the CLI prints)."""
        f = self.figures
        lines = [f"maps placed: {f['maps_placed']} of {len(self.maps)}; pairs registered {f['pairs_registered']} "
                 f"of {f['pairs_possible']} possible, kept {f['edges_kept']}, rejected {f['edges_rejected']}"]
        for m in self.maps:
            if m.status == "unplaced":
                lines.append(f"map {m.index}: unplaced (no kept measurement connects it to map 0)")
            elif m.status == "placed":
                lines.append(f"map {m.index}: placed by edges {list(m.edges)}, sigma {m.sigma_m:.3f} m, "
                             f"{m.sigma_rad:.4f} rad")
        for e, ed in enumerate(self.edges):
            if not ed.kept and ed.kind != "prior":
                lines.append(f"edge {e} ({ed.i}, {ed.j}): rejected ({ed.why})")
        lines.append("time: " + ", ".join(f"{k} {v:.2f}s" for k, v in self.timings.items()))
        lines.extend(f"warning: {w}" for w in self.warnings)
        return "\n".join(lines)


def tum_lines(transforms, timestamps=None) -> list[str]:
    """TUM trajectory lines ``"t tx ty tz qx qy qz qw\\n"`` of the transforms that are not
    ``None`` (quaternion from ``se3.to_quaternion``, ``(w, x, y, z)`` reordered to TUM's
    ``x y z w``)."""
    out = []
    for k, T in enumerate(transforms):
        if T is None:
            continue
        t = float(k if timestamps is None else timestamps[k])
        T = np.asarray(T, np.float64)
        w, x, y, z = se3.to_quaternion(T, xp=np)
        out.append(f"{t:.6f} {T[0, 3]:.9f} {T[1, 3]:.9f} {T[2, 3]:.9f} {x:.9f} {y:.9f} {z:.9f} {w:.9f}\n")
    return out
