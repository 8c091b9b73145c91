"""CiA 402 drives made of code the project did not write, for the conformance tests:
canopen's LocalNode with the vendor-style
tests/data/generic_servo_cia402.eds (its default mapping RPDO1 = controlword, TPDO1 =
statusword, no 0x2000/0x2001) is the SDO server (object dictionary, access and size
checks), the NMT slave, the heartbeat producer and the PDO codec.  `CanopenDrive` adds
only what canopen leaves to a drive's application: the 402 state machine on the
controlword, the PDO configuration taking effect at NMT start, TPDOs on SYNC and
event-driven ones on change, RPDO dummy entries skipped, and the consumer heartbeat
0x1016 with its 0x6007 / 0x605A reaction (`check_heartbeat`)."""

from __future__ import annotations

import contextlib
import struct
import time
from collections.abc import Callable
from contextlib import AbstractContextManager
from pathlib import Path

import canopen

VENDOR_EDS = Path(__file__).resolve().parent / "data" / "generic_servo_cia402.eds"

# statusword of each 402 state the slave reaches (CiA 402 table, bit 5 quick stop)
SWITCH_ON_DISABLED, READY, SWITCHED_ON, ENABLED, QUICK_STOP = 0x0240, 0x0221, 0x0223, 0x0227, 0x0207


def next_statusword(statusword: int, controlword: int) -> int:
    """The CiA 402 state machine's transitions the host uses (2, 3, 4, 5, 7, 9, 11, 12)."""
    if not controlword & 0x02:  # disable voltage
        return SWITCH_ON_DISABLED
    if not controlword & 0x04:  # quick stop
        return QUICK_STOP if statusword == ENABLED else SWITCH_ON_DISABLED
    command = controlword & 0x0F
    if command == 0x06:  # shutdown
        return READY
    if command == 0x07 and statusword in (READY, ENABLED):  # switch on / disable operation
        return SWITCHED_ON
    if command == 0x0F and statusword in (READY, SWITCHED_ON, ENABLED):  # enable operation
        return ENABLED
    return statusword


