"""Bus-load accounting (sim_bus.bus.busload): frame bits, bit stuffing, CRC-15, load meter."""

from __future__ import annotations

import random

import can
import pytest
from hypothesis import given
from hypothesis import strategies as st

from sim_bus.bus.busload import (
    ERROR_FRAME_BITS,
    BusLoadMeter,
    FrameShape,
    crc15,
    cycle_load,
    destuff,
    expected_stuff_bits,
    frame_bits,
    frame_bitstream,
    message_bits,
    stuff,
    stuff_bit_count,
    stuffable_bits,
    unstuffed_bits,
    worst_case_stuff_bits,
)

bitstrings = st.text(alphabet="01", max_size=200)


def longest_run(bits: str) -> int:
    best = run = 0
    prev = ""
    for b in bits:
        run = run + 1 if b == prev else 1
        prev = b
        best = max(best, run)
    return best


@pytest.mark.parametrize("n", range(9))
def test_unstuffed_frame_lengths(n: int) -> None:
    assert unstuffed_bits(n) == 47 + 8 * n
    assert stuffable_bits(n) == 34 + 8 * n
    assert unstuffed_bits(n, extended=True) == 67 + 8 * n
    assert stuffable_bits(n, extended=True) == 54 + 8 * n
    assert worst_case_stuff_bits(n) == (33 + 8 * n) // 4
    assert unstuffed_bits(n, remote=True) == 47  # no data field


def test_known_worst_case_frame_lengths() -> None:
    assert frame_bits(8) == 135  # the textbook 8-byte standard frame
    assert frame_bits(0) == 55
    assert frame_bits(8, extended=True) == 160
    assert frame_bits(8, stuffing="none") == 111
    assert frame_bits(8, stuffing="expected") == pytest.approx(111 + 98 / 30)


def test_crc15_check_value() -> None:
    """CRC-15/CAN catalogue check: CRC of ASCII "123456789" is 0x059E."""
    assert crc15("".join(f"{b:08b}" for b in b"123456789")) == 0x059E


def test_all_zero_frame_by_hand() -> None:
    """Id 0, DLC 0: SOF..DLC are 19 dominant bits and their CRC is 0, so 34 zeros; a stuff
    bit after every 5 zeros (the '1' starts a new run): 6 stuff bits, 47 + 6 bits."""
    stream = frame_bitstream(0, b"")
    assert stream == "0" * 34
    assert stuff(stream) == ("00000" + "1") * 6 + "0000"
    assert message_bits(can.Message(arbitration_id=0, is_extended_id=False)) == 53


def test_extended_frame_layout() -> None:
    """SOF, base id, SRR=1, IDE=1, id extension, RTR, r1, r0, DLC, data, CRC."""
    stream = frame_bitstream(0x1ABCDEF0, b"\xa5", extended=True)
    ident = 0x1ABCDEF0
    assert stream[0] == "0"
    assert stream[1:12] == f"{ident >> 18:011b}"
    assert stream[12:14] == "11"
    assert stream[14:32] == f"{ident & 0x3FFFF:018b}"
    assert stream[32:35] == "000"
    assert stream[35:39] == "0001"
    assert stream[39:47] == "10100101"
    assert int(stream[47:], 2) == crc15(stream[:47])
    assert len(stream) == stuffable_bits(1, extended=True)


def test_remote_frame_sends_its_dlc_but_no_data() -> None:
    msg = can.Message(arbitration_id=0x701, is_remote_frame=True, dlc=4, is_extended_id=False)
    stream = frame_bitstream(0x701, b"", remote=True, dlc=4)
    assert stream[12] == "1" and stream[15:19] == "0100"
    assert message_bits(msg) == len(stream) + stuff_bit_count(stream) + 13


@given(bitstrings)
def test_stuffing_property(bits: str) -> None:
    stuffed = stuff(bits)
    assert longest_run(stuffed) <= 5
    assert destuff(stuffed) == bits
    assert stuff_bit_count(bits) == len(stuffed) - len(bits)
    if bits:
        assert stuff_bit_count(bits) <= (len(bits) - 1) // 4


@given(
    st.integers(0, 0x7FF),
    st.binary(max_size=8),
    st.booleans(),
    st.integers(0, 0x1FFFFFFF),
)
def test_exact_frame_bits_within_bounds(std_id: int, data: bytes, ext: bool, ext_id: int) -> None:
    ident = ext_id if ext else std_id
    stream = frame_bitstream(ident, data, extended=ext)
    stuffed = stuff(stream)
    assert longest_run(stuffed) <= 5
    assert destuff(stuffed) == stream
    msg = can.Message(arbitration_id=ident, data=data, is_extended_id=ext)
    exact = message_bits(msg)
    assert exact == len(stuffed) + 13
    n = len(data)
    assert frame_bits(n, ext, stuffing="none") <= exact <= frame_bits(n, ext, stuffing="worst")


def test_destuff_rejects_six_equal_bits_and_a_missing_stuff_bit() -> None:
    with pytest.raises(ValueError, match="six equal bits"):
        destuff("0000001")
    with pytest.raises(ValueError, match="stuff bit is due"):
        destuff("11111")


