"""The daemon's Eclipse Zenoh interface (DESIGN §10): commands, trajectories, state, events.

Keys under the prefix (default cdpr/<robot>):
    trajectory   subscriber (put) and queryable (get with payload): a trajectory to run
    cmd/<name>   queryable, one for cmd/**: the COMMANDS of daemon/api.py, JSON replies
    state        published at zenoh.state_rate_hz
    events       trajectory accepted / rejected, and the service's state changes and faults
    alive        liveliness token, present while the interface runs

Threads.  zenoh calls the callbacks on its own threads.  They check the size, decode the
JSON and the schema (daemon/messages.py: bad input is answered there and then, and never
reaches the handler) and hand the decoded request to the event loop through a BOUNDED
queue.  A full queue drops the message, counts it and, for a query, replies "busy" at
once.  The loop side takes at most MESSAGES_PER_PASS messages per queue per loop pass
before yielding to the other callbacks (the control cycle), then calls the handler and
replies.  So a flood costs bounded memory, and each loop pass at most one handler call
per queue (commands, trajectories) plus one event publication.

One queryable serves cmd/** (rather than one per command) so that an unknown command gets
a clear error reply, and so that a wildcard query (cmd/*) is refused instead of running
every command at once.  Trajectory puts and queries with wildcards are refused too.
"""

from __future__ import annotations

import asyncio
import contextlib
import inspect
import logging
import threading
import time
from collections import Counter, deque
from collections.abc import Awaitable, Callable
from typing import Any, Generic, TypeVar

import zenoh

from cdpr.trajectory import SCHEMA_VERSION, TrajectoryLimits
from daemon.api import CommandError, DaemonHandler
from daemon.messages import (
    EVENT_KEY,
    VERSION_KEY,
    TrajectoryRequest,
    check_size,
    decode_command,
    decode_json,
    decode_trajectory,
    encode,
    error_body,
    jsonable,
    reply_error,
    reply_ok,
    request_id,
)
from daemon.zenoh_config import ZenohSettings, build_zenoh_config

log = logging.getLogger(__name__)

MESSAGES_PER_PASS = 1  # per queue and loop pass: the control cycle waits for at most one
# handler call per queue (a pass costs tens of µs, so throughput hardly suffers)
CLOSE_GRACE = 1.0  # s: how long close() waits for commands still running (enable, reset)
_Item = TypeVar("_Item")


class _Inbox(Generic[_Item]):
    """A bounded hand-over of items from any thread to `process` on the event loop."""

    def __init__(
        self, loop: asyncio.AbstractEventLoop, depth: int, process: Callable[[_Item], None]
    ) -> None:
        self._loop = loop
        self._loop_thread = threading.get_ident()  # built on the loop thread
        self._depth = depth
        self._process = process
        self._items: deque[_Item] = deque()
        self._lock = threading.Lock()
        self._scheduled = False
        self._closed = False
        self.dropped = 0
        self.high_water = 0

    def has_room(self, limit: int | None = None) -> bool:
        """A hint (no reservation): would an item be accepted now?"""
        return len(self._items) < (self._depth if limit is None else min(limit, self._depth))

    def drop(self) -> None:
        """Count an item dropped before it was offered (see has_room)."""
        with self._lock:
            self.dropped += 1

    def offer(self, item: _Item, limit: int | None = None) -> bool:
        """Queue `item` unless `limit` (default: the depth) items wait already."""
        limit = self._depth if limit is None else min(limit, self._depth)
        with self._lock:
            if self._closed or len(self._items) >= limit:
                self.dropped += 1
                return False
            self._items.append(item)
            self.high_water = max(self.high_water, len(self._items))
            wake, self._scheduled = not self._scheduled, True
        if wake:
            try:
                if threading.get_ident() == self._loop_thread:
                    self._loop.call_soon(self._drain)
                else:
                    self._loop.call_soon_threadsafe(self._drain)
            except RuntimeError:  # the loop is closed: shutting down
                return False
        return True

    def close(self) -> list[_Item]:
        """Accept nothing more; return what was waiting."""
        with self._lock:
            self._closed = True
            items, self._items = list(self._items), deque()
            return items

    def _drain(self) -> None:
        for _ in range(MESSAGES_PER_PASS):
            with self._lock:
                if not self._items:
                    self._scheduled = False
                    return
                item = self._items.popleft()
            self._process(item)
        self._loop.call_soon(self._drain)  # more may wait: let other callbacks run first


