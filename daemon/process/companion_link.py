"""The companion's side of its link to the real-time core: a daemon.service.planner.
CoreLink over the socket of daemon.process.wire (DESIGN §16).

Calls (core commands, the reference at a time, a planned trajectory written into the
shared curve ring) wait for the core's reply; events, state snapshots and recorded batches arrive
unasked and go to whoever subscribed.  Planning and validation run here on the
companion's own loop, a slice at a time so that zenoh stays served meanwhile.
"""

from __future__ import annotations

import asyncio
import itertools
import logging
import pickle
import socket
import time
from collections.abc import Callable, Generator
from typing import Any, TypeVar

from cdpr.trajectory import Reference, Trajectory
from daemon.config import DaemonConfig
from daemon.process import wire
from daemon.process.curve_ring import CurveRing, RingFullError
from daemon.service.api import CommandError
from daemon.service.lease import Kept

log = logging.getLogger("cdprd")

ALIVE_PERIOD = 0.1  # s between "alive" messages (the core kills a silent companion)
CALL_TIMEOUT = 30.0  # s for the core to answer a call (enable waits for the drives)
STEP_SLICE = 0.005  # s of planning or validation between two turns of the loop
MESSAGES_PER_PASS = 256
Result = TypeVar("Result")
EventSink = Callable[[dict[str, Any]], None]


def greeted(
    sock: socket.socket, ring_fd: int, timeout: float
) -> tuple[DaemonConfig, str, RemoteLink]:
    """Wait (blocking, at most `timeout` s) for the core's hello on `sock`: the config,
    the log level and the link (the shared ring on `ring_fd`, the ranges the core still
    uses reserved; the leases it kept from the last companion).  OSError if none comes,
    OtherCodeError if the core's code is not this process's (checked first)."""
    sock.settimeout(timeout)
    kind, code = pickle.loads(sock.recv(wire.MAX_MESSAGE))
    if kind != "code" or code != wire.code_fingerprint():
        raise OtherCodeError(
            f"this companion's code ({wire.code_fingerprint()}) is not the core's ({code}): "
            "the installed cdprd changed after the service started; restart it"
        )
    hello = pickle.loads(sock.recv(wire.MAX_MESSAGE))
    kind, config, t0, state, level, in_use, leases = hello
    if kind != "hello":
        raise OSError(f"the core's first message is {kind!r}, not its hello")
    ring = CurveRing.attach(ring_fd)
    ring.reserve(in_use)
    return config, level, RemoteLink(sock, ring, t0, state, leases)


class OtherCodeError(Exception):
    """The core runs other code than this companion (wire.code_fingerprint)."""


