"""Confirm, drive by drive, that a CiA 402 brake holds, whatever the drive's NMT state.

The host's brake is an RPDO (drivers.cia402.host), and a CiA 301 node that is STOPPED or
PRE-OPERATIONAL processes no PDO: another node's NMT stop / enter pre-operational /
reset communication leaves a drive in OPERATION ENABLED in torque mode at its last
torque, while the host believes it braked.  So after every brake the host asks each drive
by SDO (served in PRE-OPERATIONAL and OPERATIONAL, whatever the PDO configuration: a
reset communication puts the mapping back to the EDS's) what it does, and acts where the
answer is not a hold:

1. read the statusword 0x6041 (and, in OPERATION ENABLED, the mode display 0x6061);
2. a hold (below) is confirmed; a drive still producing torque gets controlword
   QUICK STOP by SDO (0x605A was set to "stay in QUICK STOP ACTIVE", a hold, at start-up;
   `disable operation` instead where the brake is the holding brake), then back to 1;
3. no answer within `timeout`: the drive is STOPPED (no SDO there) or off the bus; it
   gets NMT enter-pre-operational (which keeps its 402 state and its configuration) and
   back to 1; a drive that still does not answer is reported unconfirmed and asked
   again every `retry` seconds while the brake stands.

A hold is: OPERATION ENABLED in cyclic synchronous position (mode 8, the hold RPDO
acted); QUICK STOP ACTIVE; or the power stage off with the drive's latched hold reaction
(statusword bit 14, drivers.cia402.statemachine) or a holding brake fitted.  A drive in
OPERATION ENABLED in any other mode is driven to a hold (2); a drive whose power stage is
off with nothing holding its cable cannot be helped by SDO: it is reported.

Sans-IO like the driver: `frames(now)` returns what to send (the driver's keepalive
calls it every cycle while braked), `receive` takes each SDO answer.  One request per
drive at a time; the driver disarms it before any sequence of its own uses SDO.
"""

from __future__ import annotations

import enum
import math
from collections.abc import Sequence

import can

from drivers.base import BrakeMode, NodeStatus
from drivers.cia402.codec import (
    CONTROLWORD,
    MODE_DISPLAY,
    STATUSWORD,
    NmtCommand,
    SdoKind,
    abort_text,
    decode_sdo_response,
    encode_nmt,
    encode_sdo_download_request,
    encode_sdo_upload_request,
)
from drivers.cia402.statemachine import (
    DISABLE_OPERATION,
    MODE_CSP,
    STATUS_HOLD,
    Command,
    State,
    decode_statusword,
)


class _Step(enum.Enum):
    STATUS = "statusword read"
    MODE = "mode display read"
    ACT = "controlword write"
    DONE = "confirmed"
    WAIT = "waiting to ask again"


