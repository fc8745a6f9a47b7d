"""One status vocabulary for every solver and report: ICP, the dense alignment and merges.

Solvers return ``status`` as an int32 array (jit-friendly, as optimistix's ``RESULTS``); on
the host ``Status(int(status))`` names it and ``Status.message`` says what it means. Codes are
unique across solvers, so a report can carry any of them.
"""

from __future__ import annotations

import enum

import numpy as np

__all__ = ["Status", "usable_mask"]


class Status(enum.IntEnum):
    """Outcome of a registration solver (``IcpResult.status``, ``AlignResult.status``)."""

    CONVERGED = 0
    MAX_ITERATIONS = 1
    TOO_FEW_INLIERS = 2
    POOR_AGREEMENT = 3
    LOW_OVERLAP = 4
    NOT_FINITE = 5

    @property
    def message(self) -> str:
        """One line for users: what happened."""
        return _MESSAGES[self]

    @property
    def usable(self) -> bool:
        """Whether the solver's transform may be used (converged, or ran out of iterations
        while still improving)."""
        return self in (Status.CONVERGED, Status.MAX_ITERATIONS)

    def __str__(self) -> str:  # the name used in reports and JSON: "converged", ...
        return self.name.lower()


_MESSAGES = {
    Status.CONVERGED: "converged: the update fell below the tolerance",
    Status.MAX_ITERATIONS: "stopped at the iteration limit before converging; the last transform is returned",
    Status.TOO_FEW_INLIERS: "too few correspondences within the correspondence distance: the guess is "
                            "probably too far off",
    Status.POOR_AGREEMENT: "the maps agree poorly at the result: probably a wrong basin",
    Status.LOW_OVERLAP: "too little commonly known space at the result to judge the alignment",
    Status.NOT_FINITE: "the solve produced non-finite values",
}


def usable_mask(status, *, xp=np):
    """Elementwise ``Status.usable`` of status codes ``status`` (any shape, int): a bool array
    of that shape. ``xp``: ``numpy`` (host) or ``jax.numpy`` (inside ``jit``)."""
    return xp.isin(status, xp.asarray([int(s) for s in Status if s.usable]))
