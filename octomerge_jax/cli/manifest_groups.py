"""Groups in an ``octomerge batch`` manifest: rows sharing a ``group`` id are one N-map job,
merged by ``pipeline.merge_many`` (``docs/design.md``, "Batch groups of N maps").

A group's rows read as any manifest row: ``map1, map2``, the guess ``T_1_2`` (map2's frame
into map1's) and the truth. Together they name the group's maps, in order of first appearance
(the first row's ``map1`` is map 0, the frame of the merged map), and, when any row gives a
guess, the guessed edges of the pose graph (``merge_many(pairs={(i, k): T_i_k})``): a chain
``a-b, b-c``, a star ``a-b, a-c`` or a loop. A group none of whose rows gives a guess is merged
without guesses (every pair of its maps searched). ``cli/manifest.py`` reads the rows, runs
the jobs and keeps ``summary.csv``; this module turns rows into groups and groups into
``merge_many`` calls.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import NamedTuple, Sequence

import numpy as np

from ..map import OccupancyMap
from ..pipeline import ManyReport, MergeConfig, merge_many, transform_from_xyz_rpy
from ..registration import posegraph

__all__ = ["GroupPair", "ManifestGroup", "assemble_groups", "group_figures", "merge_group"]


class GroupPair(NamedTuple):
    """One manifest row of a group: maps ``i`` and ``k`` (indices into ``ManifestGroup.maps``)."""

    i: int  # map1's index in the group
    k: int  # map2's index in the group
    guess: tuple | None  # (x, y, z, roll, pitch, yaw) [m, rad] of T_i_k; None: the row gives none
    truth: tuple | None  # the same for the true T_i_k; None: not given


@dataclasses.dataclass(frozen=True)
class ManifestGroup:
    """One group of a manifest: ``index`` (its first row's), ``group`` (the id), absolute
    ``output`` and ``maps`` paths (``maps[0]``: the frame of the merged map), one ``GroupPair``
    per row. ``error``: why the group cannot run (paths then as written), else ``""``.
    ``map1`` / ``map2`` (map 0, ``""``) fill the summary's pair columns."""

    index: int
    group: str
    output: str
    maps: tuple[str, ...]
    pairs: tuple[GroupPair, ...] = ()
    error: str = ""

    @property
    def map1(self) -> str:
        return self.maps[0] if self.maps else ""

    @property
    def map2(self) -> str:
        return ""

    @property
    def guessed(self) -> bool:
        """Whether any row gives a guess (else the group is merged without guesses)."""
        return any(p.guess is not None for p in self.pairs)


def assemble_groups(rows: Sequence, manifest) -> list:
    """Replace the rows that carry a group id (``ManifestRow.group``) by one ``ManifestGroup``
    per id, at the position of the group's first row; rows without a group id stay as they are.

    A group is an error (``ManifestGroup.error``, naming ``manifest`` and the group) when one
    of its rows is bad, a pair of maps is listed twice, or the rows that give a guess (or a
    truth) do not connect every map of the group to map 0."""
    members: dict[str, list] = {}
    order: list = []
    for r in rows:
        if not r.group:
            order.append(r)
        elif r.group in members:
            members[r.group].append(r)
        else:
            members[r.group] = [r]
            order.append(r.group)
    return [_group(members[r], manifest) if isinstance(r, str) else r for r in order]


def _group(rows: list, manifest) -> ManifestGroup:
    first = rows[0]
    maps: dict[str, int] = {}
    for r in rows:
        for p in (r.map1, r.map2):
            maps.setdefault(p, len(maps))
    names = tuple(maps)
    bad = [r.error for r in rows if r.error]
    if bad:
        return ManifestGroup(first.index, first.group, first.output, names, error="; ".join(bad))
    pairs = tuple(GroupPair(maps[r.map1], maps[r.map2], r.guess, r.truth) for r in rows)
    where = f"{manifest}: group {first.group}"
    seen: set = set()
    for p in pairs:
        if (p.i, p.k) in seen:
            return ManifestGroup(first.index, first.group, first.output, names, error=(
                f"{where}: {Path(names[p.i]).name} and {Path(names[p.k]).name} are paired twice"))
        seen.add((p.i, p.k))
    for what, key in (("guesses (x..yaw)", "guess"), ("truths (true_x..true_yaw)", "truth")):
        given = [p for p in pairs if getattr(p, key) is not None]
        if given:
            lost = sorted(set(range(len(names))) - _reached([(p.i, p.k) for p in given]))
            if lost:
                return ManifestGroup(first.index, first.group, first.output, names, error=(
                    f"{where}: the rows' {what} do not connect {', '.join(Path(names[k]).name for k in lost)} to "
                    f"{Path(names[0]).name} (give them on rows that link every map, or on none)"))
    return ManifestGroup(first.index, first.group, first.output, names, pairs)


def _reached(edges: list[tuple[int, int]]) -> set[int]:
    """Maps connected to map 0 by ``edges`` (either direction)."""
    reached, grown = {0}, True
    while grown:
        grown = False
        for i, k in edges:
            if (i in reached) != (k in reached):
                reached |= {i, k}
                grown = True
    return reached


def _chained(n: int, pairs: Sequence[GroupPair], key: str) -> list[np.ndarray]:
    """``T_0_k`` (k = 1..n-1) chained along the rows' ``key`` transforms (connected: checked)."""
    given = [p for p in pairs if getattr(p, key) is not None]
    Z = np.stack([transform_from_xyz_rpy(*getattr(p, key)) for p in given])
    T0, _, _ = posegraph.spanning_tree_poses(n, [p.i for p in given], [p.k for p in given], Z,
                                            np.ones(len(given)), np.ones(len(given), bool))
    return list(T0[1:])


def merge_group(group: ManifestGroup, maps: Sequence[OccupancyMap], config: MergeConfig
                ) -> tuple[OccupancyMap, ManyReport]:
    """``merge_many`` over a group's loaded ``maps`` (in ``group.maps`` order): the rows'
    guesses as ``pairs`` (a row without one adds no edge; none at all: no guesses), their
    truths chained to ``T_trues``. Returns ``(merged, report)``, the report's ``inputs`` the
    map paths. Raises what ``merge_many`` raises."""
    pairs = None
    if group.guessed:
        pairs = {(p.i, p.k): transform_from_xyz_rpy(*p.guess) for p in group.pairs if p.guess is not None}
    truths = None
    if any(p.truth is not None for p in group.pairs):
        truths = _chained(len(maps), group.pairs, "truth")
    merged, report = merge_many(list(maps), pairs=pairs, T_trues=truths, config=config)
    return merged, dataclasses.replace(report, inputs=tuple(group.maps))


def group_figures(report: ManyReport) -> dict:
    """A group's summary columns from its report: maps placed, edges kept / rejected, leaves
    merged and the thesis errors of the worst map (largest over the maps; blank without truths)."""
    def worst(values) -> str:
        values = [v for v in values if v is not None]
        return f"{max(values):.6g}" if values else ""

    f = report.figures
    return {"maps_placed": f["maps_placed"], "edges_kept": f["edges_kept"], "edges_rejected": f["edges_rejected"],
            "leaves_merged": f["leaves_merged"],
            "epsilon_r_init": worst(r.epsilon_r_init for r in report.merge_reports),
            "epsilon_t_init": worst(r.epsilon_t_init for r in report.merge_reports),
            "epsilon_r": worst(m.epsilon_r for m in report.maps), "epsilon_t": worst(m.epsilon_t for m in report.maps)}
