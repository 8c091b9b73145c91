"""The daemon's Eclipse Zenoh interface (DESIGN §10): commands, trajectories, state, events.

Keys under the prefix (default cdpr/<robot>):
    trajectory   subscriber (put) and queryable (get with payload): a trajectory to run
    path         the same for a path: poses without times, which the interface times
                 within the cables' tensions (cdpr.path.timing) into the trajectory to run
    cmd/<name>   queryable, one for cmd/**: the COMMANDS of daemon/service/api.py, JSON replies
    state        published at zenoh.state_rate_hz
    events       trajectory accepted / rejected, and the service's state changes and faults
    alive        liveliness token, present while the interface runs

Threads.  zenoh calls the callbacks on its own threads, and they do little there: a
command (at most MAX_COMMAND_BYTES) is decoded and schema-checked (bad input is answered
at once and never reaches the handler); a trajectory is size-checked and copied, and a
small one (DECODE_ON_ARRIVAL_BYTES) decoded and its head checked too.  Each goes to the
event loop through a BOUNDED queue; a full queue drops the message, counts it and, for
a query, replies "busy" at once.  The loop takes at most MESSAGES_PER_PASS messages per
queue per loop pass before yielding to the other callbacks (the control cycle).  So a
flood costs bounded memory, and each loop pass at most one handler call per queue plus
one event publication.

Trajectories run one at a time. Parsing one (JSON, schema, the curve through the
waypoints: ~3 ms for 100 waypoints, ~0.1-0.2 s for 10000) happens in a parse thread,
never on the loop (except a move of two waypoints, ~0.1 ms); so does timing a path
(`path`: its poses timed within the tensions by the `timer`, 0.24-0.34 s for 100 blended
poses); the loop calls the handler with the result and awaits its validation, while the
next one is parsed. The parse thread must not delay the loop either: while it computes,
the loop would wait for the GIL up to the switch interval (5 ms) and, on a loaded host,
for a CPU. So it pauses every PARSE_SLICE (a profile hook, _Yielding: cdpr's parser has
no points to pause at), runs below the loop's OS priority, uses at most PARSE_SHARE of a
core in a long flood, and long JSON is decoded in pieces
(daemon.interface.messages.decode_json, which pauses between them itself) so that no
single C call holds the GIL long. The ROS 2 bridge on this session parses its
trajectories in the same thread, within the same budget (run_parser): a flood of Paths
costs the loop no more than a flood of JSON. Of the commands that wait for the drives or
for planning (enable, reset, goto: _ONE_AT_A_TIME) one runs at a time; another one
meanwhile is answered "busy" and never started. A hold, which plans its stop for a few
ms, is never turned away, nor is a request that preempts (it replaces what runs:
daemon.service.motion).

One queryable serves cmd/** (rather than one per command) so that an unknown command gets
a clear error reply, and so that a wildcard query (cmd/*) is refused instead of running
every command at once.  Trajectory puts and queries with wildcards are refused too.
"""

from __future__ import annotations

import asyncio
import contextlib
import ctypes
import functools
import inspect
import logging
import os
import sys
import threading
import time
from collections import Counter, deque
from collections.abc import Awaitable, Callable, Iterator, Mapping
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any, Generic, TypeGuard, TypeVar

import zenoh

from cdpr.path import Path
from cdpr.trajectory import SCHEMA_VERSION, Trajectory, TrajectoryError, TrajectoryLimits
from daemon.config.zenoh_config import ZenohSettings, build_zenoh_config, zenoh_reason
from daemon.interface.messages import (
    EVENT_KEY,
    VERSION_KEY,
    TrajectoryMessage,
    TrajectoryRequest,
    check_size,
    check_trajectory_head,
    decode_command,
    decode_json,
    encode,
    error_body,
    jsonable,
    no_checkpoint,
    parse_waypoints,
    reply_error,
    reply_ok,
    request_id,
    time_path_message,
)
from daemon.service.api import CommandError, DaemonHandler, rejection

log = logging.getLogger(__name__)

