"""The `drives:` config section: which protocol, which nodes, how units scale, how to brake.

Shared by the daemon (host side) and the simulator (device side), so both sides of the
bus agree on node ids, scaling and watchdogs by construction.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Annotated, Any, Literal

import can
from pydantic import BeforeValidator, Field, model_validator

from cdpr import Robot
from cdpr.description import FiniteFloat, PositiveFloat, StrictModel, validate_section
from drivers.base import BrakeMode, Scaling


def _an_int(value: Any) -> Any:
    """pydantic matches the literal 1 to true and to 1.0 (equal in Python): refuse them."""
    if type(value) is not int:
        raise ValueError("Input should be the integer 1 or -1")
    return value


Direction = Annotated[Literal[1, -1], BeforeValidator(_an_int)]
PositiveSeconds = Annotated[float, Field(gt=0.0, le=10.0, allow_inf_nan=False)]


class DrivesConfig(StrictModel):
    """One protocol per bus; lists run in cable order (one entry per cable), scalars
    apply to every drive.

    protocol: cia402 (CANopen CiA 402, cyclic synchronous torque) or odrive (CANSimple).
    nodes: node id of each cable's drive (402: 1..127; ODrive: 0..63).
    gear_ratio: motor revolutions per drum revolution.
    counts_per_rev: encoder increments per motor revolution (ODrive reports turns: 1).
    direction: +1 when a positive motor rotation pays cable out.
    length_offset: cable length (m) at motor position 0 (set by homing).
    rated_torque: motor rated torque (N·m), the 402 torque unit is its per-mille (0x6076).
    brake: position_hold (servo at the current length) or holding_brake (mechanical
      brake, needs has_holding_brake).  Also the drives' own watchdog reaction.
    watchdog_timeout: drive-side command timeout (402 RPDO timeout, ODrive axis watchdog).
    heartbeat_period / heartbeat_timeout: drive heartbeat production / host consumer.
    feedback_rate_hz: cyclic feedback rate for drives that stream it (ODrive encoder
      estimates); SYNC-driven drives answer every SYNC instead.
    """

    protocol: Literal["cia402", "odrive"]
    nodes: list[Annotated[int, Field(ge=0, le=127)]]
    gear_ratio: PositiveFloat = 1.0
    counts_per_rev: PositiveFloat = 1.0
    direction: Direction | list[Direction] = 1
    length_offset: FiniteFloat | list[FiniteFloat] = 0.0
    rated_torque: PositiveFloat | None = None
    brake: BrakeMode = BrakeMode.POSITION_HOLD
    has_holding_brake: bool = False
    watchdog_timeout: PositiveSeconds = 0.05
    heartbeat_period: PositiveSeconds = 0.1
    heartbeat_timeout: PositiveSeconds = 0.35
    feedback_rate_hz: Annotated[float, Field(gt=0.0, le=10000.0)] = 500.0

    @model_validator(mode="after")
    def _consistent(self) -> DrivesConfig:
        if len(set(self.nodes)) != len(self.nodes):
            raise ValueError(f"node ids must be distinct, got {self.nodes}")
        if self.protocol == "cia402":
            if any(not 1 <= node <= 127 for node in self.nodes):
                raise ValueError("CANopen node ids run 1..127")
            if self.rated_torque is None:
                raise ValueError("rated_torque (N·m) is required for cia402 drives")
        if self.protocol == "odrive" and any(node > 63 for node in self.nodes):
            raise ValueError("ODrive CANSimple node ids run 0..63")
        if self.brake is BrakeMode.HOLDING_BRAKE and not self.has_holding_brake:
            raise ValueError("brake: holding_brake needs has_holding_brake: true")
        if self.heartbeat_timeout <= self.heartbeat_period:
            raise ValueError(
                f"heartbeat_timeout ({self.heartbeat_timeout} s) must exceed "
                f"heartbeat_period ({self.heartbeat_period} s)"
            )
        for name in ("direction", "length_offset"):
            value = getattr(self, name)
            if isinstance(value, list) and len(value) != len(self.nodes):
                raise ValueError(f"{name} has {len(value)} entries for {len(self.nodes)} nodes")
        return self

    @property
    def streamed(self) -> bool:
        """True when the drives stream feedback at feedback_rate_hz (ODrive) instead of
        answering the host's SYNC (CiA 402)."""
        return self.protocol == "odrive"

    def scalings_for(self, robot: Robot) -> list[Scaling]:
        """One Scaling per cable of `robot` (drum radii from its description)."""
        return self.scalings([a.drum_radius for a in robot.actuators])

    def scalings(self, drum_radii: Sequence[float]) -> list[Scaling]:
        """One Scaling per cable, drum radii from the robot description."""
        if len(drum_radii) != len(self.nodes):
            raise ValueError(f"drives list {len(self.nodes)} nodes for {len(drum_radii)} cables")
        n = len(self.nodes)
        directions = self.direction if isinstance(self.direction, list) else [self.direction] * n
        offsets = (
            self.length_offset if isinstance(self.length_offset, list) else [self.length_offset] * n
        )
        return [
            Scaling(
                drum_radius=float(radius),
                gear_ratio=self.gear_ratio,
                counts_per_rev=self.counts_per_rev,
                direction=direction,
                length_offset=offset,
            )
            for radius, direction, offset in zip(drum_radii, directions, offsets, strict=True)
        ]


class CanConfig(StrictModel):
    """python-can bus arguments (`can:` section).  `options` go to can.Bus unchanged."""

    interface: str = "socketcan"
    channel: str = "can0"
    bitrate: Annotated[int, Field(gt=0, le=8_000_000)] = 1_000_000
    options: dict[str, Any] = Field(default_factory=dict)

    def open(self) -> can.BusABC:
        """The python-can bus these arguments name."""
        return can.Bus(
            interface=self.interface, channel=self.channel, bitrate=self.bitrate, **self.options
        )


def parse_drives(data: Any, source: str = "config", key: str = "drives") -> DrivesConfig:
    """Validate a `drives:` section; ConfigError names the key and the problem."""
    return validate_section(DrivesConfig, data, source, key)
