"""What a fusion returns with its report: ``FuseReport`` (counts, overflow) and
``FuseResult`` (map and report)."""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import jax
import numpy as np

from ..map import OccupancyMap


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class FuseReport:
    """Counts of a fusion (thesis §5.2.3 cases), all int32 device scalars (vmappable).

    - ``leaves_in``: ``(m,)`` valid leaves of each input map.
    - ``refined_cells``: cells of the common refinement before pruning (the capacity needed).
    - ``leaves_out``: leaves of the fused, pruned map.
    - ``same_depth``: leaf pairs at the same depth in both maps (case 2, eq. 5.15).
    - ``split``: ``(m,)`` leaves of each map split because another map is finer inside them
      (pair: ``split[0]`` = case 3, M1 coarser; ``split[1]`` = case 4, M2 coarser).
    - ``cells_both``: refined cells known in at least two maps (combined by the rule).
    - ``cells_new``: refined cells unknown in the first map (case 1, eq. 5.14).
    - ``overflow``: bool, the refinement did not fit ``capacity``, or its gap cells did not
      fit a ``gap_capacity`` given under ``jit`` (result truncated).
    Static: ``capacity``, rows of the output map.
    """

    leaves_in: jax.Array
    refined_cells: jax.Array
    leaves_out: jax.Array
    same_depth: jax.Array
    split: jax.Array
    cells_both: jax.Array
    cells_new: jax.Array
    overflow: jax.Array
    capacity: int = dataclasses.field(metadata=dict(static=True), default=0)

    @property
    def pruned(self):
        """Refined cells removed by pruning."""
        return self.refined_cells - self.leaves_out

    def host(self) -> dict:
        """The counts as Python ints / lists (for logs and CLIs)."""
        out = {}
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            out[f.name] = np.asarray(v).tolist() if f.name != "capacity" else v
        # on the host (a device subtraction compiles a program); a list for a vmapped report
        out["pruned"] = (np.asarray(self.refined_cells) - np.asarray(self.leaves_out)).tolist()
        return out


class FuseResult(NamedTuple):
    """``fuse_with_report`` / ``fuse_many_with_report``: ``merged, report = ...``."""

    map: OccupancyMap  # the fused map (rows: the report's capacity)
    report: FuseReport  # its counts; ``report.overflow`` when the output was truncated
