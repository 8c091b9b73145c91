"""Run the service: the real-time core process (bus, drives, the cycle, signals) and
its companion (daemon.process.companion_host).

`serve()` is what `cdprd run` and `cdprd demo` call.  READY=1 goes to systemd (from the
companion) only once the bus is open, the drives are up and zenoh is listening; the
watchdog is fed only while control cycles keep completing, so a stalled core gets the
service killed and restarted — and a restarted daemon comes up IDLE, held, never moving.
"""

from __future__ import annotations

import asyncio
import logging
import signal
import socket
import sys
from collections.abc import Awaitable, Callable, Mapping
from typing import Any

import can

from daemon.config import DaemonConfig
from daemon.process.companion_host import CompanionHost
from daemon.process.realtime import enter_realtime, leave_realtime
from daemon.process.systemd import Notifier
from daemon.service.bus_port import Buses
from daemon.service.safety import Trigger
from daemon.service.service import EXIT_BUS_LOST, Service

log = logging.getLogger("cdprd")

SOCKETCAND_CONNECT_TIMEOUT = 2.0  # s
ServiceHook = Callable[[Service], Awaitable[None]]


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
    companion: bool = True,
    after_start: ServiceHook | None = None,
) -> int:
    """The real-time core: run until SIGTERM/SIGINT (or `after_start` returns, for the
    demo); exit code.  With `companion`, the companion process (zenoh, planning,
    recordings, systemd notification) is started first and kept alive: its start-up
    (seconds of imports) is over before the drives start and their feedback counts."""
    loop = asyncio.get_running_loop()
    service = Service(config, bus)
    host = CompanionHost(service, config) if companion else None
    # before the drives start: locking the memory takes ~0.1 s, longer than their watchdogs
    realtime = enter_realtime(config.realtime)
    notifier = Notifier()  # start-up and shutdown; the companion sends READY=1 and the rest
    try:
        if host is not None:
            notifier.status("starting the companion process")
            host.start()
            failed = await host.wait_ready()
            if failed is not None:
                return failed
        notifier.status("starting drives")
        await service.start()
        for sig in (signal.SIGTERM, signal.SIGINT):
            loop.add_signal_handler(sig, service.stop)
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
        return code
    finally:
        # braked and shutting down: another SIGTERM/SIGINT (an impatient operator) must
        # not kill the clean-up half way and leave the recordings unfinished; it is logged
        # and ignored for the rest of the loop's life (closing the loop restores defaults)
        for sig in (signal.SIGTERM, signal.SIGINT):
            loop.add_signal_handler(sig, log.warning, "already stopping: signal ignored")
        if host is not None:
            await host.close()
        service.close()
        notifier.close()
        leave_realtime(realtime)
        ignore_stop_signals(loop)


def ignore_stop_signals(loop: asyncio.AbstractEventLoop) -> None:
    """SIGTERM and SIGINT ignored from now on, the loop's handlers removed with no
    window for a signal to slip through: asyncio's loop.close() closes its wakeup fd
    before it removes its handlers, and a signal in between prints a traceback."""
    signals = {signal.SIGTERM, signal.SIGINT}
    signal.pthread_sigmask(signal.SIG_BLOCK, signals)
    try:
        for sig in signals:
            loop.remove_signal_handler(sig)
            signal.signal(sig, signal.SIG_IGN)
    finally:
        signal.pthread_sigmask(signal.SIG_UNBLOCK, signals)
