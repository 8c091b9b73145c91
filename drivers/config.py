"""The `drives:` config section: which protocol, which nodes, how units scale, how to brake.

Shared by the daemon (host side) and the simulator (device side), so both sides of the
bus agree on node ids, scaling and watchdogs by construction.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Annotated, Any, Literal

import can
from pydantic import BeforeValidator, Discriminator, Field, Tag, model_validator

from cdpr import ConfigError, Robot
from cdpr.control_spec import DEFAULT_FORCE_LAG
from cdpr.description import FiniteFloat, PositiveFloat, StrictModel, validate_section
from cdpr.spool import Spool, drum_spool
from drivers.base import BrakeMode, Scaling


def _an_int(value: Any) -> Any:
    """pydantic matches the literal 1 to true and to 1.0 (equal in Python): refuse them."""
    if type(value) is not int:
        raise ValueError("Input should be the integer 1 or -1")
    return value


BusName = Annotated[str, Field(min_length=1, max_length=64)]
Direction = Annotated[Literal[1, -1], BeforeValidator(_an_int)]
PositiveSeconds = Annotated[float, Field(gt=0.0, le=10.0, allow_inf_nan=False)]


def _whole_ms(value: Any) -> Any:
    """CiA 301 heartbeat times (0x1016, 0x1017) count whole milliseconds."""
    if type(value) in (int, float) and abs(value * 1000 - round(value * 1000)) > 1e-6:
        raise ValueError(f"{value} s is no whole number of milliseconds (CiA 301 counts ms)")
    return value


WholeMs = Annotated[
    float, Field(ge=0.001, le=10.0, allow_inf_nan=False), BeforeValidator(_whole_ms)
]


# -- the CiA 402 drive profile (drives.profile) ------------------------------------------


def _object_ref(value: Any) -> Any:
    """An object as the profile names it: an index (sub 0) or "0xIIII:SS"."""
    if type(value) is int:
        return (value, 0)
    if isinstance(value, tuple):  # already parsed (the defaults)
        return value
    if isinstance(value, str):
        index, _, sub = value.partition(":")
        try:
            return (int(index, 16), int(sub or "0", 16))
        except ValueError:
            pass
    raise ValueError(f"an object is an index (0x6040) or a string '0x60C2:01', not {value!r}")


ObjectRef = Annotated[
    tuple[Annotated[int, Field(ge=0, le=0xFFFF)], Annotated[int, Field(ge=0, le=0xFF)]],
    BeforeValidator(_object_ref),
]


class PdoSpec(StrictModel):
    """One PDO the host maps: its number (1..4, predefined COB-IDs), the objects in frame
    order (0x0002-0x0007: dummy entries, where the EDS's [DummyUsage] allows them), and
    its transmission type (RPDO: 254/255 event-driven; TPDO: 1 = every SYNC, 254/255 = on
    change, at most once per inhibit_time).

    shared: (RPDO only) one frame for all the drives of a bus: each drive's objects in
      turn, in cable order, every drive mapping dummy entries over the others' bytes.
    cob_id: the COB-ID every drive of the bus takes for this RPDO (default: the
      predefined one of each drive; a shared RPDO: that of the bus's lowest node id).
    inhibit_time: (TPDO) 0x18xx:03, least time between two event-driven TPDOs (100 us).
    """

    number: Annotated[int, Field(ge=1, le=4)]  # RPDOn or TPDOn, with its predefined COB-ID
    objects: Annotated[list[ObjectRef], Field(min_length=1, max_length=8)]
    """The objects mapped, in frame order: an index (sub 0) or "0xIIII:SS"."""
    transmission_type: Annotated[int, Field(ge=0, le=255)]
    """CiA 301 transmission type (0x14xx/0x18xx:02): RPDO 254/255 event-driven; TPDO 1
    every SYNC, 254/255 on change."""
    shared: bool = False
    cob_id: Annotated[int, Field(ge=1, le=0x7FF)] | None = None
    inhibit_time: Annotated[int, Field(ge=0, le=0xFFFF)] = 0


class SdoWrite(StrictModel):
    """An extra SDO write at start-up (vendor specifics, 0x60C2, current limits)."""

    object: ObjectRef  # the object written: an index (sub 0) or "0xIIII:SS"
    value: int | str  # an integer, or a string for a string object; checked against the EDS


def _default_rpdos() -> list[PdoSpec]:
    return [
        PdoSpec(number=1, objects=[(0x6040, 0), (0x6071, 0), (0x6060, 0)], transmission_type=255),
        PdoSpec(number=2, objects=[(0x6040, 0), (0x607A, 0), (0x6060, 0)], transmission_type=255),
    ]


def _default_tpdos() -> list[PdoSpec]:
    return [
        PdoSpec(number=1, objects=[(0x6041, 0), (0x6064, 0), (0x6061, 0)], transmission_type=1),
        PdoSpec(number=2, objects=[(0x606C, 0)], transmission_type=1),
    ]


class Cia402Profile(StrictModel):
    """What the host makes of each CiA 402 drive (drivers/cia402/profile.py checks it
    against the EDS when the config loads).

    eds: the drive's EDS (the vendor's file; relative to the config file); default the
      simulated drive's config/can/cia402_cst.eds.
    host_node: the node id of the host's own heartbeat (0x700 + it), which the drives
      consume (0x1016).
    rpdo / tpdo: the PDO mapping the host writes at start-up (defaults: RPDO1 controlword
      + target torque + mode, RPDO2 controlword + target position + mode, event-driven;
      TPDO1 statusword + position actual + mode display, TPDO2 velocity actual, every SYNC).
    sdo_writes: extra writes after the mapping, each checked against the EDS.
    """

    eds: str | None = None
    host_node: Annotated[int, Field(ge=1, le=127)] = 127
    rpdo: Annotated[list[PdoSpec], Field(min_length=1, max_length=4)] = Field(
        default_factory=_default_rpdos
    )
    tpdo: Annotated[list[PdoSpec], Field(min_length=1, max_length=4)] = Field(
        default_factory=_default_tpdos
    )
    sdo_writes: list[SdoWrite] = Field(default_factory=list)


# the host heartbeat's defaults (DrivesConfig.host_heartbeat)
DEFAULT_CYCLE_PERIOD = 1.0 / 500.0  # s: the controller's default rate, for a bare drives config
HEARTBEAT_PERIOD_MIN = 0.005  # s


def _ceil_ms(seconds: float) -> float:
    return math.ceil(seconds * 1000 - 1e-6) / 1000


class DrivesConfig(StrictModel):
    """One protocol per bus; lists run in cable order (one entry per cable), scalars
    apply to every drive.

    protocol: cia402 (CANopen CiA 402, cyclic synchronous torque) or odrive (CANSimple).
    nodes: node id of each cable's drive (402: 1..127; ODrive: 0..63).
    gear_ratio: motor revolutions per drum revolution.
    counts_per_rev: encoder increments per motor revolution (ODrive reports turns: 1).
    encoder_cpr: the encoder's increments per motor revolution behind a position the
      drives report in turns (ODrive: the encoder's CPR, e.g. 8192); null: counts_per_rev.
      The feedback tolerance's quantisation (daemon.config.feedback_tolerance).
    encoder_noise: RMS noise of one reported length (m), measured with the cables at
      rest; the feedback tolerance allows six standard deviations of it.
    direction: +1 when a positive motor rotation pays cable out.
    length_offset: cable length (m) at motor position 0 (set by homing).
    rated_torque: motor rated torque (N·m), the 402 torque unit is its per-mille (0x6076).
    brake: position_hold (servo at the current length) or holding_brake (mechanical
      brake, needs has_holding_brake).  Also the drives' own watchdog reaction.
    watchdog_timeout: drive-side command timeout: the ODrive axis watchdog; for 402
      drives the host silence the default consumer time of the host heartbeat allows (the
      host sets no RPDO deadline 0x14xx:05: drivers.cia402.profile).
    heartbeat_period / heartbeat_timeout: drive heartbeat production / host consumer.
    feedback_rate_hz: cyclic feedback rate for drives that stream it (ODrive encoder
      estimates); SYNC-driven drives answer every SYNC instead.
    bus: the `can:` bus (by name) each drive is on; one name for every drive; needed
      only when `can:` lists several buses.  Node ids are distinct on each bus.
    accept_fall_on_axis_error: (odrive only) the user accepts that, without holding
      brakes, an axis error (a dead daemon's watchdog expiry included) drops the platform:
      ODrive firmware 0.6 disarms the axis on every error.  `check_fall_on_axis_error`.
    force_lag: time constant (s) with which a drive's force follows its command (first
      order: torque loop, current rise), measured at bring-up; controller.command_lead
      "auto" allows for it.  Default: the simulator's actuator (2 ms).
    profile: CiA 402 only: the drive's EDS, the PDO mapping and extra SDO writes the host
      configures at start-up (Cia402Profile).
    host_heartbeat_period / consumer_heartbeat_time: (CiA 402) how often the host sends
      its own heartbeat, and the time after its last one at which each drive's consumer
      (0x1016) declares the daemon dead and reacts (0x6007/0x605A): the drives' detection
      time of a dead daemon.  Whole ms; default (null): `host_heartbeat`
      (whole control cycles of at least 5 ms; watchdog_timeout + a period + a cycle).
      The consumer time must be at least twice the period.
    """

    protocol: Literal["cia402", "odrive"]
    nodes: list[Annotated[int, Field(ge=0, le=127)]]
    gear_ratio: PositiveFloat = 1.0
    counts_per_rev: PositiveFloat = 1.0
    encoder_cpr: PositiveFloat | None = None
    encoder_noise: Annotated[float, Field(ge=0.0, le=0.01)] = 0.0
    direction: Direction | list[Direction] = 1
    length_offset: FiniteFloat | list[FiniteFloat] = 0.0
    rated_torque: PositiveFloat | None = None
    brake: BrakeMode = BrakeMode.POSITION_HOLD
    has_holding_brake: bool = False  # the winches have mechanical holding brakes
    watchdog_timeout: PositiveSeconds = 0.05
    heartbeat_period: PositiveSeconds = 0.1
    heartbeat_timeout: PositiveSeconds = 0.35
    feedback_rate_hz: Annotated[float, Field(gt=0.0, le=10000.0)] = 500.0
    bus: BusName | list[BusName] | None = None
    accept_fall_on_axis_error: bool = False
    force_lag: Annotated[float, Field(ge=0.0, le=0.05, allow_inf_nan=False)] = DEFAULT_FORCE_LAG
    profile: Cia402Profile = Field(default_factory=Cia402Profile)
    host_heartbeat_period: WholeMs | None = None
    consumer_heartbeat_time: WholeMs | None = None

    @model_validator(mode="after")
    def _consistent(self) -> DrivesConfig:
        for name in ("direction", "length_offset", "bus"):
            value = getattr(self, name)
            if isinstance(value, list) and len(value) != len(self.nodes):
                raise ValueError(f"{name} has {len(value)} entries for {len(self.nodes)} nodes")
        if self.bus is None and len(set(self.nodes)) != len(self.nodes):
            raise ValueError(f"node ids must be distinct, got {self.nodes}")
        seen: set[tuple[str | None, int]] = set()
        for node, bus in zip(self.nodes, self.bus_names(), strict=True):
            if (bus, node) in seen:
                raise ValueError(
                    f"node id {node} is on bus {bus!r} twice: node ids must be distinct on each bus"
                )
            seen.add((bus, node))
        if self.protocol == "cia402":
            if any(not 1 <= node <= 127 for node in self.nodes):
                raise ValueError("CANopen node ids run 1..127")
            if self.rated_torque is None:
                raise ValueError("rated_torque (N·m) is required for cia402 drives")
            if self.profile.host_node in self.nodes:
                raise ValueError(
                    f"profile.host_node {self.profile.host_node} is also a drive's node id"
                )
        if self.protocol == "odrive" and any(node > 63 for node in self.nodes):
            raise ValueError("ODrive CANSimple node ids run 0..63")
        if self.brake is BrakeMode.HOLDING_BRAKE and not self.has_holding_brake:
            raise ValueError("brake: holding_brake needs has_holding_brake: true")
        if self.accept_fall_on_axis_error and self.protocol != "odrive":
            raise ValueError("accept_fall_on_axis_error applies to protocol odrive only")
        if self.heartbeat_timeout <= self.heartbeat_period:
            raise ValueError(
                f"heartbeat_timeout ({self.heartbeat_timeout} s) must exceed "
                f"heartbeat_period ({self.heartbeat_period} s)"
            )
        period, consumer = self.host_heartbeat_period, self.consumer_heartbeat_time
        if period is not None and consumer is not None and consumer < 2 * period:
            raise ValueError(
                f"consumer_heartbeat_time ({consumer} s) must be at least twice "
                f"host_heartbeat_period ({period} s): one late heartbeat must not stop the drives"
            )
        return self

    def host_heartbeat(self, cycle_period: float = DEFAULT_CYCLE_PERIOD) -> tuple[float, float]:
        """(host heartbeat period, drives' consumer time) in whole ms, for a control cycle
        of `cycle_period` s; ValueError names the key a configured pair breaks.

        The heartbeat goes out with a cycle's SYNC, so at most once per cycle.  Default
        period: whole cycles, at least HEARTBEAT_PERIOD_MIN (a 1-byte frame every 5 ms is
        1.2 % of a 1 Mbit/s bus).  Default consumer time: watchdog_timeout, the host
        silence tolerated (19 ms stopped the drives when a loaded host stalled), counted
        from the heartbeat that would have come next (+ one period and one cycle).  At
        least two periods.  Short either way: the drives apply the last torque for that
        long after the daemon dies (the consumer heartbeat is their only watchdog)."""
        period = self._host_heartbeat_period(cycle_period)
        sent = self.host_heartbeat_interval(cycle_period)
        consumer = self.consumer_heartbeat_time or _ceil_ms(
            max(2 * sent, self.watchdog_timeout + sent + cycle_period)
        )
        if consumer < 2 * sent:
            raise ValueError(
                f"consumer_heartbeat_time: {consumer * 1e3:g} ms is less than twice the host "
                f"heartbeat's period ({sent * 1e3:g} ms: host_heartbeat_period, at most once "
                "per control cycle): one late heartbeat would stop the drives"
            )
        return period, consumer

    def _host_heartbeat_period(self, cycle_period: float) -> float:
        """The configured host heartbeat period, or the default: whole cycles, at least
        HEARTBEAT_PERIOD_MIN, in whole ms."""
        cycles = max(1, math.ceil(HEARTBEAT_PERIOD_MIN / cycle_period - 1e-9))
        return self.host_heartbeat_period or _ceil_ms(cycles * cycle_period)

    def host_heartbeat_interval(self, cycle_period: float = DEFAULT_CYCLE_PERIOD) -> float:
        """How often (s) the host heartbeat goes out: its period, but never more often
        than the cycle whose SYNC carries it."""
        return max(self._host_heartbeat_period(cycle_period), cycle_period)

    def bus_names(self) -> list[str | None]:
        """The bus each drive is on, in cable order (None: `bus` not given, the only bus)."""
        bus = self.bus
        return list(bus) if isinstance(bus, list) else [bus] * len(self.nodes)

    def on_bus(self, name: str) -> tuple[list[int], DrivesConfig]:
        """The cables whose drives are on bus `name`, and this config for those drives only
        (what one protocol driver of that bus, or its simulated drives, is built from)."""
        cables = [i for i, bus in enumerate(self.bus_names()) if bus == name]

        def part(value: Any) -> Any:
            return [value[i] for i in cables] if isinstance(value, list) else value

        update = {key: part(getattr(self, key)) for key in ("nodes", "direction", "length_offset")}
        return cables, self.model_copy(update={**update, "bus": name})

    def single(self, cable: int) -> DrivesConfig:
        """This config for cable `cable`'s drive alone (one winch on the bench: `cdprd
        tune` and the simulator's rig); ConfigError names a cable the config lacks."""
        if not 0 <= cable < len(self.nodes):
            raise ConfigError(
                f"drives: no drive for cable {cable} (the config lists cables "
                f"0..{len(self.nodes) - 1})"
            )

        def part(value: Any) -> Any:
            return [value[cable]] if isinstance(value, list) else value

        keys = ("nodes", "direction", "length_offset", "bus")
        return self.model_copy(update={key: part(getattr(self, key)) for key in keys})

    @property
    def streamed(self) -> bool:
        """True when the drives stream feedback at feedback_rate_hz (ODrive) instead of
        answering the host's SYNC (CiA 402)."""
        return self.protocol == "odrive"

    def scalings_for(self, robot: Robot) -> list[Scaling]:
        """One Scaling per cable of `robot` (drum radii and spools from its description)."""
        spools = [drum_spool(a) for a in robot.actuators]
        return self.scalings([a.drum_radius for a in robot.actuators], spools)

    def scalings(
        self, drum_radii: Sequence[float], spools: Sequence[Spool | None] | None = None
    ) -> list[Scaling]:
        """One Scaling per cable, drum radii (and spools, default none) from the robot
        description."""
        if len(drum_radii) != len(self.nodes):
            raise ValueError(f"drives list {len(self.nodes)} nodes for {len(drum_radii)} cables")
        n = len(self.nodes)
        directions = self.direction if isinstance(self.direction, list) else [self.direction] * n
        offsets = (
            self.length_offset if isinstance(self.length_offset, list) else [self.length_offset] * n
        )
        spools = [None] * n if spools is None else spools
        return [
            Scaling(
                drum_radius=float(radius),
                gear_ratio=self.gear_ratio,
                counts_per_rev=self.counts_per_rev,
                direction=direction,
                length_offset=offset,
                spool=spool,
            )
            for radius, direction, offset, spool in zip(
                drum_radii, directions, offsets, spools, strict=True
            )
        ]


class CanConfig(StrictModel):
    """python-can bus arguments (`can:` section, or one entry of its list of buses).
    `options` go to can.Bus unchanged.  `name` is what `drives.bus` calls the bus
    (default: its channel)."""

    name: BusName | None = None  # what drives.bus calls this bus; null: its channel
    interface: str = "socketcan"  # the python-can interface (socketcan, socketcand, ...)
    channel: str = "can0"  # the python-can channel (for SocketCAN: the network interface)
    bitrate: Annotated[int, Field(gt=0, le=8_000_000)] = 1_000_000
    """bit/s, passed to python-can (SocketCAN takes the interface's own, set with ip link)
    and the base of the simulator's bus-load figures."""
    options: dict[str, Any] = Field(default_factory=dict)  # further keyword arguments of can.Bus

    @property
    def bus_name(self) -> str:
        return self.channel if self.name is None else self.name

    def open(self) -> can.BusABC:
        """The python-can bus these arguments name."""
        return can.Bus(
            interface=self.interface, channel=self.channel, bitrate=self.bitrate, **self.options
        )


def check_fall_on_axis_error(drives: DrivesConfig, source: str = "config") -> None:
    """ConfigError for an ODrive robot without holding brakes whose config does not say
    that it accepts the fall: ODrive firmware 0.6 disarms an axis (IDLE, motor off) on
    every axis error, its watchdog's included, so a dead daemon or any drive error lets a
    suspended platform fall unless the winches have mechanical brakes."""
    if drives.protocol != "odrive" or drives.has_holding_brake or drives.accept_fall_on_axis_error:
        return
    raise ConfigError(
        f"{source}: drives.has_holding_brake: an ODrive robot needs holding brakes: ODrive "
        "firmware 0.6 disarms an axis (IDLE, motor unpowered) on every axis error, a dead "
        "daemon's watchdog expiry included, and without brakes the platform then falls. Fit "
        "brakes and set has_holding_brake: true, or set drives.accept_fall_on_axis_error: "
        "true to accept that risk (a platform resting on a support)"
    )


def parse_drives(data: Any, source: str = "config", key: str = "drives") -> DrivesConfig:
    """Validate a `drives:` section; ConfigError names the key and the problem."""
    return validate_section(DrivesConfig, data, source, key)


def _can_shape(value: Any) -> str:
    return "list" if isinstance(value, list) else "dict"


# `can:` is one bus (a mapping) or several (a list); validated as the one its shape says
CanSection = Annotated[
    Annotated[CanConfig, Tag("dict")]
    | Annotated[list[CanConfig], Field(min_length=1), Tag("list")],
    Discriminator(_can_shape),
]


class CanFile(StrictModel):
    """A config file's `can:` section alone (for readers of a few sections: the simulator)."""

    can: CanSection = CanConfig()


def can_buses(can: CanSection, drives: DrivesConfig, source: str = "config") -> list[CanConfig]:
    """The buses of a `can:` section (one mapping, or a list of them), checked against the
    drives on them: names and channels distinct, every drive on a listed bus, every bus
    with a drive.  ConfigError names the file and the key."""
    buses = can if isinstance(can, list) else [can]
    names = [bus.bus_name for bus in buses]
    keys = [f"can.{k}" for k in range(len(buses))] if isinstance(can, list) else ["can"]
    opened: dict[tuple[Any, ...], int] = {}
    for k, bus in enumerate(buses):
        same = (
            bus.interface,
            bus.channel,
            repr(bus.options.get("host")),
            repr(bus.options.get("port")),
        )
        if same in opened:
            raise ConfigError(
                f"{source}: {keys[k]}.channel: {bus.interface} channel {bus.channel!r} is also "
                f"{keys[opened[same]]}'s: one bus listed twice"
            )
        opened[same] = k
        if names.index(names[k]) != k:
            raise ConfigError(
                f"{source}: {keys[k]}.name: bus name {names[k]!r} is also "
                f"{keys[names.index(names[k])]}'s (a name defaults to the channel)"
            )
    on = drives.bus_names()
    if len(buses) > 1 and None in on:
        raise ConfigError(
            f"{source}: drives.bus: required with several buses in can: name each drive's "
            f"bus (a list in cable order, of {', '.join(names)})"
        )
    for i, name in enumerate(on):
        if name is not None and name not in names:
            raise ConfigError(
                f"{source}: drives.bus: cable {i}'s drive (node {drives.nodes[i]}) is on bus "
                f"{name!r}, which can: does not list (buses: {', '.join(names)})"
            )
    for k, name in enumerate(names):
        if None not in on and name not in on:
            raise ConfigError(f"{source}: {keys[k]}: no drive is on bus {name!r} (drives.bus)")
    return buses
