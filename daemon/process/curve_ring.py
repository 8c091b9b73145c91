"""The shared memory that planned trajectories cross into the core in (DESIGN §16).

One memfd of RING_BYTES, made and mapped by the core before its memory is locked and the
drives start, passed to every companion it spawns.  The companion writes a planned
trajectory's packed curve (cdpr.trajectory.core.Curve.packed) into a free range and
names the range in its call; the core samples the curve where it lies, so that taking a
trajectory costs the core the same whatever its length: no copy, no mapping (mapping 9 MB
into a process whose memory is locked costs 1-2 ms, a missed cycle at 1 kHz).  The
core tells the companion when a curve is dropped, and only then is its range reused.
"""

from __future__ import annotations

import bisect
import mmap
import os

import numpy as np

from cdpr.trajectory import Trajectory
from cdpr.trajectory.core import Curve

RING_BYTES = 64 << 20  # room for several 10,000-waypoint curves (9 MB each)
ALIGN = 64  # bytes: each curve starts on a cache line


class RingFullError(Exception):
    """No free range is large enough: trajectories in use hold the ring."""


class CurveRing:
    """The ring, mapped: `create` it in the core, `attach` to its fd in the companion."""

    def __init__(self, fd: int, size: int) -> None:
        self.fd = fd
        self.size = size
        self._map = mmap.mmap(fd, size)
        self._values = np.frombuffer(self._map, dtype=np.float64)
        self._free: list[tuple[int, int]] = [(0, size)]  # (start, end), sorted, disjoint

    @classmethod
    def create(cls, size: int = RING_BYTES) -> CurveRing:
        fd = os.memfd_create("cdprd-curves")  # close-on-exec: passed on explicitly
        os.ftruncate(fd, size)
        return cls(fd, size)

    @classmethod
    def attach(cls, fd: int) -> CurveRing:
        return cls(fd, os.fstat(fd).st_size)

    # -- the companion's side ----------------------------------------------------------------

    def write(self, trajectory: Trajectory) -> tuple[dict, int, int]:
        """The trajectory's curve written into a free range: (header, offset, count of
        float64 values) for the core; RingFullError if none is large enough."""
        header, data = trajectory.curve.packed()
        offset = self.allocate(data.nbytes)
        start = offset // 8
        self._values[start : start + data.size] = data
        return header, offset, data.size

    def allocate(self, nbytes: int) -> int:
        """The offset of a free range of at least `nbytes` (first fit), now in use."""
        need = -(-nbytes // ALIGN) * ALIGN
        for k, (start, end) in enumerate(self._free):
            if end - start >= need:
                if end - start == need:
                    del self._free[k]
                else:
                    self._free[k] = (start + need, end)
                return start
        largest = max((end - start for start, end in self._free), default=0)
        raise RingFullError(
            f"no {nbytes} bytes free in the trajectory ring ({self.size >> 20} MiB, the "
            f"largest free range {largest} bytes): trajectories in use hold it"
        )

    def release(self, offset: int, nbytes: int) -> None:
        """The range at `offset` (of `nbytes` as allocated) is free again."""
        end = offset + -(-nbytes // ALIGN) * ALIGN
        k = bisect.bisect(self._free, (offset, end))
        if k > 0 and self._free[k - 1][1] == offset:  # joins the range before
            offset = self._free.pop(k - 1)[0]
            k -= 1
        if k < len(self._free) and self._free[k][0] == end:  # and the one after
            end = self._free.pop(k)[1]
        self._free.insert(k, (offset, end))

    def reserve(self, ranges: list[tuple[int, int]]) -> None:
        """Mark (offset, nbytes) ranges in use: those of curves the core still follows,
        when a new companion attaches."""
        for offset, nbytes in ranges:
            end = offset + -(-nbytes // ALIGN) * ALIGN
            kept: list[tuple[int, int]] = []
            for start, stop in self._free:
                if stop <= offset or start >= end:
                    kept.append((start, stop))
                    continue
                if start < offset:
                    kept.append((start, offset))
                if stop > end:
                    kept.append((end, stop))
            self._free = kept

    @property
    def free_bytes(self) -> int:
        return sum(end - start for start, end in self._free)

    # -- the core's side ---------------------------------------------------------------------

    def curve(self, header: dict, offset: int, count: int) -> Curve:
        """The curve written at `offset`, read in place."""
        if offset % 8 or offset < 0 or offset + 8 * count > self.size:
            raise ValueError(f"a curve at {offset} of {count} values lies outside the ring")
        start = offset // 8
        return Curve.unpacked(header, self._values[start : start + count])
