"""drivers.base.data_frame builds the same frame as python-can's constructor."""

from __future__ import annotations

import can
import pytest

from drivers.base import data_frame


@pytest.mark.parametrize("data", [b"", b"\x01", bytes(range(8)), bytearray(b"\x0f\x00\x10")])
def test_data_frame_equals_the_constructors_frame_in_every_field(data: bytes) -> None:
    built = data_frame(0x201, data)
    expected = can.Message(arbitration_id=0x201, data=data, is_extended_id=False)
    # every field python-can's Message has (a new one in a later python-can would be
    # missing from data_frame's and fail here)
    fields = [name for name in can.Message.__slots__ if name != "__weakref__"]
    assert {name: getattr(built, name) for name in fields} == {
        name: getattr(expected, name) for name in fields
    }
    assert built.equals(expected, timestamp_delta=None)


def test_data_frame_owns_its_data() -> None:
    source = bytearray(b"\x01\x02")
    frame = data_frame(0x181, source)
    source[0] = 0xFF
    assert frame.data == bytearray(b"\x01\x02")
