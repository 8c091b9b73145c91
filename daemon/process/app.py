"""Run the service: bus, drives, zenoh, systemd notification, signals, recordings.

`serve()` is what `cdprd run` and `cdprd demo` call.  READY=1 goes to systemd only once
the bus is open, the drives are up and zenoh is listening; the watchdog is fed from the
event loop only while control cycles keep completing, so a stalled loop gets the
service killed and restarted — and a restarted daemon comes up IDLE, held, never moving.
"""

from __future__ import annotations

import asyncio
import logging
import signal
import socket
import sys
from collections.abc import Awaitable, Callable, Mapping
from pathlib import Path
from typing import Any, TypeVar

import can

from cdpr.controller import ControlOutput
from daemon.config import DaemonConfig
from daemon.process.recording import CanRecorder, CycleRecord, TelemetryRecorder, session_path
from daemon.process.systemd import Notifier, Progress, run_watchdog
from daemon.service.bus_port import Buses
from daemon.service.safety import Trigger
from daemon.service.service import EXIT_BUS_LOST, Service

log = logging.getLogger("cdprd")

SOCKETCAND_CONNECT_TIMEOUT = 2.0  # s
ServiceHook = Callable[[Service], Awaitable[None]]
Recorder = TypeVar("Recorder", TelemetryRecorder, CanRecorder)


def open_bus(config: DaemonConfig) -> Buses:
    """The python-can bus the config names (hardware, vcan, socketcand, ...), or its buses
    by name when it has several; if one cannot be opened, one line on stderr naming it
    and exit code EXIT_BUS_LOST."""
    opened: dict[str, can.BusABC] = {}
    for k, c in enumerate(config.buses):
        try:
            if c.interface == "socketcand":
                _reach_socketcand(c.options)
            opened[c.bus_name] = c.open()
        except (can.CanError, OSError, ValueError, ImportError) as exc:
            for bus in opened.values():
                bus.shutdown()
            key = "can" if len(config.buses) == 1 else f"can.{k}"
            print(
                f"error: {config.source}: {key}: cannot open the bus interface={c.interface} "
                f"channel={c.channel}: {' '.join(str(exc).split())}",
                file=sys.stderr,
            )
            raise SystemExit(EXIT_BUS_LOST) from None
    return opened if len(opened) > 1 else opened.popitem()[1]


def close_bus(buses: Buses) -> None:
    """Shut down what open_bus opened."""
    for bus in buses.values() if isinstance(buses, Mapping) else [buses]:
        bus.shutdown()


def _reach_socketcand(options: dict[str, Any]) -> None:
    """Connect once to the socketcand server the options name (OSError naming it if
    none answers).  python-can's client retries a refused connection for 10 s in a busy
    loop, logging a warning per attempt (hundreds of thousands of lines)."""
    host, port = options.get("host"), options.get("port")
    if host is None or port is None:
        return  # python-can names what is missing
    try:
        socket.create_connection((host, port), SOCKETCAND_CONNECT_TIMEOUT).close()
    except OSError as exc:
        raise OSError(f"no socketcand server answers at {host}:{port}: {exc}") from None


