"""Physics for the canopen drives of tests/canopen_drive.py: the project's plant, stepped
in real time by a thread, under eight CanopenDrives.  canopen still does all
the protocol (SDO, PDO, NMT, heartbeat); `CanopenActuator` is only each drive's power
stage and encoder, coupled to its winch by sim_bus.virtual_robot.VirtualRobot as the
project's own virtual drives are: OPERATION ENABLED in mode 10 pulls with the target
torque 0x6071 (per mille of the rated torque), in mode 8 the drive's position loop
(PositionServo) holds 0x607A; in any other state (QUICK STOP ACTIVE, or before and after
operation) it holds the length it had when it got there, from power-on (no holding
brake: the power-on hold of the project's strict simulated drive, sim_bus/devices).
After every plant step the drum's position and velocity go into 0x6064 / 0x606C (the
devices' Scaling), so the TPDOs canopen sends on SYNC carry the real motion (those of
the moment the SYNC was sent), and each drive's consumer heartbeat is checked.  An RPDO
acts from its arrival, whole: the plant is brought up to that moment under the old
command, then the frame's objects are written together (a plant step never sees the
new mode with the old target), as a drive's power stage takes a command when it
arrives, not at the simulation thread's next wake-up.  `command_delays()`: how long after
the latest SYNC (the moment its readings are of) each command arrived."""

from __future__ import annotations

import math
import threading
import time
from collections import deque
from collections.abc import Iterator
from contextlib import contextmanager

import can
import canopen
import numpy as np

from daemon.cli.simulated import sim_section
from daemon.config import DaemonConfig
from drivers.base import Actuation, Scaling, VirtualDrive
from drivers.config import DrivesConfig
from sim_bus.virtual_robot import VirtualRobot
from tests.canopen_drive import ENABLED, CanopenDrive

TRUTH_PERIOD = 0.01  # s between two samples of the true platform position
HISTORY = 200  # plant steps of encoder readings kept, to answer a SYNC seen late


class CanopenActuator(VirtualDrive):
    """The power stage and encoder of one CanopenDrive (module docstring)."""

    def __init__(self, drive: CanopenDrive, scaling: Scaling) -> None:
        super().__init__(drive.node.id, scaling)
        self.drive = drive
        self.brake_engaged = False  # no holding brake: the drive holds (power-on hold)
        self.actuation = Actuation.POSITION
        self.latched = True  # holding the length it latched (here: the first measured)
        self.readings: deque[tuple[int, int]] = deque(maxlen=HISTORY)  # one per plant step
        drive.node.add_read_callback(self._torque_actual)

    def _torque_actual(self, index: int, subindex: int, od: object) -> int | None:
        """Torque actual 0x6077 when read (by SDO or into a TPDO): what the power stage
        produces, as its current sensing says.  Worked out on reading rather than after
        every plant step: eight drives' stores at the plant's rate held the lock and the
        GIL long enough to make canopen's answers to SYNC miss the cycle's deadline."""
        if index != 0x6077:
            return None  # the object's stored value
        rated = self.drive.value(0x6076)
        permille = self.scaling.motor_torque(self.produced, self.length) * 1e6 / rated
        return max(-0x8000, min(0x7FFF, round(permille)))

    def measure(self, length: float, rate: float) -> None:
        super().measure(length, rate)
        if self.latched and math.isnan(self.target_length):
            self.target_length = length
        reading = round(self.scaling.position(length)), round(self.scaling.velocity(rate))
        self.readings.append(reading)
        self.report(0)

    def report(self, steps_ago: int) -> None:
        """0x6064 / 0x606C as the encoder read them `steps_ago` plant steps ago (at most
        HISTORY - 1)."""
        position, velocity = self.readings[-1 - min(steps_ago, len(self.readings) - 1)]
        self.drive.store(0x6064, "<i", position)
        self.drive.store(0x606C, "<i", velocity)

    def on_frame(self, message: can.Message, now: float) -> list[can.Message]:
        return []  # canopen hears and answers the bus

    def on_tick(self, now: float) -> list[can.Message]:
        """After a plant step: the consumer heartbeat, then what the power stage does."""
        drive = self.drive
        drive.check_heartbeat(time.monotonic())
        statusword, mode = drive.value(0x6041), drive.value(0x6061)
        if statusword == ENABLED and mode == 10:
            torque = drive.value(0x6071) * drive.value(0x6076) / 1e6  # N·m
            self.actuation, self.force = Actuation.TORQUE, self.scaling.force(torque)
            self.latched = False
        elif statusword == ENABLED and mode == 8:
            self.actuation, self.force = Actuation.POSITION, 0.0
            self.target_length = self.scaling.length(drive.value(0x607A))
            self.latched = False
        else:  # QUICK STOP ACTIVE, or not operating: hold the length it had then
            if not self.latched:
                self.target_length, self.latched = self.length, True
            self.actuation, self.force = Actuation.POSITION, 0.0
        return []

    def inject_fault(self, code: int, text: str) -> list[can.Message]:
        raise NotImplementedError("the canopen drives have no simulated device faults")


