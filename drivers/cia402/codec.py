"""CANopen / CiA 402 frame codecs, host and device directions, struct-based.

Frames (11-bit ids, node id n = 1..127; layout fixed by config/can/cia402_cst.eds, which
`check_eds` compares with the structs below):

  NMT        0x000      command u8, node u8 (0 = all)
  SYNC       0x080      no data (a 1-byte SYNC counter is accepted by the device)
  EMCY       0x080+n    error code u16, error register u8, 5 manufacturer bytes
  TPDO1      0x180+n    statusword 0x6041 u16, position actual 0x6064 i32 (increments),
                        mode of operation display 0x6061 i8             7 bytes, every SYNC
  TPDO2      0x280+n    velocity actual 0x606C i32 (increments/s)       4 bytes, every SYNC
  RPDO1      0x200+n    controlword 0x6040 u16, target torque 0x6071 i16 (per mille of
                        rated torque 0x6076), mode of operation 0x6060 i8   5 bytes
  RPDO2      0x300+n    controlword 0x6040 u16, target position 0x607A i32 (increments),
                        mode of operation 0x6060 i8                     7 bytes
  SDO        0x600+n request, 0x580+n response; expedited (<= 4 bytes) and segmented
  heartbeat  0x700+n    NMT state u8 (0x00 = boot-up); the host produces its own too

These four PDOs are the default drive profile (drivers.config.Cia402Profile), which the
host writes into each drive at start-up; a profile may map them differently, and
`pdo_layout` builds the struct of any mapping from the EDS's data types.

RPDO1 carries the torque commands (mode 10, CST), RPDO2 the position hold (mode 8, CSP):
an i16 torque and an i32 position do not fit one 8-byte PDO with the controlword and the
mode.  Both RPDOs are event-driven (transmission type 255): the drive acts on reception,
so a brake frame needs no following SYNC and a torque command no extra cycle of delay.
Both TPDOs are synchronous (type 1): the drive sends them, TPDO1 first, on every SYNC.

Decoders take the frame id (for the error text) and the data, and raise
`Cia402FrameError` (a FrameError with a short `reason` for the rejection counters) on a
wrong length or a value outside what the protocol defines.  A mode of operation 0 means
"no change" (402); which modes a drive may display is the caller's business (an
unexpected one is a fault the host reports, not a malformed frame).
"""

from __future__ import annotations

import enum
import functools
import io
import struct
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import can
from canopen.objectdictionary import ObjectDictionary, ODArray, ODRecord, ODVariable, import_od
from canopen.sdo.exceptions import SdoAbortedError

from cdpr.trusted_file import read_trusted
from drivers.base import FrameError, data_frame
from drivers.cia402.statemachine import COMMANDED_MODES, decode_statusword

EDS_PATH = Path(__file__).resolve().parents[2] / "config" / "can" / "cia402_cst.eds"
EDS_MAX_BYTES = 1 << 22  # an EDS longer than this is refused unread (vendors' run to ~1 MB)

NMT_ID = 0x000
SYNC_ID = 0x080
EMCY_BASE = 0x080
TPDO1_BASE = 0x180
RPDO1_BASE = 0x200
TPDO2_BASE = 0x280
RPDO2_BASE = 0x300
SDO_RESPONSE_BASE = 0x580
SDO_REQUEST_BASE = 0x600
HEARTBEAT_BASE = 0x700

