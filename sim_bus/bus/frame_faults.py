"""Frame-level fault injection between a CAN bus and its users, for any drive protocol.

Rules (FrameFaultConfig) act on frames that match id/mask filters, in one direction
("rx": frames the bus user receives, "tx": frames it sends) or both:

- drop     a frame disappears (probability and/or every Nth matching frame);
- corrupt  data bits flipped and/or the DLC changed (the data cut or zero-padded to it);
- delay    a frame is held for a fixed time and released by `due(now)` (no threads:
           whoever runs the simulation calls it, e.g. once per step);
- error bursts  `count` error frames (can.Message(is_error_frame=True)) every `period`
           seconds, or on demand through `error_burst()`.

Order per frame: drop, then corrupt, then delay.  Error frames passing through are never
touched.  A node is selected protocol-independently with an id mask (CANopen node 5:
can_id 0x005, can_mask 0x07F; ODrive CANSimple node 3: can_id 0x060, can_mask 0x7E0).

Deterministic: every rule draws from its own random.Random seeded by (seed, rule name),
so the same traffic with the same seed gives the same faults, and switching one rule
does not change what the others do.  Faulted frames are new Message objects (frames are
immutable by convention, see sim_bus.bus.loopbus); passing frames are not copied.

FrameFaultInjector is the sans-IO core (the simulator may call it directly);
FaultyBus wraps a python-can bus with it.
"""

from __future__ import annotations

import heapq
import random
import time
from collections import Counter
from collections.abc import Callable
from typing import Annotated, Any, Literal

import can
from pydantic import Field, model_validator

from cdpr.description import PositiveFloat, StrictModel, validate_section

Direction = Literal["rx", "tx"]
RuleDirection = Literal["rx", "tx", "both"]
Probability = Annotated[float, Field(ge=0.0, le=1.0, allow_inf_nan=False)]
CanId = Annotated[int, Field(ge=0, le=0x1FFFFFFF)]

#: SocketCAN error class bits (linux/can/error.h): protocol violation | bus error.
CAN_ERR_PROT_BUSERROR = 0x08 | 0x80
RULE_KINDS = ("drop", "corrupt", "delay", "error_bursts")


class FrameMatch(StrictModel):
    """Matches when (frame id ^ can_id) & can_mask == 0 (and the id type, if given)."""

    can_id: CanId  # the id to match, under can_mask
    can_mask: CanId = 0x1FFFFFFF  # the id bits compared
    extended: bool | None = None  # true: 29-bit ids only; false: 11-bit only; null: either

    def matches(self, msg: can.Message) -> bool:
        if self.extended is not None and msg.is_extended_id != self.extended:
            return False
        return (msg.arbitration_id ^ self.can_id) & self.can_mask == 0


class _Rule(StrictModel):
    name: str | None = None  # unique; defaults to "<kind>[<index>]"
    enabled: bool = True  # false: off from the start (FrameFaultInjector.set_enabled switches it)
    direction: RuleDirection = "both"
    """rx: the frames the simulated drives receive, tx: those they send, or both."""
    match: tuple[FrameMatch, ...] = ()  # empty: every frame


class _Selective(_Rule):
    """Acts on every `every_nth` matching frame, and on others with `probability`."""

    probability: Probability = 0.0  # chance of acting on a matching frame every_nth leaves
    every_nth: Annotated[int, Field(ge=1)] | None = None
    """Act on every Nth matching frame (1: every one); null: by probability alone."""

    @model_validator(mode="after")
    def _selects_something(self) -> _Selective:
        if self.probability == 0.0 and self.every_nth is None:
            raise ValueError("the rule needs probability > 0 or every_nth (1: every frame)")
        return self


class DropRule(_Selective):
    pass


class CorruptRule(_Selective):
    flip_bits: Annotated[int, Field(ge=0, le=64)] = 1  # distinct data bits flipped per frame
    change_dlc: bool = False  # give the frame another DLC, its data cut or zero-padded to it

    @model_validator(mode="after")
    def _changes_something(self) -> CorruptRule:
        if self.flip_bits == 0 and not self.change_dlc:
            raise ValueError("a corrupt rule needs flip_bits > 0 or change_dlc: true")
        return self