MESSAGES_PER_PASS = 1  # per queue and loop pass: the control cycle waits for at most one
# handler call per queue (a pass costs tens of µs, so throughput hardly suffers)
CLOSE_GRACE = 1.0  # s: how long close() waits for commands still running (enable, reset)
# the commands that wait for the drives or for planning and validation: one at a time
# (another meanwhile gets "busy"); a hold plans too but must never be turned away
_ONE_AT_A_TIME = ("enable", "reset", "goto", "identify_payload", "home", "pretension")
MAX_COMMAND_BYTES = 16 * 1024  # commands are small: decoding one on a zenoh thread is short
PARSE_SLICE = 2e-4  # s: the parse thread works at most about this long at a time,
PARSE_PAUSE = 1e-5  # s: then sleeps at least this long (see _Yielding)
PARSE_NICE = 5  # and runs below the loop's OS priority (see _set_up_parse_thread)
PARSE_TIMER_SLACK_NS = 1000  # how late its pauses may end (Linux's default: 50,000)
PR_SET_TIMERSLACK = 29  # <linux/prctl.h>
PARSE_SHARE = 0.25  # of one core: what the parse thread may use in a long flood, after
PARSE_BURST = 0.5  # s of CPU time it may use at once (a planner never notices the limit)
DECODE_ON_ARRIVAL_BYTES = 8 * 1024  # a trajectory this small is decoded (<= ~0.1 ms) and
# its head checked on the zenoh thread; bad ones are answered at once and never queued
QUEUED_LARGEST_MESSAGES = 2  # undecoded trajectories waiting weigh at most this many of
# the largest allowed (zenoh.max_message_bytes): each is parsed within PARSE_SHARE, a ~2 MB
# one in seconds, so sixteen of them (the queue's depth) kept the last waiting 30 s and
# more on a slow host; the depth still bounds how many small ones wait
INLINE_WAYPOINTS = 2  # a decoded trajectory of at most 2 waypoints is parsed on the loop
# (a move from A to B: no spline system to solve, ~0.1 ms), longer ones in the parse thread
_Parsed = TrajectoryRequest | tuple[str | None, CommandError]  # or (id, why refused)


@dataclass(frozen=True)
class _Raw:
    """A message queued undecoded (too long to decode on zenoh's thread): its bytes, and
    whether it came as a path.  (Not a tuple: a refusal is one.)"""

    data: bytes
    path: bool


_Message = _Raw | TrajectoryMessage
Reply = Callable[[dict[str, Any], bool], None]  # a command's answer: (body, ok), once
_Command = tuple[str, dict[str, Any], Reply]  # queued: the name, its args, who answers
_TrajectoryItem = tuple[_Message, zenoh.Query | None]  # queued, and who asks
_Item = TypeVar("_Item")
_Result = TypeVar("_Result")


class SessionError(RuntimeError):
    """zenoh could not open the daemon's session (an endpoint already in use, a router
    that cannot be reached, ...): one line naming the key, the endpoints and why."""


class _Inbox(Generic[_Item]):
    """A bounded hand-over of items from any thread to `process` on the event loop.

    When `process` returns a future, the next item waits until that future is done (one
    job at a time); the running item does not count against the depth.  With `weigh`,
    the items waiting also weigh at most `max_weight` together (an item that alone weighs
    more is taken when none waits): what bounds the wait of the last one when items cost
    work in proportion to their weight.
    """

    def __init__(
        self,
        loop: asyncio.AbstractEventLoop,
        depth: int,
        process: Callable[[_Item], asyncio.Future[Any] | None],
        weigh: Callable[[_Item], int] | None = None,
        max_weight: int = 0,
    ) -> None:
        self._loop = loop
        self._loop_thread = threading.get_ident()  # built on the loop thread
        self._depth = depth
        self._process = process
        self._weigh = weigh
        self._max_weight = max_weight
        self._weight = 0  # of the items waiting
        self._items: deque[_Item] = deque()
        self._lock = threading.Lock()
        self._scheduled = False
        self._running = False
        self._closed = False
        self.dropped = 0
        self.high_water = 0

    def has_room(self, limit: int | None = None, weight: int = 0) -> bool:
        """A hint (no reservation): would an item (of `weight`) be accepted now?"""
        limit = self._depth if limit is None else min(limit, self._depth)
        return len(self._items) < limit and self._fits(weight)

    def _fits(self, weight: int) -> bool:
        return self._weigh is None or not self._items or self._weight + weight <= self._max_weight

    def drop(self) -> None:
        """Count an item dropped before it was offered (see has_room)."""
        with self._lock:
            self.dropped += 1

    def offer(self, item: _Item, limit: int | None = None) -> bool:
        """Queue `item` unless `limit` (default: the depth) items wait already."""
        limit = self._depth if limit is None else min(limit, self._depth)
        weight = 0 if self._weigh is None else self._weigh(item)
        with self._lock:
            if self._closed or len(self._items) >= limit or not self._fits(weight):
                self.dropped += 1
                return False
            self._items.append(item)
            self._weight += weight
            self.high_water = max(self.high_water, len(self._items))
            wake = not (self._scheduled or self._running)
            self._scheduled = self._scheduled or wake
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
            items, self._items, self._weight = list(self._items), deque(), 0
            return items

    def _drain(self) -> None:
        for _ in range(MESSAGES_PER_PASS):
            with self._lock:
                if not self._items:
                    self._scheduled = False
                    return
                item = self._items.popleft()
                if self._weigh is not None:
                    self._weight -= self._weigh(item)
            job = self._process(item)
            if job is not None and not job.done():
                with self._lock:
                    self._scheduled, self._running = False, True
                job.add_done_callback(self._job_done)
                return
        self._loop.call_soon(self._drain)  # more may wait: let other callbacks run first

    def _job_done(self, _job: asyncio.Future[Any]) -> None:
        with self._lock:
            self._running = False
            self._scheduled = bool(self._items)
        if self._scheduled:
            self._drain()