# object dictionary indices used by the driver (sub-index 0 unless noted)
DEVICE_TYPE = 0x1000
ERROR_REGISTER = 0x1001
COB_ID_SYNC = 0x1005
CONSUMER_HEARTBEAT = 0x1016  # sub k: node << 16 | time (ms)
PRODUCER_HEARTBEAT = 0x1017
RPDO_DEADLINE_SUB = 5  # 0x1400:05 event timer = RPDO deadline monitoring (ms)
PDO_INVALID = 0x8000_0000  # COB-ID bit 31: the PDO does not exist (CiA 301)
ERROR_CODE = 0x603F
ABORT_CONNECTION_OPTION = 0x6007  # 402: reaction to a lost heartbeat / RPDO deadline
QUICK_STOP_OPTION_CODE = 0x605A
CONTROLWORD = 0x6040
STATUSWORD = 0x6041
MODE_OF_OPERATION = 0x6060
MODE_DISPLAY = 0x6061
POSITION_ACTUAL = 0x6064
VELOCITY_ACTUAL = 0x606C
TARGET_TORQUE = 0x6071
MAX_TORQUE = 0x6072
RATED_TORQUE = 0x6076  # mN·m
TORQUE_ACTUAL = 0x6077  # per mille of rated torque
TARGET_POSITION = 0x607A
SUPPORTED_MODES = 0x6502
MANUFACTURER_OBJECTS = range(0x2000, 0x6000)  # CiA 301: manufacturer-specific area

# 0x6007 abort connection option codes, 0x605A quick stop option codes (CiA 402)
ABORT_QUICK_STOP = 3  # abort connection -> "quick stop" command
QUICK_STOP_HOLD = range(5, 9)  # 5..8: stop, then stay in QUICK STOP ACTIVE (holding)
QUICK_STOP_HOLD_CODE = 6  # stop on the quick stop ramp, stay in QUICK STOP ACTIVE

DEVICE_PROFILE_402 = 402
I16_MIN, I16_MAX = -0x8000, 0x7FFF
I32_MIN, I32_MAX = -0x8000_0000, 0x7FFF_FFFF


class Cia402FrameError(FrameError):
    """A malformed CANopen frame; `reason` is a short category for the counters."""

    def __init__(self, can_id: int, reason: str, detail: str) -> None:
        super().__init__(f"frame 0x{can_id:03X}: {reason}: {detail}")
        self.reason = reason


class NmtCommand(enum.IntEnum):
    START = 0x01
    STOP = 0x02
    ENTER_PRE_OPERATIONAL = 0x80
    RESET_NODE = 0x81
    RESET_COMMUNICATION = 0x82


class NmtState(enum.IntEnum):
    BOOT_UP = 0x00
    STOPPED = 0x04
    OPERATIONAL = 0x05
    PRE_OPERATIONAL = 0x7F


_NMT_COMMANDS = frozenset(c.value for c in NmtCommand)
_NMT_STATES: dict[int, NmtState] = {s.value: s for s in NmtState}


@dataclass(frozen=True)
class PdoEntry:
    """One mapped object: the 0x16xx/0x1Axx mapping value is index << 16 | sub << 8 | bits."""

    index: int
    subindex: int
    bits: int

    @property
    def mapping(self) -> int:
        return self.index << 16 | self.subindex << 8 | self.bits


DUMMIES = range(0x0002, 0x0008)  # CiA 301 data-type objects usable as dummy mapping entries


