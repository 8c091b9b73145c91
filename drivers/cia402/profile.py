"""The CiA 402 drive profile against the drive's EDS: what the host will write, checked
before anything is sent.

`plan(config)` turns `drives.profile` (drivers.config.Cia402Profile) and the EDS into a
`DrivePlan`: the PDO layouts (structs from the EDS's data types), every SDO write of the
start-up (the host's own standard objects where the EDS has them, then the profile's
extra writes), and the drive-side watchdog a dead daemon leaves behind.  Every problem
is a `ProfileError` naming the profile key and the object: index missing, wrong access
type, a value the data type or the EDS limits refuse, an object that cannot be mapped, a
PDO longer than 8 bytes, or no watchdog that makes the drive hold.

The host touches only standard objects (0x1000-0x1FFF, 0x6000-0x9FFF) unless the profile's
sdo_writes name a manufacturer object (0x2000-0x5FFF).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from canopen.objectdictionary import ObjectDictionary, ODVariable, datatypes

from drivers.base import BrakeMode
from drivers.cia402.codec import (
    ABORT_CONNECTION_OPTION,
    ABORT_QUICK_STOP,
    COB_ID_SYNC,
    CONSUMER_HEARTBEAT,
    CONTROLWORD,
    DEVICE_TYPE,
    EDS_PATH,
    MANUFACTURER_OBJECTS,
    MAX_TORQUE,
    MODE_DISPLAY,
    MODE_OF_OPERATION,
    POSITION_ACTUAL,
    PRODUCER_HEARTBEAT,
    QUICK_STOP_HOLD_CODE,
    QUICK_STOP_OPTION_CODE,
    RATED_TORQUE,
    RPDO_DEADLINE_SUB,
    STATUSWORD,
    SYNC_ID,
    TARGET_POSITION,
    TARGET_TORQUE,
    VELOCITY_ACTUAL,
    PdoLayout,
    load_eds,
    od_variable,
    pdo_layout,
)
from drivers.config import DrivesConfig, PdoSpec

# objects the host reads or writes outside the PDOs
_NEEDED = (DEVICE_TYPE, PRODUCER_HEARTBEAT, STATUSWORD, CONTROLWORD, MAX_TORQUE, RATED_TORQUE)
_EVENT_DRIVEN = (254, 255)
_CYCLIC = (CONTROLWORD, MODE_OF_OPERATION, TARGET_TORQUE, TARGET_POSITION)  # the host's
_EVERY_SYNC = 1


class ProfileError(ValueError):
    """A profile the EDS refuses; `key` is the profile key (e.g. profile.rpdo.0)."""

    def __init__(self, key: str, message: str) -> None:
        super().__init__(f"{key}: {message}")
        self.key = key


@dataclass(frozen=True)
class SdoStep:
    """One SDO write of the start-up; `value` is an integer or the bytes of a string."""

    index: int
    subindex: int
    value: int | bytes
    what: str


@dataclass(frozen=True)
class DrivePlan:
    """What the host writes into every drive of one bus, and what it then relies on."""

    eds: Path
    od: ObjectDictionary
    rpdos: tuple[PdoLayout, ...]
    tpdos: tuple[PdoLayout, ...]
    torque: PdoLayout  # the RPDO with controlword, target torque and mode
    hold: PdoLayout  # the RPDO with controlword, target position and mode
    writes: tuple[SdoStep, ...]
    unused: tuple[int, ...]  # communication indices of the EDS's other PDOs (disabled)
    watchdog: str  # what a drive does when the daemon dies
    detection: float  # s: the longest a dead daemon goes unnoticed by a drive

    @property
    def layouts(self) -> tuple[PdoLayout, ...]:
        return self.rpdos + self.tpdos


def eds_path(config: DrivesConfig) -> Path:
    """The profile's EDS file (default: the simulated drive's)."""
    eds = config.profile.eds
    return EDS_PATH if eds is None else Path(eds)


def with_eds_from(config: DrivesConfig, base: Path) -> DrivesConfig:
    """`config` with a relative profile.eds taken from `base` (the config file's
    directory), as every other path of a config is."""
    eds = config.profile.eds
    if eds is None or Path(eds).is_absolute():
        return config
    profile = config.profile.model_copy(update={"eds": str(base / eds)})
    return config.model_copy(update={"profile": profile})


def plan(config: DrivesConfig) -> DrivePlan:
    """The checked plan for `config`'s drives; ProfileError naming the key otherwise."""
    path = eds_path(config)
    try:
        od = load_eds(path, config.nodes[0] if config.nodes else 1)
    except (OSError, ValueError, KeyError) as exc:
        raise ProfileError("profile.eds", f"cannot read EDS {path}: {exc}") from None
    profile = config.profile
    for index in _NEEDED:
        _variable(od, "profile.eds", index, 0)
    rpdos = _layouts(od, profile.rpdo, receive=True)
    tpdos = _layouts(od, profile.tpdo, receive=False)
    torque = _carrying(rpdos, "profile.rpdo", (CONTROLWORD, TARGET_TORQUE, MODE_OF_OPERATION))
    hold = _carrying(rpdos, "profile.rpdo", (CONTROLWORD, TARGET_POSITION, MODE_OF_OPERATION))
    mapped = {(e.index, e.subindex) for layout in tpdos for e in layout.entries}
    for index in (STATUSWORD, POSITION_ACTUAL, VELOCITY_ACTUAL, MODE_DISPLAY):
        if (index, 0) not in mapped:
            name = od_variable(od, index).name if index in od else "it"
            raise ProfileError("profile.tpdo", f"no TPDO maps 0x{index:04X} ({name})")
    writes, watchdog, detection = _host_writes(od, config, rpdos)
    own = {(step.index, step.subindex) for step in writes}
    for k, extra in enumerate(profile.sdo_writes):
        key, (index, sub) = f"profile.sdo_writes.{k}", extra.object
        step = _checked(od, key, index, sub, extra.value)
        if (index, sub) in own or 0x1400 <= index < 0x1C00 or index in _CYCLIC:
            raise ProfileError(
                key,
                f"{step.what}: the host sets this object itself (PDO configuration, "
                "controlword, mode, heartbeats, watchdog and its reaction); another value "
                "could leave the drive free-wheeling when the daemon dies",
            )
        writes.append(step)
    used = {layout.comm_index for layout in rpdos + tpdos}
    unused = tuple(
        comm
        for comm in (*range(0x1400, 0x1600), *range(0x1800, 0x1A00))
        if comm in od and comm not in used
    )
    return DrivePlan(
        path, od, rpdos, tpdos, torque, hold, tuple(writes), unused, watchdog, detection
    )


