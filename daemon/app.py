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
from collections.abc import Awaitable, Callable

import can

from cdpr.controller import ControlOutput
from daemon.config import DaemonConfig
from daemon.recording import CanRecorder, CycleRecord, TelemetryRecorder, session_path
from daemon.safety import Trigger
from daemon.service import Service
from daemon.systemd import Notifier, Progress, run_watchdog

log = logging.getLogger("cdprd")

ServiceHook = Callable[[Service], Awaitable[None]]


def open_bus(config: DaemonConfig) -> can.BusABC:
    """The python-can bus the config names (hardware, vcan, socketcand, ...)."""
    c = config.can
    try:
        return c.open()
    except (can.CanError, OSError, ValueError, ImportError) as exc:
        raise SystemExit(
            f"cannot open CAN bus interface={c.interface} channel={c.channel}: {exc}"
        ) from None


async def serve(
    config: DaemonConfig,
    bus: can.BusABC,
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
            from daemon.zenoh_io import ZenohInterface

            prefix = config.zenoh.key_prefix(config.robot.name)
            interface = ZenohInterface(config.zenoh, service, prefix, config.trajectory)
            await interface.start()
            service.subscribe(interface.publish_event)
        for sig in (signal.SIGTERM, signal.SIGINT):
            loop.add_signal_handler(sig, service.stop)
        notifier.ready()
        notifier.status(
            f"{service.machine.state.value}; {config.robot.name} on {config.can.channel}"
        )
        watchdog = asyncio.create_task(
            run_watchdog(notifier, Progress(lambda: service.stats.cycles))
        )
        log.info(
            "cdprd %s: %d drives (%s) on %s, %g Hz, state %s",
            config.robot.name,
            service.n,
            config.drives.protocol,
            config.can.channel,
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
        for sig in (signal.SIGTERM, signal.SIGINT):
            loop.remove_signal_handler(sig)
        if interface is not None:
            await interface.close()
        for writer in writers:
            writer.cancel()
        for recorder in recorders:
            recorder.close()
        service.close()


def _recorders(config: DaemonConfig, service: Service) -> list:
    """Telemetry (MCAP) and raw CAN recorders the config asks for, attached to the
    service's observers; each file is named after the session's start time."""
    recorders: list = []
    rec = config.recording
    if rec.telemetry:
        telemetry = TelemetryRecorder(session_path(config.path(rec.telemetry)))

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
        frames = CanRecorder(session_path(config.path(rec.can_log)))
        service.frame_listeners.append(lambda msg, rx: frames.record(msg, rx=rx))
        recorders.append(frames)
    return recorders
