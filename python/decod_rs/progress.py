"""Progress for long stages, on stderr: a redrawn bar on a terminal, a line every ~10 %
otherwise (logs and CI stay readable). No dependency: a dozen lines do the job."""

from __future__ import annotations

import sys
import time
from collections.abc import Iterable, Iterator
from typing import TypeVar

T = TypeVar("T")


class Progress:
    """Counts work done towards ``total`` and shows rate and remaining time; without a total,
    the count (of ``unit``, e.g. ``"graphs"``) and the rate."""

    def __init__(self, label: str, total: int | None, enabled: bool = True, unit: str = "") -> None:
        self.label = label
        self.unit = unit
        self.total = total
        self.done = 0
        self.enabled = enabled
        self._start = time.perf_counter()
        self._tty = sys.stderr.isatty()
        self._last_decile = -1

    def advance(self, n: int = 1) -> None:
        self.done += n
        if not self.enabled:
            return
        if self._tty:
            self._draw(final=False)
        elif self.total:
            decile = int(10 * self.done / self.total)
            if decile != self._last_decile:
                self._last_decile = decile
                self._draw(final=False, newline=True)

    def close(self) -> None:
        if self.enabled:
            self._draw(final=True, newline=True)

    def _draw(self, final: bool, newline: bool = False) -> None:
        elapsed = time.perf_counter() - self._start
        rate = self.done / elapsed if elapsed > 0 else 0.0
        if self.total:
            frac = min(1.0, self.done / self.total)
            bar = "#" * int(24 * frac) + "-" * (24 - int(24 * frac))
            eta = (self.total - self.done) / rate if rate > 0 and not final else 0.0
            text = (
                f"{self.label:<14} [{bar}] {self.done}/{self.total} "
                f"{rate:7.1f}/s {elapsed:6.1f}s" + (f" eta {eta:5.1f}s" if not final else "")
            )
        else:
            count = f"{self.done} {self.unit}".rstrip()
            text = f"{self.label:<14} {count} {rate:7.1f}/s {elapsed:6.1f}s"
        end = "\n" if newline or final else ""
        sys.stderr.write(("\r" if self._tty else "") + text + end)
        sys.stderr.flush()


def track(items: Iterable[T], label: str, total: int | None = None) -> Iterator[T]:
    """Iterate ``items`` while showing progress."""
    if total is None and hasattr(items, "__len__"):
        total = len(items)  # type: ignore[arg-type]
    bar = Progress(label, total)
    try:
        for item in items:
            yield item
            bar.advance()
    finally:
        bar.close()
