"""Reading a file the daemon is given: the config, robot files, an EDS, stored state.

Such a path is data from outside, not a promise: it may name a FIFO (opening it for
reading waits for a writer, for ever), a device (/dev/zero never ends), a directory, or a
file larger than anything the daemon should hold.  `read_trusted` is the one way every
such file is read: opened with O_NONBLOCK (a FIFO opens at once instead of waiting),
checked with fstat on the descriptor it reads (not the path, which may be swapped between
a check and the open) to be a regular file, and read to at most `max_bytes`.  Anything
else is an UnreadableFileError whose message is one line naming the file and the problem.
"""

from __future__ import annotations

import os
import stat
from pathlib import Path


class UnreadableFileError(ValueError):
    """The file cannot be used: 'PATH: cannot read: problem' (one line); `problem` alone
    for a caller that names the file its own way."""

    def __init__(self, path: str, problem: str) -> None:
        super().__init__(f"{path}: cannot read: {problem}")
        self.problem = problem


def read_trusted(path: str | Path, max_bytes: int) -> bytes:
    """The content of the regular file at `path`, at most `max_bytes` long, read without
    ever blocking on what the path names (module docstring); UnreadableFileError otherwise."""
    shown = show_path(path)

    def refuse(problem: str) -> UnreadableFileError:
        return UnreadableFileError(shown, problem)

    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_NOCTTY | os.O_CLOEXEC)
    except OSError as exc:
        raise refuse(exc.strerror or str(exc)) from None
    except ValueError as exc:  # e.g. a NUL character in the path
        raise refuse(str(exc)) from None
    try:
        mode = os.fstat(fd).st_mode
        if not stat.S_ISREG(mode):
            raise refuse(f"{_kind(mode)}, not a regular file")
        chunks, size = [], 0
        while size <= max_bytes:
            chunk = os.read(fd, max_bytes + 1 - size)
            if not chunk:
                break
            chunks.append(chunk)
            size += len(chunk)
    except OSError as exc:
        raise refuse(exc.strerror or str(exc)) from None
    finally:
        os.close(fd)
    if size > max_bytes:
        raise refuse(f"longer than {max_bytes} bytes")
    return b"".join(chunks)


def show_path(path: str | Path) -> str:
    """A path as error messages print it: as is, or quoted if it holds a line break or
    another character that is not printable, shortened if very long."""
    text = str(path)
    if text.isprintable() and len(text) <= 200:
        return text
    quoted = repr(text)
    return quoted if len(quoted) <= 200 else f"{quoted[:195]}...{quoted[-1]}"


def _kind(mode: int) -> str:
    if stat.S_ISDIR(mode):
        return "a directory"
    if stat.S_ISFIFO(mode):
        return "a FIFO (named pipe)"
    if stat.S_ISSOCK(mode):
        return "a socket"
    return "a device"
