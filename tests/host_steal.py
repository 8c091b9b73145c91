"""How much CPU time the hypervisor took from this host (`steal` in /proc/stat) while a
block ran.  On a virtual machine whose CPUs are taken away for milliseconds at a time, a
real-time figure (a latency, an identified lag, the longest stall) measures the host,
not the code: a test of such a figure that misses its bound skips, saying how much was
stolen, where that was above STEAL_LIMIT, and fails otherwise.  Tests of behaviour (a
brake, an answer, a refusal) never skip for a share of stolen time; a brake that came
right after the hypervisor froze a CPU for longer than the control loop may go without
(FreezeWatch) is the robot's right answer to a frozen loop and cannot be judged: such a
test skips, naming the brake and the freeze."""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from types import TracebackType

import pytest

STEAL_LIMIT = 0.02  # of all CPU time: above it, real-time figures are the host's
FREEZE_LIMIT = 0.02  # s: a CPU frozen this long in FREEZE_WINDOW: a brake then is the host's
FREEZE_WINDOW = 1.0  # s before a brake
_ROOT = Path(__file__).resolve().parent.parent
_STAT = Path("/proc/stat")


def _times() -> tuple[int, int]:
    """(steal, total) jiffies over every CPU since boot; (0, 0) where not known."""
    try:
        fields = _STAT.read_text().split("\n", 1)[0].split()
    except OSError:
        return 0, 0
    counts = [int(x) for x in fields[1:9]]  # user .. steal (guest time is in user)
    return (counts[7], sum(counts)) if len(counts) == 8 else (0, 0)


class StealMeter:
    """`with StealMeter() as meter:` ...; then `meter.fraction`, the share of the host's
    CPU time stolen meanwhile."""

    def __enter__(self) -> StealMeter:
        self._start = _times()
        self._end: tuple[int, int] | None = None
        return self

    def __exit__(
        self,
        kind: type[BaseException] | None,
        error: BaseException | None,
        trace: TracebackType | None,
    ) -> None:
        self._end = _times()

    @property
    def fraction(self) -> float:
        end = self._end if self._end is not None else _times()
        total = end[1] - self._start[1]
        return (end[0] - self._start[0]) / total if total > 0 else 0.0

    def check(self, ok: bool, what: str, detail: str) -> None:
        """Assert a real-time figure: `ok`, or else a skip where more than STEAL_LIMIT was
        stolen (`what` then measured the host), or else a failure saying `detail`."""
        if ok:
            return
        if self.fraction > STEAL_LIMIT:
            pytest.skip(
                f"{what}: {detail}, with {self.fraction:.1%} of this host's CPU time taken "
                f"by the hypervisor meanwhile (over {STEAL_LIMIT:.0%}): the host's figure, "
                "not the code's"
            )
        raise AssertionError(f"{what}: {detail}")


class FreezeWatch:
    """`with FreezeWatch() as freezes:` ...: a process (tests.freeze_probe) that notes
    every time a CPU of this host was frozen for more than 10 ms, so that a brake can be
    set beside what the hypervisor took just before it (on this host: one CPU at a time,
    20-130 ms, unseen in /proc/stat's steal)."""

    def __init__(self) -> None:
        self._file = Path(tempfile.mkstemp(prefix="cdprd-freezes-", suffix=".txt")[1])
        self._probe: subprocess.Popen | None = None

    def __enter__(self) -> FreezeWatch:
        self._probe = subprocess.Popen(
            [sys.executable, "-m", "tests.freeze_probe", str(self._file), str(os.getpid())],
            cwd=_ROOT,
        )
        return self

    def __exit__(self, *exc: object) -> None:
        if self._probe is not None:
            self._probe.kill()
            self._probe.wait()
        self._file.unlink(missing_ok=True)

    def freezes(self) -> list[tuple[int, float, float]]:
        """(cpu, monotonic start, seconds) of every freeze noted so far."""
        rows = [line.split() for line in self._file.read_text().splitlines()]
        return [(int(c), float(t), float(d)) for c, t, d in rows if d]

    def longest(self, since: float, until: float) -> float:
        """The longest freeze (s) that overlapped monotonic [since, until]."""
        return max((d for _, t, d in self.freezes() if t <= until and t + d >= since), default=0.0)

    def excuse(self, fault: object, at: float | None = None) -> None:
        """Skip, naming `fault` and the freeze, where a CPU was frozen for FREEZE_LIMIT
        or more in the FREEZE_WINDOW before `at` (monotonic; now if None)."""
        until = time.monotonic() if at is None else at
        frozen = self.longest(until - FREEZE_WINDOW, until)
        if frozen >= FREEZE_LIMIT:
            pytest.skip(
                f"braked ({fault}) after this host's hypervisor froze a CPU for "
                f"{frozen * 1e3:.0f} ms in the {FREEZE_WINDOW:g} s before: a frozen loop's "
                "right answer, not a judgement of the code"
            )


def judged(ok: bool, frozen: float, what: str, detail: str) -> None:
    """Assert a real-time figure measured while a FreezeWatch ran (`frozen`: its longest
    freeze, s): `ok`, or else a skip where a CPU froze for FREEZE_LIMIT or more meanwhile
    (`what` then measured the host), or else a failure saying `detail`."""
    if ok:
        return
    if frozen >= FREEZE_LIMIT:
        pytest.skip(
            f"{what}: {detail}, with a CPU of this host frozen for {frozen * 1e3:.0f} ms "
            "meanwhile: the host's figure, not the code's"
        )
    raise AssertionError(f"{what}: {detail}")
