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
the control cycle.  What survives this process is kept in the core as plain data: with
every payload or observer command the core takes, it keeps the leases as they stand then,
{name: (lease s, deadline on the core's clock)}, and hands them to the next companion in
its hello (daemon.process.companion_host), which re-arms each with the time it has left
(`Leases.resume`; one that ran out meanwhile lapses at once).  Kept with the command, in
the same call, the record never disagrees with what the core holds, whenever a companion
dies; in the hello rather than the published state, as nobody but the next companion
needs it, before it serves anything.  The core runs no timer for them.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Awaitable, Callable
from typing import Any

from daemon.service.api import CommandError

log = logging.getLogger("cdprd")

HELD_BY = {"payload": "frozen", "observer": "held"}
"""The commands that take a lease, and the key of theirs that holds (true) or lets go."""
WHAT = {"payload": "payload estimate's freeze", "observer": "external wrench observer's hold"}

Kept = dict[str, tuple[float, float]]
"""The running leases as the core keeps them: name -> (lease s, deadline on its clock)."""
Command = Callable[[str, dict[str, Any], Kept], Awaitable[dict[str, Any]]]
EventSink = Callable[[dict[str, Any]], None]


class Leases:
    """The running leases, by command name; `command` runs a payload or observer command
    through `send` (the core's, which keeps the leases it is given if it takes the
    command), starting, renewing or ending its lease; `emit` gets the event of a lapse;
    `now` is the core's clock (s)."""

    def __init__(self, send: Command, emit: EventSink, now: Callable[[], float]) -> None:
        self._send = send
        self._emit = emit
        self._now = now
        self._leases: Kept = {}
        self._timers: dict[str, asyncio.TimerHandle] = {}
        self._lapses: set[asyncio.Task] = set()
        self._lock = asyncio.Lock()  # a lapse waits for a renewal under way, and rechecks

    async def command(self, name: str, args: dict[str, Any]) -> dict[str, Any]:
        """Run `name` (payload or observer) with `args`, its "lease" kept here."""
        key = HELD_BY[name]
        lease = args.get("lease")
        async with self._lock:
            after = dict(self._leases)
            if key in args:
                after.pop(name, None)
                if args[key] and lease is not None:
                    after[name] = (lease, self._now() + lease)
            body = {k: v for k, v in args.items() if k != "lease"}
            reply = await self._send(name, body, after)
            if key in args:
                self._end(name)
                if name in after:
                    self._arm(name, *after[name])
            return reply

    def resume(self, kept: Kept) -> None:
        """Re-arm the leases the core kept from the previous companion (its hello's), each
        with the time it has left; one that ran out meanwhile lapses at once."""
        now = self._now()
        for name, (lease, deadline) in kept.items():
            left = max(deadline - now, 0.0)
            log.info("the %s runs on: %.3g s left of its lease of %g s", WHAT[name], left, lease)
            self._arm(name, lease, deadline)

    def remaining(self) -> dict[str, float | None]:
        """Each lease's time left (s), None where none runs: for the state."""
        now = self._now()
        return {
            name: max(self._leases[name][1] - now, 0.0) if name in self._leases else None
            for name in HELD_BY
        }

    def _arm(self, name: str, lease: float, deadline: float) -> None:
        self._leases[name] = (lease, deadline)
        loop = asyncio.get_running_loop()
        delay = max(deadline - self._now(), 0.0)
        self._timers[name] = loop.call_later(delay, self._lapsed, name, lease)

    def _end(self, name: str) -> None:
        self._leases.pop(name, None)
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
                reply = await self._send(name, {HELD_BY[name]: False}, dict(self._leases))
            except CommandError as exc:
                log.error("letting go of the lapsed %s failed: %s", WHAT[name], exc)
                event["error"] = {"code": exc.code, "reason": exc.reason}
            else:
                event["result"] = reply
            self._emit(event)