@dataclass(frozen=True)
class PdoLayout:
    """One PDO: where the EDS describes it and the struct that codes it.

    A shared RPDO (`slots` > 1) is one frame for several drives on a bus, all at COB-ID
    `cob`: `entries` are one drive's objects, the frame holds `slots` of them in turn, and
    drive k maps `dummies` (CiA 301 dummy entries, the same sizes) over the others' bytes
    (`mapped(k)`).  `struct` codes the whole frame; `inhibit` is a TPDO's 0x18xx:03 (in
    100 us)."""

    name: str
    cob_base: int
    comm_index: int
    map_index: int
    transmission_type: int
    entries: tuple[PdoEntry, ...]
    struct: struct.Struct
    cob: int | None = None  # the COB-ID of every drive (None: cob_base + node id)
    slots: int = 1
    dummies: tuple[PdoEntry, ...] = ()
    inhibit: int = 0

    def cob_id(self, node: int) -> int:
        return self.cob_base + node if self.cob is None else self.cob

    @property
    def on_sync(self) -> bool:
        """A TPDO sent on SYNC (transmission type 1..240), not on an event."""
        return 1 <= self.transmission_type <= 240

    def mapped(self, slot: int = 0) -> tuple[PdoEntry, ...]:
        """The mapping of the drive that fills `slot` (dummies over the other slots)."""
        if self.slots == 1:
            return self.entries
        return self.dummies * slot + self.entries + self.dummies * (self.slots - 1 - slot)

    @property
    def receive(self) -> bool:
        """True for an RPDO (the drive receives it)."""
        return self.comm_index < 0x1800

    def mapping_procedure(self, node: int, slot: int = 0) -> tuple[tuple[int, int, int], ...]:
        """The (index, sub, value) writes that set this PDO in drive `node` (filling
        `slot` of a shared one) by the CiA 301 procedure: COB-ID bit 31 set, transmission
        type (and a TPDO's inhibit time), sub0 = 0, entries, sub0, COB-ID valid again."""
        comm, mapping, cob = self.comm_index, self.map_index, self.cob_id(node)
        mapped = self.mapped(slot)
        entries = tuple((mapping, k + 1, e.mapping) for k, e in enumerate(mapped))
        inhibit = ((comm, 3, self.inhibit),) if self.inhibit else ()
        return (
            (comm, 1, cob | PDO_INVALID),
            (comm, 2, self.transmission_type),
            *inhibit,
            (mapping, 0, 0),
            *entries,
            (mapping, 0, len(mapped)),
            (comm, 1, cob),
        )


_PDO_BASES = {0x1400: RPDO1_BASE, 0x1800: TPDO1_BASE}


def pdo_layout(
    od: ObjectDictionary,
    receive: bool,
    number: int,
    objects: Sequence[tuple[int, int]],
    transmission_type: int,
) -> PdoLayout:
    """RPDO or TPDO `number` (1..4, the predefined connection set's COB-IDs) mapping
    `objects` (index, sub) with the EDS's data types; KeyError or ValueError naming the
    object the EDS lacks or whose type no PDO field can carry."""
    if not 1 <= number <= 4:
        raise ValueError(f"PDO number {number}: only 1..4 have predefined COB-IDs")
    comm = (0x1400 if receive else 0x1800) + number - 1
    entries, fields = [], ""
    for index, sub in objects:
        var = od_variable(od, index, sub)
        form = ODVariable.STRUCT_TYPES.get(var.data_type)
        if form is None:
            raise ValueError(f"object 0x{index:04X}:{sub:02X} ({var.name}) has no PDO field type")
        entries.append(PdoEntry(index, sub, len(var)))
        fields += form.format.lstrip("<").translate(_SAME_SIZE)
    cob_base = _PDO_BASES[comm & 0xFC00] + 0x100 * (number - 1)
    name = f"{'R' if receive else 'T'}PDO{number}"
    return PdoLayout(
        name,
        cob_base,
        comm,
        comm + 0x200,
        transmission_type,
        tuple(entries),
        struct.Struct("<" + fields),
    )


RPDO1 = PdoLayout(
    "RPDO1",
    RPDO1_BASE,
    0x1400,
    0x1600,
    255,
    (
        PdoEntry(CONTROLWORD, 0, 16),
        PdoEntry(TARGET_TORQUE, 0, 16),
        PdoEntry(MODE_OF_OPERATION, 0, 8),
    ),
    struct.Struct("<Hhb"),
)
RPDO2 = PdoLayout(
    "RPDO2",
    RPDO2_BASE,
    0x1401,
    0x1601,
    255,
    (
        PdoEntry(CONTROLWORD, 0, 16),
        PdoEntry(TARGET_POSITION, 0, 32),
        PdoEntry(MODE_OF_OPERATION, 0, 8),
    ),
    struct.Struct("<Hib"),
)
TPDO1 = PdoLayout(
    "TPDO1",
    TPDO1_BASE,
    0x1800,
    0x1A00,
    1,
    (PdoEntry(STATUSWORD, 0, 16), PdoEntry(POSITION_ACTUAL, 0, 32), PdoEntry(MODE_DISPLAY, 0, 8)),
    struct.Struct("<Hib"),
)
TPDO2 = PdoLayout(
    "TPDO2", TPDO2_BASE, 0x1801, 0x1A01, 1, (PdoEntry(VELOCITY_ACTUAL, 0, 32),), struct.Struct("<i")
)
PDO_LAYOUTS = (RPDO1, RPDO2, TPDO1, TPDO2)

