"""A flood on a real SocketCAN ``vcan0`` of frames on ids no driver reads:
the daemon's bus port installs the kernel's receive filter for the drivers'
ids, so the kernel drops the flood before the daemon reads a single frame of it, and
the frames it does read reach it in batches of at most FRAMES_PER_PASS."""

from __future__ import annotations

import asyncio
import subprocess

import can
import pytest

from daemon.service.bus_port import BusPort
from drivers.bus import FRAMES_PER_PASS

pytestmark = [pytest.mark.vcan, pytest.mark.timeout(120), pytest.mark.slow]

CHANNEL = "vcan0"
FLOOD = 20_000
WANTED = {0x181, 0x701}  # a TPDO1 and a heartbeat of node 1


def test_the_kernel_drops_a_flood_on_other_ids_before_the_port_reads_it() -> None:
    async def scenario() -> tuple[list[list[int]], int]:
        loop = asyncio.get_running_loop()
        batches: list[list[int]] = []
        with (
            can.Bus(interface="socketcan", channel=CHANNEL) as sender,
            can.Bus(interface="socketcan", channel=CHANNEL) as bus,
        ):
            port = BusPort(
                bus, lambda frames, now: batches.append([m.arbitration_id for m in frames]), WANTED
            )
            port.open(loop)
            # cangen: -g 0 back to back, ids 0x6E0 on (SDO requests to nodes no drive has)
            flood = ["cangen", CHANNEL, "-g", "0", "-n", str(FLOOD), "-I", "6E0", "-L", "8"]
            done = await asyncio.to_thread(subprocess.run, flood, check=True, timeout=60)
            assert done.returncode == 0
            for k in range(300):
                sender.send(can.Message(arbitration_id=0x181, is_extended_id=False, data=bytes(8)))
                if k % 50 == 0:  # a stranger now and then, and time to read (a socket's
                    sender.send(can.Message(arbitration_id=0x6E1, is_extended_id=False))
                    await asyncio.sleep(0.005)  # queue holds a few hundred frames)
            sender.send(can.Message(arbitration_id=0x701, is_extended_id=False, data=b"\x05"))
            for _ in range(500):
                if sum(map(len, batches)) >= 301:
                    break
                await asyncio.sleep(0.01)
            port.close()
            return batches, port.ignored

    batches, ignored = asyncio.run(scenario())
    received = [ident for batch in batches for ident in batch]
    assert received == [0x181] * 300 + [0x701]
    assert ignored == 0  # the kernel dropped the rest: the port never read a frame of it
    assert max(map(len, batches)) <= FRAMES_PER_PASS
