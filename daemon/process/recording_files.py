"""The files of one recording over a long run: when to begin a new one, which old ones to
delete, and when the disk has too little room to write at all (config `recording:`).

A recording of a service that runs for weeks cannot be one file: cycle telemetry and
raw CAN grow by the better part of a gigabyte an hour.  A recorder (daemon.process.
recording) therefore writes a series of files named after the time each began
(`session_path`: "cycle.mcap" -> "cycle-20250102-030405.mcap"), begins the next one
when the current one reaches `rotate_mb` or `rotate_minutes`, and deletes the oldest
files of its series (this run's and earlier runs') beyond `keep_mb` in all or
`keep_files`.  Below `min_free_mb` of free space on the file system, it pauses rather
than fill the disk the daemon's state and logs live on.

Pure bookkeeping on paths and sizes, no recorder state: the recorder asks, and decides.
"""

from __future__ import annotations

import datetime
import logging
import os
import re
from dataclasses import dataclass
from pathlib import Path

from daemon.config import RecordingConfig

log = logging.getLogger(__name__)

MB = 1_000_000  # bytes: the config's sizes are decimal megabytes, as df -H shows them
RESUME_MARGIN = 0.1  # a paused recording resumes once free space exceeds the floor by this
RESUME_MIN = 16 * MB  # ... and by at least this: a full disk with no floor does not flap


def session_path(path: str | Path, start: datetime.datetime | None = None) -> Path:
    """`path` with the start time inserted before the suffix ("cycle.mcap" ->
    "cycle-20250102-030405.mcap", local time), plus "-2", "-3", … if that file exists."""
    path = Path(path)
    stamp = (start or datetime.datetime.now()).strftime("%Y%m%d-%H%M%S")
    candidate = path.with_name(f"{path.stem}-{stamp}{path.suffix}")
    n = 1
    while candidate.exists():
        n += 1
        candidate = path.with_name(f"{path.stem}-{stamp}-{n}{path.suffix}")
    return candidate


@dataclass(frozen=True, slots=True)
class FileLimits:
    """The config's recording limits in bytes and seconds; None: no such limit."""

    rotate_bytes: int | None = None
    rotate_seconds: float | None = None
    keep_bytes: int | None = None
    keep_files: int | None = None
    min_free_bytes: int = 0

    @property
    def resume_bytes(self) -> int:
        """Free space at which a paused recording begins a new file."""
        return self.min_free_bytes + max(round(RESUME_MARGIN * self.min_free_bytes), RESUME_MIN)


def file_limits(config: RecordingConfig) -> FileLimits:
    """The config's `recording:` limits in bytes and seconds."""
    return FileLimits(
        rotate_bytes=None if config.rotate_mb is None else round(config.rotate_mb * MB),
        rotate_seconds=None if config.rotate_minutes is None else 60.0 * config.rotate_minutes,
        keep_bytes=None if config.keep_mb is None else round(config.keep_mb * MB),
        keep_files=config.keep_files,
        min_free_bytes=round(config.min_free_mb * MB),
    )


class Series:
    """The files of the recording configured as `base` ("dir/cycle.mcap"): those named by
    session_path from it, in its directory, and nothing else there."""

    def __init__(self, base: Path, limits: FileLimits) -> None:
        self.base = base
        self.limits = limits
        stem, suffix = re.escape(base.stem), re.escape(base.suffix)
        self._name = re.compile(rf"{stem}-\d{{8}}-\d{{6}}(-\d+)?{suffix}")

    def next_path(self) -> Path:
        """The name of a file beginning now."""
        return session_path(self.base)

    def files(self) -> list[Path]:
        """The series' files, oldest first (by modification time, then name)."""
        found = []
        with os.scandir(self.base.parent) as entries:
            for entry in entries:
                if self._name.fullmatch(entry.name) and entry.is_file(follow_symlinks=False):
                    found.append((entry.stat().st_mtime, entry.name))
        return [self.base.parent / name for _, name in sorted(found)]

    def rotation_due(self, size: int, age: float) -> bool:
        """Whether the current file, `size` bytes and `age` seconds old, is complete."""
        limits = self.limits
        return (limits.rotate_bytes is not None and size >= limits.rotate_bytes) or (
            limits.rotate_seconds is not None and age >= limits.rotate_seconds
        )

    def prune(self, current: Path | None) -> list[Path]:
        """Delete the oldest files beyond keep_files (counting `current`, the file being
        written) and beyond keep_bytes (leaving room for `current` to grow to
        rotate_bytes); `current` itself is never deleted.  The files deleted; one that
        cannot be is logged and skipped."""
        limits = self.limits
        older = [p for p in self.files() if p != current]
        sizes = [_size(p) for p in older]
        room = limits.keep_bytes
        if room is not None and current is not None:
            room -= limits.rotate_bytes or 0
        excess_files = 0 if limits.keep_files is None else len(older) + 1 - limits.keep_files
        total = sum(sizes)
        deleted = []
        for path, size in zip(older, sizes, strict=True):
            if len(deleted) >= excess_files and (room is None or total <= room):
                break
            try:
                path.unlink()
            except FileNotFoundError:
                pass
            except OSError as exc:
                log.warning("recording: cannot delete %s: %s", path, exc.strerror or exc)
                continue
            deleted.append(path)
            total -= size
        return deleted

    def free_bytes(self) -> int:
        """Free space for this process on the file system of the series' directory."""
        st = os.statvfs(self.base.parent)
        return st.f_bavail * st.f_frsize


def _size(path: Path) -> int:
    try:
        return path.stat().st_size
    except FileNotFoundError:
        return 0
