"""Drives spread over several CAN buses: the `can:` list and each drive's
`drives.bus` in the config, and the daemon with the simulator on two in-process buses:
one SYNC per bus, each drive's frames on its bus only, frames routed by the bus they came
on (a frame for a node on the other bus is not that drive's)."""

from __future__ import annotations

import asyncio
import time

import can
import numpy as np
import pytest
import yaml

from cdpr import ConfigError, Pose
from daemon.config import DaemonConfig, load_config
from daemon.service.safety import SafetyState, Trigger
from drivers.base import FrameError
from drivers.cia402 import codec as cia402
from drivers.factory import make_driver
from drivers.multibus import MultiBusDriver
from sim_bus.bus import loopbus
from sim_bus.bus.loopbus import LoopBus
from sim_bus.config import load_sim_setup
from tests.daemon_stack import DRIVER_CONFIGS, Stack

pytestmark = pytest.mark.timeout(60)

LOOP = {"interface": "cdprd_loop"}
# node 3 is on both buses (cable 2 on left, cable 4 on right): allowed, distinct per bus
NODES = [1, 2, 3, 4, 3, 5, 6, 7]
ON = ["left"] * 4 + ["right"] * 4


def two_bus_config(protocol: str = "cia402", **drives: object) -> DaemonConfig:
    def edit(data: dict) -> None:
        data["can"] = [{**LOOP, "channel": "left"}, {**LOOP, "channel": "right"}]
        data["drives"].update({"nodes": NODES, "bus": ON, **drives})

    return load_config(DRIVER_CONFIGS[protocol], edit)


def with_can(can: object, **drives: object) -> DaemonConfig:
    """The CiA 402 example with `can:` replaced and `drives:` keys updated."""

    def edit(data: dict) -> None:
        data["can"] = can
        data["drives"].update(drives)

    return load_config(DRIVER_CONFIGS["cia402"], edit)


# -- config ------------------------------------------------------------------------------


def test_a_can_list_puts_each_drive_on_its_named_bus() -> None:
    config = two_bus_config()
    assert [bus.bus_name for bus in config.buses] == ["left", "right"]
    assert config.drives.bus_names() == ON
    named = with_can(
        [{**LOOP, "channel": "vcan0", "name": "a"}, {**LOOP, "channel": "vcan1", "name": "b"}],
        nodes=[1, 1, 2, 2, 3, 3, 4, 4],
        bus=["a", "b"] * 4,
    )
    assert [(b.bus_name, b.channel) for b in named.buses] == [("a", "vcan0"), ("b", "vcan1")]
    driver = make_driver(named.drives, named.robot)
    assert isinstance(driver, MultiBusDriver) and driver.bus_names == ["a", "b"]
    assert [part.cables for part in driver.parts] == [[0, 2, 4, 6], [1, 3, 5, 7]]


def test_one_can_mapping_keeps_every_drive_on_it() -> None:
    config = load_config(DRIVER_CONFIGS["cia402"])
    (bus,) = config.buses
    assert (bus.bus_name, bus.interface) == ("cdprd-sim", "cdprd_loop")
    assert config.drives.bus_names() == [None] * 8
    assert not isinstance(make_driver(config.drives, config.robot), MultiBusDriver)
    named = with_can({**LOOP, "channel": "c0", "name": "main"}, bus="main")
    assert named.buses[0].bus_name == "main"


@pytest.mark.parametrize(
    ("can", "drives", "error"),
    [
        (
            [{"channel": "can0"}, {"channel": "can1"}],
            {"bus": ["can0"] * 4 + ["can2"] * 4},
            "drives.bus: cable 4's drive (node 5) is on bus 'can2', which can: does not list",
        ),
        (
            [{"channel": "can0"}, {"channel": "can1"}],
            {"bus": "can0"},
            "can.1: no drive is on bus 'can1' (drives.bus)",
        ),
        (
            [{"channel": "can0"}, {"channel": "can0"}],
            {"bus": "can0"},
            "can.1.channel: socketcan channel 'can0' is also can.0's",
        ),
        (
            [{"channel": "can0"}, {"channel": "can1", "name": "can0"}],
            {"bus": "can0"},
            "can.1.name: bus name 'can0' is also can.0's",
        ),
        (
            [{"channel": "can0"}, {"channel": "can1"}],
            {"bus": ["can0"] * 4 + ["can1"] * 4, "nodes": [1, 2, 3, 4, 5, 6, 6, 7]},
            "drives: node id 6 is on bus 'can1' twice",
        ),
        (
            [{"channel": "can0"}, {"channel": "can1"}],
            {},
            "drives.bus: required with several buses in can:",
        ),
        (
            [{"channel": "can0"}, {"channel": "can1"}],
            {"bus": ["can0"] * 7},
            "drives: bus has 7 entries for 8 nodes",
        ),
        ({"channel": "can0"}, {"bus": "can1"}, "drives.bus: cable 0's drive (node 1) is on bus"),
        ([], {}, "can: List should have at least 1 item"),
        ([{"channel": "can0", "bitrate": "fast"}], {}, "can.0.bitrate: Input should be"),
        ({"channel": "can0", "bogus": 1}, {}, "can.bogus: Extra inputs are not permitted"),
    ],
)
def test_bad_bus_layouts_are_named(can: object, drives: dict, error: str) -> None:
    with pytest.raises(ConfigError) as caught:
        with_can(can, **drives)
    assert f"reference8-cia402.yaml: {error}" in str(caught.value)


