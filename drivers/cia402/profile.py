"""The CiA 402 drive profile against the drive's EDS: what the host will write, checked
before anything is sent.

`plan(config)` turns `drives.profile` (drivers.config.Cia402Profile) and the EDS into a
`DrivePlan` for the drives of one bus (`plans` for each bus of a config): the PDO layouts
(structs from the EDS's data types), every SDO write of the start-up (the host's own
standard objects where the EDS has them, then the profile's extra writes), and the
drive-side watchdog a dead daemon leaves behind.  Every problem is a `ProfileError`
naming the profile key and the object: index missing, wrong access type, a value the
data type or the EDS limits refuse, an object that cannot be mapped, a dummy entry the
EDS's [DummyUsage] does not allow, a PDO longer than 8 bytes (a shared one: for all the
drives of the bus), a COB-ID that two things on the bus would use or whose bytes two
drives claim, or no watchdog that makes the drive hold.

Layouts (CiA 301 only): the default maps controlword, target torque and mode in one RPDO
per drive.  A compact one maps every drive's target torque into one shared RPDO per bus
(`shared: true`), controlword and mode into an RPDO the host sends only when they change
(`DrivePlan.control`), position actual alone on SYNC, and statusword and mode display in
an event-driven TPDO (sent on change); without velocity actual the host differentiates
positions (`DrivePlan.velocity`).

The host touches only standard objects (0x1000-0x1FFF, 0x6000-0x9FFF) unless the profile's
sdo_writes name a manufacturer object (0x2000-0x5FFF).
"""

from __future__ import annotations

import struct
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path

from canopen.objectdictionary import ObjectDictionary, ODVariable, datatypes

from cdpr.trusted_file import UnreadableFileError
from drivers.base import BrakeMode
from drivers.cia402.codec import (
    ABORT_CONNECTION_OPTION,
    ABORT_QUICK_STOP,
    COB_ID_SYNC,
    CONSUMER_HEARTBEAT,
    CONTROLWORD,
    DEVICE_TYPE,
    DUMMIES,
    EDS_PATH,
    EMCY_BASE,
    HEARTBEAT_BASE,
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
    SDO_REQUEST_BASE,
    SDO_RESPONSE_BASE,
    STATUSWORD,
    SYNC_ID,
    TARGET_POSITION,
    TARGET_TORQUE,
    VELOCITY_ACTUAL,
    PdoEntry,
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
# the dummy entries (CiA 301 data-type objects) of each size, unsigned first
_DUMMY_FOR_BITS = {8: (0x0005, 0x0002), 16: (0x0006, 0x0003), 32: (0x0007, 0x0004)}
_DUMMY_NAMES = {
    0x0002: "INTEGER8",
    0x0003: "INTEGER16",
    0x0004: "INTEGER32",
    0x0005: "UNSIGNED8",
    0x0006: "UNSIGNED16",
    0x0007: "UNSIGNED32",
}


class ProfileError(ValueError):
    """A profile the EDS refuses; `key` is the profile key (e.g. profile.rpdo.0), `bus`
    the bus whose drives it was planned for (`plans`; None: the only one)."""

    def __init__(self, key: str, message: str) -> None:
        super().__init__(f"{key}: {message}")
        self.key = key
        self.bus: str | None = None


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
    torque: PdoLayout  # the RPDO with target torque (and controlword and mode, or control)
    hold: PdoLayout  # the RPDO with controlword, target position and mode
    writes: tuple[SdoStep, ...]
    unused: tuple[int, ...]  # communication indices of the EDS's other PDOs (disabled)
    watchdog: str  # what a drive does when the daemon dies
    detection: float  # s: the longest a dead daemon goes unnoticed by a drive
    # the RPDO with controlword and mode, sent when they change, if `torque` lacks them
    control: PdoLayout | None = None

    @property
    def layouts(self) -> tuple[PdoLayout, ...]:
        return self.rpdos + self.tpdos

    @property
    def velocity(self) -> bool:
        """True if a TPDO on SYNC carries velocity actual; else the host differentiates."""
        return any(e.index == VELOCITY_ACTUAL for t in self.tpdos if t.on_sync for e in t.entries)


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


def plans(config: DrivesConfig) -> dict[str | None, DrivePlan]:
    """The checked plan of each bus's drives, by bus name (None: `bus` not given)."""
    names = dict.fromkeys(config.bus_names())
    if list(names) == [None]:
        return {None: plan(config)}
    checked: dict[str | None, DrivePlan] = {}
    for name in names:
        assert name is not None  # DrivesConfig: one bus for all drives, or each named
        try:
            checked[name] = plan(config.on_bus(name)[1])
        except ProfileError as exc:
            exc.bus = name
            raise
    return checked


def plan(config: DrivesConfig) -> DrivePlan:
    """The checked plan for `config`'s drives, all on one bus (a shared RPDO has a slot
    for each, in cable order); ProfileError naming the key otherwise."""
    path = eds_path(config)
    try:
        od = load_eds(path, config.nodes[0] if config.nodes else 1)
    except UnreadableFileError as exc:
        raise ProfileError("profile.eds", f"cannot read EDS {path}: {exc.problem}") from None
    except (OSError, ValueError, KeyError) as exc:
        raise ProfileError("profile.eds", f"cannot read EDS {path}: {exc}") from None
    profile = config.profile
    for index in _NEEDED:
        _variable(od, "profile.eds", index, 0)
    nodes = config.nodes or [1]
    rpdos = _layouts(od, profile.rpdo, receive=True, nodes=nodes)
    tpdos = _layouts(od, profile.tpdo, receive=False, nodes=nodes)
    _check_cob_ids(config, nodes, rpdos + tpdos)
    torque, control = _torque_and_control(rpdos)
    hold = _carrying(rpdos, "profile.rpdo", (CONTROLWORD, TARGET_POSITION, MODE_OF_OPERATION))
    mapped = {(e.index, e.subindex) for layout in tpdos for e in layout.entries}
    for index in (STATUSWORD, MODE_DISPLAY):
        if (index, 0) not in mapped:
            name = od_variable(od, index).name if index in od else "it"
            raise ProfileError("profile.tpdo", f"no TPDO maps 0x{index:04X} ({name})")
    if not any(e.index == POSITION_ACTUAL for t in tpdos if t.on_sync for e in t.entries):
        raise ProfileError(
            "profile.tpdo",
            f"no TPDO on SYNC (transmission type 1) maps 0x{POSITION_ACTUAL:04X} (position "
            "actual): it is the host's feedback, and the sign that a drive is alive, every cycle",
        )
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
        path, od, rpdos, tpdos, torque, hold, tuple(writes), unused, watchdog, detection,
        control,
    )


