"""When a frame reached the host (drivers.bus.FrameIO.arrival): where a Notifier thread
reads the bus (python-can's virtual bus), its own stamp moved onto the monotonic clock;
where the loop reads it, the moment it was delivered; and the daemon's port hands
frames a Notifier thread queued to the cycle at once when polled (BusPort.poll), so
that an answer read late is still taken before the next SYNC goes out."""

from __future__ import annotations

import asyncio
import itertools
import os
import time

import can

from daemon.service.bus_port import BusPort
from drivers.bus import MAX_FRAME_AGE, frame_io
from sim_bus.bus.loopbus import LoopBus

CHANNELS = itertools.count()
NOW = 100.0  # s on the monotonic clock: when the frames below are delivered


def _channel() -> str:
    return f"cdprd-arrival-{os.getpid()}-{next(CHANNELS)}"


def _virtual(channel: str) -> can.BusABC:
    return can.Bus(interface="virtual", channel=channel, receive_own_messages=False)


def test_a_virtual_frame_arrived_when_it_was_sent() -> None:
    bus = _virtual(_channel())
    try:
        io = frame_io(bus)
        sent = can.Message(arbitration_id=0x181, data=b"\0", timestamp=time.time() - 0.03)
        before = time.monotonic()
        arrived = io.arrival(sent, NOW)
        # its 30 ms of age back from the moment it is handled (both clocks read then);
        # a pause while handling it can only make it look newer
        assert before - MAX_FRAME_AGE <= arrived <= time.monotonic() - 0.03 + 0.001
        future = can.Message(arbitration_id=0x181, timestamp=time.time() + 5.0)
        ancient = can.Message(arbitration_id=0x181, timestamp=time.time() - 5.0)
        unstamped = can.Message(arbitration_id=0x181, timestamp=0.0)
        before = time.monotonic()
        assert before <= io.arrival(future, NOW) <= time.monotonic()  # never later than now
        before = time.monotonic()
        old = io.arrival(ancient, NOW)  # a bad stamp: at most MAX_FRAME_AGE back
        assert before - MAX_FRAME_AGE <= old <= time.monotonic() - MAX_FRAME_AGE
        assert io.arrival(unstamped, NOW) == NOW  # no stamp: when delivered
    finally:
        bus.shutdown()


def test_a_frame_handled_well_after_its_batch_was_delivered_keeps_its_own_arrival() -> None:
    """The batch's delivery time is read before its frames are handled (listeners, other
    frames, a preempted loop): a frame sent just before it must not look older by the
    time the handling took, or an answer to a SYNC looks sent before that SYNC."""
    bus = _virtual(_channel())
    try:
        io = frame_io(bus)
        before_sent = time.monotonic()
        sent = can.Message(arbitration_id=0x181, data=b"\0", timestamp=time.time())
        delivered = time.monotonic()
        time.sleep(0.02)  # handling the batch up to this frame took 20 ms
        arrived = io.arrival(sent, delivered)
        assert arrived >= before_sent - 0.001, f"arrived {(delivered - arrived) * 1e3:.1f} ms early"
        assert arrived <= time.monotonic()
    finally:
        bus.shutdown()


def test_a_bus_the_loop_reads_arrives_when_delivered() -> None:
    """The loop bus (as SocketCAN and socketcand: a file descriptor the loop reads, and
    the cycle polls before each SYNC): a frame arrived when it was delivered, whatever
    its stamp says (a virtual machine's stamps were milliseconds off its clock)."""
    bus = LoopBus(_channel())
    try:
        io = frame_io(bus)
        assert io.fileno() >= 0
        old = can.Message(arbitration_id=0x181, timestamp=time.time() - 0.05)
        assert io.arrival(old, NOW) == NOW
    finally:
        bus.shutdown()


def test_polling_hands_over_what_the_notifier_thread_queued() -> None:
    """With the loop not running (held up), a frame the Notifier thread queued reaches
    the sink when the port is polled, not only at the loop's next pass."""
    channel = _channel()
    bus, drive = _virtual(channel), None
    loop = asyncio.new_event_loop()
    delivered: list[int] = []
    port = BusPort(bus, lambda frames, now: delivered.extend(m.arbitration_id for m in frames))
    try:
        drive = _virtual(channel)
        port.open(loop)
        drive.send(can.Message(arbitration_id=0x181, data=b"\1", is_extended_id=False))
        watch = port._watch
        assert watch is not None and not watch.polled
        for _ in range(400):  # a bound, not a measurement: the thread queues it
            if watch._queue:
                break
            time.sleep(0.005)
        assert watch._queue, "the Notifier thread never queued the frame"
        assert delivered == []  # the loop has not run
        port.poll()
        assert delivered == [0x181]
    finally:
        port.close()
        loop.close()
        bus.shutdown()
        if drive is not None:
            drive.shutdown()
