"""The companion process: everything of the daemon that is not the control cycle
(DESIGN §16).

    python -m daemon.process.companion FD RING

spawned by the core (daemon.process.companion_host) with its end of the link on FD and
the shared curve ring (daemon.process.curve_ring) on RING.
It runs zenoh (daemon.interface.zenoh_io) with the planner (daemon.service.planner)
behind it, the recordings, the live view (daemon.process.live_view: the scene of
daemon.process.scene, also recorded), and systemd notification: READY=1 once zenoh listens and
the core's drives are up (the core starts them when this process says it is ready),
STATUS= as the safety state changes, the watchdog fed only while the core's cycles keep
completing.  It exits when the core closes the link; SIGTERM and SIGINT are the core's
to act on (they brake the robot there) and are ignored here, so that the recordings
get finished.  Exit code 1 with one line on stderr when it cannot start.
"""

from __future__ import annotations

import asyncio
import logging
import signal
import socket
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeVar

from cdpr import ConfigError
from daemon.config import DaemonConfig
from daemon.process import warm_up, wire
from daemon.process.app import ignore_stop_signals
from daemon.process.companion_link import OtherCodeError, RemoteLink, greeted
from daemon.process.cycle_rows import Throttle, records
from daemon.process.heap import freeze_start_up, reuse_freed_memory
from daemon.process.logsetup import configure_logging
from daemon.process.ordinary import drop_inherited_realtime
from daemon.process.recording import CanRecorder, TelemetryRecorder
from daemon.process.recording_files import file_limits
from daemon.process.systemd import Notifier, Progress, run_watchdog
from daemon.service.planner import Planner, load_checks, path_timer
from daemon.service.safety import Fault, Trigger

if TYPE_CHECKING:
    from daemon.process.live_view import LiveView

log = logging.getLogger("cdprd")

HELLO_TIMEOUT = 10.0  # s for the core's first message
Recorder = TypeVar("Recorder", TelemetryRecorder, CanRecorder)


def main(argv: list[str] | None = None) -> int:
    drop_inherited_realtime()
    reuse_freed_memory()  # the path timing's large arrays, without page faults
    args = sys.argv[1:] if argv is None else argv
    if len(args) != 2 or not all(arg.isdigit() for arg in args):
        print(
            "usage: python -m daemon.process.companion FD RING (spawned by the core)",
            file=sys.stderr,
        )
        return 2
    sock = socket.socket(fileno=int(args[0]))
    try:
        config, level, link = greeted(sock, int(args[1]), HELLO_TIMEOUT)
    except OSError as exc:
        print(f"error: companion: no hello from the core: {exc}", file=sys.stderr)
        return 1
    except OtherCodeError as exc:
        print(f"error: companion: {exc}", file=sys.stderr)
        return wire.OTHER_CODE
    configure_logging(level)
    _announce_start_up_check(sock)
    try:
        load_checks(config)  # compiled or loaded before the core's hang timer runs
    except ConfigError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    freeze_start_up()
    return asyncio.run(run(config, link))


def _announce_start_up_check(sock: socket.socket) -> None:
    """Tell the core and systemd that the workspace and wrench checks are being compiled
    or loaded: both then wait up to wire.STARTING_LIMIT for "ready", not the seconds
    imports take."""
    if not warm_up.is_warm():
        log.info(
            "compiling the workspace and wrench checks (numba's cache is cold after an "
            "install or upgrade): up to minutes on a small computer, once"
        )
    wire.send(sock, ("starting",))
    Notifier().notify(f"EXTEND_TIMEOUT_USEC={int(wire.STARTING_LIMIT * 1e6)}")