class CanopenDrive:
    """A CiA 402 drive made of canopen's LocalNode with the vendor EDS (module docstring)."""

    def __init__(self, network: canopen.Network, node_id: int, position: int) -> None:
        self.network = network
        self.node = canopen.LocalNode(node_id, str(VENDOR_EDS))
        network.add_node(self.node)
        self.store(0x6041, "<H", SWITCH_ON_DISABLED)
        self.store(0x6064, "<i", position)
        self.torques: list[int] = []  # target torques received while enabled in mode 10
        self.heard: float | None = None  # monotonic time of the consumed heartbeat
        self.lost: float | None = None  # when the consumer heartbeat expired
        self.sent: dict[int, bytes] = {}  # event-driven TPDO COB-ID -> the data last sent
        # entered around applying an RPDO: a power stage coupled to a plant
        # (tests/canopen_robot.py) takes its whole content at once, at its arrival
        self.rpdo_guard: Callable[[], AbstractContextManager] = contextlib.nullcontext
        self.node.add_write_callback(self._on_write)
        network.subscribe(0x000, self._on_nmt)
        network.subscribe(0x080, self.on_sync)
        self.node.nmt.state = "PRE-OPERATIONAL"

    def store(self, index: int, form: str, value: int) -> None:
        """Set an object as the drive's firmware would (no SDO, no access check)."""
        self.node.data_store.setdefault(index, {})[0] = struct.pack(form, value)

    def value(self, index: int, subindex: int = 0) -> int:
        """An object as the drive holds it (canopen decodes it with the EDS's type)."""
        entry = self.node.object_dictionary[index]
        var = entry if isinstance(entry, canopen.objectdictionary.ODVariable) else entry[subindex]
        return var.decode_raw(self.node.get_data(index, subindex))

    def _on_write(self, index: int, subindex: int, od, data: bytes) -> None:
        if index == 0x6040:
            controlword = struct.unpack("<H", data)[0]
            self.store(0x6041, "<H", next_statusword(self.value(0x6041), controlword))
            self.events()
        elif index == 0x6060 and data[0] != 0:  # 0: no change
            self.store(0x6061, "<b", struct.unpack("<b", data)[0])
            self.events()
        elif index == 0x6071 and self.value(0x6041) == ENABLED and self.value(0x6061) == 10:
            self.torques.append(struct.unpack("<h", data)[0])
        elif (index, subindex) == (0x1016, 1):
            producer = struct.unpack("<I", data)[0] >> 16 & 0x7F
            self.heard = None
            self.network.subscribe(0x700 + producer, self._on_heartbeat)

    def _on_heartbeat(self, can_id: int, data: bytearray, timestamp: float) -> None:
        self.heard = time.monotonic()

    def check_heartbeat(self, now: float) -> None:
        """The consumer heartbeat (armed by the first heartbeat heard): once it is older
        than 0x1016:01's time, the abort connection option 0x6007 (3: quick stop, which
        0x605A 5..8 ends holding in QUICK STOP ACTIVE; 2: disable voltage)."""
        timeout = (self.value(0x1016, 1) & 0xFFFF) / 1000.0
        if self.heard is None or self.lost is not None or not timeout:
            return
        if now - self.heard > timeout:
            self.lost = now
            option, statusword = self.value(0x6007), self.value(0x6041)
            if option == 3 and statusword == ENABLED and 5 <= self.value(0x605A) <= 8:
                self.store(0x6041, "<H", QUICK_STOP)
            elif option in (2, 3):
                self.store(0x6041, "<H", SWITCH_ON_DISABLED)
            self.events()

    def events(self, starting: bool = False) -> None:
        """The event-driven TPDOs (type 254/255) whose data changed, sent while
        operational (`starting`: at NMT start, which canopen's NMT slave may apply later)."""
        if not starting and self.node.nmt.state != "OPERATIONAL":
            return
        for pdo in self.node.tpdo.map.values():
            if pdo.enabled and pdo.trans_type in (254, 255):
                for var in pdo.map:
                    var.set_data(self.node.get_data(var.index, var.subindex))
                if self.sent.get(pdo.cob_id) != bytes(pdo.data):
                    self.sent[pdo.cob_id] = bytes(pdo.data)
                    pdo.transmit()

    def _on_nmt(self, can_id: int, data: bytearray, timestamp: float) -> None:
        """At NMT start the PDO configuration written by SDO takes effect."""
        if data[0] == 0x01 and data[1] in (0, self.node.id):
            self.node.tpdo.read()
            self.node.rpdo.read()
            for pdo in self.node.rpdo.map.values():
                if pdo.enabled and self._on_rpdo not in pdo.callbacks:
                    pdo.add_callback(self._on_rpdo)
            self.sent = {}
            self.events(starting=True)

    def _on_rpdo(self, pdo) -> None:
        """Mapped objects written in frame order (mode before the torque it is for), as
        one (`rpdo_guard`); a dummy entry (0x0002-0x0007) skips another drive's bytes.
        Only in OPERATIONAL (CiA 301: no PDO in STOPPED or PRE-OPERATIONAL), which
        canopen's PDO callbacks do not check."""
        if self.node.nmt.state != "OPERATIONAL":
            return
        with self.rpdo_guard():
            for var in sorted(pdo.map, key=lambda v: v.index != 0x6060):
                if var.index >= 0x1000:
                    self.node.set_data(var.index, var.subindex, var.get_data())

    def on_sync(self, can_id: int, data: bytearray, timestamp: float) -> None:
        """In OPERATIONAL, the SYNC-triggered TPDOs with the objects as they are now."""
        if self.node.nmt.state != "OPERATIONAL":
            return
        for pdo in self.node.tpdo.map.values():
            if pdo.enabled and pdo.trans_type is not None and 1 <= pdo.trans_type <= 240:
                for var in pdo.map:
                    var.set_data(self.node.get_data(var.index, var.subindex))
                pdo.transmit()