def test_the_simulator_reads_the_same_buses(tmp_path) -> None:
    data = yaml.safe_load(DRIVER_CONFIGS["cia402"].read_text())
    data["robot"] = str(DRIVER_CONFIGS["cia402"].parent / data["robot"])
    data["can"] = [{**LOOP, "channel": "left"}, {**LOOP, "channel": "right"}]
    data["drives"].update(nodes=NODES, bus=ON)
    path = tmp_path / "two.yaml"
    path.write_text(yaml.safe_dump(data))
    setup = load_sim_setup(path)
    assert [bus.bus_name for bus in setup.buses] == ["left", "right"]
    data["drives"].update(nodes=list(range(1, 9)), bus="left")
    path.write_text(yaml.safe_dump(data))
    with pytest.raises(ConfigError, match=r"two\.yaml: can\.1: no drive is on bus 'right'"):
        load_sim_setup(path)


# -- the driver: frames by bus ------------------------------------------------------------


def test_a_frame_is_its_drives_only_on_the_bus_it_came_on() -> None:
    """Node 3 is cable 2 on left and cable 4 on right; node 1 only on left."""
    config = two_bus_config()
    driver = make_driver(config.drives, config.robot)
    syncs = driver.cycle_start()
    # one SYNC per bus, and the host's heartbeat (each drive consumes it, 0x1016) on each
    host = cia402.HEARTBEAT_BASE + config.drives.profile.host_node
    assert [(m.arbitration_id, m.channel) for m in syncs] == [
        (0x080, "left"),
        (host, "left"),
        (0x080, "right"),
        (host, "right"),
    ]

    def sample(node: int, bus: str | None, position: int) -> int | None:
        tpdo1 = cia402.encode_tpdo1(node, 0x0237, position, 10)
        tpdo2 = cia402.encode_tpdo2(node, 0)
        tpdo1.channel = tpdo2.channel = bus
        now = time.monotonic()  # received after the SYNCs went out
        driver.receive(tpdo1, now)
        return driver.receive(tpdo2, now)

    assert sample(3, "left", 1000) == 2
    assert sample(3, "right", 2000) == 4
    assert driver.feedback[2].length != driver.feedback[4].length
    assert sample(1, "right", 3000) is None  # node 1 is not on right
    assert sample(1, None, 3000) is None  # nor a frame of no bus
    assert driver.feedback[0].count == 0
    assert sample(1, "left", 3000) == 0
    commands = driver.commands([float(i) for i in range(8)])
    on = {(m.channel, m.arbitration_id) for m in commands}
    assert on == {("left", 0x200 + n) for n in (1, 2, 3, 4)} | {
        ("right", 0x200 + n) for n in (3, 5, 6, 7)
    }
    with pytest.raises(FrameError, match=r"cable 5 \(node 5 on bus right\)"):
        driver.commands([0.0] * 5 + [float("nan")] + [0.0] * 2)


# -- the daemon and the simulator on two buses --------------------------------------------


class Spy:
    """Every frame on one loop bus, read by a bus of its own (the daemon and the
    simulator are the others); `send` puts a frame on that bus as a third node would."""

    def __init__(self, channel: str) -> None:
        self.bus = LoopBus(channel=channel, rx_queue_size=1 << 16)
        self.frames: list[can.Message] = []

    def read(self) -> None:
        self.frames.extend(self.bus.drain())

    def send(self, msg: can.Message) -> None:
        self.bus.send(msg)