def _layouts(od: ObjectDictionary, specs: Sequence[PdoSpec], receive: bool) -> tuple:
    kind = "rpdo" if receive else "tpdo"
    layouts, numbers = [], set()
    for k, spec in enumerate(specs):
        key = f"profile.{kind}.{k}"
        if spec.number in numbers:
            raise ProfileError(key, f"{kind.upper()}{spec.number} is listed twice")
        numbers.add(spec.number)
        wanted = _EVENT_DRIVEN if receive else (_EVERY_SYNC,)
        if spec.transmission_type not in wanted:
            raise ProfileError(
                f"{key}.transmission_type",
                f"{spec.transmission_type}: the host needs "
                + ("event-driven RPDOs (254 or 255)" if receive else "TPDOs on every SYNC (1)"),
            )
        comm = (0x1400 if receive else 0x1800) + spec.number - 1
        for index, sub in ((comm, 1), (comm, 2), (comm + 0x200, 0)):
            _variable(od, key, index, sub, writable=True)
        for j, (index, sub) in enumerate(spec.objects):
            var = _variable(od, f"{key}.objects.{j}", index, sub)
            if not var.pdo_mappable:
                raise ProfileError(
                    f"{key}.objects.{j}",
                    f"0x{index:04X}:{sub:02X} ({var.name}) is not PDO-mappable in the EDS",
                )
            _variable(od, f"{key}.objects.{j}", comm + 0x200, j + 1, writable=True)
        try:
            layout = pdo_layout(od, receive, spec.number, spec.objects, spec.transmission_type)
        except (KeyError, ValueError) as exc:
            raise ProfileError(key, str(exc.args[0])) from None
        if layout.struct.size > 8:
            raise ProfileError(
                f"{key}.objects", f"{layout.struct.size} bytes: a PDO carries at most 8"
            )
        layouts.append(layout)
    return tuple(layouts)


def _carrying(layouts: Sequence[PdoLayout], key: str, indices: tuple[int, ...]) -> PdoLayout:
    for layout in layouts:
        if set(indices) <= {e.index for e in layout.entries}:
            return layout
    wanted = " + ".join(f"0x{i:04X}" for i in indices)
    raise ProfileError(key, f"no RPDO maps {wanted} together (the host needs one)")


