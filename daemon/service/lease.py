"""Leases on what a client holds in the daemon's model: the payload estimate frozen
(`payload` {"frozen": true, "lease": s}) and the external wrench observer held out of the
loop (`observer` {"held": true, "lease": s}).

A holder that dies (`kill -9`, its machine or network gone) cannot let go; with a lease
the daemon does it for them: unless the holder renews it within `lease` seconds, the
daemon sends the core the release a client would (`{"frozen": false}`, `{"held": false}`:
the same bumpless paths), logs a warning and emits the event `lease_lapsed`.  Without a
lease, a hold lasts until released, as before.

A lease belongs to whoever took it: the hold that starts one replies with its
`lease_id`, a random token, and only a request that carries it renews the lease (the
same hold with `lease`) or ends it (a release).  Anything else on that hold while the
lease runs is refused ("not_owner", naming the holder and the time left): a release or
a renewal without the id or with another, and a hold without a lease.  An id of a lease
that no longer runs (lapsed, released) is refused too, so that a late holder learns its
lease is gone rather than taking what another client holds now.  Every change (hold,
renew, release, lapse) is an event naming the client (the request's `client`); the id
is never published: it is the capability, the client's name is only a label.

The timing runs here, beside the planner in the companion process (DESIGN §16), never in
the control cycle.  What survives this process is kept in the core as plain data: with
every payload or observer command the core takes, it keeps the leases as they stand then,
{name: (lease s, deadline on the core's clock, lease id, client)}, and hands them to the
next companion in its hello (daemon.process.companion_host), which re-arms each with the
time it has left and the same id and holder (`Leases.resume`; one that ran out meanwhile
lapses at once).  Kept with the command, in the same call, the record never disagrees
with what the core holds, whenever a companion dies; in the hello rather than the
published state, as nobody but the next companion needs it, before it serves anything.
The core runs no timer for them.
"""

from __future__ import annotations

import asyncio
import logging
import secrets
from collections.abc import Awaitable, Callable
from typing import Any, NamedTuple

from daemon.service.api import ANONYMOUS, CommandError

log = logging.getLogger("cdprd")

HELD_BY = {"payload": "frozen", "observer": "held"}
"""The commands that take a lease, and the key of theirs that holds (true) or lets go."""
WHAT = {"payload": "payload estimate's freeze", "observer": "external wrench observer's hold"}
ID_BYTES = 12  # of randomness in a lease id (24 hex digits)


class Lease(NamedTuple):
    """A running lease: its length (s), its deadline on the core's clock, its id and the
    client that took it (a tuple: kept by the core as plain data)."""

    lease: float
    deadline: float
    id: str
    client: str


Kept = dict[str, Lease]
"""The running leases as the core keeps them, by command name."""
Command = Callable[[str, dict[str, Any], Kept], Awaitable[dict[str, Any]]]
EventSink = Callable[[dict[str, Any]], None]
REQUEST_KEYS = ("lease", "lease_id", "client")  # taken here, never sent to the core