async def run(config: DaemonConfig, link: RemoteLink) -> int:
    """Serve until the core closes the link; the exit code."""
    link.start()  # "alive" from now on: the core's hang timer runs
    from daemon.config.zenoh_config import build_zenoh_config
    from daemon.interface.zenoh_io import SessionError, ZenohInterface

    loop = asyncio.get_running_loop()
    for sig in (signal.SIGTERM, signal.SIGINT):
        loop.add_signal_handler(sig, log.debug, "companion: signal left to the core")
    notifier = Notifier()
    # fed from now on while the core's cycles complete: a restarted companion takes over
    # before zenoh is up, within the unit's WatchdogSec
    watchdog = asyncio.create_task(run_watchdog(notifier, Progress(lambda: link.cycles)))
    planner = Planner(config, link)
    interface = view = ros2 = warming = None
    recorders = _recorders(config, link)
    _report_recordings(planner, recorders)
    writers = [asyncio.create_task(r.run()) for r in recorders.values()]
    try:
        if config.view.enabled:
            from daemon.process.live_view import LiveView, ViewError

            try:
                view = LiveView(config.view, config.robot.name)
            except ViewError as exc:  # e.g. the port is in use
                print(f"error: {config.source}: {exc}", file=sys.stderr)
                return 1
        _feed(config, link, recorders.get("telemetry"), view)
        prefix = config.zenoh.key_prefix(config.robot.name)
        limits: dict[str, float] = {}  # the ROS 2 topics' and services' ingress limits
        if config.ros2.enabled:  # ROS 2 over rmw_zenoh: on the daemon's session, or
            # on a session of its own to the ROS 2 graph's router (ros2.router)
            from daemon.interface.ros2_bridge import Ros2Bridge, ingress_limits

            limits = ingress_limits(config.ros2, config.zenoh)
        router = None
        if config.ros2_router is not None:
            router = build_zenoh_config(config.ros2_router, prefix, limits)
        interface = ZenohInterface(
            config.zenoh,
            planner,
            prefix,
            config.trajectory,
            limits if router is None else {},
            path_timer(config),
        )
        try:
            await interface.start()
        except SessionError as exc:  # e.g. the port is in use
            print(f"error: {config.source}: {exc}", file=sys.stderr)
            return 1
        planner.subscribe(interface.publish_event)
        for name, recorder in recorders.items():  # paused from the start: no room
            if recorder.status != "recording":
                planner.emit(_recording_event(name, recorder))
        # the leases the core kept from the last companion: a lapse now reaches zenoh
        planner.leases.resume(link.kept_leases)
        if config.ros2.enabled:
            ros2 = Ros2Bridge(config.ros2, planner, interface, router, config.robot)
            await ros2.start()
        link.ready()  # the core starts its drives now
        await link.core_started()
        notifier.ready()  # bus, drives and zenoh all up
        warming = warm_up.start(config.source)  # the first path's kernels, if not cached
        update_status = _status_updates(notifier, link, config)
        planner.subscribe(update_status)
        update_status({})
        await link.closed.wait()  # the core has stopped (and said STOPPING=1)
        return 0
    finally:
        watchdog.cancel()
        if warming is not None and warming.poll() is None:
            warming.kill()  # what it compiled so far stays cached
            warming.wait()
        # the recordings first: the core handed its last records over before it closed
        # the link, and closing zenoh under a flood of queries on a busy host may outlast
        # the core's wait for this process (companion_host.STOP_WAIT)
        for writer in writers:
            writer.cancel()
        for recorder in recorders.values():
            recorder.close()
        if ros2 is not None:
            await ros2.close()
        if interface is not None:
            await interface.close()
        if view is not None:
            view.close()
        link.close()
        ignore_stop_signals(loop)  # systemd signals the whole service: us too


def _status_text(state: dict[str, Any], config: DaemonConfig) -> str:
    """`systemctl status`'s one line: the safety state, the fault that braked, where."""
    fault = state.get("fault")
    where = f"{config.robot.name} on {config.channels}"
    name = state.get("state", "init")
    if not fault:
        return f"{name}; {where}"
    return f"{name}: {Fault(Trigger(fault['trigger']), fault['message']).line()}; {where}"


def _status_updates(
    notifier: Notifier, link: RemoteLink, config: DaemonConfig
) -> Callable[[dict], None]:
    """An event sink that keeps STATUS= current: sent when the line changes."""
    last = [""]

    def on_event(event: dict) -> None:
        text = _status_text(link.state(), config)
        if text != last[0]:
            last[0] = text
            notifier.status(text)

    return on_event


WORKSPACE_EVERY = 5.0  # s between the workspace scenes sent to the live view
VIEW_VOXELS = 4000  # the boundary's cubes in the view (~0.2 MB a scene)


def _workspace_view(config: DaemonConfig) -> list[tuple[str, bytes]]:
    """The workspace scene (daemon.process.scene.workspace_scene): the saved map's
    boundary at home if the map is still this config's (logged if not), the
    environment's boxes and planes and the workspace box."""
    import numpy as np

    from cdpr.workspace_map import shell
    from daemon.config.workspace_files import stored_map
    from daemon.process.scene import WORKSPACE_TOPIC, workspace_scene

    saved, why = stored_map(config)
    if saved is None:
        log.info("live view: no workspace boundary (%s)", why)
        voxels, margins, size = np.zeros((0, 3)), np.zeros(0), 0.0
    else:
        voxels, margins = shell(saved, 0, VIEW_VOXELS)
        size = saved.step
    limits = config.pose_limits
    anchors = config.robot.geometry.anchors
    corners = (limits.lower, limits.upper)
    update = workspace_scene(corners, voxels, margins, size, config.environment, anchors)
    return [(WORKSPACE_TOPIC, update.encode())]