_SAME_SIZE = str.maketrans("lL", "iI")  # canopen codes 32-bit integers as l/L
_RPDO1, _RPDO2, _TPDO1, _TPDO2 = RPDO1.struct, RPDO2.struct, TPDO1.struct, TPDO2.struct
_RPDO1_SIZE, _RPDO2_SIZE, _TPDO1_SIZE, _TPDO2_SIZE = (p.struct.size for p in PDO_LAYOUTS)
_EMCY = struct.Struct("<HB5s")
_NMT = struct.Struct("<BB")
_SDO = struct.Struct("<BHB4s")
_SDO_HEAD = struct.Struct("<BHB")
_U32 = struct.Struct("<L")


message = data_frame  # a standard-id data frame (drivers.base)


def _length(can_id: int, data: bytes | bytearray, size: int, what: str) -> None:
    if len(data) != size:
        raise Cia402FrameError(can_id, f"{what} length", f"{len(data)} bytes, {what} has {size}")


# -- NMT, SYNC, heartbeat ---------------------------------------------------------------


def encode_nmt(command: NmtCommand, node: int) -> can.Message:
    """NMT command to `node` (0: every node)."""
    return message(NMT_ID, _NMT.pack(command, node))


def decode_nmt(data: bytes | bytearray) -> tuple[NmtCommand, int]:
    _length(NMT_ID, data, 2, "NMT")
    command, node = _NMT.unpack(data)
    if command not in _NMT_COMMANDS:
        raise Cia402FrameError(NMT_ID, "NMT command", f"0x{command:02X} is not an NMT command")
    if node > 127:
        raise Cia402FrameError(NMT_ID, "NMT node", f"node id {node} is above 127")
    return NmtCommand(command), node


def encode_sync() -> can.Message:
    return message(SYNC_ID)


def is_sync(msg: can.Message) -> bool:
    """Whether `msg` is a SYNC by its id (standard, 0x080); its data are decode_sync's."""
    return msg.arbitration_id == SYNC_ID and not msg.is_extended_id


def decode_sync(data: bytes | bytearray) -> None:
    """A SYNC has no data or a 1-byte counter (1..240)."""
    if len(data) > 1:
        raise Cia402FrameError(SYNC_ID, "SYNC length", f"{len(data)} bytes, SYNC has 0 or 1")
    if data and not 1 <= data[0] <= 240:
        raise Cia402FrameError(SYNC_ID, "SYNC counter", f"{data[0]} is outside 1..240")


def encode_heartbeat(node: int, state: NmtState) -> can.Message:
    return message(HEARTBEAT_BASE + node, bytes((state,)))


def decode_heartbeat(can_id: int, data: bytes | bytearray) -> NmtState:
    _length(can_id, data, 1, "heartbeat")
    state = _NMT_STATES.get(data[0])
    if state is None:
        raise Cia402FrameError(can_id, "heartbeat state", f"0x{data[0]:02X} is no NMT state")
    return state


# -- PDOs (hot path) ---------------------------------------------------------------------


def encode_rpdo1(node: int, controlword: int, torque: int, mode: int) -> can.Message:
    """Controlword, target torque (per mille of rated torque), mode of operation."""
    return can.Message(
        arbitration_id=RPDO1_BASE + node,
        data=_RPDO1.pack(controlword, torque, mode),
        is_extended_id=False,
    )