def _host_writes(
    od: ObjectDictionary, config: DrivesConfig, rpdos: Sequence[PdoLayout]
) -> tuple[list[SdoStep], str, float]:
    """The host's own standard writes where the EDS has them, the watchdog verdict and
    its detection time (s: the shortest of the consumer time and the RPDO deadlines; the
    torque RPDO goes out every cycle, the heartbeat every host_heartbeat_period)."""
    key = "profile.eds"
    heartbeat_ms = max(1, round(config.heartbeat_period * 1000))
    try:
        consumer_ms = round(config.host_heartbeat()[1] * 1000)
    except ValueError as exc:
        raise ProfileError(key, str(exc)) from None
    deadline_ms = max(1, round(config.watchdog_timeout * 1000))
    host = config.profile.host_node
    writes = [_checked(od, key, PRODUCER_HEARTBEAT, 0, heartbeat_ms)]
    if COB_ID_SYNC in od:
        writes.append(_checked(od, key, COB_ID_SYNC, 0, SYNC_ID))
    watchdogs, detection = [], []
    if _has(od, CONSUMER_HEARTBEAT, 1):
        writes.append(_checked(od, key, CONSUMER_HEARTBEAT, 1, host << 16 | consumer_ms))
        watchdogs.append(f"consumer heartbeat 0x1016 on node {host}, {consumer_ms} ms")
        detection.append(consumer_ms / 1000)
    for layout in rpdos:
        if _has(od, layout.comm_index, RPDO_DEADLINE_SUB):
            writes.append(_checked(od, key, layout.comm_index, RPDO_DEADLINE_SUB, deadline_ms))
            detection.append(deadline_ms / 1000)
            watchdogs.append(
                f"{layout.name} deadline 0x{layout.comm_index:04X}:05, {deadline_ms} ms"
            )
    where = f"{eds_path(config).name}"
    if not watchdogs:
        raise ProfileError(
            key,
            f"{where} has neither a consumer heartbeat 0x1016 nor an RPDO deadline "
            "0x1400:05: a dead daemon would leave the drives applying their last torque",
        )
    if ABORT_CONNECTION_OPTION not in od:
        raise ProfileError(
            key,
            f"{where} has no abort connection option 0x6007: what the drive does when the "
            "daemon dies is unknown, it may free-wheel under load",
        )
    writes.append(_checked(od, key, ABORT_CONNECTION_OPTION, 0, ABORT_QUICK_STOP))
    if QUICK_STOP_OPTION_CODE in od:
        writes.append(_checked(od, key, QUICK_STOP_OPTION_CODE, 0, QUICK_STOP_HOLD_CODE))
        reaction = (
            "quick stop (0x6007 = 3), then holds in QUICK STOP ACTIVE "
            f"(0x605A = {QUICK_STOP_HOLD_CODE})"
        )
    elif config.has_holding_brake and config.brake is BrakeMode.HOLDING_BRAKE:
        reaction = "quick stop (0x6007 = 3), power stage off, holding brake engaged"
    else:
        raise ProfileError(
            key,
            f"{where} has no quick stop option code 0x605A and the drives have no holding "
            "brake: a quick stop may ramp torque to zero and a dead daemon would leave "
            "them free-wheeling under load",
        )
    return writes, f"{'; '.join(watchdogs)} -> {reaction}", min(detection)


def _has(od: ObjectDictionary, index: int, sub: int) -> bool:
    try:
        return od_variable(od, index, sub).writable
    except KeyError:
        return False


def _variable(
    od: ObjectDictionary, key: str, index: int, sub: int, writable: bool = False
) -> ODVariable:
    try:
        var = od_variable(od, index, sub)
    except KeyError as exc:
        raise ProfileError(key, str(exc.args[0])) from None
    if writable and not var.writable:
        raise ProfileError(
            key, f"0x{index:04X}:{sub:02X} ({var.name}) is {var.access_type} in the EDS"
        )
    return var


def _checked(od: ObjectDictionary, key: str, index: int, sub: int, value: int | str) -> SdoStep:
    """A write the EDS allows: the object exists and is writable, and `value` fits its
    data type and limits."""
    var = _variable(od, key, index, sub, writable=True)
    where = f"0x{index:04X}:{sub:02X} ({var.name})"
    if index in MANUFACTURER_OBJECTS and key == "profile.eds":
        raise ProfileError(key, f"{where}: the host writes only standard objects")
    if var.data_type in (datatypes.VISIBLE_STRING, datatypes.UNICODE_STRING):
        if not isinstance(value, str):
            raise ProfileError(key, f"{where} is a string, not {value!r}")
        return SdoStep(index, sub, var.encode_raw(value), f"{where} = {value!r}")
    if var.data_type not in ODVariable.STRUCT_TYPES or var.data_type in datatypes.FLOAT_TYPES:
        raise ProfileError(key, f"{where}: only integer and string objects can be written")
    if type(value) is not int:
        raise ProfileError(key, f"{where} is an integer, not {value!r}")
    low, high = _range(var)
    if not low <= value <= high:
        raise ProfileError(key, f"{where} = {value} is outside {low}..{high}")
    return SdoStep(index, sub, value, f"{where} = {value}")


def _range(var: ODVariable) -> tuple[int, int]:
    """The EDS limits of an integer object, else its data type's range."""
    bits = len(var)
    if var.data_type in datatypes.SIGNED_TYPES:
        low, high = -(1 << bits - 1), (1 << bits - 1) - 1
    else:
        low, high = 0, (1 << bits) - 1
    return (
        low if var.min is None else max(low, var.min),
        high if var.max is None else min(high, var.max),
    )