def spy_on(stack: Stack) -> dict[str, Spy]:
    """A spy on each of the stack's buses, by bus name."""
    return {name: Spy(bus.channel) for name, bus in stack.sim.daemon_bus.items()}


async def read_spies(spies: dict[str, Spy], seconds: float) -> None:
    """Let the stack run `seconds`, every spy reading its bus every 5 ms."""
    for _ in range(int(seconds / 0.005)):
        for spy in spies.values():
            spy.read()
        await asyncio.sleep(0.005)


async def goto_reading(stack: Stack, spies: dict[str, Spy], offset: list[float]) -> float:
    """Goto `offset` (m) from home, the spies reading until the robot holds again and
    0.3 s longer (at most 10 s): how far (mm) the platform ended from the target."""
    home, service = stack.service.config.robot.home, stack.service
    target = Pose(home.position + np.array(offset), home.quaternion)
    reply = await stack.planner.command("goto", {"pose": target})
    assert reply["accepted"], reply
    for _ in range(200):
        if service.now() >= reply["end"] and service.machine.state is not SafetyState.TRACKING:
            break
        await read_spies(spies, 0.05)
    await read_spies(spies, 0.3)
    assert service.machine.state is SafetyState.HOLD, service.machine.fault
    return float(np.linalg.norm(stack.plant.pose.position - target.position) * 1e3)


def _nodes_heard(frames: list[can.Message]) -> set[int]:
    """The node ids of the node-addressed CiA 402 frames (all but NMT and SYNC)."""
    return {m.arbitration_id & 0x7F for m in frames if m.arbitration_id > cia402.SYNC_ID}


def test_eight_drives_on_two_buses_enable_hold_and_move() -> None:
    async def scenario() -> None:
        config = two_bus_config()
        async with Stack(config) as stack:
            service = stack.service
            spies = spy_on(stack)
            try:
                assert service.machine.state is SafetyState.IDLE
                await stack.enable()
                cycles = service.stats.cycles
                await read_spies(spies, 0.3)
                error_mm = await goto_reading(stack, spies, [0.03, -0.02, 0.04])
                assert error_mm < 1.0, f"{error_mm:.3f} mm from the goto target"
                cycles = service.stats.cycles - cycles
                for name, spy in spies.items():
                    syncs = sum(m.arbitration_id == cia402.SYNC_ID for m in spy.frames)
                    assert syncs >= cycles // 2, f"{syncs} SYNCs on {name} in {cycles} cycles"
                # the drives of each bus, and the host's own heartbeat (node 127) on both
                assert _nodes_heard(spies["left"].frames) == {1, 2, 3, 4, 127}
                assert _nodes_heard(spies["right"].frames) == {3, 5, 6, 7, 127}

                # node 1 (cable 0, on left) forged on right, far from its true length
                right = service.port.ports["right"]
                ignored, counts = right.ignored, [fb.count for fb in service.driver.feedback]
                length = service.driver.feedback[0].length
                for _ in range(20):
                    spies["right"].send(cia402.encode_tpdo1(1, 0x0237, 10**6, 10))
                    spies["right"].send(cia402.encode_tpdo2(1, 0))
                    await read_spies(spies, 0.01)
                assert right.ignored - ignored == 40  # read on right, no drive's there
                fresh = [
                    fb.count - c for fb, c in zip(service.driver.feedback, counts, strict=True)
                ]
                assert min(fresh) > 0  # every drive on both buses still answers
                assert abs(service.driver.feedback[0].length - length) < 1e-3
                assert service.machine.state is SafetyState.HOLD, service.machine.fault
            finally:
                for spy in spies.values():
                    spy.bus.shutdown()

    asyncio.run(asyncio.wait_for(scenario(), 45))


def test_losing_one_of_two_buses_brakes_naming_it() -> None:
    async def scenario() -> None:
        async with Stack(two_bus_config()) as stack:
            service = stack.service
            await stack.enable()
            loopbus.set_link(stack.sim.daemon_bus["right"].channel, up=False)
            await stack.until(lambda: service.machine.state is SafetyState.BRAKED, 2.0)
            fault = service.machine.fault
            assert fault.trigger is Trigger.BUS_LOST, fault
            assert "bus right: " in fault.message and "network is down" in fault.message
            assert service.port.lost.startswith("bus right: ")
            positions, lowest = await stack.watch(0.3)  # left holds; right's watchdogs
            drift_mm = np.linalg.norm(positions - positions[0], axis=1).max() * 1e3
            assert drift_mm < 2.0 and lowest > 0.0

    asyncio.run(asyncio.wait_for(scenario(), 45))