class _ParseStopped(BaseException):
    """The interface is closing: the parse thread drops its message (a BaseException, so
    that no decoder's `except Exception` takes it for a bug)."""


class _Yielding:
    """A profile hook for the parse thread: every PARSE_SLICE it sleeps PARSE_PAUSE, and
    stops the parse (_ParseStopped) once `stop` is set.

    CPython makes a thread that wants the GIL wait up to the switch interval (5 ms) for a
    busy one, and on a loaded host the kernel may not run the loop at once while the
    parse thread computes; cdpr's parser has no points to pause at.  So at every
    function call and return in the parse thread this hook checks the clock and, after
    PARSE_SLICE of work, sleeps: the loop, if it waits, gets the GIL and a CPU meanwhile.
    Code that has points to pause at calls `checkpoint` there itself with the hook off
    (`unhooked`): a hook called at every call doubles the time of a long JSON decode.
    """

    def __init__(self, stop: threading.Event) -> None:
        self._since = time.perf_counter()
        self._stop = stop

    def checkpoint(self, *_hooked: object) -> None:
        """Sleep PARSE_PAUSE if PARSE_SLICE has gone by since the last pause; stop the
        parse if asked to.  Also the hook itself (frame, event, arg: unused)."""
        if time.perf_counter() - self._since > PARSE_SLICE:
            if self._stop.is_set():
                raise _ParseStopped
            time.sleep(PARSE_PAUSE)
            self._since = time.perf_counter()

    __call__ = checkpoint

    @contextlib.contextmanager
    def unhooked(self) -> Iterator[Callable[[], None]]:
        """The hook off meanwhile, for code that calls the checkpoint it gives itself."""
        sys.setprofile(None)
        try:
            yield self.checkpoint
        finally:
            sys.setprofile(self)


def _shutting_down(item: _Message) -> tuple[str | None, CommandError]:
    """The parse thread's answer to `item` once the interface closes (_ParseStopped)."""
    ident = item.id if isinstance(item, TrajectoryMessage) else None
    return ident, CommandError("busy", "the daemon is shutting down")


def _set_up_parse_thread() -> None:
    """Run the calling thread at nice PARSE_NICE (Linux: the nice value is per thread), so
    that the kernel favours the loop (3:1 at nice 5) whenever both want a CPU.  Not the
    lowest priority: at nice 19 a host's ordinary CPU-bound processes starved it (the
    first figure-eight took 3.9 s to accept beside two of them, against 0.28 s at 5;
    parsing is CPU-limited by PARSE_SHARE anyway).  And with a timer slack of
    PARSE_TIMER_SLACK_NS (also per thread): at Linux's default of 50 us each PARSE_PAUSE
    slept ~65 us, a third of a slice (10,000 waypoints: ~2,000 pauses)."""
    if sys.platform.startswith("linux"):  # elsewhere the nice value is the process's
        with contextlib.suppress(OSError):
            os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), PARSE_NICE)
        with contextlib.suppress(AttributeError, OSError):
            ctypes.CDLL(None).prctl(PR_SET_TIMERSLACK, PARSE_TIMER_SLACK_NS, 0, 0, 0)


