"""A progress bar for long command-line work: tqdm when installed, else a one-line counter."""

from __future__ import annotations

import sys
import time

__all__ = ["Progress"]


class Progress:
    """Count finished items of ``total`` on stderr: a tqdm bar (``unit``, last status as its
    postfix) if tqdm is installed, else ``desc n/total (seconds) status`` rewritten in place.
    ``enabled=False`` counts silently."""

    def __init__(self, total: int, enabled: bool, desc: str = "merging", unit: str = "pair"):
        self.total, self.n, self.enabled, self.bar = total, 0, enabled, None
        self.desc = desc
        if enabled:
            try:
                from tqdm import tqdm

                self.bar = tqdm(total=total, desc=desc, unit=unit, file=sys.stderr)
            except ImportError:
                self.t0 = time.perf_counter()

    def update(self, status: str) -> None:
        """One more item done; ``status`` is shown next to the count."""
        self.n += 1
        if not self.enabled:
            return
        if self.bar is not None:
            self.bar.update(1)
            self.bar.set_postfix_str(status)
        else:
            dt = time.perf_counter() - self.t0
            sys.stderr.write(f"\r{self.desc} {self.n}/{self.total} ({dt:.0f}s) {status:<8}")
            sys.stderr.flush()

    def close(self) -> None:
        """Finish the bar (or end the counter's line)."""
        if self.bar is not None:
            self.bar.close()
        elif self.enabled:
            sys.stderr.write("\n")
