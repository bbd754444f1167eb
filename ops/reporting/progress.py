"""Progress on the command line: one updating line per stage on a terminal, sparse lines otherwise."""

from __future__ import annotations

import sys
from typing import TextIO

from ops.engine.loop import ProgressEvent


class ConsoleProgress:
    """A ``ProgressFn`` printing ``photo:stage  step/total  bar  ref_psnr  elapsed``."""

    def __init__(self, stream: TextIO | None = None, width: int = 24) -> None:
        self.stream = stream or sys.stderr
        self.tty = self.stream.isatty()
        self.width = width
        self._last_stage = ""
        self._last_tenth = -1

    def __call__(self, event: ProgressEvent) -> None:
        frac = event.step / max(event.total, 1)
        bar = "#" * int(frac * self.width) + "-" * (self.width - int(frac * self.width))
        extra = "".join(f"  {k} {v:.2f}" for k, v in event.metrics.items() if k in ("ref_psnr", "loss"))
        line = f"{event.stage:<40} {event.step:>6}/{event.total:<6} [{bar}] {event.elapsed_s:7.1f}s{extra}"
        if self.tty:
            end = "\n" if event.step >= event.total else ""
            print("\r" + line, end=end, file=self.stream, flush=True)
            return
        tenth = int(frac * 10)
        if event.stage != self._last_stage or tenth != self._last_tenth or event.step >= event.total:
            print(line, file=self.stream, flush=True)
            self._last_stage, self._last_tenth = event.stage, tenth