class RemoteLink:
    """The core, as the planner and the interfaces of the companion see it."""

    def __init__(
        self,
        sock: socket.socket,
        ring: CurveRing,
        t0: float,
        state: dict[str, Any],
        leases: Kept,
    ) -> None:
        self._sock = sock
        self._ring = ring
        self._t0 = t0
        self._state = state
        self.kept_leases = leases  # the last companion's, as the core kept them
        self._ids = itertools.count()
        self._waiting: dict[int, asyncio.Future] = {}
        self._sinks: list[EventSink] = []
        self.batch_sinks: dict[str, Callable[[list], None]] = {}  # "cycles", "frames"
        self.closed = asyncio.Event()
        self._alive: asyncio.Task | None = None

    def start(self) -> None:
        """Serve the socket on the running loop, and tell the core this process lives."""
        self._sock.setblocking(False)
        loop = asyncio.get_running_loop()
        loop.add_reader(self._sock.fileno(), self._on_readable)
        self._alive = loop.create_task(self._keep_alive())

    def ready(self) -> None:
        """Tell the core that this companion is up (zenoh listening)."""
        wire.send(self._sock, ("ready",))

    async def core_started(self) -> None:
        """Return once the core's drives are up (its state has left INIT) or it closed."""
        while self.safety_state == "init" and not self.closed.is_set():
            await asyncio.sleep(0.02)

    def close(self) -> None:
        if self._alive is not None:
            self._alive.cancel()
        if self._sock.fileno() >= 0:
            asyncio.get_running_loop().remove_reader(self._sock.fileno())
            self._sock.close()
        self._fail_waiting("the core link is closed")

    # -- CoreLink ---------------------------------------------------------------------------

    def now(self) -> float:
        return time.monotonic() - self._t0

    @property
    def safety_state(self) -> str:
        return str(self._state.get("state", "init"))

    @property
    def cycles(self) -> int:
        """Control cycles the core has completed, as last reported."""
        return int(self._state.get("cycle", {}).get("cycles", 0))

    async def command(self, name: str, args: dict[str, Any]) -> dict[str, Any]:
        return await self._call("command", (name, args))

    async def command_keeping(
        self, name: str, args: dict[str, Any], leases: Kept
    ) -> dict[str, Any]:
        return await self._call("command_keeping", (name, args, leases))

    async def reference_at(self, t: float) -> tuple[Reference, int]:
        reference, version = await self._call("reference_at", (t,))
        return reference, version

    async def follow(self, trajectory: Trajectory, version: int, what: str) -> dict[str, Any]:
        try:
            header, offset, count = self._ring.write(trajectory)
        except RingFullError as exc:
            raise CommandError("busy", str(exc)) from None
        # from here the core hands the range back (a "free" message) once it drops the
        # curve, whatever it replies, unless the call never reached it
        return await self._call(
            "follow",
            (header, offset, count, version, what),
            unsent=lambda: self._ring.release(offset, 8 * count),
        )

    async def run_steps(self, steps: Generator[Any, None, Result]) -> Result:
        while True:
            until = time.monotonic() + STEP_SLICE
            while time.monotonic() < until:
                try:
                    next(steps)
                except StopIteration as done:
                    return done.value
            await asyncio.sleep(0)  # let zenoh's queries and the core's messages in

    def state(self) -> dict[str, Any]:
        return self._state

    async def slack(self) -> None:
        return  # the core's cycle is in another process: publishing here costs it nothing

    def subscribe(self, sink: EventSink) -> None:
        self._sinks.append(sink)

    # -- the socket -------------------------------------------------------------------------

    async def _call(
        self, method: str, args: tuple, unsent: Callable[[], None] | None = None
    ) -> Any:
        """The core's reply to a call (CommandError if it refused); `unsent` runs if the
        call could not be sent at all."""
        ident = next(self._ids)
        future = asyncio.get_running_loop().create_future()
        self._waiting[ident] = future
        try:
            deadline = time.monotonic() + CALL_TIMEOUT
            while not wire.send(self._sock, ("call", ident, method, args)):
                if self.closed.is_set() or time.monotonic() > deadline:
                    if unsent is not None:
                        unsent()
                    raise CommandError("busy", "the control core is not taking requests")
                await asyncio.sleep(0.001)  # its buffer is full: it reads between cycles
            ok, payload = await asyncio.wait_for(future, max(deadline - time.monotonic(), 0.0))
        except TimeoutError:
            raise CommandError("internal", f"the control core did not answer {method}") from None
        finally:
            self._waiting.pop(ident, None)
        if not ok:
            code, reason, details = payload
            raise CommandError(code, reason, **details)
        return payload

    def _on_readable(self) -> None:
        messages, closed = wire.receive(self._sock, MESSAGES_PER_PASS)
        for message in messages:
            self._dispatch(message)
        if closed and not self.closed.is_set():
            log.info("the control core closed the link")
            asyncio.get_running_loop().remove_reader(self._sock.fileno())
            self.closed.set()
            self._fail_waiting("the control core has stopped")

    def _dispatch(self, message: tuple) -> None:
        kind = message[0]
        if kind == "reply":
            _, ident, ok, payload = message
            future = self._waiting.get(ident)
            if future is not None and not future.done():
                future.set_result((ok, payload))
        elif kind == "event":
            event = message[1]
            self._follow_state(event)
            for sink in self._sinks:
                sink(event)
        elif kind == "state":
            self._state = message[1]
        elif kind == "free":
            _, offset, nbytes = message
            self._ring.release(offset, nbytes)
        elif kind in self.batch_sinks:
            self.batch_sinks[kind](message[1])

    def _follow_state(self, event: dict[str, Any]) -> None:
        """Keep the safety state and its fault current between two snapshots."""
        if "state" not in event:
            return
        state = {**self._state, "state": event["state"]}
        if event.get("event") == "brake":
            state["fault"] = {"trigger": event["trigger"], "message": event["message"]}
        elif event["state"] != "braked":
            state["fault"] = None
        self._state = state

    def _fail_waiting(self, why: str) -> None:
        for future in self._waiting.values():
            if not future.done():
                future.set_result((False, ("internal", why, {})))

    async def _keep_alive(self) -> None:
        while True:
            wire.send(self._sock, ("alive",))
            await asyncio.sleep(ALIVE_PERIOD)
