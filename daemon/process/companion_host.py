"""The core's side of the companion process (DESIGN §16).

The real-time core runs the cycle and nothing else; its companion (daemon.process.
companion) runs zenoh, planning and validation, recordings and systemd notification.
This module, in the core:

- spawns the companion (`python -m daemon.process.companion FD RING`) with one end of a
  SOCK_SEQPACKET pair (daemon.process.wire) and the shared curve ring
  (daemon.process.curve_ring), and says hello (after its code's fingerprint: a companion
  of other code stops the daemon; then the config, the core's clock origin,
  the ring's ranges still in use, the leases the last companion had it keep:
  daemon.service.lease);
- serves its calls in the cycle's slack, or at the turn every completed cycle gives
  (Service.slack: however long a silent drive keeps each cycle waiting): core
  commands, the reference at a time, and planned trajectories (a curve in the ring,
  sampled in place; its range is handed back when the core drops the curve); its
  "alive" messages are read the same way, so a companion is judged silent only when
  it is;
- pushes events as they happen, the state at zenoh.state_rate_hz and, when recording,
  cycle records (fixed-size rows, daemon.process.cycle_rows) and CAN frames in batches,
  each in the cycle's slack (for the live view alone, one row per 1/view.rate_hz of
  cycle time: the companion draws it); a full socket
  drops the message (counted), the core never waits;
- supervises it: a companion silent for safety.companion_hang is killed, a dead one is
  restarted (with a growing pause); a moving robot without a live companion for
  safety.companion_lost brakes.  A companion that exits with an error before it was
  ever ready (a zenoh port in use, a recording file it cannot create) stops the daemon
  with its exit code instead: restarting would fail the same way.
"""

from __future__ import annotations

import asyncio
import logging
import os
import socket
import sys
import time
import weakref
from collections.abc import Awaitable
from typing import Any

import can

from cdpr.controller import ControlOutput
from cdpr.trajectory.core import Curve
from daemon.config import DaemonConfig
from daemon.process import wire
from daemon.process.curve_ring import CurveRing
from daemon.process.cycle_rows import CycleRows, Throttle
from daemon.process.realtime import Child, spawn_ordinary
from daemon.process.recording import frame_fields
from daemon.service.api import CommandError
from daemon.service.lease import Kept
from daemon.service.safety import Fault, Trigger
from daemon.service.service import Service

log = logging.getLogger("cdprd")

SUPERVISE_PERIOD = 0.1  # s between checks of the companion's health
BATCH_PERIOD = 0.05  # s between batches of cycle records and CAN frames
CALL_SLACK = 4e-4  # s a call may still start before the next tick (one takes <~0.2 ms)
STATE_SLACK = 5e-4  # s the state snapshot needs before the next tick (~0.15-0.3 ms)
START_TIMEOUT = 30.0  # s for a new companion's first message (its imports, on a busy host)
RESTART_PAUSES = (0.2, 0.5, 1.0, 2.0, 5.0)  # s before restarting, after each death in a row
MAX_BATCH = 200  # cycle records held between batches
# CAN frames held between batches: as many cycles' worth as MAX_BATCH, each with a SYNC, a
# heartbeat and up to 4 TPDOs and 4 RPDOs per drive (CiA 301); the records and the frames
# of a hold-up are then dropped together, and a recording's two files agree
FRAMES_PER_DRIVE = 8
FRAMES_PER_MESSAGE = 4096  # CAN frames per datagram (~34 bytes each: < wire.MAX_MESSAGE)
STOP_WAIT = 3.0  # s the companion gets to finish its recordings after the core stops