def decode_rpdo1(can_id: int, data: bytes | bytearray) -> tuple[int, int, int]:
    if len(data) != _RPDO1_SIZE:
        _length(can_id, data, _RPDO1_SIZE, "RPDO1")
    controlword, torque, mode = _RPDO1.unpack(data)
    if mode not in COMMANDED_MODES:
        raise Cia402FrameError(can_id, "mode of operation", f"{mode} is not 0, 8 or 10")
    return controlword, torque, mode


def encode_rpdo2(node: int, controlword: int, position: int, mode: int) -> can.Message:
    """Controlword, target position (increments), mode of operation."""
    return can.Message(
        arbitration_id=RPDO2_BASE + node,
        data=_RPDO2.pack(controlword, position, mode),
        is_extended_id=False,
    )


def decode_rpdo2(can_id: int, data: bytes | bytearray) -> tuple[int, int, int]:
    if len(data) != _RPDO2_SIZE:
        _length(can_id, data, _RPDO2_SIZE, "RPDO2")
    controlword, position, mode = _RPDO2.unpack(data)
    if mode not in COMMANDED_MODES:
        raise Cia402FrameError(can_id, "mode of operation", f"{mode} is not 0, 8 or 10")
    return controlword, position, mode


def encode_tpdo1(node: int, statusword: int, position: int, mode: int) -> can.Message:
    """Statusword, position actual (increments), mode of operation display."""
    return can.Message(
        arbitration_id=TPDO1_BASE + node,
        data=_TPDO1.pack(statusword, position, mode),
        is_extended_id=False,
    )


def decode_tpdo1(can_id: int, data: bytes | bytearray) -> tuple[int, int, int]:
    if len(data) != _TPDO1_SIZE:
        _length(can_id, data, _TPDO1_SIZE, "TPDO1")
    statusword, position, mode = _TPDO1.unpack(data)
    if decode_statusword(statusword) is None:
        raise Cia402FrameError(can_id, "statusword pattern", f"0x{statusword:04X} is no 402 state")
    return statusword, position, mode


def encode_tpdo2(node: int, velocity: int) -> can.Message:
    """Velocity actual (increments/s)."""
    return can.Message(
        arbitration_id=TPDO2_BASE + node, data=_TPDO2.pack(velocity), is_extended_id=False
    )


def decode_tpdo2(can_id: int, data: bytes | bytearray) -> int:
    if len(data) != _TPDO2_SIZE:
        _length(can_id, data, _TPDO2_SIZE, "TPDO2")
    return _TPDO2.unpack(data)[0]


# -- EMCY --------------------------------------------------------------------------------

EMCY_TEXTS: dict[int, str] = {
    0x0000: "error reset / no error",
    0x1000: "generic error",
    0x2310: "continuous overcurrent",
    0x2320: "short circuit or earth leakage at the motor output",
    0x3210: "DC link overvoltage",
    0x3220: "DC link undervoltage",
    0x4310: "drive overtemperature",
    0x6320: "parameter error",
    0x7121: "motor blocked",
    0x7305: "position encoder fault",
    0x8110: "CAN overrun, frames lost",
    0x8120: "CAN error passive",
    0x8130: "life guard or heartbeat error",
    0x8140: "recovered from bus off",
    0x8210: "PDO not processed: length error",
    0x8220: "PDO length exceeded",
    0x8250: "RPDO timeout",
    0x8611: "following error",
}

HEARTBEAT_LOST = 0x8130  # EMCY: a consumed heartbeat (the host's: 0x1016) stopped

# CiA 301 error register 0x1001 bits
REGISTER_GENERIC = 0x01
_REGISTER_BY_CLASS = {0x2: 0x02, 0x3: 0x04, 0x4: 0x08}  # current, voltage, temperature
REGISTER_COMMUNICATION = 0x10
REGISTER_PROFILE = 0x20