class ZenohInterface:
    """The zenoh side of the daemon; `await start()`, then `await close()`.

    `handler` is called on the loop that ran start(); `publish_event` is thread-safe.
    `limits` bound the trajectories the interface will parse (its max_waypoints is
    lowered to zenoh.max_waypoints); the service checks the robot-specific limits.
    `ingress_limits` (full key -> Hz) are limited like zenoh.ingress_limits_hz: the keys
    outside the prefix that the session takes in (the ROS 2 bridge's trajectory topics).
    `timer` times a path's poses into the trajectory to run (cdpr.path.timing with the
    robot's model and tensions); without one, paths are refused.
    """

    def __init__(
        self,
        settings: ZenohSettings,
        handler: DaemonHandler,
        prefix: str,
        limits: TrajectoryLimits | None = None,
        ingress_limits: Mapping[str, float] | None = None,
        timer: Callable[[Path], Trajectory] | None = None,
    ) -> None:
        limits = TrajectoryLimits() if limits is None else limits
        self.timer = timer
        self.settings = settings
        self.ingress_limits = dict(ingress_limits or {})
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
        self._command_task: asyncio.Future[Any] | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._parser: ThreadPoolExecutor | None = None
        self._parse_credit = PARSE_BURST  # s of CPU time the parse thread may use now
        # set by close(): the parse thread drops what it parses, or waits for, at once (a
        # process exits only once it is done: in debt after a 2 MB message, seconds)
        self._stop_parsing = threading.Event()
        self._credit_time = 0.0  # (monotonic) when the credit was reckoned
        self._submission: asyncio.Future[Any] | None = None  # the verdict awaited
        self._commands: _Inbox[_Command] | None = None
        self._trajectories: _Inbox[_TrajectoryItem] | None = None
        self._events: _Inbox[bytes] | None = None
        self._state_task: asyncio.Task[None] | None = None

    @property
    def session(self) -> zenoh.Session:
        """The open session (after start()), which the ROS 2 bridge shares."""
        assert self._session is not None, "start() first"
        return self._session

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
        self._trajectories = _Inbox(
            loop,
            depth,
            self._run_trajectory,
            _undecoded_bytes,
            QUEUED_LARGEST_MESSAGES * self.settings.max_message_bytes,
        )
        self._events = _Inbox(loop, depth, self._put_event)
        self._parser = ThreadPoolExecutor(
            1, thread_name_prefix="cdprd-trajectory-parse", initializer=_set_up_parse_thread
        )
        conf = build_zenoh_config(self.settings, self.prefix, self.ingress_limits)
        try:
            session = await loop.run_in_executor(None, zenoh.open, conf)
        except BaseException as exc:
            self._parser.shutdown(wait=False)
            if isinstance(exc, zenoh.ZError):
                raise SessionError(self._open_failure(exc)) from None
            raise
        self._session = session
        drop = zenoh.CongestionControl.DROP  # a congested network never blocks the loop
        self._state_pub = session.declare_publisher(self.key("state"), congestion_control=drop)
        self._event_pub = session.declare_publisher(self.key("events"), congestion_control=drop)
        self._entities = [
            session.declare_subscriber(self.key("trajectory"), self._on_trajectory_put),
            session.declare_queryable(self.key("trajectory"), self._on_trajectory_query),
            session.declare_subscriber(self.key("path"), self._on_trajectory_put),
            session.declare_queryable(self.key("path"), self._on_trajectory_query),
            session.declare_queryable(self.key("cmd/**"), self._on_command_query),
            session.liveliness().declare_token(self.key("alive")),
        ]
        self._state_task = loop.create_task(self._publish_states())
        log.info("zenoh interface on %s (listen %s)", self.prefix, self.settings.listen_endpoints)

    def _open_failure(self, exc: zenoh.ZError) -> str:
        peer = self.settings.mode == "peer"
        key = "zenoh.listen" if peer else "zenoh.connect"
        endpoints = self.settings.listen_endpoints if peer else self.settings.connect
        return f"{key}: {', '.join(endpoints)}: cannot open the zenoh session: {zenoh_reason(exc)}"

    async def close(self) -> None:
        """Stop taking requests, answer the waiting ones "busy", publish the events still
        queued (those of the answers too), then close the session."""
        session, self._session = self._session, None
        if session is None:
            return
        self._closing = True
        self._stop_parsing.set()
        if self._state_task is not None:
            self._state_task.cancel()
        for entity in self._entities:
            _quietly(entity.undeclare)
        assert self._commands is not None and self._trajectories is not None
        waiting = self._trajectories.close()  # the running one may finish, no other starts
        if self._tasks:
            await asyncio.wait(self._tasks, timeout=CLOSE_GRACE)
        for task in list(self._tasks):
            task.cancel()
        if self._tasks:
            await asyncio.wait(self._tasks)  # their busy answers
        gone = CommandError("busy", "the daemon is shutting down")
        for name, _args, reply in self._commands.close():
            reply(reply_error(name, gone), False)
        for item, query in waiting:
            self._trajectory_outcome(_id(item), query, None, gone)
        assert self._events is not None and self._parser is not None
        for payload in self._events.close():
            self._put_event(payload)
        for publisher in (self._state_pub, self._event_pub):
            _quietly(publisher.undeclare)
        self._parser.shutdown(wait=False, cancel_futures=True)
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
        """Counters and the queues' high-water marks (docs/reference/zenoh-api.md, "Flow
        control")."""
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

    # -- zenoh threads ---------------------------------------------------------------------

    def _on_trajectory_put(self, sample: zenoh.Sample) -> None:
        try:
            if self._closing or sample.kind != zenoh.SampleKind.PUT:
                return  # a delete: nothing to run
            self._count("trajectory_puts")
            self._queue_trajectory(str(sample.key_expr), sample.payload, None)
        except Exception:
            self._count("callback_errors")
            log.exception("trajectory put callback failed")

    def _on_trajectory_query(self, query: zenoh.Query) -> None:
        try:
            if self._closing:
                self._reply(query, reply_error("trajectory", _busy("trajectory")), ok=False)
                return
            self._count("trajectory_queries")
            self._queue_trajectory(str(query.key_expr), query.payload, query)
        except Exception:
            self._count("callback_errors")
            log.exception("trajectory query callback failed")
            _quietly(query.drop)

    def _queue_trajectory(
        self, key: str, payload: zenoh.ZBytes | None, query: zenoh.Query | None
    ) -> None:
        """Queue a trajectory message (put, or query) for the loop, or refuse it now."""
        item = self._take_trajectory(key, payload)
        assert self._trajectories is not None
        if isinstance(item, tuple):
            self._trajectory_refused(*item, query)
        elif not self._trajectories.offer((item, query)):
            self._trajectory_refused(_id(item), _busy("trajectory"), query)

    def _take_trajectory(
        self, key: str, payload: zenoh.ZBytes | None
    ) -> _Message | tuple[str | None, CommandError]:
        """What to queue: the payload, or a small one decoded with its head checked; or
        (the sender's id if known, why not)."""
        if key not in (self.key("trajectory"), self.key("path")):
            return None, CommandError(
                "bad_request",
                f"send trajectories to the exact key {self.key('trajectory')}, paths to "
                f"{self.key('path')}",
            )
        path = key == self.key("path")
        assert self._trajectories is not None
        size = 0 if payload is None else len(payload)
        undecoded = 0 if _decoded_on_arrival(size) else size  # as _undecoded_bytes weighs
        if not self._trajectories.has_room(weight=undecoded):  # do not read what would drop
            self._trajectories.drop()
            return None, _busy("trajectory")
        if size == 0:
            what = "path" if path else "trajectory"
            return None, CommandError("bad_request", f"a {what} message needs a JSON payload")
        try:
            check_size(size, self.settings.max_message_bytes)
        except CommandError as exc:
            return None, exc
        assert payload is not None
        raw = _Raw(payload.to_bytes(), path)
        return self._decode_head(raw) if _decoded_on_arrival(len(raw.data)) else raw

    def _decode_head(
        self, raw: _Raw, checkpoint: Callable[[], None] = no_checkpoint
    ) -> TrajectoryMessage | tuple[str | None, CommandError]:
        """The JSON decoded (decode_json: `checkpoint` between pieces) and the message's
        head checked; or (the id if known, why not)."""
        try:
            data = decode_json(raw.data, self.settings.max_message_bytes, checkpoint)
        except CommandError as exc:
            return None, exc
        try:
            return check_trajectory_head(data, self.limits, raw.path)
        except CommandError as exc:
            return request_id(data), exc

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
            data: Any = {}  # no payload: no arguments (docs/reference/zenoh-api.md, "Commands")
            if payload is not None and len(payload) > 0:
                limit = min(MAX_COMMAND_BYTES, self.settings.max_message_bytes)
                check_size(len(payload), limit, "max_command_bytes")
                data = decode_json(payload.to_bytes(), limit)
            args = decode_command(name, data, self.limits.unit_tolerance)
            self.offer_command(name, args, functools.partial(self._reply, query))
        except CommandError as exc:
            self._count("commands_refused")
            self._reply(query, reply_error(name, exc), ok=False)
        except Exception:
            self._count("callback_errors")
            log.exception("command query callback failed")
            _quietly(query.drop)

    def offer_command(self, name: str, args: dict[str, Any], reply: Reply) -> None:
        """Queue command `name` with its validated `args` for the handler (any thread);
        `reply(body, ok)` gets its answer once, "busy" at once if the queue is full.  The
        ROS 2 bridge's services come in here too: one queue, one command at a time."""
        assert self._commands is not None
        if not self._commands.offer((name, args, reply)):
            reply(reply_error(name, _busy(name)), False)

    # -- parsing: in the parse thread, or on the loop for the smallest ---------------------

    def _parse_payload(self, payload: _Raw) -> _Parsed:
        """A whole message, from its bytes (in the parse thread: decode_json pauses
        between pieces itself, the profile hook off meanwhile)."""
        hook = sys.getprofile()
        assert isinstance(hook, _Yielding), "parsed outside the parse thread's budget"
        with hook.unhooked() as checkpoint:
            head = self._decode_head(payload, checkpoint)
        return head if isinstance(head, tuple) else self._parse_waypoints(head)

    def _parse_waypoints(self, message: TrajectoryMessage) -> _Parsed:
        """A trajectory's waypoints, or a path's poses timed (`timer`)."""
        try:
            if not message.path:
                return parse_waypoints(message, self.limits)
            if self.timer is None:
                raise CommandError("rejected", "this interface takes no paths (no timer)")
            return time_path_message(message, self.limits, self.timer)
        except CommandError as exc:
            return message.id, exc
        except Exception as exc:  # a bug in a decoder must not reach the sender as silence
            log.exception("trajectory decoding raised")
            return message.id, CommandError("internal", f"decoding failed: {type(exc).__name__}")

    async def _parse(self, item: _Message) -> _Parsed:
        if _inline(item):
            return self._parse_waypoints(item)
        parse = self._parse_payload if isinstance(item, _Raw) else self._parse_waypoints
        return await self.run_parser(functools.partial(parse, item), lambda: _shutting_down(item))

    async def run_parser(
        self, parse: Callable[[], _Result], stopped: Callable[[], _Result]
    ) -> _Result:
        """`parse()` in the parse thread, within its CPU budget; `stopped()` is the answer
        once the interface closes.  Every way a trajectory comes in (this interface and
        the ROS 2 bridge on its session) parses here: one thread, one budget."""
        assert self._loop is not None
        return await self._loop.run_in_executor(self._parser, self._in_budget, parse, stopped)

    def _in_budget(self, parse: Callable[[], _Result], stopped: Callable[[], _Result]) -> _Result:
        """Parse in the parse thread, pausing every PARSE_SLICE (_Yielding), within its CPU
        budget: PARSE_BURST seconds at once, PARSE_SHARE of a core in the long run, so
        that a flood of long trajectories leaves CPU time to the loop (and the host)."""
        now = time.monotonic()
        credit = min(PARSE_BURST, self._parse_credit + (now - self._credit_time) * PARSE_SHARE)
        if credit < 0.0:
            if self._stop_parsing.wait(-credit / PARSE_SHARE):
                return stopped()
            credit = 0.0
        began = time.thread_time()
        sys.setprofile(_Yielding(self._stop_parsing))
        try:
            parsed = parse()
        except _ParseStopped:
            return stopped()
        finally:
            sys.setprofile(None)
        self._parse_credit = credit - (time.thread_time() - began)
        self._credit_time = time.monotonic()
        return parsed

    # -- event loop ------------------------------------------------------------------------

    def _run_command(self, item: _Command) -> None:
        name, args, reply = item
        try:
            result = self._handler.command(name, args)
        except CommandError as exc:
            reply(reply_error(name, exc), False)
            return
        except Exception as exc:
            reply(reply_error(name, _failure(name, exc)), False)
            return
        one_at_a_time = name in _ONE_AT_A_TIME and not args.get("preempt")
        if not inspect.isawaitable(result):
            reply(reply_ok(name, result), True)
        elif one_at_a_time and self._command_task is not None and inspect.iscoroutine(result):
            result.close()  # never started: nothing happened
            self._count("commands_busy")
            busy = CommandError("busy", f"{name}: another command is still running, retry")
            reply(reply_error(name, busy), False)
        elif one_at_a_time:
            task = self._track(self._finish_command(name, result, reply))
            self._command_task = task
            task.add_done_callback(self._command_done)
        else:  # a hold plans its stop for a few ms, and never waits for the slot; a
            # request that preempts replaces what holds it
            self._track(self._finish_command(name, result, reply))

    def _command_done(self, task: asyncio.Future[Any]) -> None:
        if self._command_task is task:
            self._command_task = None

    async def _finish_command(
        self, name: str, pending: Awaitable[dict[str, Any]], reply: Reply
    ) -> None:
        try:
            body, ok = reply_ok(name, await pending), True
        except CommandError as exc:
            body, ok = reply_error(name, exc), False
        except asyncio.CancelledError:
            reply(reply_error(name, _busy(name)), False)
            raise
        except Exception as exc:
            body, ok = reply_error(name, _failure(name, exc)), False
        if self._command_task is asyncio.current_task():
            self._command_task = None  # free before replying: the sender may go on at once
        reply(body, ok)

    def _run_trajectory(self, item: _TrajectoryItem) -> asyncio.Future[Any] | None:
        """Submit one trajectory, or start the job that parses and submits it.

        Submissions run one at a time: an awaitable verdict (validation) holds the slot.
        The future returned is done once the job's trajectory is parsed and holds the
        slot, so the next one is parsed while this one is validated, and one parsed
        trajectory waits at most.  A small trajectory arriving with the slot free is
        parsed and submitted right here."""
        message, query = item
        free = self._submission is None or self._submission.done()
        if free and _inline(message):
            self._submit(self._parse_waypoints(message), query)
            return None
        assert self._loop is not None
        handed_over = self._loop.create_future()
        job = self._track(self._trajectory_job(message, query, handed_over))
        job.add_done_callback(lambda _: handed_over.done() or handed_over.set_result(None))
        return handed_over

    async def _trajectory_job(
        self,
        item: _Message,
        query: zenoh.Query | None,
        handed_over: asyncio.Future[None],
    ) -> None:
        """Parse, wait for the submission slot, submit."""
        try:
            parsed = await self._parse(item)
            while self._submission is not None and not self._submission.done():
                await asyncio.wait([self._submission])
        except asyncio.CancelledError:
            self._trajectory_outcome(_id(item), query, None, _busy("trajectory"))
            raise
        handed_over.set_result(None)
        self._submit(parsed, query)

    def _submit(self, parsed: _Parsed, query: zenoh.Query | None) -> None:
        """Refuse, or call the handler (the slot is free); an awaitable verdict takes it."""
        if isinstance(parsed, tuple):
            self._trajectory_refused(*parsed, query)
            return
        try:
            result = self._handler.submit_trajectory(parsed.trajectory, parsed.start, parsed.claim)
        except CommandError as exc:
            self._trajectory_outcome(parsed.id, query, None, exc)
        except Exception as exc:
            self._trajectory_outcome(parsed.id, query, None, _failure("trajectory", exc))
        else:
            if inspect.isawaitable(result):  # validation between control cycles
                self._submission = self._track(self._verdict(parsed.id, query, result))
            else:
                self._trajectory_outcome(parsed.id, query, result, None)

    async def _verdict(
        self, ident: str | None, query: zenoh.Query | None, pending: Awaitable[dict[str, Any]]
    ) -> None:
        try:
            result = await pending
        except CommandError as exc:
            self._trajectory_outcome(ident, query, None, exc)
        except asyncio.CancelledError:
            self._trajectory_outcome(ident, query, None, _busy("trajectory"))
            raise
        except Exception as exc:
            self._trajectory_outcome(ident, query, None, _failure("trajectory", exc))
        else:
            self._trajectory_outcome(ident, query, result, None)

    def _track(self, coroutine: Awaitable[None]) -> asyncio.Future[Any]:
        task = asyncio.ensure_future(coroutine)
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)
        return task

    def _trajectory_refused(
        self, ident: str | None, error: CommandError, query: zenoh.Query | None
    ) -> None:
        """Bad input or a full queue (any thread): the rejected event, and the reply.
        (A full queue counts its own drops.)"""
        if error.code != "busy":
            self._count("trajectories_refused")
        self._interface_event(_rejected_event(ident, error))
        if query is not None:
            self._reply(query, reply_error("trajectory", error, ident), ok=False)

    def _trajectory_outcome(
        self,
        ident: str | None,
        query: zenoh.Query | None,
        result: dict[str, Any] | None,
        error: CommandError | None,
    ) -> None:
        """The handler's verdict: the accepted / rejected event, and the reply when the
        trajectory came by query."""
        self._count("trajectories_accepted" if error is None else "trajectories_rejected")
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

    async def _publish_states(self) -> None:
        """The state at `state_rate_hz`, each in the control cycle's slack (a snapshot
        costs a few hundred microseconds, which must not land between a SYNC and its
        feedback).  A whole period late: skipped, never a burst to catch up."""
        loop = asyncio.get_running_loop()
        period = 1.0 / self.settings.state_rate_hz
        due = loop.time()
        while True:
            await asyncio.sleep(due - loop.time())
            await self._handler.slack()
            self._publish_state()
            due += period
            now = loop.time()
            if due <= now:
                self._count("state_late")
                due = now + period

    def _publish_state(self) -> None:
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
        else:
            self._count("replies")
        finally:
            _quietly(query.drop)


