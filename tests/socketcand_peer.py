"""A separate process for tests/sim_bus/test_socketcand.py and bench/bus.py: a LoopBus served by a
SocketcandServer on 127.0.0.1 (a free port, printed as "PORT <n>"), with a device on the
same bus that answers every frame with id + 1 and the same data.  Exits when its stdin
closes or after --lifetime seconds, whichever comes first.

    python tests/socketcand_peer.py [--lifetime 60]
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import os
import sys

import can

from sim_bus.bus.loopbus import LoopBus
from sim_bus.bus.socketcand import SocketcandServer


async def serve(lifetime: float) -> None:
    loop = asyncio.get_running_loop()
    done = asyncio.Event()
    with LoopBus("peer") as served, LoopBus("peer") as device:

        def answer() -> None:
            for m in device.drain():
                device.send(
                    can.Message(
                        arbitration_id=m.arbitration_id + 1,
                        is_extended_id=m.is_extended_id,
                        data=m.data,
                    )
                )

        def stdin_readable() -> None:
            if not os.read(sys.stdin.fileno(), 4096):
                done.set()

        loop.add_reader(device.fileno(), answer)
        loop.add_reader(sys.stdin.fileno(), stdin_readable)
        async with SocketcandServer(served) as server:
            print(f"PORT {server.port}", flush=True)
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(done.wait(), lifetime)
        loop.remove_reader(sys.stdin.fileno())
        loop.remove_reader(device.fileno())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--lifetime", type=float, default=60.0)
    asyncio.run(serve(parser.parse_args().lifetime))


if __name__ == "__main__":
    main()