def _layouts(
    od: ObjectDictionary, specs: Sequence[PdoSpec], receive: bool, nodes: Sequence[int]
) -> tuple:
    kind = "rpdo" if receive else "tpdo"
    layouts, numbers = [], set()
    for k, spec in enumerate(specs):
        key = f"profile.{kind}.{k}"
        if spec.number in numbers:
            raise ProfileError(key, f"{kind.upper()}{spec.number} is listed twice")
        numbers.add(spec.number)
        wanted = _EVENT_DRIVEN if receive else (_EVERY_SYNC, *_EVENT_DRIVEN)
        if spec.transmission_type not in wanted:
            raise ProfileError(
                f"{key}.transmission_type",
                f"{spec.transmission_type}: the host needs "
                + (
                    "event-driven RPDOs (254 or 255)"
                    if receive
                    else "TPDOs on every SYNC (1) or on change (254 or 255)"
                ),
            )
        for name, given in (("shared", spec.shared), ("cob_id", spec.cob_id is not None)):
            if given and not receive:
                raise ProfileError(f"{key}.{name}", "only an RPDO: each drive sends its own TPDOs")
        if spec.inhibit_time and (receive or spec.transmission_type not in _EVENT_DRIVEN):
            raise ProfileError(f"{key}.inhibit_time", "only an event-driven TPDO has one")
        comm = (0x1400 if receive else 0x1800) + spec.number - 1
        for index, sub in ((comm, 1), (comm, 2), (comm + 0x200, 0)):
            _variable(od, key, index, sub, writable=True)
        if spec.inhibit_time:
            _variable(od, f"{key}.inhibit_time", comm, 3, writable=True)
        for j, (index, sub) in enumerate(spec.objects):
            _mappable(od, f"{key}.objects.{j}", index, sub)
        try:
            layout = pdo_layout(od, receive, spec.number, spec.objects, spec.transmission_type)
        except (KeyError, ValueError) as exc:
            raise ProfileError(key, str(exc.args[0])) from None
        layout = replace(layout, cob=spec.cob_id, inhibit=spec.inhibit_time)
        drives = ""
        if spec.shared and list(spec.objects) != [(TARGET_TORQUE, 0)]:
            raise ProfileError(
                f"{key}.objects",
                "a shared RPDO carries each drive's target torque 0x6071 only (controlword "
                "and mode go in an RPDO of each drive's own, sent when they change)",
            )
        if spec.shared:
            drives = f" for the {len(nodes)} drives of the bus ({layout.struct.size} each)"
            cob = spec.cob_id or layout.cob_base + min(nodes)
            layout = _shared(od, key, layout, len(nodes), cob)
        if layout.struct.size > 8:
            raise ProfileError(
                f"{key}.objects", f"{layout.struct.size} bytes{drives}: a PDO carries at most 8"
            )
        for j in range(len(layout.mapped())):
            _variable(od, f"{key}.objects", comm + 0x200, j + 1, writable=True)
        layouts.append(layout)
    return tuple(layouts)