class DelayRule(_Selective):
    delay: PositiveFloat  # seconds


class ErrorBurstRule(_Rule):
    period: PositiveFloat  # seconds between bursts
    count: Annotated[int, Field(ge=1, le=10_000)] = 1  # error frames per burst
    error_class: Annotated[int, Field(ge=0, le=0x1FFFFFFF)] = CAN_ERR_PROT_BUSERROR
    """The error frames' id: SocketCAN error class bits (default: protocol violation and
    bus error)."""


class FrameFaultConfig(StrictModel):
    seed: int = 0  # with each rule's name, seeds the rule's random draws
    drop: tuple[DropRule, ...] = ()  # rules that drop frames
    corrupt: tuple[CorruptRule, ...] = ()  # rules that corrupt frames
    delay: tuple[DelayRule, ...] = ()  # rules that hold frames back
    error_bursts: tuple[ErrorBurstRule, ...] = ()  # rules that send error frames periodically

    @model_validator(mode="after")
    def _unique_names(self) -> FrameFaultConfig:
        seen: set[str] = set()
        for _, name, _ in self.named_rules():
            if name in seen:
                raise ValueError(f"fault rule name {name!r} is used twice")
            seen.add(name)
        return self

    def named_rules(self) -> list[tuple[str, str, _Rule]]:
        """(kind, name, rule) for every rule; the name is given or "<kind>[<index>]"."""
        out: list[tuple[str, str, _Rule]] = []
        for kind in RULE_KINDS:
            for i, rule in enumerate(getattr(self, kind)):
                out.append((kind, rule.name or f"{kind}[{i}]", rule))
        return out


def parse_frame_faults(data: Any, source: str = "frame_faults") -> FrameFaultConfig:
    """Validate a frame-fault section; ConfigError names every bad key."""
    return validate_section(FrameFaultConfig, data, source)


def error_frame(error_class: int = CAN_ERR_PROT_BUSERROR, timestamp: float = 0.0) -> can.Message:
    """An error frame as python-can's socketcan interface reports one (class in the id)."""
    return can.Message(
        timestamp=timestamp,
        arbitration_id=error_class,
        is_extended_id=True,
        is_error_frame=True,
        dlc=8,
        data=bytes(8),
    )


class _Active:
    """Run-time state of one rule: on/off, its random stream, its match counter."""

    __slots__ = ("acted", "enabled", "kind", "matched", "name", "next_burst", "rng", "rule")

    def __init__(self, kind: str, name: str, rule: _Rule, seed: int) -> None:
        self.kind = kind
        self.name = name
        self.rule = rule
        self.enabled = rule.enabled
        self.rng = random.Random(f"{seed}:{name}")
        self.matched = 0
        self.acted = 0
        self.next_burst: float | None = None

    def applies(self, msg: can.Message, direction: Direction) -> bool:
        rule = self.rule
        if not self.enabled or rule.direction not in (direction, "both"):
            return False
        return not rule.match or any(m.matches(msg) for m in rule.match)

    def selects(self) -> bool:
        """Count a matching frame; True if the rule acts on it."""
        rule = self.rule
        self.matched += 1
        if rule.every_nth is not None and self.matched % rule.every_nth == 0:
            return True
        return rule.probability > 0.0 and self.rng.random() < rule.probability


