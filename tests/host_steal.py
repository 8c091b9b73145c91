"""How much CPU time the hypervisor took from this host (`steal` in /proc/stat) while a
block ran.  On a virtual machine whose CPUs are taken away for milliseconds at a time, a
real-time figure (a latency, an identified lag, the longest stall) measures the host,
not the code: a test of such a figure that misses its bound skips, saying how much was
stolen, where that was above STEAL_LIMIT, and fails otherwise.  Tests of behaviour (a
brake, an answer, a refusal) never skip for it."""

from __future__ import annotations

from pathlib import Path
from types import TracebackType

import pytest

STEAL_LIMIT = 0.02  # of all CPU time: above it, real-time figures are the host's
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