def _feed(
    config: DaemonConfig,
    link: RemoteLink,
    telemetry: TelemetryRecorder | None,
    view: LiveView | None,
) -> None:
    """Hand the core's cycle rows to the telemetry recording (every one) and the scene
    (daemon.process.scene, at view.rate_hz of cycle time) to the recording and the live
    view; the core's events to both as log messages.  Stamps are wall-clock times."""
    if telemetry is None and view is None:
        return
    from daemon.interface.robot_drawing import cable_faults
    from daemon.process.scene import SceneBuilder, timing_figures

    n = config.robot.n_cables
    limits = config.pose_limits
    scene = SceneBuilder(config.robot, (limits.lower, limits.upper))
    throttle = Throttle(config.view.rate_hz)
    sinks = [sink for sink in (telemetry, view) if sink is not None]
    workspace = _workspace_view(config)
    shown = Throttle(1.0 / WORKSPACE_EVERY)  # the workspace to the view, now and then
    recorded = telemetry is None  # the workspace to the recording, once

    def on_rows(rows: bytes) -> None:
        nonlocal recorded
        origin = time.time_ns() - round(link.now() * 1e9)  # the core's clock -> wall clock
        state = link.state()
        now = time.time_ns()
        if not recorded:
            telemetry.log_messages(workspace, now)
            recorded = True
        if view is not None and shown.due(link.now()):
            view.log_messages(workspace, now)
        for record in records(rows, n):
            stamp = origin + round(record.t * 1e9)
            if telemetry is not None:
                telemetry.record(record, stamp)
            if throttle.due(record.t):
                faults = cable_faults(state, n)
                messages = scene.encode(record, stamp, faults, timing_figures(state.get("cycle")))
                for sink in sinks:
                    sink.log_messages(messages, stamp)

    def on_event(event: dict) -> None:
        stamp = time.time_ns()
        messages = scene.encode_event(event, stamp)
        for sink in sinks:
            sink.log_messages(messages, stamp)

    link.batch_sinks["cycles"] = on_rows
    link.subscribe(on_event)


def _recorders(config: DaemonConfig, link: RemoteLink) -> dict[str, Any]:
    """Telemetry (MCAP, with the scene's standard channels) and raw CAN recorders the
    config asks for, by key ("telemetry", "can_log"), fed by the core's batches; each
    writes a series of files within the config's limits.  A file that cannot be
    created stops the start-up with one line naming the key and the file."""
    recorders: dict[str, Any] = {}
    rec = config.recording
    limits = file_limits(rec)
    if rec.telemetry:
        from daemon.process.scene import standard_channels

        key = f"{config.source}: recording.telemetry"
        path = config.path(rec.telemetry)
        channels = standard_channels()
        recorders["telemetry"] = _open(
            key, TelemetryRecorder, path, recorders, limits=limits, channels=channels
        )
    if rec.can_log:
        # names the frames sent (they carry none on SocketCAN; on several buses, the name)
        channel = config.buses[0].channel
        key = f"{config.source}: recording.can_log"
        frames = _open(
            key, CanRecorder, config.path(rec.can_log), recorders, limits=limits, channel=channel
        )

        def record_frames(batch: list) -> None:
            for fields in batch:
                frames.record_fields(fields)

        link.batch_sinks["frames"] = record_frames
        recorders["can_log"] = frames
    return recorders


def _open(
    key: str, make: Callable[..., Recorder], path: Path, opened: dict, **options: Any
) -> Recorder:
    """`make(path, **options)`.  If its file cannot be created (missing or read-only
    directory, bad suffix, ...): close the recorders already `opened` and exit with an
    error naming `key` and the file, not a traceback."""
    try:
        return make(path, **options)
    except (OSError, ValueError) as exc:
        for recorder in opened.values():
            recorder.close()
        if isinstance(exc, OSError):
            file, reason = exc.filename or path, exc.strerror or str(exc)
        else:
            file, reason = path, str(exc)
        raise SystemExit(f"error: {key}: cannot record to {file}: {reason}") from None


def _report_recordings(planner: Planner, recorders: dict[str, Any]) -> None:
    """Each recorder in every status reply and the state ("recording": {key: its
    report}), and each change of its status (paused, resumed, stopped) as an event."""
    planner.reports["recording"] = lambda: {k: r.report() for k, r in recorders.items()}
    for name, recorder in recorders.items():
        recorder.on_change = lambda changed, name=name: planner.emit(
            _recording_event(name, changed)
        )


def _recording_event(name: str, recorder: Any) -> dict[str, Any]:
    return {"event": "recording", "recording": name, **recorder.report()}


if __name__ == "__main__":
    sys.exit(main())
