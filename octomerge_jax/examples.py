"""Built-in example data: a small room with boxes, shipped inside the package.

``example_map()`` loads the shipped ``data/example_room.ot``; ``make_example_room()`` is the
generator that made it (deterministic), so the file can be rebuilt and checked.
"""

from __future__ import annotations

from importlib import resources
from pathlib import Path

import numpy as np

from .io import load
from .map import OccupancyMap, OccupancyParams, logit
from .tree import from_voxels

__all__ = ["example_map", "example_map_path", "make_example_room"]

EXAMPLE_FILE = "example_room.ot"


def example_map_path() -> Path:
    """Path of the shipped example map (an OctoMap ``.ot`` file)."""
    return Path(str(resources.files("octomerge_jax") / "data" / EXAMPLE_FILE))


def example_map() -> OccupancyMap:
    """The shipped example: a 6 x 4 x 2.5 m room with four boxes at 0.1 m resolution."""
    return load(example_map_path())


def _grid(lo, hi, res):
    axes = [np.arange(a + res / 2, b, res) for a, b in zip(lo, hi)]
    return np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)


def make_example_room(resolution: float = 0.1) -> OccupancyMap:
    """A room ``[-3, 3] x [-2, 2] x [0, 2.5]`` m: floor and walls occupied (log-odds of the
    clamp max), four boxes occupied, the air observed free (log-odds -1.2), the ceiling
    unknown. Built with ``tree.from_voxels`` (finest voxels, then pruned maximally)."""
    r = resolution
    inside_lo, inside_hi = np.array([-3.0, -2.0, 0.0]), np.array([3.0, 2.0, 2.5])
    shell = _grid(inside_lo - [r, r, r], inside_hi + [r, r, 0.0], r)
    is_shell = np.any((shell < inside_lo) | (shell > inside_hi), axis=1)
    boxes = [((-2.0, -1.2, 0.0), (-1.2, -0.4, 0.8)), ((-0.6, 0.6, 0.0), (0.4, 1.4, 1.2)),
             ((1.0, -1.5, 0.0), (1.6, -0.9, 0.6)), ((1.9, 0.5, 0.0), (2.5, 1.1, 1.5))]
    air = _grid(inside_lo, inside_hi, r)
    in_box = np.zeros(len(air), bool)
    for lo, hi in boxes:
        in_box |= np.all((air > lo) & (air < hi), axis=1)
    occ_value = logit(0.971)
    points = np.concatenate([shell[is_shell], air[in_box], air[~in_box]])
    values = np.concatenate([
        np.full(int(is_shell.sum()), occ_value, np.float32),
        np.full(int(in_box.sum()), occ_value, np.float32),
        np.full(int((~in_box).sum()), -1.2, np.float32),
    ])
    return from_voxels(points, values, r, params=OccupancyParams())