class HoldCheck:
    """The brake confirmation of the drives `nodes` (cable order).  `status[i].held`
    says what is known: None while asking (or no brake stands), True once the drive's
    own answer shows a hold, False with `status[i].hold_problem` naming why not."""

    def __init__(
        self,
        nodes: Sequence[int],
        status: Sequence[NodeStatus],
        has_holding_brake: bool,
        *,
        timeout: float,
        retry: float = 0.5,
    ) -> None:
        self.nodes = list(nodes)
        self.status = status
        self.has_holding_brake = has_holding_brake
        self.timeout = timeout
        self.retry = retry
        n = len(self.nodes)
        self._mode = BrakeMode.POSITION_HOLD
        self._armed = False
        self._step = [_Step.DONE] * n
        self._due = [math.inf] * n  # the answer's deadline, or when to ask again
        self._asked = [(0, 0)] * n  # (index, subindex) of the request in flight
        self._statusword = [0] * n
        self._nudged = [False] * n  # NMT pre-operational sent since the last answer
        self._acts = [0] * n  # controlword writes since the brake
        self._outbox: list[can.Message | None] = [None] * n  # the next request, unsent
        self._now = 0.0  # the time of the latest frames()

    @property
    def armed(self) -> bool:
        return self._armed

    def arm(self, mode: BrakeMode) -> None:
        """A brake went out: check every drive from the start."""
        self._mode, self._armed = mode, True
        for i in range(len(self.nodes)):
            self._step[i], self._due[i], self._acts[i] = _Step.WAIT, -math.inf, 0
            self._nudged[i], self._outbox[i] = False, None
            self.status[i].held, self.status[i].hold_problem = None, None

    def disarm(self) -> None:
        """No brake stands (torque commands, an enable or a reset of the host's own)."""
        self._armed = False
        for st in self.status:
            st.held, st.hold_problem = None, None

    def pause(self) -> None:
        """A sequence of the host's own uses SDO now: forget the requests in flight (their
        answers may go to it); every drive not confirmed is asked afresh afterwards."""
        for i, step in enumerate(self._step):
            if step is not _Step.DONE:
                self._step[i], self._due[i] = _Step.WAIT, -math.inf
                self._nudged[i], self._outbox[i] = False, None

    def frames(self, now: float) -> list[can.Message]:
        """What is due at `now`: the requests that answers made due, first questions and
        retries, and the NMT nudge of a drive that did not answer in time."""
        if not self._armed:
            return []
        self._now = now
        out: list[can.Message] = []
        for i, step in enumerate(self._step):
            request = self._outbox[i]
            if request is not None:
                self._outbox[i], self._due[i] = None, now + self.timeout
                out.append(request)
                continue
            if step is _Step.DONE or now < self._due[i]:
                continue
            if step is not _Step.WAIT:  # no answer in time
                node = self.nodes[i]
                if self._nudged[i]:
                    self._unconfirmed(
                        i,
                        f"node {node}: no answer to the {step.value} within "
                        f"{self.timeout * 1e3:.0f} ms, also after NMT pre-operational "
                        "(off the bus, or deaf to NMT)",
                    )
                    continue
                self._nudged[i] = True
                out.append(encode_nmt(NmtCommand.ENTER_PRE_OPERATIONAL, node))
            self._ask(i, STATUSWORD, _Step.STATUS)
            self._outbox[i], self._due[i] = None, now + self.timeout
            out.append(encode_sdo_upload_request(self.nodes[i], STATUSWORD, 0))
        return out

    def receive(self, i: int, can_id: int, data: bytes | bytearray) -> None:
        """An SDO answer from drive i (any; those to no request of ours are ignored).
        Raises Cia402FrameError for a malformed frame, as the driver's other decoders."""
        step = self._step[i]
        if not self._armed or step in (_Step.DONE, _Step.WAIT) or self._outbox[i] is not None:
            return
        sdo = decode_sdo_response(can_id, data)
        if (sdo.index, sdo.subindex) != self._asked[i]:
            return  # a segment, or an answer to another client
        self._nudged[i] = False
        if sdo.kind is SdoKind.ABORT:
            node = self.nodes[i]
            self._unconfirmed(i, f"node {node}: {step.value} aborted: {abort_text(sdo.abort_code)}")
        elif step is _Step.ACT:
            if sdo.kind is SdoKind.DOWNLOAD:
                self._ask(i, STATUSWORD, _Step.STATUS)
        elif sdo.kind is SdoKind.UPLOAD and not sdo.segmented and sdo.data:
            value = int.from_bytes(sdo.data[:2], "little")
            if step is _Step.STATUS:
                self._statusword[i] = value
                if decode_statusword(value) is State.OPERATION_ENABLED:
                    self._ask(i, MODE_DISPLAY, _Step.MODE)
                    return
                self._judge(i, value, None)
            else:  # the mode display, a signed byte
                mode = value & 0xFF
                self._judge(i, self._statusword[i], mode - 256 if mode > 127 else mode)

    def _judge(self, i: int, statusword: int, mode: int | None) -> None:
        state = decode_statusword(statusword)
        node = self.nodes[i]
        if state is State.QUICK_STOP_ACTIVE or (
            state is State.OPERATION_ENABLED and mode == MODE_CSP
        ):
            self._confirmed(i)
        elif state is State.OPERATION_ENABLED:
            if self._acts[i] >= 2:
                self._unconfirmed(
                    i, f"node {node}: still in operation enabled, mode {mode}, after a stop"
                )
                return
            self._acts[i] += 1
            by_brake = self._mode is BrakeMode.HOLDING_BRAKE and self.has_holding_brake
            command = DISABLE_OPERATION if by_brake else Command.QUICK_STOP
            data = command.value.to_bytes(2, "little")
            self._step[i], self._asked[i], self._due[i] = _Step.ACT, (CONTROLWORD, 0), math.inf
            self._outbox[i] = encode_sdo_download_request(node, CONTROLWORD, 0, data)
        elif statusword & STATUS_HOLD or self.has_holding_brake:
            self._confirmed(i)
        else:
            name = "no 402 state" if state is None else state.name
            self._unconfirmed(
                i,
                f"node {node}: {name} (statusword 0x{statusword:04X}): power stage off, no "
                "latched hold and no holding brake: nothing holds its cable",
            )

    def _ask(self, i: int, index: int, step: _Step) -> None:
        """Send a read of `index` at the next frames()."""
        self._step[i], self._asked[i], self._due[i] = step, (index, 0), math.inf
        self._outbox[i] = encode_sdo_upload_request(self.nodes[i], index, 0)

    def _confirmed(self, i: int) -> None:
        self._step[i], self._due[i] = _Step.DONE, math.inf
        self.status[i].held, self.status[i].hold_problem = True, None

    def _unconfirmed(self, i: int, why: str) -> None:
        self._step[i], self._due[i] = _Step.WAIT, self._now + self.retry
        self._nudged[i], self._outbox[i] = False, None
        self.status[i].held, self.status[i].hold_problem = False, why
