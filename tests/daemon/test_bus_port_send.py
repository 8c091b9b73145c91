"""The daemon's end of the bus sends a cycle's frames together: one write per bus where
the bus allows, each bus's frames in order on their own bus, and a failed write counted
and reported once, none of its frames reported sent."""

from __future__ import annotations

import can

from daemon.service.bus_port import BusPort, MultiBusPort
from sim_bus.bus.pairbus import FRAME, PairBus, bus_pair


def _frame(can_id: int, bus: str | None = None) -> can.Message:
    return can.Message(arbitration_id=can_id, data=b"\x01", is_extended_id=False, channel=bus)


def test_each_bus_gets_its_frames_in_order_in_one_write() -> None:
    ends = {name: bus_pair() for name in ("can0", "can1")}
    buses = {name: PairBus(ours, name) for name, (ours, _) in ends.items()}
    port = MultiBusPort(buses, lambda frames, now: None, {name: [] for name in buses})
    sent: list[int] = []
    port.on_sent = lambda msg: sent.append(msg.arbitration_id)
    frames = [_frame(0x80, "can0"), _frame(0x80, "can1"), _frame(0x201, "can0"),
              _frame(0x202, "can1"), _frame(0x203, "can0")]  # fmt: skip
    port.send_all(frames)
    for name, ids in (("can0", [0x80, 0x201, 0x203]), ("can1", [0x80, 0x202])):
        data = ends[name][1].recv(1 << 16)  # the whole bus's share in the first read
        got = [FRAME.unpack(data[k : k + FRAME.size])[1] for k in range(0, len(data), FRAME.size)]
        assert got == ids, name
    assert sorted(sent) == sorted(m.arbitration_id for m in frames)
    port.close()
    for bus in buses.values():
        bus.shutdown()
    for _, theirs in ends.values():
        theirs.close()


def test_a_failed_write_counts_once_and_sends_none_of_its_frames() -> None:
    ours, theirs = bus_pair()
    bus = PairBus(ours, "can0")
    errors: list[str] = []
    port = BusPort(bus, lambda frames, now: None)
    port.on_error = errors.append
    sent: list[can.Message] = []
    port.on_sent = sent.append
    theirs.close()  # the simulator's end gone: the write fails
    port.send_all([_frame(0x80), _frame(0x201)])
    assert port.failures == 1 and sent == []
    assert port.lost is not None and "closed its end" in port.lost
    assert errors == []  # a gone bus is reported as lost, not as a transient error
    bus.shutdown()


class _RefusingBus(can.BusABC):
    """A bus that sends frame by frame (as SocketCAN) and refuses frames on `refused`, as
    a full transmit queue refuses one frame while the next may go."""

    def __init__(self, refused: int) -> None:
        super().__init__(channel="refusing")
        self.refused = refused
        self.sent: list[int] = []

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        if msg.arbitration_id == self.refused:
            raise can.CanOperationError("Failed to transmit: No buffer space available")
        self.sent.append(msg.arbitration_id)

    def _recv_internal(self, timeout: float | None) -> tuple[None, bool]:
        return None, False


def test_a_frame_by_frame_bus_sends_the_rest_after_a_refused_frame() -> None:
    bus = _RefusingBus(refused=0x201)
    errors: list[str] = []
    port = BusPort(bus, lambda frames, now: None)
    port.on_error = errors.append
    sent: list[int] = []
    port.on_sent = lambda msg: sent.append(msg.arbitration_id)
    port.send_all([_frame(0x80), _frame(0x201), _frame(0x202), _frame(0x201)])
    assert bus.sent == [0x80, 0x202] and sent == [0x80, 0x202]
    assert port.failures == 2 and len(errors) == 2  # each refused frame, as the bus saw it
    assert port.lost is None
    bus.shutdown()