def error_register(code: int) -> int:
    """The 0x1001 error register a drive reports with EMCY `code` (0 for a reset)."""
    if code == 0:
        return 0
    register = REGISTER_GENERIC | _REGISTER_BY_CLASS.get(code >> 12, 0)
    if code & 0xFF00 in (0x8100, 0x8200):
        register |= REGISTER_COMMUNICATION
    elif code & 0xFF00 == 0x8600:
        register |= REGISTER_PROFILE
    return register


# CiA 301 error code classes, by the code's top hex digit
_EMCY_CLASSES = (
    "error reset",
    "generic error",
    "current error",
    "voltage error",
    "temperature error",
    "device hardware error",
    "device software error",
    "additional modules error",
    "monitoring error",
    "external error",
    "unknown error",
    "unknown error",
    "unknown error",
    "unknown error",
    "unknown error",
    "additional functions error",
)


def emcy_text(code: int) -> str:
    """Readable text for an EMCY error code: exact for common codes, else its class."""
    if code & 0xFF00 == 0xFF00:
        text = EMCY_TEXTS.get(code, "device-specific error")
    else:
        text = EMCY_TEXTS.get(code) or _EMCY_CLASSES[code >> 12 & 0xF]
    return f"EMCY 0x{code:04X}: {text}"


def encode_emcy(node: int, code: int, register: int, manufacturer: bytes = b"") -> can.Message:
    return message(EMCY_BASE + node, _EMCY.pack(code, register, manufacturer))


def decode_emcy(can_id: int, data: bytes | bytearray) -> tuple[int, int, bytes]:
    """(error code, error register, manufacturer bytes)."""
    _length(can_id, data, 8, "EMCY")
    return _EMCY.unpack(data)


# -- SDO: expedited and segmented transfers ------------------------------------------------
# canopen's SdoClient/SdoServer block on threads and a Network, not a sans-IO Link, so
# the transfers are coded here (command specifiers as in CiA 301; no block transfer).


class SdoKind(enum.Enum):
    UPLOAD = "upload"  # initiate: request = read; response = expedited data or a size
    DOWNLOAD = "download"  # initiate: request = expedited data or a size; response = ok
    SEGMENT = "segment"  # download segment request / upload segment response: data
    SEGMENT_ASK = "segment ask"  # upload segment request / download segment response
    ABORT = "abort"
    UNSUPPORTED = "unsupported"  # block transfers


@dataclass(frozen=True)
class Sdo:
    """One decoded SDO frame (request or response).  An initiate frame of a segmented
    transfer has `size` (bytes to come, None if not indicated) and no data; a segment has
    `toggle` and `last`.  Segments name no object: index and subindex are 0.  `size` is
    -1 for a segmented transfer that does not indicate its size.  An expedited frame
    without its size (CiA 301: e=1, s=0) has `sized` False and all 4 data bytes: the
    object's own size says how many of them count."""

    kind: SdoKind
    index: int
    subindex: int
    data: bytes = b""  # expedited payload or segment data
    abort_code: int = 0
    size: int | None = None
    toggle: int = 0
    last: bool = False
    sized: bool = True

    @property
    def segmented(self) -> bool:
        """An initiate frame that opens a segmented transfer."""
        return self.kind in (SdoKind.UPLOAD, SdoKind.DOWNLOAD) and self.size is not None


ABORT_TOGGLE = 0x0503_0000
ABORT_UNSUPPORTED_COMMAND = 0x0504_0001
ABORT_WRITE_READ_ONLY = 0x0601_0002
ABORT_READ_WRITE_ONLY = 0x0601_0001
ABORT_NOT_IN_OD = 0x0602_0000
ABORT_NOT_MAPPABLE = 0x0604_0041
ABORT_PDO_TOO_LONG = 0x0604_0042
ABORT_LENGTH = 0x0607_0010
ABORT_NO_SUBINDEX = 0x0609_0011
ABORT_VALUE_RANGE = 0x0609_0030
ABORT_VALUE_HIGH = 0x0609_0031
ABORT_VALUE_LOW = 0x0609_0032
ABORT_DEVICE_STATE = 0x0800_0022
ABORT_NO_DATA = 0x0800_0024


