"""Tile progress on stderr, for the long steps of a run (tiles, land strips, ingest, simulate)."""

from __future__ import annotations

import sys
import time
from collections.abc import Callable


class Progress:
    """Tile progress on stderr: a live line on a terminal, a line per 10 % otherwise."""

    def __init__(self, total: int, label: str, enabled: bool = True):
        self.total, self.label, self.enabled = total, label, enabled
        self.done = 0
        self.t0 = time.perf_counter()
        self.px = 0
        self.tty = sys.stderr.isatty()
        self.last_decile = -1

    def step(self, pixels: int = 0) -> None:
        """One more tile done (``pixels``: its size, for the Mpx/s rate; 0: no rate)."""
        self.done += 1
        self.px += pixels
        if not self.enabled:
            return
        pct = 100.0 * self.done / self.total
        line = f"{self.label}: {self.done}/{self.total} tiles ({pct:3.0f}%)"
        if self.px:
            el = time.perf_counter() - self.t0
            line += f" {self.px / el / 1e6 if el > 0 else 0.0:7.1f} Mpx/s"
        if self.tty:
            print("\r" + line, end="\n" if self.done == self.total else "", file=sys.stderr, flush=True)
        else:
            dec = int(pct // 10)
            if dec != self.last_decile or self.done == self.total:
                self.last_decile = dec
                print(line, file=sys.stderr, flush=True)

    @classmethod
    def callback(cls, label: str) -> Callable[[int, int], None]:
        """A ``progress(done, total)`` callback (as ingest and simulate take) on this display."""
        bar: list[Progress] = []

        def cb(done: int, total: int) -> None:
            if not bar:
                bar.append(cls(total, label))
            while bar[0].done < done:
                bar[0].step()

        return cb
