"""The live progress line of the `cdprd` commands that take a while: one line on stderr,
redrawn in place, with a bar where the fraction done is known, the phase, the time
elapsed and an ETA (the daemon's where it says how long, else extrapolated from the
fraction).  Shown only where a person watches (stderr a TTY) or with --progress; never
on stdout, which carries the result (--json)."""

from __future__ import annotations

import argparse
import sys
import threading
import time
from collections.abc import Callable
from typing import TextIO

PROGRESS_HELP = "show the progress line on stderr even when it is not a terminal"
WIDTH = 24  # characters of the bar
INTERVAL = 0.1  # s: the fastest redraw


def add_progress_flag(parser: argparse.ArgumentParser) -> None:
    """The --progress option (`args.progress`)."""
    parser.add_argument("--progress", action="store_true", help=PROGRESS_HELP)


def duration(seconds: float) -> str:
    """`seconds` as 7s, 1m05s or 2h03m."""
    s = max(0, round(seconds))
    if s < 60:
        return f"{s}s"
    if s < 3600:
        return f"{s // 60}m{s % 60:02d}s"
    return f"{s // 3600}h{s // 60 % 60:02d}m"


def render(
    label: str, elapsed: float, fraction: float | None, phase: str, eta: float | None
) -> str:
    """The line: label, bar and percentage (fraction known), phase, elapsed, ETA."""
    parts = [label]
    if fraction is not None:
        f = min(max(fraction, 0.0), 1.0)
        filled = int(WIDTH * f)
        parts.append(f"[{'#' * filled}{'.' * (WIDTH - filled)}] {f:4.0%}")
        if eta is None and 0.0 < f < 1.0:
            eta = elapsed * (1.0 - f) / f
    if phase:
        parts.append(phase)
    parts.append(duration(elapsed))
    if eta is not None:
        parts.append(f"ETA {duration(eta)}")
    return "  ".join(parts)


class ProgressLine:
    """One live line on `stream` (nothing at all unless `enabled`); thread-safe, as
    zenoh's callbacks update it from their own threads.  Use as a context manager: the
    line is ended (a newline) when the work is."""

    def __init__(
        self,
        label: str,
        enabled: bool,
        stream: TextIO | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.label = label
        self.enabled = enabled
        self.stream = sys.stderr if stream is None else stream
        self.clock = clock
        self.started = clock()
        self._drawn = -INTERVAL  # when it was last drawn (clock, relative to the start)
        self._width = 0  # characters on the line now, to blank what a shorter one leaves
        self._lock = threading.Lock()

    def update(
        self,
        fraction: float | None = None,
        phase: str = "",
        eta: float | None = None,
        force: bool = False,
    ) -> None:
        """Redraw, at most every INTERVAL s unless `force`: `fraction` done (None:
        unknown), the `phase`, and the `eta` in s (None: extrapolated from fraction)."""
        if not self.enabled:
            return
        with self._lock:
            elapsed = self.clock() - self.started
            if not force and elapsed - self._drawn < INTERVAL:
                return
            self._drawn = elapsed
            line = render(self.label, elapsed, fraction, phase, eta)
            self.stream.write("\r" + line.ljust(self._width))
            self.stream.flush()
            self._width = max(len(line), self._width)

    def count(self, done: int, total: int) -> None:
        """`done` steps of `total` (the shape of tuning's progress callbacks)."""
        self.update(done / total if total else None, f"{done}/{total}", force=done == total)

    def note(self, text: str) -> None:
        """A line of its own on the stream, shown whether or not the progress is (a
        warning, a skipped step): the live line is blanked first and redrawn by the
        next update."""
        with self._lock:
            if self._width:
                self.stream.write("\r" + " " * self._width + "\r")
                self._width = 0
                self._drawn = -INTERVAL
            self.stream.write(text + "\n")
            self.stream.flush()

    def close(self) -> None:
        """End the line (if one was drawn)."""
        with self._lock:
            if self._width:
                self.stream.write("\n")
                self.stream.flush()
                self._width = 0

    def __enter__(self) -> ProgressLine:
        return self

    def __exit__(self, *_exc: object) -> None:
        self.close()


def progress_line(label: str, forced: bool, stream: TextIO | None = None) -> ProgressLine:
    """A ProgressLine shown when `forced` (--progress) or `stream` (stderr) is a TTY."""
    stream = sys.stderr if stream is None else stream
    return ProgressLine(label, forced or stream.isatty(), stream)
