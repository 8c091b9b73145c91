"""The daemon and the simulator as separate processes with eight CiA 402 drives on two
real SocketCAN buses, ``vcan0`` and ``vcan1``: each process opens both,
the daemon sends one SYNC per bus, each drive's frames travel on its bus only, a frame
for a node of ``vcan0`` forged on ``vcan1`` is not that drive's, and the simulator
reports the load of each bus.  Settings for the UML guest as in test_vcan_end_to_end."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
import uml
from test_vcan_end_to_end import (
    CIA402,
    _cansend,
    _check_flight,
    _dropped,
    _fly_trajectory,
    _frames,
    _stop,
    running_stack,
)

from drivers.cia402 import codec as cia402

pytestmark = [
    pytest.mark.vcan,
    pytest.mark.timeout(240),
    pytest.mark.slow,
    pytest.mark.host_timing,
]

# node 3 is on both buses: cable 2 on vcan0, cable 4 on vcan1
NODES = [1, 2, 3, 4, 3, 5, 6, 7]
# node 1's TPDO1 and RPDO1 (it is on vcan0) forged on vcan1, its length 1 m off
FORGED = (f"181#3712{(10**7).to_bytes(4, 'little').hex()}0A", "281#00000000")
ON = ["vcan0"] * 4 + ["vcan1"] * 4


def _two_buses(data: dict) -> None:
    data["can"] = [
        {"interface": "socketcan", "channel": channel, "bitrate": 1_000_000}
        for channel in ("vcan0", "vcan1")
    ]
    data["drives"].update(nodes=NODES, bus=ON)


def _node_frames(frames: list[tuple[float, int, bytes | None]]) -> list[tuple[int, bytes | None]]:
    """(id, data) of the node-addressed CiA 402 frames (all but NMT and SYNC)."""
    return [(i, data) for _, i, data in frames if cia402.SYNC_ID < i <= 0x7FF]


def _nodes_heard(frames: list[tuple[float, int, bytes | None]]) -> set[int]:
    """Node ids of the node-addressed CiA 402 frames."""
    return {can_id & 0x7F for can_id, _ in _node_frames(frames)}


def test_cia402_drives_on_vcan0_and_vcan1(tmp_path: Path) -> None:
    problem = uml.native_vcan_reason("vcan1")
    assert problem is None, problem  # the guest has vcan1; a host with vcan0 can add it
    try:
        with running_stack(
            CIA402, tmp_path, _two_buses, ("vcan0", "vcan1"), ("--report-every", "1")
        ) as stack:
            done = _fly_trajectory(stack)
            _check_flight(stack, done)
            before = stack.watch.wait_settled(15)
            for _ in range(10):  # node 1 (cable 0, on vcan0) forged on vcan1, 1 m off
                _cansend(*FORGED, channel="vcan1")
            after = stack.watch.wait_state(lambda s: True, 5, "a state after the forgery")
            assert after["state"] == "hold" and after["fault"] is None, (
                f"after the forged frames: {after['state']}, fault {after['fault']}"
            )
            assert abs(after["lengths"][0] - before["lengths"][0]) < 0.002
            assert _stop(stack.daemon) == 0
            assert _stop(stack.simulator) == 0
    except BaseException:
        for log in sorted((tmp_path / "logs").glob("*.log")):
            print(f"----- {log.name} -----\n{log.read_text()[-4000:]}")
        raise
    vcan0, vcan1 = _frames(stack.capture, "vcan0"), _frames(stack.capture, "vcan1")
    for name, frames in (("vcan0", vcan0), ("vcan1", vcan1)):
        syncs = sum(can_id == cia402.SYNC_ID and data == b"" for _, can_id, data in frames)
        assert syncs > 300, f"{syncs} SYNCs on {name}"
    # 127: the host's heartbeat, which the drives consume (0x1016), on each bus
    assert _nodes_heard(vcan0) == {1, 2, 3, 4, 127}
    assert _nodes_heard(vcan1) - {1} == {3, 5, 6, 7, 127}
    # node 1's own frames never on vcan1: what candump saw of it there is the forgeries
    # (cansend succeeded, so they were on the bus; all seen unless candump dropped frames)
    forged = {(int(i, 16), bytes.fromhex(d)) for i, d in (f.split("#") for f in FORGED)}
    node1 = {(i, d) for i, d in _node_frames(vcan1) if i & 0x7F == 1}
    assert node1 <= forged, node1 - forged
    assert node1 == forged or _dropped(stack.capture) > 0, "the forged frames not captured"
    sim_log = (tmp_path / "logs" / "sim.log").read_text()
    for name in ("vcan0", "vcan1"):
        assert re.search(rf"bus load \d+\.\d% .* on bus {name}", sim_log), sim_log[-2000:]
