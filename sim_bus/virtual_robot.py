"""The simulated robot as the bus sees it: the plant plus one virtual drive per cable.

Time is the simulator's own: `advance_to(t)` steps the plant in whole plant steps up to
t, applying each drive's actuation before every step and letting each drive's clock run
after it (heartbeats, cyclic feedback, watchdogs).  `handle(frame, t)` first brings the
plant up to t, so a SYNC at t is answered with the state at t (the drums' readings
carried from the last whole step to t).  Nothing here touches a
bus or a wall clock: the asyncio runner (sim_bus.runner) and the tests drive it.

With drives on several buses (`drives.bus`), each drive hears only frames whose
`channel` names its bus, and the frames it sends carry its bus's name there (the
runner sends them on that bus).

Device-level faults live here (a silent node, a stuck encoder, a glitching one, a drive
fault, a snapped cable); frame-level faults (drops, delays, corruption, error frames) are
sim_bus.bus.frame_faults.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Sequence

import can
import numpy as np

from cdpr import ConfigError, Robot
from drivers.base import Actuation, Scaling, VirtualDrive
from drivers.cia402.codec import is_sync
from drivers.config import DrivesConfig
from sim_bus.config import RigConfig
from sim_bus.plant import Plant, PlantConfig
from sim_bus.plant.rig import SingleActuatorRig

# an overcurrent as each protocol reports it: CiA 402 EMCY error code, ODrive 0.6 axis
# error bit CURRENT_LIMIT_VIOLATION
OVERCURRENT = {"cia402": 0x2310, "odrive": 0x1000}


class PositionServo:
    """The drive's internal position loop (PID on the cable length) used while it holds
    a length.  Starts bumpless: the integrator takes the force the drive was producing
    (less the drive's feed-forward), so a platform that was held by torque is not dropped
    when the hold begins."""

    def __init__(self, kp: float = 5.0e4, ki: float = 2.0e5, kd: float = 800.0) -> None:
        self.kp, self.ki, self.kd = kp, ki, kd
        self.integral = 0.0

    def start(self, force: float) -> None:
        self.integral = force

    def force(self, target: float, length: float, rate: float, h: float) -> float:
        error = target - length
        self.integral += self.ki * error * h
        return self.integral + self.kp * error - self.kd * rate


def true_scalings(
    config: DrivesConfig, robot: Robot, encoder_offsets: Sequence[float] | None = None
) -> list[Scaling]:
    """The devices' scalings: like the host side's but with `robot`'s drum radii (the
    true robot's) and each motor position zero `encoder_offsets` (m) further in than
    the host believes (MismatchConfig)."""
    scalings = config.scalings_for(robot)
    if encoder_offsets is None:
        return scalings
    return [
        dataclasses.replace(s, length_offset=s.length_offset - offset)
        for s, offset in zip(scalings, encoder_offsets, strict=True)
    ]


def make_virtual_drives(config: DrivesConfig, scalings: list[Scaling]) -> list[VirtualDrive]:
    """One device per drive of `config`, of its protocol, with the devices' `scalings`."""
    if config.protocol == "cia402":
        from sim_bus.devices.cia402 import Cia402Drive

        return [
            Cia402Drive(node, s, config) for node, s in zip(config.nodes, scalings, strict=True)
        ]
    from sim_bus.devices.odrive import OdriveAxis

    return [OdriveAxis(node, s, config) for node, s in zip(config.nodes, scalings, strict=True)]


def bench_rig(robot: Robot, config: PlantConfig, rig: RigConfig) -> SingleActuatorRig:
    """The single-actuator rig `rig` describes: the TRUE actuator of its cable (the
    config's mismatch applied to `robot`), its load hanging under gravity |g|."""
    if rig.drive >= robot.n_cables:
        raise ConfigError(
            f"sim.rig.drive: cable {rig.drive} does not exist (cables 0..{robot.n_cables - 1})"
        )
    rng = np.random.default_rng(np.random.SeedSequence(config.seed).spawn(1)[0])
    actuator = config.mismatch.apply(robot, rng).actuators[rig.drive]
    if rig.clamped:
        load, preload = math.inf, rig.preload
    else:
        load, preload = rig.load_mass, rig.load_mass * float(np.linalg.norm(robot.platform.gravity))
    return SingleActuatorRig(actuator, load, config, rig.cable_length, preload)


DeviceFactory = Callable[[DrivesConfig, list[Scaling]], list[VirtualDrive]]


class VirtualRobot:
    """Plant + virtual drives.  `t` is simulated time in seconds from the start.  With
    `rig`, the plant is one winch on the bench (sim_bus.config.RigConfig) behind the
    drive of cable `rig.drive` alone (its index here is 0).  `devices` makes the drives
    from the config and the devices' scalings (default: the project's virtual drives)."""

    def __init__(
        self,
        robot: Robot,
        drives: DrivesConfig,
        plant: PlantConfig | None = None,
        rig: RigConfig | None = None,
        devices: DeviceFactory = make_virtual_drives,
    ) -> None:
        if rig is None:
            self.plant: Plant | SingleActuatorRig = Plant(robot, plant)
            offsets = self.plant.config.mismatch.encoder_offsets_for(self.plant.n)
            scalings = true_scalings(drives, self.plant.robot, offsets)
        else:
            self.plant = bench_rig(robot, plant or PlantConfig(), rig)
            drives, scalings = drives.single(rig.drive), [drives.scalings_for(robot)[rig.drive]]
        self.protocol = drives.protocol
        self.drives = devices(drives, scalings)
        self.n = len(self.drives)
        buses = drives.bus_names()
        # each drive's bus where there are several (frames are routed by channel), else None
        self.buses: list[str | None] | None = buses if len(set(buses)) > 1 else None
        self.servos = [PositionServo() for _ in self.drives]
        self.silent = [False] * self.n
        self.stuck: list[tuple[float, float] | None] = [None] * self.n
        self._applied: list[Actuation | None] = [None] * self.n
        self._brakes: list[bool | None] = [None] * self.n
        self._step = self.plant.config.step
        # (bus, CAN id; -1 extended or error frame) -> the drives that hear it
        self._listeners: dict[tuple[str | None, int], list[int]] = {}
        for drive in self.drives:
            drive.routes_changed = self._listeners.clear
        self._measure()
        self._apply()

    @property
    def t(self) -> float:
        return self.plant.time

    # -- time and frames ------------------------------------------------------------

    def advance_to(self, t: float) -> list[can.Message]:
        """Step the plant up to `t` (whole steps); the frames the drives send meanwhile."""
        out: list[can.Message] = []
        while self.plant.time + self._step <= t + 1e-12:
            self._apply()
            self.plant.step()
            self._measure()
            now = self.plant.time
            for k, drive in enumerate(self.drives):
                frames = drive.on_tick(now)
                if frames and not self.silent[k]:
                    out.extend(self._from(k, frames))
        return out

    def is_sync(self, message: can.Message) -> bool:
        """Whether `message` is a SYNC to these drives: CiA 402 drives latch on one; to
        ODrives the same id (0x080) is node 4's command 0."""
        return self.protocol == "cia402" and is_sync(message)

    def handle(self, message: can.Message, t: float) -> list[can.Message]:
        """Deliver one bus frame at time `t` to every drive on its bus; the frames they
        answer."""
        out = self.advance_to(t)
        now = self.plant.time
        if t > now and self.is_sync(message):
            self._measure(t - now)  # the drives latch at the SYNC's instant, between steps
        drives, silent = self.drives, self.silent
        for k in self._hearing(message):
            if silent[k]:
                continue
            frames = drives[k].on_frame(message, now)
            if frames:
                out.extend(self._from(k, frames))
        return out

    def _hearing(self, message: can.Message) -> list[int]:
        """The drives a frame reaches: those on its bus that hear its id (extended and
        error frames: every drive on its bus, to ignore as theirs do)."""
        buses = self.buses
        channel = None if buses is None else message.channel
        key = (channel, -1 if message.is_extended_id or message.is_error_frame else
               message.arbitration_id)  # fmt: skip
        hearing = self._listeners.get(key)
        if hearing is None:
            hearing = self._listeners[key] = [
                k
                for k, drive in enumerate(self.drives)
                if (buses is None or buses[k] == channel) and (key[1] < 0 or drive.hears(key[1]))
            ]
        return hearing

    def _from(self, k: int, frames: list[can.Message]) -> list[can.Message]:
        """Frames drive k sends, tagged with its bus where there are several."""
        if self.buses is not None:
            for msg in frames:
                msg.channel = self.buses[k]
        return frames

    # -- device faults ----------------------------------------------------------------

    def silence(self, k: int, silent: bool = True) -> None:
        """Node k stops sending and hearing frames (a dead or unplugged drive); its
        power stage keeps doing what it did."""
        self.silent[k] = silent

    def stick_encoder(self, k: int, stuck: bool = True) -> None:
        """Drive k's encoder freezes at its current reading."""
        drive = self.drives[k]
        self.stuck[k] = (drive.length, 0.0) if stuck else None

    def glitch_encoder(self, k: int, offset: float) -> None:
        """Drive k reports its length `offset` metres off (0: the glitch ends), in its
        feedback frames only: its own position loop keeps the true encoder, so whatever
        moves the platform is the host's doing."""
        self.drives[k].glitch = offset

    def drive_fault(
        self, k: int, code: int | None = None, text: str = "overcurrent"
    ) -> list[can.Message]:
        """Drive k detects an internal fault (default: an overcurrent, in the protocol's
        own code) and reacts as the real drive would."""
        if code is None:
            code = OVERCURRENT[self.protocol]
        frames = self.drives[k].inject_fault(code, text)
        self._apply()
        return [] if self.silent[k] else self._from(k, frames)

    def snap_cable(self, k: int) -> None:
        """Cable k breaks."""
        self.plant.break_cable(k)

    # -- coupling -------------------------------------------------------------------

    def _measure(self, ahead: float = 0.0) -> None:
        """Each drive's encoder reading: after the last step, or `ahead` s later."""
        lengths, rates = self.plant.measure(ahead)
        for drive, stuck, length, rate in zip(
            self.drives, self.stuck, lengths.tolist(), rates.tolist(), strict=True
        ):
            if stuck is None:
                drive.measure(length, rate)
            else:
                drive.measure(*stuck)

    def _apply(self) -> None:
        """Each drive's power stage and brake onto its winch, then the force commands."""
        plant = self.plant
        commands = plant.winches.commands
        forces = list(commands)
        for k, drive in enumerate(self.drives):
            actuation = drive.actuation
            brake = drive.brake_engaged
            if brake != self._brakes[k]:
                plant.set_brake(k, brake)
                self._brakes[k] = brake
            previous = self._applied[k]
            if actuation is not previous:
                powered = actuation is not Actuation.OFF
                if previous is None or powered != (previous is not Actuation.OFF):
                    plant.set_drive_enabled(k, powered)  # restarts the electrical state
                if actuation is Actuation.POSITION:  # from OFF the drive produced nothing
                    off = previous is Actuation.OFF
                    self.servos[k].start(0.0 if off else commands[k] - drive.force)
                self._applied[k] = actuation
            if actuation is Actuation.TORQUE:
                forces[k] = drive.force
            elif actuation is Actuation.POSITION:
                forces[k] = drive.force + self.servos[k].force(
                    drive.target_length, drive.length, drive.rate, self._step
                )
            else:
                forces[k] = 0.0
            if not math.isfinite(forces[k]):
                forces[k] = 0.0
            drive.produced = forces[k]
        plant.set_commands(forces)
