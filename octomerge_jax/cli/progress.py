"""Progress bars for long command-line work (tqdm on stderr), shown only on a terminal:
``show_bars`` decides, ``Progress`` counts items (pairs, scans), ``StageBar`` follows named
stages, the pipeline's own included (docs/design.md, "Progress bars on a terminal only")."""

from __future__ import annotations

import contextlib
import sys
import threading

from tqdm import tqdm

from ..pipeline import stage_listener

__all__ = ["Progress", "StageBar", "show_bars"]


def show_bars(quiet: bool = False, stream=None) -> bool:
    """Whether to draw bars: not ``quiet`` and ``stream`` (default ``sys.stderr``) is a
    terminal. Piped or redirected output stays free of bars."""
    stream = sys.stderr if stream is None else stream
    isatty = getattr(stream, "isatty", None)
    return not quiet and bool(isatty and isatty())


class Progress:
    """Count finished items of ``total`` on stderr as a tqdm bar (``unit``, the last status as
    its postfix). ``enabled=False`` counts silently."""

    def __init__(self, total: int, enabled: bool, desc: str = "merging", unit: str = "pair"):
        self.total, self.n, self.enabled = total, 0, enabled
        self.bar = tqdm(total=total, desc=desc, unit=unit, file=sys.stderr, dynamic_ncols=True) \
            if enabled else None

    def update(self, status: str = "", n: int = 1) -> None:
        """``n`` more items done; ``status`` is shown next to the count."""
        self.n += n
        if self.bar is not None:
            self.bar.update(n)
            if status:
                self.bar.set_postfix_str(status)

    def close(self) -> None:
        """Finish the bar."""
        if self.bar is not None:
            self.bar.close()


class StageBar:
    """A bar over the named stages of one command (``total`` of them if known): each stage
    shows its name while it runs and counts when done. ``watch()`` adds the stages the
    pipeline times (``pipeline.stage_listener``: occupied points, correlation, icp, transform,
    fuse, ...). The elapsed time is redrawn every second, so a long stage does not look stuck.
    ``enabled=False`` does nothing."""

    def __init__(self, enabled: bool, desc: str, total: int | None = None):
        self.bar = tqdm(total=total, desc=desc, unit="stage", file=sys.stderr, dynamic_ncols=True,
                        bar_format="{desc} [{elapsed}] {n_fmt} stages done{postfix}" if total is None else None) \
            if enabled else None
        self._stop = threading.Event()
        if enabled:
            threading.Thread(target=self._tick, daemon=True).start()

    def _tick(self) -> None:
        while not self._stop.wait(1.0):
            self.bar.refresh()

    def _event(self, name: str, seconds: float | None) -> None:
        if self.bar is None:
            return
        if seconds is None:
            self.bar.set_postfix_str(name)
        else:
            self.bar.update(1)

    @contextlib.contextmanager
    def stage(self, name: str):
        """Show ``name`` while the block runs; count it when it ends."""
        self._event(name, None)
        yield
        self._event(name, 0.0)

    @contextlib.contextmanager
    def watch(self):
        """Follow the pipeline's stages while inside."""
        with stage_listener(self._event):
            yield

    def close(self) -> None:
        """Finish the bar."""
        self._stop.set()
        if self.bar is not None and not self.bar.disable:
            self.bar.set_postfix_str("done")
            self.bar.close()
