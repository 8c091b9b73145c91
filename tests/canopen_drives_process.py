"""A separate process for tests/daemon/test_canopen_drives.py: the eight canopen drives
of tests/canopen_drive.py on the plant (tests/canopen_robot.py) for a daemon config's
`drives:` and `sim:`, on a LoopBus served over socketcand on 127.0.0.1 (a free port,
printed as "PORT <n>").  A line "status" on stdin prints one JSON line: per drive its
statusword, mode display, target position, position actual, the torque commands it
received, its consumer heartbeat 0x1016:01 and when (monotonic) that expired; a line
"truth SINCE" prints the true platform positions sampled at monotonic time >= SINCE as
one JSON line of [t, x, y, z] rows; a line "delays" prints the seconds from the latest
SYNC to each command the drives received as one JSON list.  Exits when stdin closes or
after --lifetime seconds.

    python -m tests.canopen_drives_process --config FILE [--lifetime 120]
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import os
import sys

import canopen

from daemon.config import load_config
from sim_bus.bus.loopbus import LoopBus
from sim_bus.bus.socketcand import SocketcandServer
from tests.canopen_robot import CanopenRobot


async def serve(config_path: str, lifetime: float) -> None:
    loop = asyncio.get_running_loop()
    config = load_config(config_path)
    channel = f"canopen-drives-{os.getpid()}"
    network = canopen.Network()
    network.connect(interface="cdprd_loop", channel=channel)
    robot = CanopenRobot(config, network)
    drives = robot.drives
    done = asyncio.Event()
    lines = bytearray()

    def status() -> str:
        return json.dumps(
            [
                {
                    "statusword": d.value(0x6041),
                    "mode": d.value(0x6061),
                    "target": d.value(0x607A),
                    "position": d.value(0x6064),
                    "torques": d.torques[-100:],
                    "consumer": d.value(0x1016, 1),
                    "lost": d.lost,
                }
                for d in drives
            ]
        )

    def stdin_readable() -> None:
        data = os.read(sys.stdin.fileno(), 4096)
        if not data:
            done.set()
        lines.extend(data)
        while b"\n" in lines:
            line, _, rest = bytes(lines).partition(b"\n")
            lines[:] = rest
            command, *args = line.split() or [b""]
            if command == b"status":
                print(status(), flush=True)
            elif command == b"truth":
                print(json.dumps(robot.truth(float(args[0])).tolist()), flush=True)
            elif command == b"delays":
                print(json.dumps(robot.command_delays().tolist()), flush=True)

    with LoopBus(channel) as served:
        loop.add_reader(sys.stdin.fileno(), stdin_readable)
        robot.start()
        async with SocketcandServer(served) as server:
            print(f"PORT {server.port}", flush=True)
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(done.wait(), lifetime)
        robot.close()
        loop.remove_reader(sys.stdin.fileno())
    network.disconnect()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--config", required=True)
    parser.add_argument("--lifetime", type=float, default=120.0)
    args = parser.parse_args()
    asyncio.run(serve(args.config, args.lifetime))


if __name__ == "__main__":
    main()