def _mappable(od: ObjectDictionary, key: str, index: int, sub: int) -> None:
    """A mappable object, or a dummy entry the EDS's [DummyUsage] allows."""
    if index in DUMMIES and index not in od:
        raise ProfileError(
            key,
            f"dummy entry 0x{index:04X} ({_DUMMY_NAMES[index]}) is not allowed by the EDS "
            f"([DummyUsage] Dummy{index:04X} is not 1)",
        )
    var = _variable(od, key, index, sub)
    if index not in DUMMIES and not var.pdo_mappable:
        raise ProfileError(
            key, f"0x{index:04X}:{sub:02X} ({var.name}) is not PDO-mappable in the EDS"
        )


def _shared(od: ObjectDictionary, key: str, layout: PdoLayout, slots: int, cob: int) -> PdoLayout:
    """`layout` as one frame for `slots` drives at COB-ID `cob`, each mapping dummy
    entries (the first size-matching one the EDS allows) over the others' bytes."""
    dummies = []
    for entry in layout.entries:
        allowed = [i for i in _DUMMY_FOR_BITS.get(entry.bits, ()) if i in od]
        if not allowed:
            names = " or ".join(
                f"0x{i:04X} ({_DUMMY_NAMES[i]})" for i in _DUMMY_FOR_BITS.get(entry.bits, ())
            )
            raise ProfileError(
                f"{key}.shared",
                f"each drive skips the others' {entry.bits}-bit 0x{entry.index:04X} with a "
                f"dummy entry, {names or 'of that size'}, which the EDS does not allow "
                "([DummyUsage])",
            )
        dummies.append(PdoEntry(allowed[0], 0, entry.bits))
    frame = struct.Struct("<" + layout.struct.format.lstrip("<") * slots)
    return replace(layout, struct=frame, cob=cob, slots=slots, dummies=tuple(dummies))


def _check_cob_ids(
    config: DrivesConfig, nodes: Sequence[int], layouts: Sequence[PdoLayout]
) -> None:
    """Every COB-ID on the bus has one use (the SYNC, the host's heartbeat, each drive's
    EMCY, SDO, heartbeat and PDOs), except an RPDO several drives take whose bytes each
    claim apart (dummies over the others')."""
    users = {SYNC_ID: "the SYNC", HEARTBEAT_BASE + config.profile.host_node: "the host heartbeat"}
    for node in nodes:
        for base, what in (
            (EMCY_BASE, "EMCY"),
            (SDO_RESPONSE_BASE, "SDO response"),
            (SDO_REQUEST_BASE, "SDO request"),
            (HEARTBEAT_BASE, "heartbeat"),
        ):
            users[base + node] = f"node {node}'s {what}"
    claims: dict[int, tuple[PdoLayout, dict[int, int]]] = {}  # COB-ID -> layout, byte -> node
    for layout in sorted(layouts, key=lambda pdo: pdo.cob is not None):  # set COB-IDs named
        key = f"profile.{'rpdo' if layout.receive else 'tpdo'}.{_position(config, layout)}"
        for slot, node in enumerate(nodes):
            cob, what = layout.cob_id(node), f"node {node}'s {layout.name}"
            claim = claims.get(cob)
            if cob in users and (claim is None or claim[0] is not layout):
                raise ProfileError(
                    f"{key}.cob_id" if layout.cob is not None else key,
                    f"COB-ID 0x{cob:03X} of {what} is also {users[cob]}'s",
                )
            users.setdefault(cob, what)
            taken = claims.setdefault(cob, (layout, {}))[1]
            offset = 0
            for entry in layout.mapped(slot):
                size = entry.bits // 8
                if entry.index not in DUMMIES:
                    for byte in range(offset, offset + size):
                        if byte in taken:
                            raise ProfileError(
                                f"{key}.cob_id",
                                f"nodes {taken[byte]} and {node} both take byte {byte} of "
                                f"COB-ID 0x{cob:03X} (0x{entry.index:04X}): two drives "
                                "claiming the same bytes (shared: true gives each its own)",
                            )
                        taken[byte] = node
                offset += size