def abort_text(code: int) -> str:
    """An abort code with its CiA 301 meaning."""
    return f"0x{code:08X} {SdoAbortedError.CODES.get(code, 'unknown abort code')}"


def encode_sdo_upload_request(node: int, index: int, subindex: int) -> can.Message:
    return message(SDO_REQUEST_BASE + node, _SDO.pack(0x40, index, subindex, b""))


def encode_sdo_download_request(node: int, index: int, subindex: int, data: bytes) -> can.Message:
    """Expedited write of 1..4 bytes."""
    if not 1 <= len(data) <= 4:
        raise ValueError(f"an expedited SDO carries 1..4 bytes, not {len(data)}")
    command = 0x23 | (4 - len(data)) << 2
    return message(SDO_REQUEST_BASE + node, _SDO.pack(command, index, subindex, data))


def encode_sdo_download_initiate(node: int, index: int, subindex: int, size: int) -> can.Message:
    """Opens a segmented write of `size` bytes (size indicated)."""
    return message(SDO_REQUEST_BASE + node, _SDO.pack(0x21, index, subindex, _U32.pack(size)))


def encode_sdo_upload_response(node: int, index: int, subindex: int, data: bytes) -> can.Message:
    """Expedited answer (1..4 bytes), or the initiate answer of a segmented upload (with
    the size) when `data` is longer."""
    if len(data) > 4:
        return message(
            SDO_RESPONSE_BASE + node, _SDO.pack(0x41, index, subindex, _U32.pack(len(data)))
        )
    command = 0x43 | (4 - len(data)) << 2
    return message(SDO_RESPONSE_BASE + node, _SDO.pack(command, index, subindex, data))


def encode_sdo_download_response(node: int, index: int, subindex: int) -> can.Message:
    return message(SDO_RESPONSE_BASE + node, _SDO.pack(0x60, index, subindex, b""))


def encode_sdo_segment(
    node: int, toggle: int, data: bytes, last: bool, *, server: bool
) -> can.Message:
    """A segment of 0..7 bytes: download segment (client) or upload segment (server)."""
    if len(data) > 7:
        raise ValueError(f"an SDO segment carries 0..7 bytes, not {len(data)}")
    command = toggle << 4 | (7 - len(data)) << 1 | int(last)
    base = SDO_RESPONSE_BASE if server else SDO_REQUEST_BASE
    return message(base + node, bytes((command,)) + data.ljust(7, b"\0"))


def encode_sdo_segment_ask(node: int, toggle: int, *, server: bool) -> can.Message:
    """Upload segment request (client) or download segment confirmation (server)."""
    if server:
        return message(SDO_RESPONSE_BASE + node, bytes((0x20 | toggle << 4,)) + bytes(7))
    return message(SDO_REQUEST_BASE + node, bytes((0x60 | toggle << 4,)) + bytes(7))


def encode_sdo_abort(
    node: int, index: int, subindex: int, code: int, *, server: bool
) -> can.Message:
    base = SDO_RESPONSE_BASE if server else SDO_REQUEST_BASE
    return message(base + node, _SDO.pack(0x80, index, subindex, _U32.pack(code)))


def _initiate(kind: SdoKind, data: bytes | bytearray) -> Sdo:
    """An initiate frame (upload response or download request): expedited or sized."""
    command, index, subindex = _SDO_HEAD.unpack_from(data)
    if command & 0x02:  # expedited
        sized = bool(command & 0x01)
        size = 4 - (command >> 2 & 3) if sized else 4
        return Sdo(kind, index, subindex, bytes(data[4 : 4 + size]), sized=sized)
    size = _U32.unpack_from(data, 4)[0] if command & 0x01 else None
    return Sdo(kind, index, subindex, size=size if size is not None else -1)


