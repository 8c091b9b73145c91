"""Benchmark of frame I/O on a real SocketCAN vcan0: python-can's own send/recv against
the raw non-blocking socket of drivers.bus.SocketcanIO.  Prints one JSON object with
per-frame microseconds (median and p99 over rounds of 8 frames, a cycle's worth):
`send_python_can`, `send_raw`, `drain_python_can`, `drain_raw`.

Where the kernel has no vcan0 (this project's CI), run it inside user-mode Linux:

    python tests/vcan/uml.py -- python bench/socketcan_io.py [--rounds N]
"""

from __future__ import annotations

import argparse
import json
import sys
import time

import can
import numpy as np

from drivers.bus import FrameIO, SocketcanIO

FRAMES = 8


def _rounds(send, drain, rounds: int) -> tuple[list[float], list[float]]:
    """Per-frame send and drain times (s) of `rounds` rounds of FRAMES frames."""
    frame = can.Message(arbitration_id=0x201, data=bytes(5), is_extended_id=False)
    sends, drains = [], []
    for _ in range(rounds):
        started = time.perf_counter()
        for _ in range(FRAMES):
            send(frame)
        sent = time.perf_counter()
        got = drain()
        done = time.perf_counter()
        if len(got) != FRAMES:
            raise SystemExit(f"drained {len(got)} frames, sent {FRAMES}")
        sends.append((sent - started) / FRAMES)
        drains.append((done - sent) / FRAMES)
    return sends, drains


def _summary(values: list[float]) -> dict[str, float]:
    median, p99 = np.percentile(values, [50, 99]) * 1e6
    return {"median_us": round(float(median), 2), "p99_us": round(float(p99), 2)}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--channel", default="vcan0")
    parser.add_argument("--rounds", type=int, default=2000)
    args = parser.parse_args()
    try:
        sender = can.Bus(interface="socketcan", channel=args.channel)
        receiver = can.Bus(interface="socketcan", channel=args.channel)
    except (OSError, can.CanError) as exc:
        print(f"no SocketCAN {args.channel} here ({exc}); see the docstring", file=sys.stderr)
        return 2
    try:
        plain_tx, plain_rx = FrameIO(sender), FrameIO(receiver)
        send_pc, drain_pc = _rounds(plain_tx.send, plain_rx.drain, args.rounds)
        raw_tx, raw_rx = SocketcanIO(sender), SocketcanIO(receiver)
        send_raw, drain_raw = _rounds(raw_tx.send, raw_rx.drain, args.rounds)
    finally:
        sender.shutdown()
        receiver.shutdown()
    print(
        json.dumps(
            {
                "send_python_can": _summary(send_pc),
                "send_raw": _summary(send_raw),
                "drain_python_can": _summary(drain_pc),
                "drain_raw": _summary(drain_raw),
            }
        )
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
