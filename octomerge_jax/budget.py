"""A memory budget checked before large allocations: the last line of defence against an input
(a crafted file, a map of huge coarse free leaves, a config value) that would need more memory
than the machine has.

Readers and kernels call ``check_allocation(nbytes, what)`` with the size they are about to
allocate, before allocating it; over the budget it raises ``MemoryBudgetError`` (a
``MemoryError`` with a one-line message naming what and how much), never a crash or a swap
storm. The budget, in bytes, is the first of:

1. the innermost ``memory_budget(nbytes)`` context (this thread / task only),
2. ``$OCTOMERGE_MEMORY_BUDGET``: bytes, with an optional ``K``/``M``/``G``/``T`` suffix
   (powers of 1024), or a fraction of physical memory such as ``0.5``,
3. ``DEFAULT_FRACTION`` of the machine's physical memory.

Importing the module changes nothing.
"""

from __future__ import annotations

import contextlib
import contextvars
import os

__all__ = ["DEFAULT_FRACTION", "MemoryBudgetError", "check_allocation", "current_budget",
           "format_bytes", "memory_budget", "parse_budget", "physical_memory"]

# share of physical memory one operation may take by default
DEFAULT_FRACTION = 0.75

_SUFFIX = {"": 1, "B": 1, "K": 1 << 10, "M": 1 << 20, "G": 1 << 30, "T": 1 << 40}
_override: contextvars.ContextVar[int | None] = contextvars.ContextVar("octomerge_budget", default=None)


class MemoryBudgetError(MemoryError):
    """An allocation refused before it was made: ``what`` needs ``nbytes`` over ``budget``."""

    def __init__(self, what: str, nbytes: int, budget: int):
        self.what, self.nbytes, self.budget = what, int(nbytes), int(budget)
        super().__init__(f"{what} needs {format_bytes(nbytes)}, over the memory budget of "
                         f"{format_bytes(budget)} (set OCTOMERGE_MEMORY_BUDGET to change it)")

    def __reduce__(self):  # picklable across processes (Dask workers)
        return (type(self), (self.what, self.nbytes, self.budget))


def format_bytes(nbytes: float) -> str:
    """``1536`` -> ``"1.5 KiB"``."""
    value = float(nbytes)
    for unit in ("B", "KiB", "MiB", "GiB", "TiB"):
        if abs(value) < 1024 or unit == "TiB":
            return f"{value:.0f} {unit}" if unit == "B" else f"{value:.1f} {unit}"
        value /= 1024
    raise AssertionError("unreachable")


def physical_memory() -> int:
    """Bytes of physical memory (``os.sysconf``); ``1 << 34`` (16 GiB) where unknown."""
    try:
        return int(os.sysconf("SC_PAGE_SIZE")) * int(os.sysconf("SC_PHYS_PAGES"))
    except (ValueError, OSError, AttributeError):
        return 1 << 34


def parse_budget(text: str) -> int:
    """Bytes from ``"2G"``, ``"512M"``, ``"1000000"`` or a fraction of physical memory
    (``"0.5"``, in ``(0, 1]``). Raises ``ValueError`` naming the text otherwise."""
    s = str(text).strip().upper().removesuffix("IB").removesuffix("B")
    suffix = s[-1:] if s[-1:] in _SUFFIX else ""
    number = s[: len(s) - len(suffix)].strip()
    try:
        value = float(number) if "_" not in number else float("nan")
    except ValueError:
        value = float("nan")
    if not suffix and 0 < value <= 1 and "." in number:
        return int(value * physical_memory())
    if not value >= 1 or value == float("inf"):
        raise ValueError(f"memory budget {text!r}: expected bytes with an optional K/M/G/T suffix "
                         f"or a fraction of physical memory in (0, 1]")
    return int(value * _SUFFIX[suffix])


def current_budget() -> int:
    """The budget in force (bytes): see the module docstring for the order. Raises
    ``ValueError`` naming ``OCTOMERGE_MEMORY_BUDGET`` when that variable cannot be read."""
    override = _override.get()
    if override is not None:
        return override
    env = os.environ.get("OCTOMERGE_MEMORY_BUDGET", "").strip()
    if env:
        try:
            return parse_budget(env)
        except ValueError as err:
            raise ValueError(f"OCTOMERGE_MEMORY_BUDGET: {err}") from None
    return int(DEFAULT_FRACTION * physical_memory())


@contextlib.contextmanager
def memory_budget(nbytes: int | str):
    """``with memory_budget("4G"): ...``: the budget for the calls inside (this thread / task)."""
    value = parse_budget(nbytes) if isinstance(nbytes, str) else int(nbytes)
    if value < 1:
        raise ValueError(f"memory budget {nbytes!r} must be positive")
    token = _override.set(value)
    try:
        yield value
    finally:
        _override.reset(token)


def check_allocation(nbytes: float, what: str) -> None:
    """Raise ``MemoryBudgetError`` if ``nbytes`` (what an operation is about to allocate, its
    peak estimate) exceeds the budget. ``what`` names the operation and its input, e.g.
    ``"transform_map of map 2 (room.bt): 2.1e9 cells"``. Call it before allocating."""
    budget = current_budget()
    if not nbytes <= budget:  # also refuses NaN
        raise MemoryBudgetError(what, nbytes if nbytes == nbytes else budget + 1, budget)