class CanopenRobot:
    """The plant of `config` (its `sim.plant`) under one CanopenDrive per cable on
    `network` (their motor's rated torque 0x6076 = the config's rated_torque), stepped in
    real time by a thread between `start()` and `close()`.
    `truth()` is the true platform position every TRUTH_PERIOD s: rows (monotonic time,
    x, y, z)."""

    def __init__(self, config: DaemonConfig, network: canopen.Network) -> None:
        self.drives: list[CanopenDrive] = []
        self._lock = threading.Lock()  # the plant thread and canopen's (a SYNC, an RPDO)
        self._t0 = math.nan  # wall-clock time at plant time 0 (frames carry wall-clock stamps)

        def devices(drives: DrivesConfig, scalings: list[Scaling]) -> list[VirtualDrive]:
            self.drives = [CanopenDrive(network, node, 0) for node in drives.nodes]
            for drive in self.drives:  # the motor's, a stored parameter of the drive
                drive.store(0x6076, "<I", round(drives.rated_torque * 1000))
                drive.rpdo_guard = self._command_arrives
            return [CanopenActuator(d, s) for d, s in zip(self.drives, scalings, strict=True)]

        self.robot = VirtualRobot(
            config.robot, config.drives, sim_section(config).plant, devices=devices
        )
        network.unsubscribe(0x080)  # the drives answer a SYNC from _on_sync
        network.subscribe(0x080, self._on_sync)
        self._truth: list[tuple[float, float, float, float]] = []
        self._synced = math.nan  # wall-clock stamp of the latest SYNC
        self._period = 1.0 / config.controller.rate_hz  # s between two SYNCs
        self.unanswered = 0  # SYNCs seen too late to answer (`_on_sync`)
        self._delays: deque[float] = deque(maxlen=100_000)  # s, SYNC to each command
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="canopen-plant", daemon=True)

    @property
    def plant(self):
        return self.robot.plant

    def start(self) -> None:
        self._t0 = time.time() - self.robot.t
        self._thread.start()

    def close(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(5.0)

    def truth(self, since: float = -np.inf) -> np.ndarray:
        """(t, x, y, z) rows of the true position sampled at monotonic t >= since."""
        rows = [r for r in list(self._truth) if r[0] >= since]
        return np.array(rows).reshape(-1, 4)

    def command_delays(self) -> np.ndarray:
        """Seconds from the latest SYNC to each command (RPDO) since the start."""
        return np.array(self._delays)

    def _advance(self) -> None:
        """The plant up to now (whole steps), under the lock."""
        if not math.isnan(self._t0):
            self.robot.advance_to(time.time() - self._t0)

    @contextmanager
    def _command_arrives(self) -> Iterator[None]:
        """An RPDO's objects are written: the plant up to now first, all under the lock."""
        with self._lock:
            self._delays.append(time.time() - self._synced)
            self._advance()
            yield

    def _on_sync(self, can_id: int, data: bytearray, timestamp: float) -> None:
        """Every drive answers a SYNC with the encoder readings of the moment the SYNC
        was sent (its frame's stamp), however late canopen's thread sees it, as a drive
        latches its inputs at the SYNC (the plant waits until they all have).  A drive
        whose answer would go out half a period or more after the SYNC (canopen's thread
        held up, or waiting for the plant thread to catch up after a stall of its own)
        does not answer, nor do those after it: checked before each drive's answer, as
        answers sent from then on could reach the bus after the next SYNC, where a host
        takes them as the newest SYNC's (a real drive answers within microseconds, or
        not at all)."""
        with self._lock:
            self._synced = timestamp
            self._advance()
            robot = self.robot
            ago = max(0, round((robot.t - (timestamp - self._t0)) / robot.plant.config.step))
            for actuator in robot.drives:
                if time.time() - timestamp >= 0.5 * self._period:
                    self.unanswered += 1
                    return
                actuator.report(ago)
                actuator.drive.on_sync(can_id, data, timestamp)
                actuator.report(0)

    def _run(self) -> None:
        step = self.robot.plant.config.step
        sampled = -np.inf
        # the truth is stamped with the plant's own time, on the monotonic clock: the time
        # read after a step could be a preemption later (30 ms: 9 mm of a lift at 0.3 m/s)
        monotonic_at_zero = self._t0 + time.monotonic() - time.time()
        while not self._stop.wait(step):
            with self._lock:
                self._advance()
                now = monotonic_at_zero + self.robot.t
                if now - sampled >= TRUTH_PERIOD:
                    sampled = now
                    self._truth.append((now, *self.plant.pose.position.tolist()))