class CompanionHost:
    """Spawn, serve and supervise the companion of `service` (see the module doc)."""

    def __init__(self, service: Service, config: DaemonConfig) -> None:
        self.service = service
        self.config = config
        self.dropped = 0  # messages the companion did not take in time
        self.restarts = 0
        self.exit_code: int | None = None  # set when the companion cannot start at all
        self._process: Child | None = None
        self._killed: Child | None = None  # the silent companion killed (logged once)
        self._sock = None
        self._ever_ready = False
        self._last_heard = time.monotonic()
        self._allowed_silence = START_TIMEOUT
        self._start_limit = START_TIMEOUT  # s given for "ready", from...
        self._start_deadline = time.monotonic() + START_TIMEOUT  # ... its spawn or "starting"
        self._lost_since: float | None = None  # no live companion since
        self._deaths = 0  # in a row, for the restart pause
        self._restart_at = 0.0
        self._tasks: list[asyncio.Task] = []
        self._serving: asyncio.Task | None = None  # the calls of the current companion
        self._cycles = CycleRows(service.n, MAX_BATCH)  # recorded, not yet sent
        self._frames: list[tuple] = []  # recorded CAN frames not yet sent
        self._frame_room = MAX_BATCH * (FRAMES_PER_DRIVE * service.n + 2)
        self.unrecorded = 0  # cycle records and CAN frames dropped here (no slack)
        self.ready = asyncio.Event()  # a companion is up (zenoh listening)
        # made now, before the memory is locked and the drives start: mapping it later
        # would hold the cycle up
        self.ring = CurveRing.create()
        self._in_ring: dict[int, int] = {}  # offset -> bytes of the curves the core holds
        self._leases: Kept = {}  # the companion's, kept for the next one (plain data)
        self._code = wire.code_fingerprint()  # read now, while the installation is this one
        recording = config.recording
        if recording.telemetry:
            service.cycle_listeners.append(self._record_cycle)
        elif config.view.enabled:
            self._view_rows = Throttle(config.view.rate_hz)
            service.cycle_listeners.append(self._sample_cycle)
        if recording.can_log:
            service.frame_listeners.append(self._record_frame)
        service.subscribe(self._send_event)

    # -- lifecycle ------------------------------------------------------------------------

    def start(self) -> None:
        """Spawn the companion and start serving and supervising it (on the running loop)."""
        self._spawn()
        loop = asyncio.get_running_loop()
        self._tasks = [
            loop.create_task(self._supervise()),
            loop.create_task(self._push_states()),
        ]
        recording = self.config.recording
        if recording.telemetry or recording.can_log or self.config.view.enabled:
            self._tasks.append(loop.create_task(self._push_batches()))

    async def wait_ready(self) -> int | None:
        """Wait for the companion's first "ready" (zenoh listening): None then; else the
        exit code to stop with, if it could not start (it said why on stderr) or did not
        come up: its first message within START_TIMEOUT, "ready" within
        wire.STARTING_LIMIT of its "starting"."""
        while not self.ready.is_set():
            if self.exit_code is not None:
                return self.exit_code
            if time.monotonic() > self._start_deadline:
                log.error(
                    "the companion process did not come up within %g s of %s",
                    self._start_limit,
                    "its start-up check" if self._start_limit > START_TIMEOUT else "its start",
                )
                return 1
            await asyncio.sleep(0.02)
        return None

    async def close(self) -> None:
        """Hand over the last records, close the link and give the companion STOP_WAIT
        seconds to finish (its recordings), then kill it."""
        for task in self._tasks:
            task.cancel()
        self._flush_batches()
        self._disconnect()
        if self.unrecorded:
            log.warning(
                "recording incomplete: %d cycle records and CAN frames dropped in the core "
                "(no slack to hand them to the companion)",
                self.unrecorded,
            )
        # the ring stays mapped while the service may still sample a curve in it; the
        # process's exit unmaps it
        process = self._process
        if process is not None:
            deadline = time.monotonic() + STOP_WAIT
            while process.poll() is None and time.monotonic() < deadline:
                await asyncio.sleep(0.02)
            if process.poll() is None:
                log.warning("the companion did not exit within %g s: killed", STOP_WAIT)
                process.kill()
                while process.poll() is None:
                    await asyncio.sleep(0.01)

    def _spawn(self) -> None:
        core_end, companion_end = wire.socket_pair()
        env = dict(os.environ)
        if env.get("WATCHDOG_PID") == str(os.getpid()):
            del env["WATCHDOG_PID"]  # the companion feeds the watchdog (NotifyAccess=all)
        fd, ring = companion_end.fileno(), self.ring.fd
        try:
            argv = [sys.executable, "-m", "daemon.process.companion", str(fd), str(ring)]
            self._process = spawn_ordinary(argv, env, (fd, ring))
        finally:
            companion_end.close()
        self.connect(core_end)
        log.info("companion started (pid %d)", self._process.pid)

    def connect(self, sock: socket.socket) -> None:
        """Serve a companion on `sock` (the core's end of wire.socket_pair), from its
        hello on: the config, the core's clock origin, the ring's ranges in use, the
        leases the last companion had the core keep."""
        self._sock = sock
        self._serving = asyncio.get_running_loop().create_task(self._serve(sock))
        self._last_heard = time.monotonic()
        self._allowed_silence = START_TIMEOUT  # until it first speaks: imports take seconds
        self._start_limit = START_TIMEOUT
        self._start_deadline = self._last_heard + START_TIMEOUT
        level = logging.getLevelName(logging.getLogger().getEffectiveLevel()).lower()
        in_use = list(self._in_ring.items())
        state = self.service.state()
        hello = ("hello", self.config, self.service.t0, state, level, in_use, self._leases)
        if not (wire.send(sock, ("code", self._code)) and wire.send(sock, hello)):
            log.error("the companion did not take its hello")

    def _disconnect(self) -> None:
        if self._serving is not None:
            self._serving.cancel()
            self._serving = None
        if self._sock is not None:
            self._sock.close()
            self._sock = None

    # -- supervision ----------------------------------------------------------------------

    async def _supervise(self) -> None:
        safety = self.config.safety
        while True:
            await asyncio.sleep(SUPERVISE_PERIOD)
            now = time.monotonic()
            process = self._process
            if process is not None and process.poll() is not None:
                self._on_exit(process.returncode, now)
            elif process is not None and now - self._last_heard > self._allowed_silence:
                if process is not self._killed:  # it may take a while to die: say it once
                    log.error(
                        "the companion (pid %d) has been silent for %.1f s: killing it",
                        process.pid,
                        now - self._last_heard,
                    )
                    self._killed = process
                process.kill()
            live = process is not None and now - self._last_heard <= self._allowed_silence
            if live:
                self._lost_since = None
            elif self._lost_since is None:
                self._lost_since = self._last_heard
            elif now - self._lost_since > safety.companion_lost and self.service.machine.powered:
                self.service.brake(
                    Fault(
                        Trigger.COMPANION_LOST,
                        f"no companion process for {now - self._lost_since:.1f} s "
                        f"(safety.companion_lost {safety.companion_lost:g} s)",
                    )
                )
            if self._process is None and self.exit_code is None and now >= self._restart_at:
                self.restarts += 1
                self._spawn()

    def _on_exit(self, code: int, now: float) -> None:
        self._disconnect()
        self._process = None
        self.ready.clear()
        other_code = code == wire.OTHER_CODE
        if other_code or (not self._ever_ready and code not in (0, -9)):
            # it never came up, or runs other code than this process (an upgrade under the
            # running service): the same again on restart; it said why on stderr (one
            # line), and the daemon stops with its exit code (systemd starts it again,
            # on the installed code, in IDLE)
            if other_code:
                log.error("the installed cdprd changed under the running service: stopping")
            else:
                log.debug("the companion could not start (exit code %d): stopping", code)
            self.exit_code = code if code > 0 else 1
            if self.service.running:
                trigger = Trigger.COMPANION_LOST if other_code else Trigger.SIGTERM
                self.service.stop(trigger, exit_code=self.exit_code)
            return
        pause = RESTART_PAUSES[min(self._deaths, len(RESTART_PAUSES) - 1)]
        self._deaths += 1
        self._restart_at = now + pause
        log.error("the companion exited with code %d: restarting it in %g s", code, pause)

    # -- calls ----------------------------------------------------------------------------

    async def _serve(self, sock: socket.socket) -> None:
        """Read the companion's messages, each in the cycle's slack: a call starts only
        while the next tick is more than CALL_SLACK away, or at this task's turn (one
        message), so that no burst of them (a zenoh flood reaches the core as calls)
        delays a cycle and none waits longer than a few cycles."""
        loop = asyncio.get_running_loop()
        service = self.service
        fd = sock.fileno()  # kept: _disconnect closes the socket before this task ends
        while True:
            readable = loop.create_future()
            loop.add_reader(fd, _set_once, readable)
            try:
                await readable
            finally:
                loop.remove_reader(fd)
            while True:
                await service.slack(CALL_SLACK)
                messages, closed = wire.receive(sock, 1)
                if messages:
                    self._last_heard = time.monotonic()
                    self._allowed_silence = self.config.safety.companion_hang
                    self._dispatch(messages[0])
                if closed:
                    self._disconnect()
                    return
                if not messages:
                    break

    def _dispatch(self, message: tuple) -> None:
        kind = message[0]
        if kind == "call":
            _, ident, method, args = message
            self._call(ident, method, args)
        elif kind == "starting":  # its start-up check compiles: minutes on a cold cache
            self._allowed_silence = self._start_limit = wire.STARTING_LIMIT
            self._start_deadline = self._last_heard + wire.STARTING_LIMIT
        elif kind == "ready":
            self.ready.set()
            self._ever_ready = True
            self._deaths = 0
            log.info("companion ready")

    def _call(self, ident: int, method: str, args: tuple) -> None:
        service = self.service
        try:
            if method == "command":
                result: Any = service.command(*args)
            elif method == "command_keeping":  # payload, observer: answered at once
                name, body, leases = args
                result = service.command(name, body)
                self._leases = leases  # taken: kept for the next companion, timed by none
            elif method == "reference_at":
                result = service.reference_at(*args)
            elif method == "follow":
                header, offset, count, version, what = args
                result = service.follow_planned(
                    self._ring_curve(header, offset, count), version, what
                )
            else:
                raise CommandError("internal", f"the core has no call {method!r}")
        except Exception as exc:
            if not isinstance(exc, CommandError):  # a bug: reported as "internal"
                log.exception("core call %s failed", method)
            self._reply(ident, False, wire.error_payload(exc))
            return
        if isinstance(result, Awaitable):
            task = asyncio.ensure_future(result)
            task.add_done_callback(lambda done: self._reply_when_done(ident, done))
        else:
            self._reply(ident, True, result)

    def _ring_curve(self, header: dict, offset: int, count: int) -> Curve:
        """The curve the companion wrote into the ring; its range goes back to the
        companion when the core drops it (at once if it is not followed)."""
        curve = self.ring.curve(header, offset, count)
        self._in_ring[offset] = 8 * count
        weakref.finalize(curve, self._dropped, offset)
        return curve

    def _dropped(self, offset: int) -> None:
        nbytes = self._in_ring.pop(offset)
        self._send(("free", offset, nbytes))

    def _reply_when_done(self, ident: int, task: asyncio.Future) -> None:
        if task.cancelled():
            self._reply(ident, False, ("internal", "the core stopped", {}))
        elif task.exception() is not None:
            self._reply(ident, False, wire.error_payload(task.exception()))
        else:
            self._reply(ident, True, task.result())

    def _reply(self, ident: int, ok: bool, payload: Any) -> None:
        self._send(("reply", ident, ok, payload))

    def _send(self, message: tuple) -> None:
        try:
            sent = self._sock is not None and wire.send(self._sock, message)
        except ValueError as exc:  # larger than a datagram may be: a bug, never a stall
            log.error("not sent to the companion: %s", exc)
            sent = False
        if not sent:
            self.dropped += 1

    # -- what leaves the core -------------------------------------------------------------

    def _send_event(self, event: dict[str, Any]) -> None:
        self._send(("event", event))

    async def _push_states(self) -> None:
        """The state at zenoh.state_rate_hz, each in the cycle's slack (a snapshot costs
        a few hundred microseconds); a late one is skipped, never a burst."""
        period = 1.0 / self.config.zenoh.state_rate_hz
        while True:
            await asyncio.sleep(period)
            await self.service.slack(STATE_SLACK)
            if self._sock is not None:
                state = self.service.state()
                state["companion"] = {"restarts": self.restarts, "dropped": self.dropped}
                self._send(("state", state))

    def _record_cycle(self, t: float, out: ControlOutput) -> None:
        rows = self._cycles
        if rows.full:  # no slack for a while: drop, never grow
            self.dropped += 1
            self.unrecorded += 1
            return
        service = self.service
        rows.add(t, out, [fb.length for fb in service.driver.feedback], service.machine.state)

    def _sample_cycle(self, t: float, out: ControlOutput) -> None:
        if self._view_rows.due(t):
            self._record_cycle(t, out)

    def _record_frame(self, msg: can.Message, rx: bool) -> None:
        if len(self._frames) >= self._frame_room:
            self.dropped += 1
            self.unrecorded += 1
            return
        self._frames.append(frame_fields(msg, rx))

    async def _push_batches(self) -> None:
        while True:
            await asyncio.sleep(BATCH_PERIOD)
            await self.service.slack()
            self._flush_batches()

    def _flush_batches(self) -> None:
        if self._cycles.filled:
            self._send(("cycles", self._cycles.take()))
        frames, self._frames = self._frames, []
        for start in range(0, len(frames), FRAMES_PER_MESSAGE):
            self._send(("frames", frames[start : start + FRAMES_PER_MESSAGE]))


def _set_once(future: asyncio.Future) -> None:
    if not future.done():
        future.set_result(None)