class Leases:
    """The running leases, by command name; `command` runs a payload or observer command
    through `send` (the core's, which keeps the leases it is given if it takes the
    command), starting, renewing or ending its lease; `emit` gets the event of every
    change; `now` is the core's clock (s)."""

    def __init__(self, send: Command, emit: EventSink, now: Callable[[], float]) -> None:
        self._send = send
        self._emit = emit
        self._now = now
        self._leases: Kept = {}
        self._timers: dict[str, asyncio.TimerHandle] = {}
        self._lapses: set[asyncio.Task] = set()
        self._lock = asyncio.Lock()  # a lapse waits for a renewal under way, and rechecks

    async def command(self, name: str, args: dict[str, Any]) -> dict[str, Any]:
        """Run `name` (payload or observer) with `args`, its "lease" and "lease_id"
        kept here: the reply carries the lease's id while one runs."""
        key = HELD_BY[name]
        lease = args.get("lease")
        client = args.get("client", ANONYMOUS)
        body = {k: v for k, v in args.items() if k not in REQUEST_KEYS}
        async with self._lock:
            if key not in args:  # a report, or a payload set: no hold changes
                return await self._send(name, body, dict(self._leases))
            running = self._leases.get(name)
            self._check(name, args[key], lease, args.get("lease_id"), running)
            after = dict(self._leases)
            after.pop(name, None)
            if args[key] and lease is not None:
                ident = running.id if running is not None else secrets.token_hex(ID_BYTES)
                after[name] = Lease(lease, self._now() + lease, ident, client)
            reply = await self._send(name, body, after)
            self._end(name)
            change = "release" if not args[key] else "renew" if running is not None else "hold"
            event: dict[str, Any] = {"event": "hold_changed", "what": name, "change": change}
            self._emit({**event, "client": client, "lease": lease})
            if name not in after:
                return reply
            self._arm(name, after[name])
            return {**reply, "lease_id": after[name].id, "lease": lease}

    def resume(self, kept: Kept) -> None:
        """Re-arm the leases the core kept from the previous companion (its hello's), each
        with the time it has left, its id and its holder; one that ran out meanwhile
        lapses at once."""
        now = self._now()
        for name, held in kept.items():
            held = Lease(*held)
            left = max(held.deadline - now, 0.0)
            log.info(
                "the %s runs on: %.3g s left of its lease of %g s (held by %s)",
                WHAT[name], left, held.lease, held.client,
            )  # fmt: skip
            self._arm(name, held)

    def remaining(self) -> dict[str, float | None]:
        """Each lease's time left (s), None where none runs: for the state."""
        now = self._now()
        return {
            name: max(self._leases[name].deadline - now, 0.0) if name in self._leases else None
            for name in HELD_BY
        }

    def _check(
        self, name: str, hold: bool, lease: float | None, given: str | None, running: Lease | None
    ) -> None:
        """Refuse ("not_owner") a change of `name`'s hold that its running lease's holder
        did not ask for (the module docstring)."""
        what = f"{name}: the {WHAT[name]}"
        if running is None:
            if given is None:
                return
            problem = f"{what} has no lease running (lease_id {given!r} lapsed or was released)"
        else:
            left = max(running.deadline - self._now(), 0.0)
            holder = f"{what} is on a lease of {running.client}'s ({left:.3g} s left)"
            if given is None:
                problem = f"{holder}: only its holder, with its lease_id, may renew or release it"
            elif given != running.id:
                problem = f"{holder}: lease_id {given!r} is not that lease's"
            elif hold and lease is None:
                problem = f"{holder}: a hold without a lease while it runs (release it first)"
            else:
                return
        raise CommandError("not_owner", problem, field="lease_id")

    def _arm(self, name: str, held: Lease) -> None:
        self._leases[name] = held
        loop = asyncio.get_running_loop()
        delay = max(held.deadline - self._now(), 0.0)
        self._timers[name] = loop.call_later(delay, self._lapsed, name, held)

    def _end(self, name: str) -> None:
        self._leases.pop(name, None)
        timer = self._timers.pop(name, None)
        if timer is not None:
            timer.cancel()

    def _lapsed(self, name: str, held: Lease) -> None:
        task = asyncio.ensure_future(self._release(name, self._timers[name], held))
        self._lapses.add(task)
        task.add_done_callback(self._lapses.discard)

    async def _release(self, name: str, timer: asyncio.TimerHandle, held: Lease) -> None:
        """Let go of what the lease `timer` timed held, unless it was renewed or ended
        meanwhile (a command under way when it lapsed went first)."""
        async with self._lock:
            if self._timers.get(name) is not timer:
                return
            self._end(name)
            log.warning(
                "the %s lapsed: not renewed within its lease of %g s (held by %s); let go",
                WHAT[name], held.lease, held.client,
            )  # fmt: skip
            event: dict[str, Any] = {
                "event": "lease_lapsed", "what": name, "lease": held.lease, "client": held.client,
            }  # fmt: skip
            try:
                reply = await self._send(name, {HELD_BY[name]: False}, dict(self._leases))
            except CommandError as exc:
                log.error("letting go of the lapsed %s failed: %s", WHAT[name], exc)
                event["error"] = {"code": exc.code, "reason": exc.reason}
            else:
                event["result"] = reply
            self._emit(event)