class FrameFaultInjector:
    """Applies a FrameFaultConfig to frames; `counts` says what was done."""

    def __init__(self, config: FrameFaultConfig) -> None:
        self.config = config
        self._rules: dict[str, _Active] = {}
        for kind, name, rule in config.named_rules():
            self._rules[name] = _Active(kind, name, rule, config.seed)
        self._by_kind = {
            kind: [a for a in self._rules.values() if a.kind == kind] for kind in RULE_KINDS
        }
        # (release time, sequence, direction, held since, frame)
        self._held: list[tuple[float, int, Direction, float, can.Message]] = []
        self._seq = 0
        self._burst_queue: list[tuple[Direction, can.Message]] = []
        self.counts: Counter[str] = Counter()

    # ---- run-time control ---------------------------------------------------------
    @property
    def rule_names(self) -> list[str]:
        return list(self._rules)

    def set_enabled(self, name: str, enabled: bool) -> None:
        """Switch a rule on or off (KeyError naming the known rules if unknown)."""
        self._rule(name).enabled = enabled

    def is_enabled(self, name: str) -> bool:
        return self._rule(name).enabled

    def rule_counts(self) -> dict[str, int]:
        """Frames each rule acted on (error-burst rules: error frames emitted)."""
        return {name: a.acted for name, a in self._rules.items()}

    def error_burst(
        self,
        count: int,
        direction: RuleDirection = "both",
        error_class: int = CAN_ERR_PROT_BUSERROR,
    ) -> None:
        """Queue `count` error frames for the next `due()` call."""
        if not isinstance(count, int) or count < 1:
            raise ValueError(f"error burst count must be an integer >= 1, got {count!r}")
        self._queue_burst(count, direction, error_class)

    @property
    def held(self) -> int:
        """Frames delayed and not released yet."""
        return len(self._held)

    # ---- the frame path -------------------------------------------------------------
    def process(self, msg: can.Message, now: float, direction: Direction) -> can.Message | None:
        """The frame to pass on now (possibly corrupted), or None (dropped or held)."""
        if direction not in ("rx", "tx"):
            raise ValueError(f"direction must be 'rx' or 'tx', got {direction!r}")
        if msg.is_error_frame:
            self.counts["passed"] += 1
            return msg
        for rule in self._by_kind["drop"]:
            if rule.applies(msg, direction) and rule.selects():
                rule.acted += 1
                self.counts["dropped"] += 1
                return None
        for rule in self._by_kind["corrupt"]:
            if rule.applies(msg, direction) and rule.selects():
                rule.acted += 1
                self.counts["corrupted"] += 1
                msg = _corrupt(msg, rule.rule, rule.rng)
        for rule in self._by_kind["delay"]:
            if rule.applies(msg, direction) and rule.selects():
                rule.acted += 1
                self.counts["delayed"] += 1
                self._seq += 1
                entry = (now + rule.rule.delay, self._seq, direction, now, msg)
                heapq.heappush(self._held, entry)
                return None
        self.counts["passed"] += 1
        return msg

    def due(self, now: float, direction: Direction) -> list[can.Message]:
        """Frames to deliver in `direction` at `now`: held frames whose delay is over
        (timestamps moved on by the time held) and error frames of due bursts."""
        self._schedule_bursts(now)
        out: list[can.Message] = []
        if self._burst_queue:
            keep = []
            for d, m in self._burst_queue:
                if d == direction:
                    m.timestamp = now
                    out.append(m)
                else:
                    keep.append((d, m))
            self._burst_queue = keep
        held = self._held
        if held and held[0][0] <= now:
            later = []
            while held and held[0][0] <= now:
                entry = heapq.heappop(held)
                if entry[2] == direction:
                    msg = entry[4]
                    out.append(_replace(msg, timestamp=msg.timestamp + (now - entry[3])))
                else:
                    later.append(entry)
            for entry in later:
                heapq.heappush(held, entry)
        return out

    # ---- internals ------------------------------------------------------------------
    def _rule(self, name: str) -> _Active:
        try:
            return self._rules[name]
        except KeyError:
            raise KeyError(
                f"no fault rule named {name!r}; rules: {', '.join(self._rules) or 'none'}"
            ) from None

    def _schedule_bursts(self, now: float) -> None:
        for rule in self._by_kind["error_bursts"]:
            period = rule.rule.period
            if rule.next_burst is None:
                rule.next_burst = now + period
            if not rule.enabled or now < rule.next_burst:
                continue
            self._queue_burst(rule.rule.count, rule.rule.direction, rule.rule.error_class)
            rule.acted += rule.rule.count
            # one burst however late the call is; the next one a period after it
            rule.next_burst = now + period

    def _queue_burst(self, count: int, direction: RuleDirection, error_class: int) -> None:
        directions: tuple[Direction, ...] = ("rx", "tx") if direction == "both" else (direction,)
        for d in directions:
            self._burst_queue.extend((d, error_frame(error_class)) for _ in range(count))
        self.counts["error_frames"] += count * len(directions)


