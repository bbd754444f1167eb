"""Progress on the command line: one updating line per stage on a terminal, sparse lines otherwise."""

from __future__ import annotations

import sys
import time
from collections.abc import Callable
from typing import TextIO

from ops.engine.progress import HEARTBEAT_S, ProgressEvent


def format_event(event: ProgressEvent, width: int = 24) -> str:
    """``photo:stage  step/total  bar  elapsed  ref_psnr``; a phase without steps (``total`` 0, e.g.
    the NeRF → DMTet conversion) reads ``photo:stage (phase)  running, 40 s so far``."""
    if event.total <= 0:
        return f"{event.stage:<40} running, {event.elapsed_s:.0f} s so far"
    frac = min(event.step / event.total, 1.0)
    bar = "#" * int(frac * width) + "-" * (width - int(frac * width))
    extra = "".join(f"  {k} {v:.2f}" for k, v in event.metrics.items() if k in ("ref_psnr", "loss"))
    return f"{event.stage:<40} {event.step:>6}/{event.total:<6} [{bar}] {event.elapsed_s:7.1f}s{extra}"


class ConsoleProgress:
    """A ``ProgressFn`` printing ``format_event`` lines.

    On a terminal the line updates in place. Elsewhere (a log file, CI) a line is printed when the
    stage changes, at each tenth of its steps, at its end, for every event without metrics (the
    stage's outcome, a heartbeat of ``ops.engine.progress``) and whenever ``every_s`` seconds have
    passed since the last line: a long stage is never silent for longer than that."""

    def __init__(self, stream: TextIO | None = None, width: int = 24, every_s: float = HEARTBEAT_S,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.stream = stream or sys.stderr
        self.tty = self.stream.isatty()
        self.width = width
        self.every_s, self.clock = every_s, clock
        self._last_stage = ""
        self._last_tenth = -1
        self._last_time = -float("inf")
        self._last_len = 0

    def __call__(self, event: ProgressEvent) -> None:
        line = format_event(event, self.width)
        finished = event.total > 0 and event.step >= event.total
        if self.tty:
            # Pad over a longer line left by the previous stage or phase.
            print("\r" + line.ljust(self._last_len), end="\n" if finished else "", file=self.stream, flush=True)
            self._last_len = 0 if finished else len(line)
            return
        tenth = int(event.step / max(event.total, 1) * 10)
        now = self.clock()
        if (event.stage != self._last_stage or tenth != self._last_tenth or finished or not event.metrics
                or now - self._last_time >= self.every_s):
            print(line, file=self.stream, flush=True)
            self._last_stage, self._last_tenth, self._last_time = event.stage, tenth, now
