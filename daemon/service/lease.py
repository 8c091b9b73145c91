"""Leases on what a client holds in the daemon's model: the payload estimate frozen
(`payload` {"frozen": true, "lease": s}) and the external wrench observer held out of the
loop (`observer` {"held": true, "lease": s}).

A holder that dies (`kill -9`, its machine or network gone) cannot let go; with a lease
the daemon does it for them: unless the same command comes again within `lease` seconds
(a renewal), the daemon sends the core the release a client would (`{"frozen": false}`,
`{"held": false}`: the same bumpless paths), logs a warning and emits the event
`lease_lapsed`.  Without a lease, a hold lasts until released, as before; a release, or
a hold without a lease, ends a running lease.

The timing runs here, beside the planner in the companion process (DESIGN §16), never in
the control cycle: the core only ever sees the commands.
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Awaitable, Callable
from typing import Any

from daemon.service.api import CommandError

log = logging.getLogger("cdprd")

HELD_BY = {"payload": "frozen", "observer": "held"}
"""The commands that take a lease, and the key of theirs that holds (true) or lets go."""
WHAT = {"payload": "payload estimate's freeze", "observer": "external wrench observer's hold"}

Command = Callable[[str, dict[str, Any]], Awaitable[dict[str, Any]]]
EventSink = Callable[[dict[str, Any]], None]


class Leases:
    """The running leases, by command name; `command` runs a payload or observer command
    through `send` (the core's), starting, renewing or ending its lease; `emit` gets the
    event of a lapse."""

    def __init__(self, send: Command, emit: EventSink) -> None:
        self._send = send
        self._emit = emit
        self._deadlines: dict[str, float] = {}  # name -> time.monotonic() it lapses at
        self._timers: dict[str, asyncio.TimerHandle] = {}
        self._lapses: set[asyncio.Task] = set()
        self._lock = asyncio.Lock()  # a lapse waits for a renewal under way, and rechecks

    async def command(self, name: str, args: dict[str, Any]) -> dict[str, Any]:
        """Run `name` (payload or observer) with `args`, its "lease" kept here."""
        key = HELD_BY[name]
        lease = args.get("lease")
        async with self._lock:
            reply = await self._send(name, {k: v for k, v in args.items() if k != "lease"})
            if key in args:
                self._end(name)
                if args[key] and lease is not None:
                    self._start(name, lease)
            return reply

    def remaining(self) -> dict[str, float | None]:
        """Each lease's time left (s), None where none runs: for the state."""
        now = time.monotonic()
        return {
            name: max(self._deadlines[name] - now, 0.0) if name in self._deadlines else None
            for name in HELD_BY
        }

    def _start(self, name: str, lease: float) -> None:
        self._deadlines[name] = time.monotonic() + lease
        loop = asyncio.get_running_loop()
        self._timers[name] = loop.call_later(lease, self._lapsed, name, lease)

    def _end(self, name: str) -> None:
        self._deadlines.pop(name, None)
        timer = self._timers.pop(name, None)
        if timer is not None:
            timer.cancel()

    def _lapsed(self, name: str, lease: float) -> None:
        task = asyncio.ensure_future(self._release(name, self._timers[name], lease))
        self._lapses.add(task)
        task.add_done_callback(self._lapses.discard)

    async def _release(self, name: str, timer: asyncio.TimerHandle, lease: float) -> None:
        """Let go of what the lease `timer` timed held, unless it was renewed or ended
        meanwhile (a command under way when it lapsed went first)."""
        async with self._lock:
            if self._timers.get(name) is not timer:
                return
            self._end(name)
            log.warning(
                "the %s lapsed: not renewed within its lease of %g s; let go", WHAT[name], lease
            )
            event: dict[str, Any] = {"event": "lease_lapsed", "what": name, "lease": lease}
            try:
                reply = await self._send(name, {HELD_BY[name]: False})
            except CommandError as exc:
                log.error("letting go of the lapsed %s failed: %s", WHAT[name], exc)
                event["error"] = {"code": exc.code, "reason": exc.reason}
            else:
                event["result"] = reply
            self._emit(event)