def _segment(data: bytes | bytearray) -> Sdo:
    command = data[0]
    return Sdo(
        SdoKind.SEGMENT,
        0,
        0,
        bytes(data[1 : 8 - (command >> 1 & 7)]),
        toggle=command >> 4 & 1,
        last=bool(command & 1),
    )


def _abort(data: bytes | bytearray) -> Sdo:
    _, index, subindex = _SDO_HEAD.unpack_from(data)
    return Sdo(SdoKind.ABORT, index, subindex, abort_code=_U32.unpack_from(data, 4)[0])


def decode_sdo_request(can_id: int, data: bytes | bytearray) -> Sdo:
    """A client request as the server sees it."""
    _length(can_id, data, 8, "SDO")
    ccs = data[0] >> 5
    if ccs == 0:
        return _segment(data)
    if ccs == 1:
        return _initiate(SdoKind.DOWNLOAD, data)
    if ccs == 2:
        _, index, subindex = _SDO_HEAD.unpack_from(data)
        return Sdo(SdoKind.UPLOAD, index, subindex)
    if ccs == 3:
        return Sdo(SdoKind.SEGMENT_ASK, 0, 0, toggle=data[0] >> 4 & 1)
    if ccs == 4:
        return _abort(data)
    _, index, subindex = _SDO_HEAD.unpack_from(data)
    return Sdo(SdoKind.UNSUPPORTED, index, subindex)


def decode_sdo_response(can_id: int, data: bytes | bytearray) -> Sdo:
    """A server response as the client sees it."""
    _length(can_id, data, 8, "SDO")
    scs = data[0] >> 5
    if scs == 0:
        return _segment(data)
    if scs == 1:
        return Sdo(SdoKind.SEGMENT_ASK, 0, 0, toggle=data[0] >> 4 & 1)
    if scs == 2:
        return _initiate(SdoKind.UPLOAD, data)
    if scs == 3:
        _, index, subindex = _SDO_HEAD.unpack_from(data)
        return Sdo(SdoKind.DOWNLOAD, index, subindex)
    if scs == 4:
        return _abort(data)
    _, index, subindex = _SDO_HEAD.unpack_from(data)
    return Sdo(SdoKind.UNSUPPORTED, index, subindex)


# -- the EDS -----------------------------------------------------------------------------


@functools.lru_cache(maxsize=256)
def load_eds(path: str | Path, node_id: int) -> ObjectDictionary:
    """The object dictionary of `path` for `node_id` (parsed by canopen; cached, so
    treat it as read-only: the simulated drive keeps its values elsewhere).  The file is
    read as every file the daemon is given (cdpr.trusted_file): a regular file of at
    most EDS_MAX_BYTES, never a FIFO canopen would wait on; UnreadableFileError (a
    ValueError) otherwise."""
    text = read_trusted(path, EDS_MAX_BYTES).decode("utf-8", errors="replace")
    source = io.StringIO(text)
    source.name = str(path)  # canopen tells the format by the name's suffix
    return import_od(source, node_id)


def od_variable(od: ObjectDictionary, index: int, subindex: int = 0) -> ODVariable:
    """The variable at index:subindex; KeyError naming it if the EDS lacks it."""
    try:
        entry = od[index]
        if isinstance(entry, ODRecord | ODArray):
            entry = entry[subindex]
        elif subindex:
            raise KeyError(subindex)
    except KeyError:
        raise KeyError(f"object 0x{index:04X}:{subindex:02X} is not in the EDS") from None
    return entry


def od_value(var: ODVariable) -> int | float | str | bytes | None:
    """The EDS value of a variable: ParameterValue if given, else DefaultValue."""
    return var.value if var.value is not None else var.default
