"""Progress events (``ProgressEvent``, ``ProgressFn``), and a heartbeat for work that cannot report.

A stage's optimisation loop reports at its log rows, but a long single call between two reports
(the NeRF → DMTet conversion, a QA render over a turntable, one slow step on a CPU) would leave
the console silent for minutes. ``Heartbeat`` runs such work under a daemon thread that emits a
``ProgressEvent`` every ``every_s`` seconds with the work's real elapsed time and, when known, the
step it has reached. Events the work emits itself go through the heartbeat (it is a
``ProgressFn``), so both reach the reporter one at a time.

The method core (``morpheus_core``) never sees this: the heartbeat lives in ``ops`` and wraps the
calls into the core from outside. An exception the reporter raises on the timer thread (e.g. a
fault injected by a test, a closed stream) is re-raised in the work's thread at its next report,
or when the work ends, as if the work had reported it.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from types import TracebackType


@dataclass(frozen=True)
class ProgressEvent:
    """``step`` of ``total`` of ``stage``, ``elapsed_s`` into it; ``total`` 0: a phase without steps."""

    stage: str
    step: int
    total: int
    elapsed_s: float
    metrics: dict[str, float]


ProgressFn = Callable[[ProgressEvent], None]
HEARTBEAT_S = 10.0
"""Seconds between heartbeat events: the longest a stage stays silent on the console."""


class Heartbeat:
    """A ``ProgressFn`` that also reports on its own every ``every_s`` seconds while it is entered.

    ``total`` > 0 (a loop of steps): heartbeat events carry ``step`` (set by the work as it goes)
    of ``total``, like the loop's own events. ``total`` = 0 (one long call): they are labelled
    ``"<stage> (<phase>)"`` with step 0 of 0, and ``phase`` says what is running; ``announce`` emits
    one at once, so the console names a long phase as it starts. Elapsed times count from entering,
    plus ``elapsed_before`` (the time a resumed loop had already run). ``every_s`` None: ``HEARTBEAT_S``."""

    def __init__(self, progress: ProgressFn | None, stage: str, total: int = 0, phase: str = "",
                 every_s: float | None = None, elapsed_before: float = 0.0, announce: bool = False,
                 clock: Callable[[], float] = time.perf_counter) -> None:
        every_s = HEARTBEAT_S if every_s is None else every_s  # read now: tests shorten it
        if not every_s > 0:
            raise ValueError(f"every_s must be > 0, got {every_s}")
        self.progress, self.stage, self.total = progress, stage, total
        self.phase = phase
        self.step = 0
        self.every_s, self.elapsed_before, self.announce, self.clock = every_s, elapsed_before, announce, clock
        self.beats = 0
        self._start = clock()
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._error: BaseException | None = None

    def elapsed(self) -> float:
        return self.elapsed_before + self.clock() - self._start

    def event(self) -> ProgressEvent:
        """What a heartbeat reports now."""
        if self.total > 0:
            return ProgressEvent(self.stage, self.step, self.total, self.elapsed(), {})
        label = f"{self.stage} ({self.phase})" if self.phase else self.stage
        return ProgressEvent(label, 0, 0, self.elapsed(), {})

    def __call__(self, event: ProgressEvent) -> None:
        """Forward one of the work's own events (and raise what the timer thread's report raised)."""
        self.raise_pending()
        if self.progress is None:
            return
        with self._lock:
            self.progress(event)

    def set_phase(self, phase: str) -> None:
        """Name the call now running; announced at once when ``announce`` is set."""
        self.phase = phase
        if self.announce:
            self(self.event())

    def raise_pending(self) -> None:
        error, self._error = self._error, None
        if error is not None:
            raise error

    def __enter__(self) -> Heartbeat:
        self._start = self.clock()
        if self.progress is None:
            return self
        if self.announce and (self.phase or self.total > 0):
            self(self.event())
        self._thread = threading.Thread(target=self._beat, name=f"heartbeat {self.stage}", daemon=True)
        self._thread.start()
        return self

    def __exit__(self, kind: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
        if kind is None:  # the work's own exception wins over a reporter's
            self.raise_pending()

    def _beat(self) -> None:
        while not self._stop.wait(self.every_s):
            try:
                with self._lock:
                    if self._stop.is_set():
                        return
                    self.progress(self.event())  # type: ignore[misc]
                    self.beats += 1
            except BaseException as exc:  # surfaces in the work's thread (``raise_pending``)
                self._error = exc
                return
