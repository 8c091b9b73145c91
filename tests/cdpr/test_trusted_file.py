"""cdpr.trusted_file: every file the daemon is given is read without blocking, only if it
is a regular file, and only up to a size; otherwise one line names the file and why."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from cdpr.trusted_file import UnreadableFileError, read_trusted

pytestmark = pytest.mark.timeout(30)  # a FIFO that blocked would hang here


def test_a_regular_file_is_read_whole(tmp_path: Path) -> None:
    (tmp_path / "f").write_bytes(b"x" * 100)
    assert read_trusted(tmp_path / "f", 100) == b"x" * 100


@pytest.mark.parametrize(
    ("kind", "problem"),
    [
        ("fifo", "a FIFO (named pipe), not a regular file"),
        ("directory", "a directory, not a regular file"),
        ("device", "a device, not a regular file"),
        ("missing", "No such file or directory"),
        ("long", "longer than 100 bytes"),
    ],
)
def test_anything_else_is_named_in_one_line(kind: str, problem: str, tmp_path: Path) -> None:
    path = {"device": Path("/dev/zero"), "directory": tmp_path}.get(kind, tmp_path / "f")
    if kind == "fifo":
        os.mkfifo(path)  # no writer: a blocking open would wait for ever
    elif kind == "long":
        path.write_bytes(b"x" * 101)
    with pytest.raises(UnreadableFileError) as refused:
        read_trusted(path, 100)
    assert str(refused.value) == f"{path}: cannot read: {problem}"
    assert refused.value.problem == problem