async def serve(
    config: DaemonConfig,
    bus: Buses,
    *,
    zenoh: bool = True,
    after_start: ServiceHook | None = None,
) -> int:
    """Run until SIGTERM/SIGINT (or `after_start` returns, for the demo); exit code."""
    loop = asyncio.get_running_loop()
    notifier = Notifier()
    service = Service(config, bus)
    interface = None
    recorders = _recorders(config, service)
    writers = [asyncio.create_task(r.run()) for r in recorders]
    try:
        notifier.status("starting drives")
        await service.start()
        if zenoh:
            from daemon.interface.zenoh_io import SessionError, ZenohInterface

            prefix = config.zenoh.key_prefix(config.robot.name)
            interface = ZenohInterface(config.zenoh, service, prefix, config.trajectory)
            try:
                await interface.start()
            except SessionError as exc:  # e.g. the port is in use: one line, exit 1
                raise SystemExit(f"error: {config.source}: {exc}") from None
            service.subscribe(interface.publish_event)
        for sig in (signal.SIGTERM, signal.SIGINT):
            loop.add_signal_handler(sig, service.stop)
        notifier.ready()
        update_status = _status_updates(notifier, service, config)
        service.subscribe(update_status)
        update_status({})
        watchdog = asyncio.create_task(
            run_watchdog(notifier, Progress(lambda: service.stats.cycles))
        )
        log.info(
            "cdprd %s: %d drives (%s) on %s, %g Hz, state %s",
            config.robot.name,
            service.n,
            config.drives.protocol,
            config.channels,
            config.controller.rate_hz,
            service.machine.state.value,
        )
        if after_start is not None:
            demo = asyncio.create_task(after_start(service))
            demo.add_done_callback(lambda _: service.stop(Trigger.COMMAND))
        code = await service.wait_stopped()
        notifier.stopping()
        await asyncio.sleep(5 * service.period)  # brake frames out, drives confirm
        watchdog.cancel()
        return code
    finally:
        # braked and shutting down: another SIGTERM/SIGINT (an impatient operator) must
        # not kill the clean-up half way and leave the recordings unfinished; it is logged
        # and ignored for the rest of the loop's life (closing the loop restores defaults)
        for sig in (signal.SIGTERM, signal.SIGINT):
            loop.add_signal_handler(sig, log.warning, "already stopping: signal ignored")
        if interface is not None:
            await interface.close()
        for writer in writers:
            writer.cancel()
        for recorder in recorders:
            recorder.close()
        service.close()


def _status_text(service: Service, config: DaemonConfig) -> str:
    """`systemctl status`'s one line: the safety state, the fault that braked, where."""
    fault = service.machine.fault
    state = service.machine.state.value
    where = f"{config.robot.name} on {config.channels}"
    return f"{state}; {where}" if fault is None else f"{state}: {fault.line()}; {where}"


def _status_updates(
    notifier: Notifier, service: Service, config: DaemonConfig
) -> Callable[[dict], None]:
    """An event sink that keeps STATUS= current: sent when the line changes."""
    last = [""]

    def on_event(event: dict) -> None:
        text = _status_text(service, config)
        if text != last[0]:
            last[0] = text
            notifier.status(text)

    return on_event


def _recorders(config: DaemonConfig, service: Service) -> list:
    """Telemetry (MCAP) and raw CAN recorders the config asks for, attached to the
    service's observers; each file is named after the session's start time.  A file
    that cannot be created stops the start-up with one line naming the key and the file."""
    recorders: list = []
    rec = config.recording
    if rec.telemetry:
        path = config.path(rec.telemetry)
        key = f"{config.source}: recording.telemetry"
        telemetry = _open(key, TelemetryRecorder, path, recorders)

        def record_cycle(t: float, out: ControlOutput) -> None:
            ref = out.reference.pose
            telemetry.record(
                CycleRecord(
                    t=t,
                    position=out.pose.position,
                    quaternion=out.pose.quaternion,
                    twist=out.twist,
                    lengths=[fb.length for fb in service.driver.feedback],
                    tensions=out.tensions,
                    forces=out.commands,
                    safety=service.machine.state.value,
                    reference=(ref.position, ref.quaternion),
                )
            )

        service.cycle_listeners.append(record_cycle)
        recorders.append(telemetry)
    if rec.can_log:
        path = config.path(rec.can_log)
        # names the frames sent (they carry none on SocketCAN; on several buses, the name)
        channel = config.buses[0].channel
        key = f"{config.source}: recording.can_log"
        frames = _open(key, CanRecorder, path, recorders, channel=channel)
        service.frame_listeners.append(lambda msg, rx: frames.record(msg, rx=rx))
        recorders.append(frames)
    return recorders


def _open(
    key: str, make: Callable[..., Recorder], path: Path, opened: list, **options: Any
) -> Recorder:
    """`make(file, **options)` for this session's file.  If the file cannot be created
    (missing or read-only directory, bad suffix, ...): close the recorders already
    `opened` and exit with an error naming `key` and the file, not a traceback."""
    file = session_path(path)
    try:
        return make(file, **options)
    except (OSError, ValueError) as exc:
        for recorder in opened:
            recorder.close()
        reason = exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc)
        raise SystemExit(f"error: {key}: cannot record to {file}: {reason}") from None