def _corrupt(msg: can.Message, rule: CorruptRule, rng: random.Random) -> can.Message:
    """A corrupted copy: `flip_bits` distinct data bits flipped, then maybe a new DLC."""
    data = bytearray(msg.data)
    nbits = 8 * len(data)
    for bit in rng.sample(range(nbits), min(rule.flip_bits, nbits)):
        data[bit >> 3] ^= 0x80 >> (bit & 7)
    dlc = msg.dlc
    if rule.change_dlc:
        dlc = rng.choice([n for n in range(9) if n != msg.dlc])
        data = data[:dlc] + bytes(max(0, dlc - len(data)))
    return _replace(msg, dlc=dlc, data=b"" if msg.is_remote_frame else bytes(data))


def _replace(msg: can.Message, **changes: Any) -> can.Message:
    """A new classic-CAN Message like `msg` with some fields changed."""
    fields = {
        "timestamp": msg.timestamp,
        "arbitration_id": msg.arbitration_id,
        "is_extended_id": msg.is_extended_id,
        "is_remote_frame": msg.is_remote_frame,
        "dlc": msg.dlc,
        "data": msg.data,
        "channel": msg.channel,
        "is_rx": msg.is_rx,
    }
    fields.update(changes)
    return can.Message(**fields)


class FaultyBus(can.BusABC):
    """A python-can bus whose frames pass through a FrameFaultInjector on the way in
    (rx) and out (tx).  It owns `inner` (shutdown closes both).  Delayed frames and error
    bursts are released by `tick()`, which `drain()` calls: call one of them every cycle;
    `fileno()` is the inner bus's, so it wakes only for new inner frames."""

    def __init__(
        self,
        inner: can.BusABC,
        faults: FrameFaultConfig | FrameFaultInjector,
        clock: Callable[[], float] = time.monotonic,
        **kwargs: object,
    ) -> None:
        self.inner = inner
        self.injector = (
            faults if isinstance(faults, FrameFaultInjector) else FrameFaultInjector(faults)
        )
        self._clock = clock
        self._rx_ready: list[can.Message] = []
        self.channel_info = f"faulty {inner.channel_info}"
        super().__init__(channel=getattr(inner, "channel", None), **kwargs)

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        out = self.injector.process(msg, self._clock(), "tx")
        if out is not None:
            self.inner.send(out, timeout)

    def tick(self) -> None:
        """Send due tx frames, queue due rx frames for the next recv/drain."""
        now = self._clock()
        for msg in self.injector.due(now, "tx"):
            self.inner.send(msg)
        arrived = time.time()  # a delayed frame is received now: stamped so, as SocketCAN does
        for msg in self.injector.due(now, "rx"):
            msg.timestamp = arrived
            self._rx_ready.append(msg)

    def drain(self) -> list[can.Message]:
        """Everything receivable now: released frames, then the inner bus's frames."""
        self.tick()
        drain = getattr(self.inner, "drain", None)
        if drain is not None:
            incoming = drain()
        else:
            incoming = []
            while (m := self.inner.recv(0)) is not None:
                incoming.append(m)
        now = self._clock()
        out, self._rx_ready = self._rx_ready, []
        for msg in incoming:
            passed = self.injector.process(msg, now, "rx")
            if passed is not None:
                out.append(passed)
        if self._filters is None:
            return out
        return [m for m in out if self._matches_filters(m)]

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        if self._rx_ready:
            return self._rx_ready.pop(0), False
        msg = self.inner.recv(timeout)
        if msg is None:
            return None, False
        return self.injector.process(msg, self._clock(), "rx"), False

    def fileno(self) -> int:
        return self.inner.fileno()

    @property
    def state(self) -> can.BusState:
        return self.inner.state

    @state.setter
    def state(self, new_state: can.BusState) -> None:
        self.inner.state = new_state

    def shutdown(self) -> None:
        if self._is_shutdown:
            return
        super().shutdown()
        self.inner.shutdown()
