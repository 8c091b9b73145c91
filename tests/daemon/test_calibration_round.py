"""The calibration round on disk (daemon.cli.calibration_round): what is written is what
is read back, and a file that is not this robot's own, unchanged round is refused
naming the file and the problem."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from cdpr import Pose
from daemon.cli.calibration_round import (
    CalibrationRound,
    RoundFileError,
    load_round,
    save_round,
)
from daemon.service.calibration_state import checksum
from tuning.calibration import Sample

IDENTITY = "sha256:robot"


def a_round() -> CalibrationRound:
    """Three poses planned: the first recorded, the second skipped, the third to fly."""
    planned = [Pose((0.1 * k, 0.0, 1.2), (1.0, 0.0, 0.0, 0.0)) for k in range(3)]
    planned[2] = Pose((0.0, 0.2, 1.3), (0.9950041652780258, 0.0998334166468282, 0.0, 0.0))
    kept = CalibrationRound("reference8", IDENTITY, [0.01 * k for k in range(8)], planned)
    kept.recorded[0] = Sample(np.linspace(1.5, 2.2, 8), -np.linspace(60.0, 95.0, 8))
    kept.skipped[1] = "the way leaves the wrench-feasible set"
    return kept


def test_a_round_reads_back_as_written(tmp_path: Path) -> None:
    path = tmp_path / "reference8.calibration-round.json"
    assert load_round(path, "reference8", 8, IDENTITY) is None
    written = a_round()
    save_round(path, written)
    read = load_round(path, "reference8", 8, IDENTITY)
    assert read is not None
    assert read.remaining() == [2] and read.offsets == written.offsets
    assert read.skipped == written.skipped
    assert [p.position_tuple for p in read.planned] == [p.position_tuple for p in written.planned]
    assert read.planned[2].quaternion_tuple == pytest.approx(written.planned[2].quaternion_tuple)
    [sample] = read.samples()
    assert np.array_equal(sample.lengths, written.recorded[0].lengths)
    assert np.array_equal(sample.forces, written.recorded[0].forces)


def _resealed(path: Path, change: dict) -> None:
    """The file with `change` applied and its checksum made to match again."""
    data = json.loads(path.read_text())
    data.update(change)
    data["checksum"] = checksum({k: v for k, v in data.items() if k != "checksum"})
    path.write_text(json.dumps(data))


@pytest.mark.parametrize(
    ("change", "resealed", "words"),
    [
        ({"offsets": [0.0] * 8}, False, "checksum: does not match the content"),
        ({"robot": "other"}, True, "robot: a round of robot 'other', not of 'reference8'"),
        ({"identity": "sha256:else"}, True, "identity: a round of another robot"),
        ({"schema": 2}, True, "schema: expected 1, got 2"),
        ({"offsets": [0.0] * 7}, True, "offsets: expected 8 finite numbers"),
        ({"planned": [[0, 0, 1, 2, 0, 0, 0]]}, True, "planned[0]: expected [x, y, z, qw"),
        (
            {"skipped": [{"pose": 0, "reason": "twice"}]},
            True,
            "skipped[0]: pose 0 recorded or skipped twice",
        ),
        ({"recorded": [{"pose": 3}]}, True, "recorded[0]: expected an object whose pose is one"),
        (
            {"recorded": [{"pose": 0, "lengths": [1.0] * 8, "forces": ["x"] * 8}]},
            True,
            "recorded[0]: expected lengths and forces, 8 finite numbers each",
        ),
    ],
)
def test_a_round_that_is_not_this_robots_unchanged_own_is_refused(
    tmp_path: Path, change: dict, resealed: bool, words: str
) -> None:
    path = tmp_path / "round.json"
    save_round(path, a_round())
    if resealed:
        _resealed(path, change)
    else:
        data = json.loads(path.read_text())
        data.update(change)
        path.write_text(json.dumps(data))
    with pytest.raises(RoundFileError) as refused:
        load_round(path, "reference8", 8, IDENTITY)
    assert str(refused.value).startswith(f"{path}: {words}")


@pytest.mark.parametrize(
    ("content", "words"),
    [(b"{not json", "corrupt (not JSON"), (b"[1, 2]", "(top): expected an object, got list")],
)
def test_an_unreadable_round_is_refused_naming_the_file(
    tmp_path: Path, content: bytes, words: str
) -> None:
    path = tmp_path / "round.json"
    path.write_bytes(content)
    with pytest.raises(RoundFileError) as refused:
        load_round(path, "reference8", 8, IDENTITY)
    assert str(refused.value).startswith(f"{path}: {words}")
    directory = tmp_path / "dir.json"
    directory.mkdir()
    with pytest.raises(RoundFileError, match="a directory, not a regular file"):
        load_round(directory, "reference8", 8, IDENTITY)
