"""drivers.base.bus_frame (and data_frame) build the same frame as python-can's
constructor, whose field handling they skip for speed."""

from __future__ import annotations

import can
import pytest

from drivers.base import bus_frame, data_frame

# every field python-can's Message has (a new one in a later python-can would be missing
# from bus_frame's and fail here)
FIELDS = [name for name in can.Message.__slots__ if name != "__weakref__"]


def _fields(frame: can.Message) -> dict[str, object]:
    return {name: getattr(frame, name) for name in FIELDS}


@pytest.mark.parametrize("data", [b"", b"\x01", bytes(range(8)), bytearray(b"\x0f\x00\x10")])
def test_data_frame_equals_the_constructors_frame_in_every_field(data: bytes) -> None:
    built = data_frame(0x201, data)
    expected = can.Message(arbitration_id=0x201, data=data, is_extended_id=False)
    assert _fields(built) == _fields(expected)
    assert built.equals(expected, timestamp_delta=None)


@pytest.mark.parametrize(
    "kind",
    [
        {"arbitration_id": 0x181, "data": b"\x01\x02"},
        {"arbitration_id": 0x1ABCDE01, "data": bytes(8), "is_extended_id": True},
        {"arbitration_id": 0x601, "is_remote_frame": True, "dlc": 8},
        {"arbitration_id": 0x20000004, "is_error_frame": True, "data": bytes(8),
         "is_extended_id": True},
    ],
)  # fmt: skip
def test_bus_frame_equals_the_constructors_frame_for_every_kind(kind: dict) -> None:
    """Data, extended, remote (a DLC and no data) and error frames, stamped and on a
    channel, as a bus's receive path builds them."""
    data = kind.get("data", b"")
    built = bus_frame(
        kind["arbitration_id"],
        data,
        timestamp=12.5,
        channel="left",
        extended=kind.get("is_extended_id", False),
        remote=kind.get("is_remote_frame", False),
        error=kind.get("is_error_frame", False),
        dlc=kind.get("dlc"),
    )
    expected = can.Message(
        timestamp=12.5, channel="left", check=False, **{"is_extended_id": False, **kind}
    )
    assert _fields(built) == _fields(expected)
    assert built.equals(expected)


def test_data_frame_owns_its_data() -> None:
    source = bytearray(b"\x01\x02")
    frame = data_frame(0x181, source)
    source[0] = 0xFF
    assert frame.data == bytearray(b"\x01\x02")