def _position(config: DrivesConfig, layout: PdoLayout) -> int:
    """The index of `layout`'s spec in the profile's rpdo or tpdo list."""
    specs = config.profile.rpdo if layout.receive else config.profile.tpdo
    return [spec.number for spec in specs].index(int(layout.name[4:]))


def _torque_and_control(rpdos: Sequence[PdoLayout]) -> tuple[PdoLayout, PdoLayout | None]:
    """The RPDO with the target torque, and the one with controlword and mode (sent on
    change) when it lacks them."""
    both = (CONTROLWORD, TARGET_TORQUE, MODE_OF_OPERATION)
    for layout in rpdos:
        if set(both) <= {e.index for e in layout.entries}:
            return layout, None
    targets = {TARGET_TORQUE, TARGET_POSITION}
    torque = [r for r in rpdos if TARGET_TORQUE in {e.index for e in r.entries}]
    controls = [
        r
        for r in rpdos
        if {CONTROLWORD, MODE_OF_OPERATION} <= {e.index for e in r.entries}
        and not targets & {e.index for e in r.entries}
    ]
    if torque and controls:
        return torque[0], controls[0]
    raise ProfileError(
        "profile.rpdo",
        "no RPDO maps 0x6040 + 0x6071 + 0x6060 together, nor are 0x6071 and 0x6040 + 0x6060 "
        "(without a target) mapped in two RPDOs: the host needs the target torque, and the "
        "controlword and mode to switch the drives to torque mode",
    )


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
    its detection time (s: the consumer time of the host heartbeat).

    Every RPDO's deadline 0x14xx:05 is switched off (0) where the EDS has it: a drive
    times each RPDO apart (CiA 301), and the host sends none of them every cycle in every
    enabled state (the torque RPDO in torque control, the hold RPDO in a hold, the
    control RPDO on change), so a deadline would stop the drive at the first switch
    between hold and torque control.  The consumer heartbeat, sent at its own pace in
    every state, is the drive-side watchdog; a drive without it is refused."""
    key = "profile.eds"
    heartbeat_ms = max(1, round(config.heartbeat_period * 1000))
    try:
        consumer_ms = round(config.host_heartbeat()[1] * 1000)
    except ValueError as exc:
        raise ProfileError(key, str(exc)) from None
    host = config.profile.host_node
    writes = [_checked(od, key, PRODUCER_HEARTBEAT, 0, heartbeat_ms)]
    if COB_ID_SYNC in od:
        writes.append(_checked(od, key, COB_ID_SYNC, 0, SYNC_ID))
    where = f"{eds_path(config).name}"
    if not _has(od, CONSUMER_HEARTBEAT, 1):
        raise ProfileError(
            key,
            f"{where} has no consumer heartbeat 0x1016 (the host sets no RPDO deadline, "
            "it sends each RPDO only in some states): a dead daemon would leave the "
            "drives applying their last torque",
        )
    writes.append(_checked(od, key, CONSUMER_HEARTBEAT, 1, host << 16 | consumer_ms))
    watchdog = f"consumer heartbeat 0x1016 on node {host}, {consumer_ms} ms"
    for layout in rpdos:
        if _has(od, layout.comm_index, RPDO_DEADLINE_SUB):
            writes.append(_checked(od, key, layout.comm_index, RPDO_DEADLINE_SUB, 0))
        else:
            _refuse_fixed_deadline(od, key, where, layout)
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
    return writes, f"{watchdog} -> {reaction}", consumer_ms / 1000


def _refuse_fixed_deadline(od: ObjectDictionary, key: str, where: str, layout: PdoLayout) -> None:
    """Refuse an RPDO whose deadline the EDS fixes (read-only) at a non-zero time: the
    host cannot switch it off, and the drive would stop at the first switch between hold
    and torque control (`_host_writes`)."""
    try:
        var = od_variable(od, layout.comm_index, RPDO_DEADLINE_SUB)
    except KeyError:
        return
    if var.default:
        raise ProfileError(
            key,
            f"{where}: {layout.name}'s deadline 0x{layout.comm_index:04X}:05 is "
            f"{var.access_type} at {var.default} ms: the host cannot switch it off, and "
            "it sends no RPDO every cycle in every state (map another RPDO)",
        )


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