class ZenohInterface:
    """The zenoh side of the daemon; `await start()`, then `await close()`.

    `handler` is called on the loop that ran start(); `publish_event` is thread-safe.
    `limits` bound the trajectories the interface will parse (its max_waypoints is
    lowered to zenoh.max_waypoints); the service checks the robot-specific limits.
    """

    def __init__(
        self,
        settings: ZenohSettings,
        handler: DaemonHandler,
        prefix: str,
        limits: TrajectoryLimits | None = None,
    ) -> None:
        limits = TrajectoryLimits() if limits is None else limits
        self.settings = settings
        self.prefix = prefix
        self.limits = limits.model_copy(
            update={"max_waypoints": min(limits.max_waypoints, settings.max_waypoints)}
        )
        self._handler = handler
        self._counts: Counter[str] = Counter()
        self._count_lock = threading.Lock()
        self._event_lock = threading.Lock()
        self._event_seq = 0
        self._state_seq = 0
        self._closing = False
        self._session: zenoh.Session | None = None
        self._entities: list[Any] = []
        self._tasks: set[asyncio.Future[Any]] = set()
        self._loop: asyncio.AbstractEventLoop | None = None
        self._commands: _Inbox[tuple[str, dict[str, Any], zenoh.Query]] | None = None
        self._trajectories: _Inbox[tuple[TrajectoryRequest, zenoh.Query | None]] | None = None
        self._events: _Inbox[bytes] | None = None
        self._state_timer: asyncio.TimerHandle | None = None
        self._next_state = 0.0

    # -- keys ------------------------------------------------------------------------------

    def key(self, name: str) -> str:
        """The full key of `name` (trajectory, state, events, alive, cmd/<command>)."""
        return f"{self.prefix}/{name}"

    # -- life cycle ------------------------------------------------------------------------

    async def start(self) -> None:
        """Open the session and declare every key; the liveliness token comes last."""
        loop = asyncio.get_running_loop()
        depth = self.settings.queue_depth
        self._loop = loop
        self._commands = _Inbox(loop, depth, self._run_command)
        self._trajectories = _Inbox(loop, depth, self._run_trajectory)
        self._events = _Inbox(loop, depth, self._put_event)
        conf = build_zenoh_config(self.settings)
        session = await loop.run_in_executor(None, zenoh.open, conf)
        self._session = session
        drop = zenoh.CongestionControl.DROP  # a congested network never blocks the loop
        self._state_pub = session.declare_publisher(self.key("state"), congestion_control=drop)
        self._event_pub = session.declare_publisher(self.key("events"), congestion_control=drop)
        self._entities = [
            session.declare_subscriber(self.key("trajectory"), self._on_trajectory_put),
            session.declare_queryable(self.key("trajectory"), self._on_trajectory_query),
            session.declare_queryable(self.key("cmd/**"), self._on_command_query),
            session.liveliness().declare_token(self.key("alive")),
        ]
        self._next_state = loop.time()
        self._state_timer = loop.call_soon(self._publish_state)
        log.info("zenoh interface on %s (listen %s)", self.prefix, self.settings.listen_endpoints)

    async def close(self) -> None:
        """Stop taking requests, answer the waiting ones "busy", publish the events still
        queued (those of the answers too), then close the session."""
        session, self._session = self._session, None
        if session is None:
            return
        self._closing = True
        if self._state_timer is not None:
            self._state_timer.cancel()
        for entity in self._entities:
            _quietly(entity.undeclare)
        if self._tasks:
            await asyncio.wait(self._tasks, timeout=CLOSE_GRACE)
        for task in list(self._tasks):
            task.cancel()
        gone = CommandError("busy", "the daemon is shutting down")
        assert self._commands is not None and self._trajectories is not None
        for name, _args, query in self._commands.close():
            self._reply(query, reply_error(name, gone), ok=False)
        for request, query in self._trajectories.close():
            self._trajectory_outcome(request.id, query, None, gone)
        assert self._events is not None
        for payload in self._events.close():
            self._put_event(payload)
        for publisher in (self._state_pub, self._event_pub):
            _quietly(publisher.undeclare)
        await asyncio.get_running_loop().run_in_executor(None, session.close)

    async def __aenter__(self) -> ZenohInterface:
        await self.start()
        return self

    async def __aexit__(self, *_exc: object) -> None:
        await self.close()

    # -- events (any thread) ---------------------------------------------------------------

    def publish_event(self, event: dict[str, Any]) -> None:
        """Publish `event` ({"event": <name>, ...}) on <prefix>/events; never blocks.

        A full queue drops it and counts it; the receivers see a gap in "seq".
        """
        if not isinstance(event.get(EVENT_KEY), str):
            raise ValueError(f"an event needs a name: {{'{EVENT_KEY}': '<name>', ...}}")
        self._enqueue_event(event, limit=None)

    def _enqueue_event(self, event: dict[str, Any], limit: int | None) -> None:
        with self._event_lock:
            self._event_seq += 1
            if self._events is not None and not self._events.has_room(limit):
                self._events.drop()  # do not encode what would be dropped (a flood)
                return
            message = {VERSION_KEY: SCHEMA_VERSION, "seq": self._event_seq, "time": time.time()}
            message.update(jsonable(event))
            message.update({VERSION_KEY: SCHEMA_VERSION, "seq": self._event_seq})
            if self._events is None:
                self._count("events_dropped_before_start")
            else:
                self._events.offer(encode(message), limit)  # counts its own drops

    def _interface_event(self, event: dict[str, Any]) -> None:
        """Events the interface makes itself use at most half of the queue, so that a
        flood of bad input cannot crowd out the service's fault and state events."""
        self._enqueue_event(event, limit=max(1, self.settings.queue_depth // 2))

    # -- statistics ------------------------------------------------------------------------

    def stats(self) -> dict[str, Any]:
        """Counters (received, refused, dropped, ...) and the queues' high-water marks."""
        with self._count_lock:
            out: dict[str, Any] = dict(self._counts)
        for name, inbox in (
            ("commands", self._commands),
            ("trajectories", self._trajectories),
            ("events", self._events),
        ):
            if inbox is not None:
                out[f"{name}_queue_high_water"] = inbox.high_water
                out[f"{name}_queue_dropped"] = inbox.dropped
        return out

    def _count(self, name: str) -> None:
        with self._count_lock:
            self._counts[name] += 1

    def _count_refusal(self, error: CommandError) -> None:
        """Bad input is "refused"; a full queue counts its own drops."""
        if error.code != "busy":
            self._count("refused")

    # -- zenoh threads ---------------------------------------------------------------------

    def _on_trajectory_put(self, sample: zenoh.Sample) -> None:
        try:
            if self._closing:
                return
            self._count("trajectory_puts")
            if sample.kind != zenoh.SampleKind.PUT:
                return  # a delete: nothing to run
            request = self._decode_trajectory(str(sample.key_expr), sample.payload)
            if isinstance(request, CommandError | tuple):
                ident, error = request if isinstance(request, tuple) else (None, request)
                self._count_refusal(error)
                self._interface_event(_rejected_event(ident, error))
                return
            assert self._trajectories is not None
            if not self._trajectories.offer((request, None)):
                self._interface_event(_rejected_event(request.id, _busy("trajectory")))
        except Exception:
            self._count("callback_errors")
            log.exception("trajectory put callback failed")

    def _on_trajectory_query(self, query: zenoh.Query) -> None:
        try:
            if self._closing:
                self._reply(query, reply_error("trajectory", _busy("trajectory")), ok=False)
                return
            self._count("trajectory_queries")
            request = self._decode_trajectory(str(query.key_expr), query.payload)
            if isinstance(request, CommandError | tuple):
                ident, error = request if isinstance(request, tuple) else (None, request)
                self._count_refusal(error)
                self._interface_event(_rejected_event(ident, error))
                self._reply(query, reply_error("trajectory", error, ident), ok=False)
                return
            assert self._trajectories is not None
            if not self._trajectories.offer((request, query)):
                self._reply(
                    query, reply_error("trajectory", _busy("trajectory"), request.id), False
                )
        except Exception:
            self._count("callback_errors")
            log.exception("trajectory query callback failed")
            _quietly(query.drop)

    def _decode_trajectory(
        self, key: str, payload: zenoh.ZBytes | None
    ) -> TrajectoryRequest | CommandError | tuple[str | None, CommandError]:
        """The request, or the error (with the sender's id when it could be read)."""
        if key != self.key("trajectory"):
            return CommandError(
                "bad_request", f"send trajectories to the exact key {self.key('trajectory')}"
            )
        assert self._trajectories is not None
        if not self._trajectories.has_room():  # do not parse what would be dropped
            self._trajectories.drop()
            return _busy("trajectory")
        if payload is None or len(payload) == 0:
            return CommandError("bad_request", "a trajectory message needs a JSON payload")
        try:
            check_size(len(payload), self.settings.max_message_bytes)
            data = decode_json(payload.to_bytes(), self.settings.max_message_bytes)
        except CommandError as exc:
            return exc
        ident = request_id(data)
        try:
            return decode_trajectory(data, self.limits)
        except CommandError as exc:
            return ident, exc
        except Exception as exc:  # a bug in a decoder must not reach the sender as silence
            log.exception("trajectory decoding raised")
            return ident, CommandError("internal", f"decoding failed: {type(exc).__name__}")

    def _on_command_query(self, query: zenoh.Query) -> None:
        name = "?"
        try:
            key = str(query.key_expr)
            name = key.removeprefix(self.key("cmd/"))
            if self._closing:
                self._reply(query, reply_error(name, _busy(name)), ok=False)
                return
            self._count("command_queries")
            if "*" in key or "$" in key:
                raise CommandError(
                    "bad_request",
                    f"commands need an exact key such as {self.key('cmd/status')}, not {key}",
                )
            payload = query.payload
            data = None
            if payload is not None and len(payload) > 0:
                check_size(len(payload), self.settings.max_message_bytes)
                data = decode_json(payload.to_bytes(), self.settings.max_message_bytes)
            args = decode_command(name, data, self.limits.unit_tolerance)
            assert self._commands is not None
            if not self._commands.offer((name, args, query)):
                self._reply(query, reply_error(name, _busy(name)), ok=False)
        except CommandError as exc:
            self._count("refused")
            self._reply(query, reply_error(name, exc), ok=False)
        except Exception:
            self._count("callback_errors")
            log.exception("command query callback failed")
            _quietly(query.drop)

    # -- event loop ------------------------------------------------------------------------

    def _run_command(self, item: tuple[str, dict[str, Any], zenoh.Query]) -> None:
        name, args, query = item
        try:
            result = self._handler.command(name, args)
        except CommandError as exc:
            self._reply(query, reply_error(name, exc), ok=False)
            return
        except Exception as exc:
            self._reply(query, reply_error(name, _internal(name, exc)), ok=False)
            return
        if inspect.isawaitable(result):
            task = asyncio.ensure_future(self._finish_command(name, result, query))
            self._tasks.add(task)
            task.add_done_callback(self._tasks.discard)
        else:
            self._reply(query, reply_ok(name, result), ok=True)

    async def _finish_command(
        self, name: str, pending: Awaitable[dict[str, Any]], query: zenoh.Query
    ) -> None:
        try:
            result = await pending
        except CommandError as exc:
            self._reply(query, reply_error(name, exc), ok=False)
        except asyncio.CancelledError:
            self._reply(query, reply_error(name, _busy(name)), ok=False)
            raise
        except Exception as exc:
            self._reply(query, reply_error(name, _internal(name, exc)), ok=False)
        else:
            self._reply(query, reply_ok(name, result), ok=True)

    def _run_trajectory(self, item: tuple[TrajectoryRequest, zenoh.Query | None]) -> None:
        request, query = item
        try:
            result = self._handler.submit_trajectory(request.trajectory, request.start)
        except CommandError as exc:
            self._trajectory_outcome(request.id, query, None, exc)
        except Exception as exc:
            self._trajectory_outcome(request.id, query, None, _internal("trajectory", exc))
        else:
            if inspect.isawaitable(result):  # validation between control cycles
                task = asyncio.ensure_future(self._finish_trajectory(request, result, query))
                self._tasks.add(task)
                task.add_done_callback(self._tasks.discard)
            else:
                self._trajectory_outcome(request.id, query, result, None)

    async def _finish_trajectory(
        self,
        request: TrajectoryRequest,
        pending: Awaitable[dict[str, Any]],
        query: zenoh.Query | None,
    ) -> None:
        try:
            result = await pending
        except CommandError as exc:
            self._trajectory_outcome(request.id, query, None, exc)
        except asyncio.CancelledError:
            self._trajectory_outcome(request.id, query, None, _busy("trajectory"))
            raise
        except Exception as exc:
            self._trajectory_outcome(request.id, query, None, _internal("trajectory", exc))
        else:
            self._trajectory_outcome(request.id, query, result, None)

    def _trajectory_outcome(
        self,
        ident: str | None,
        query: zenoh.Query | None,
        result: dict[str, Any] | None,
        error: CommandError | None,
    ) -> None:
        """The accepted / rejected event, and the reply when the trajectory came by query."""
        if error is None:
            self._enqueue_event(
                {EVENT_KEY: "trajectory_accepted", "id": ident, "result": result}, limit=None
            )
            if query is not None:
                self._reply(query, reply_ok("trajectory", result or {}, ident), ok=True)
        else:
            self._enqueue_event(_rejected_event(ident, error), limit=None)
            if query is not None:
                self._reply(query, reply_error("trajectory", error, ident), ok=False)

    def _publish_state(self) -> None:
        assert self._loop is not None
        try:
            body = self._handler.state()
            self._state_seq += 1
            message = {VERSION_KEY: SCHEMA_VERSION, "seq": self._state_seq, "time": time.time()}
            message.update(jsonable(body))
            message.update(
                {VERSION_KEY: SCHEMA_VERSION, "seq": self._state_seq, "interface": self.stats()}
            )
            self._state_pub.put(encode(message))
        except Exception:
            self._count("state_errors")
            failures = self._counts["state_errors"]
            if failures == 1 or failures % 1000 == 0:
                log.exception("publishing the state failed (%d times)", failures)
        period = 1.0 / self.settings.state_rate_hz
        now = self._loop.time()
        self._next_state += period
        if self._next_state <= now:  # a whole period late: skip, never burst to catch up
            self._count("state_late")
            self._next_state = now + period
        self._state_timer = self._loop.call_at(self._next_state, self._publish_state)

    def _put_event(self, payload: bytes) -> None:
        try:
            self._event_pub.put(payload)
        except zenoh.ZError:
            self._count("events_failed")

    # -- replies (any thread) --------------------------------------------------------------

    def _reply(self, query: zenoh.Query, body: dict[str, Any], ok: bool) -> None:
        """Reply once and finalise the query (the querier stops waiting)."""
        try:
            if ok:
                query.reply(query.key_expr, encode(body))
            else:
                query.reply_err(encode(body))
        except zenoh.ZError:  # the querier gave up (timeout) or left
            self._count("replies_failed")
        finally:
            _quietly(query.drop)


def _rejected_event(ident: str | None, error: CommandError) -> dict[str, Any]:
    return {EVENT_KEY: "trajectory_rejected", "id": ident, "error": error_body(error)}


def _busy(what: str) -> CommandError:
    return CommandError("busy", f"too many {what} requests waiting: this one was dropped, retry")


def _internal(what: str, exc: Exception) -> CommandError:
    log.error("handler failed on %s", what, exc_info=exc)
    return CommandError("internal", f"the daemon failed on {what}: {type(exc).__name__}: {exc}")


def _quietly(action: Callable[[], Any]) -> None:
    """Undeclare / drop on shutdown: zenoh raises if the session is already gone."""
    with contextlib.suppress(zenoh.ZError):
        action()