def test_expected_stuffing_matches_random_bits() -> None:
    rng = random.Random(7)
    for n in (0, 4, 8):
        length = stuffable_bits(n)
        trials = 4000
        mean = (
            sum(
                stuff_bit_count("".join(rng.choice("01") for _ in range(length)))
                for _ in range(trials)
            )
            / trials
        )
        assert mean == pytest.approx(expected_stuff_bits(n), rel=0.15)


@pytest.mark.parametrize(
    ("call", "problem"),
    [
        (lambda: frame_bits(9), "0..8"),
        (lambda: frame_bits(-1), "0..8"),
        (lambda: frame_bits(8, stuffing="exact"), "concrete frame"),
        (lambda: frame_bitstream(0x800, b""), "0x800"),
        (lambda: frame_bitstream(0x123, b"\x00", dlc=2), "DLC 2 but 1"),
        (lambda: frame_bitstream(0x20000000, b"", extended=True), "0x20000000"),
        (
            lambda: message_bits(can.Message(arbitration_id=1, is_fd=True, data=bytes(12))),
            "CAN FD",
        ),
        (lambda: BusLoadMeter(0), "bitrate"),
        (lambda: BusLoadMeter(1000, window=0), "window"),
        (lambda: BusLoadMeter(1000, stuffing="bogus"), "stuffing"),
        (lambda: cycle_load([], 100, 1000), "empty"),
        (lambda: cycle_load([FrameShape(8)], 0, 1000), "rate_hz"),
        (lambda: cycle_load([FrameShape(8)], 100, 1000, max_load=1.5), "max_load"),
    ],
)
def test_bad_input_is_named(call, problem: str) -> None:
    with pytest.raises(ValueError, match=problem):
        call()


def test_meter_sliding_window_and_totals() -> None:
    meter = BusLoadMeter(1_000_000, window=1.0)
    for i in range(1000):  # one 8-byte frame per ms for 1 s
        meter.add(
            can.Message(
                timestamp=i * 1e-3, arbitration_id=0x181, data=bytes(8), is_extended_id=False
            )
        )
    assert meter.load() == pytest.approx(1000 * 135 / 1e6)
    report = meter.report()
    assert report.total_frames == 1000 and report.window_frames == 1000
    assert report.total_bits == 135_000
    assert report.mean_load == pytest.approx(135_000 / 1e6 / 0.999)
    assert meter.load(now=1.4995) == pytest.approx(500 * 135 / 1e6)  # half left the window
    assert meter.load(now=5.0) == 0.0
    assert meter.report(now=5.0).total_frames == 1000  # totals stay


def test_the_meter_holds_one_window_of_frames() -> None:
    """Frames are forgotten as they leave the window, not all at the next report: five
    seconds of them evicted at once held the simulator's loop ~9 ms, and the daemon
    braked on stale feedback."""
    meter = BusLoadMeter(1_000_000, window=1.0)
    for i in range(5000):  # one frame per ms for 5 s, no report in between
        meter.add(can.Message(timestamp=i * 1e-3, arbitration_id=0x181, data=bytes(8)))
        assert len(meter._recent) <= 1001
    assert meter.report().total_frames == 5000


def test_meter_counts_error_frames_and_exact_stuffing() -> None:
    meter = BusLoadMeter(500_000, window=0.1, stuffing="exact")
    meter.add(can.Message(timestamp=1.0, arbitration_id=0, is_extended_id=False))
    meter.add(can.Message(timestamp=1.0, is_error_frame=True, arbitration_id=0x88))
    report = meter.report()
    assert report.total_bits == 53 + ERROR_FRAME_BITS
    assert report.total_error_frames == 1
    assert report.load == pytest.approx((53 + ERROR_FRAME_BITS) / (500_000 * 0.1))


def test_cycle_of_eight_cia402_drives_at_1_mbit() -> None:
    """8 drives x (RPDO controlword+torque 4 B, TPDO statusword+position 6 B, TPDO
    velocity 4 B) + SYNC: 2495 bits worst case, 2129 expected; DESIGN §8 says roughly
    400-500 Hz fit at 1 Mbit/s, with a fully loaded bus."""
    cycle = [FrameShape(0)] + [FrameShape(4), FrameShape(6), FrameShape(4)] * 8
    worst = cycle_load(cycle, 400, 1_000_000)
    assert worst.bits_per_cycle == 55 + 8 * (95 + 115 + 95)
    assert worst.fits and worst.max_rate_hz == pytest.approx(1e6 / 2495)
    assert not cycle_load(cycle, 500, 1_000_000).fits
    expected = cycle_load(cycle, 400, 1_000_000, stuffing="expected")
    assert 400 < expected.max_rate_hz < 500
    assert expected.bus_time == pytest.approx(expected.bits_per_cycle / 1e6)
    # leaving 30 % of the bus for compute time and other traffic
    assert cycle_load(cycle, 250, 1_000_000, max_load=0.7).fits
    assert not cycle_load(cycle, 300, 1_000_000, max_load=0.7).fits


def test_cycle_load_takes_concrete_messages() -> None:
    sync = can.Message(arbitration_id=0x80, is_extended_id=False)
    exact = cycle_load([sync], 1000, 1_000_000, stuffing="exact")
    assert exact.bits_per_cycle == message_bits(sync)
    assert exact.load == pytest.approx(message_bits(sync) * 1000 / 1e6)