def _id(item: _Message) -> str | None:
    """The sender's id of a queued trajectory, if it was decoded on arrival."""
    return None if isinstance(item, _Raw) else item.id


def _inline(item: _Message) -> TypeGuard[TrajectoryMessage]:
    """A decoded trajectory of at most INLINE_WAYPOINTS waypoints: parsed on the loop (a
    path is timed in the parse thread, however short)."""
    return (
        isinstance(item, TrajectoryMessage) and not item.path and item.waypoints <= INLINE_WAYPOINTS
    )


def _decoded_on_arrival(size: int) -> bool:
    """Whether a trajectory of `size` bytes is decoded on the zenoh thread (small), not
    queued undecoded for the parse thread."""
    return size <= DECODE_ON_ARRIVAL_BYTES


def _undecoded_bytes(item: _TrajectoryItem) -> int:
    """A queued trajectory's weight: its size if it waits undecoded (the parse thread's
    work), else nothing (decoded on arrival: small)."""
    message = item[0]
    return len(message.data) if isinstance(message, _Raw) else 0


def _rejected_event(ident: str | None, error: CommandError) -> dict[str, Any]:
    return {EVENT_KEY: "trajectory_rejected", "id": ident, "error": error_body(error)}


def _busy(what: str) -> CommandError:
    return CommandError("busy", f"too many {what} requests waiting: this one was dropped, retry")


def _failure(what: str, exc: Exception) -> CommandError:
    """The refusal for an exception the handler let out: a TrajectoryError still names a
    limit the request breaks ("rejected", with its details); anything else is a bug."""
    if isinstance(exc, TrajectoryError):
        log.warning("%s: a TrajectoryError reached the interface: %s", what, exc)
        return rejection(what, exc)
    return _internal(what, exc)


def _internal(what: str, exc: Exception) -> CommandError:
    log.error("handler failed on %s", what, exc_info=exc)
    return CommandError("internal", f"the daemon failed on {what}: {type(exc).__name__}: {exc}")


def _quietly(action: Callable[[], Any]) -> None:
    """Undeclare / drop on shutdown: zenoh raises if the session is already gone."""
    with contextlib.suppress(zenoh.ZError):
        action()
