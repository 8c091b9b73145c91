"""Benchmark of the simulator's bus infrastructure; prints one JSON object:

- `loopbus_send_drain_8`: 8 LoopBus.send calls and one drain() on the receiving bus
  (median/p99 µs); `virtual_send_recv_8`: the same through python-can's virtual bus
  (deep copy per send, 8 recv calls), for comparison;
- `exact_message_bits`: busload.message_bits of an 8-byte frame with exact stuffing;
- `socketcand_client_to_bus`: python-can's socketcand client send() until a LoopBus on
  the served channel has the frame (server loop in a second thread of this process);
  `..._tcp_tune` the same with the client's tcp_tune (TCP_NODELAY);
- `socketcand_bus_to_client`: LoopBus send until the client's recv() returns it;
- `socketcand_round_trip_other_process`: client send -> server and answering device in
  another process (tests/socketcand_peer.py) -> client recv;
- `cycle_load_1mbit`: bits per cycle and the highest cycle rate on a fully loaded
  1 Mbit/s bus for 8 CiA 402 drives and for 8 ODrive axes (no timing involved).

    python bench/bus.py [--frames N]
"""

from __future__ import annotations

import argparse
import asyncio
import gc
import json
import os
import select
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path

import can
import numpy as np
from timing import per_call_us, summary_us

from sim_bus.bus.busload import FrameShape, cycle_load, message_bits
from sim_bus.bus.loopbus import LoopBus
from sim_bus.bus.socketcand import SocketcandServer

ROOT = Path(__file__).resolve().parent.parent


def eight_frames() -> list[can.Message]:
    return [
        can.Message(arbitration_id=0x200 + n, data=bytes([n, 0, 0, 0]), is_extended_id=False)
        for n in range(1, 9)
    ]


def loopbus_send_drain(calls: int) -> dict[str, float]:
    frames = eight_frames()
    with LoopBus("bench") as host, LoopBus("bench") as sim:

        def cycle(_: int) -> None:
            for m in frames:
                host.send(m)
            assert len(sim.drain()) == 8

        return per_call_us(cycle, calls)


def virtual_send_recv(calls: int) -> dict[str, float]:
    frames = eight_frames()
    host = can.Bus(interface="virtual", channel="bench", ignore_config=True)
    sim = can.Bus(interface="virtual", channel="bench", ignore_config=True)
    try:

        def cycle(_: int) -> None:
            for m in frames:
                host.send(m)
            for _ in frames:
                sim.recv(0)

        return per_call_us(cycle, calls)
    finally:
        host.shutdown()
        sim.shutdown()


def latency(
    send: Callable[[can.Message], None], recv: Callable[[], can.Message | None], n: int
) -> dict[str, float]:
    """Per-frame time from send() to recv() returning it, one frame in flight."""
    samples = np.empty(n)
    clock = time.perf_counter_ns
    for i in range(n + 100):
        msg = can.Message(arbitration_id=0x300, data=i.to_bytes(4, "little"), is_extended_id=False)
        t0 = clock()
        send(msg)
        got = recv()
        t1 = clock()
        if got is None or int.from_bytes(got.data, "little") != i:
            raise RuntimeError(f"frame {i} lost or out of order: {got}")
        if i >= 100:  # warm-up excluded
            samples[i - 100] = t1 - t0
    return summary_us(samples)


def socketcand_in_process(n: int) -> dict[str, dict[str, float]]:
    loop = asyncio.new_event_loop()
    thread = threading.Thread(target=loop.run_forever, daemon=True)
    thread.start()
    results = {}
    with LoopBus("bench_sc") as served, LoopBus("bench_sc") as device:
        server = SocketcandServer(served)
        asyncio.run_coroutine_threadsafe(server.start(), loop).result(10)
        try:
            for name, kwargs in [("", {}), ("_tcp_tune", {"tcp_tune": True})]:
                client = can.Bus(
                    interface="socketcand",
                    host="127.0.0.1",
                    port=server.port,
                    channel="vcan0",
                    **kwargs,
                )
                try:
                    results["socketcand_client_to_bus" + name] = latency(
                        client.send, lambda: device.recv(5), n
                    )
                    if not name:
                        results["socketcand_bus_to_client"] = latency(
                            device.send, lambda c=client: c.recv(5), n
                        )
                finally:
                    client.shutdown()
        finally:
            asyncio.run_coroutine_threadsafe(server.stop(), loop).result(10)
            loop.call_soon_threadsafe(loop.stop)
            thread.join(10)
            loop.close()
    return results


def socketcand_other_process(n: int) -> dict[str, float]:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    peer = subprocess.Popen(
        [sys.executable, str(ROOT / "tests" / "socketcand_peer.py"), "--lifetime", "300"],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        env=env,
    )
    try:
        if not select.select([peer.stdout], [], [], 30)[0]:
            raise RuntimeError("socketcand peer printed no port")
        port = int(peer.stdout.readline().split()[1])
        client = can.Bus(interface="socketcand", host="127.0.0.1", port=port, channel="vcan0")
        try:
            return latency(client.send, lambda: client.recv(5), n)
        finally:
            client.shutdown()
    finally:
        peer.stdin.close()
        try:
            peer.wait(10)
        except subprocess.TimeoutExpired:
            peer.kill()
            peer.wait(10)


def cycle_loads() -> dict[str, dict[str, float]]:
    """8 CiA 402 drives: SYNC + per drive RPDO (controlword, torque: 4 B) and TPDOs
    (statusword + position 6 B, velocity 4 B); 8 ODrive axes: Set_Input_Torque (8 B, as
    ODrive's DBC) + Get_Encoder_Estimates (8 B) per axis."""
    cycles = {
        "cia402_8_drives": [FrameShape(0)] + [FrameShape(4), FrameShape(6), FrameShape(4)] * 8,
        "odrive_8_axes": [FrameShape(8), FrameShape(8)] * 8,
    }
    out = {}
    for name, frames in cycles.items():
        for stuffing in ("none", "expected", "worst"):
            load = cycle_load(frames, 1.0, 1_000_000, stuffing=stuffing)
            out[f"{name}_{stuffing}"] = {
                "bits_per_cycle": round(load.bits_per_cycle, 1),
                "max_rate_hz": round(load.max_rate_hz, 1),
            }
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=3000, help="frames per latency figure")
    args = parser.parse_args()
    sample = can.Message(arbitration_id=0x181, data=bytes(range(8)), is_extended_id=False)
    results: dict[str, object] = {
        "loopbus_send_drain_8": loopbus_send_drain(20_000),
        "virtual_send_recv_8": virtual_send_recv(20_000),
        "exact_message_bits": per_call_us(lambda _: message_bits(sample), 20_000),
    }
    gc.disable()
    try:
        results.update(socketcand_in_process(args.frames))
        results["socketcand_round_trip_other_process"] = socketcand_other_process(args.frames)
    finally:
        gc.enable()
    results["cycle_load_1mbit"] = cycle_loads()
    print(json.dumps(results, indent=1))


if __name__ == "__main__":
    main()
