"""What a control cycle's I/O alone costs on this host: the floor under any cycle design.

A core process (SCHED_FIFO where permitted, on CPU 0, the CPUs kept awake as the core
keeps them: realtime.cpu_latency_us 0) runs cycles of nothing but the core's I/O on
socket-pair buses (sim_bus.bus.pairbus's stream pairs and records): a timerfd tick, a
SYNC record written to each bus, a deadline timerfd armed, the drives' answers read
(another process, on CPU 1, writes each bus's answers to a SYNC in one go, as the
simulator does), the command records written (one write a bus), the deadline left to
fire (its expiry read, as the core reads it).  No frame is decoded past its record,
nothing is checked or computed.  Two ways of waiting:

- `asyncio`: the readers on an asyncio loop, as the real-time core runs its cycle today
  (daemon.service.service: PeriodicTimer, DeadlineTimer and the buses' fds added with
  loop.add_reader);
- `plain`: one thread blocking in the timerfd's read and in poll() on the buses.

Per way: the core's CPU per cycle (time.process_time: user and system) and the cycles
that did not get every answer before their deadline.  And `tick_us`: the CPU of the
tick alone, a SCHED_FIFO thread blocking in the periodic timerfd's read and doing
nothing else (what one wake-up costs on this host; the cycle above has several).
Compare with bench/cycle_profile.py's `idle_core_us_per_cycle` (the daemon's core,
nothing enabled) and the 0.15 of a core issue 30 asks of the whole cycle at 1 kHz
(150 us a cycle).

    python bench/io_floor.py [--json] [--seconds 5] [--rate 1000] [--buses 2] [--drives 8]
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import os
import select
import socket
import time
from collections.abc import Callable

from daemon.config import RealtimeConfig
from daemon.process.realtime import realtime
from drivers.clock import DeadlineTimer, PeriodicTimer
from sim_bus.bus.pairbus import FRAME, bus_pair

SYNC_ID, TPDO_BASE, RPDO_BASE = 0x080, 0x180, 0x200
DEADLINE = 0.8  # of a period: the daemon's default safety.feedback_deadline
SETTLE = 0.5  # s before measuring
CORE = RealtimeConfig(priority=50, cpus=(0,), lock_memory=False)  # the core's, unlocked
# (CPU s at the end, (CPU s, cycles, misses) at the start, cycles, misses at the end)
Window = tuple[float, tuple[float, int, int], int, int]


def _records(base: int, count: int) -> bytes:
    return b"".join(FRAME.pack(time.time(), base + i, 0, 8, bytes(8)) for i in range(count))


def drives(ends: list[socket.socket], per_bus: int) -> None:
    """The drives' process: each SYNC record on a bus answered with `per_bus` records in
    one write; returns when the core closes its ends."""
    with contextlib.suppress(OSError):
        os.sched_setaffinity(0, {1})
    by_fd = {end.fileno(): end for end in ends}
    poller = select.poll()
    for fd in by_fd:
        poller.register(fd, select.POLLIN)
    while True:
        for fd, _ in poller.poll():
            try:
                data = by_fd[fd].recv(1 << 16)
            except ConnectionResetError:
                return
            if not data:
                return
            for _, can_id, *_rest in FRAME.iter_unpack(data):
                if can_id == SYNC_ID:
                    by_fd[fd].send(_records(TPDO_BASE, per_bus))


class Cycle:
    """The core's side: what a tick sends and what the answers complete."""

    def __init__(self, ends: list[socket.socket], per_bus: int, period: float) -> None:
        self.ends, self.per_bus, self.period = ends, per_bus, period
        self.due = 0  # answers still due this cycle
        self.waiting = False  # a cycle is open
        self.cycles = self.misses = 0
        for end in ends:
            end.setblocking(False)

    def open(self, deadline: DeadlineTimer) -> None:
        if self.waiting:  # the last cycle's answers never all came
            self.misses += 1
        sync = FRAME.pack(time.time(), SYNC_ID, 0, 0, bytes(8))
        for end in self.ends:
            end.send(sync)
        self.due, self.waiting = self.per_bus * len(self.ends), True
        deadline.arm(time.monotonic() + DEADLINE * self.period)

    def take(self, end: socket.socket) -> None:
        with contextlib.suppress(BlockingIOError):
            self.due -= len(end.recv(1 << 16)) // FRAME.size
        if self.waiting and self.due <= 0:
            self.waiting = False
            commands = _records(RPDO_BASE, self.per_bus)
            for each in self.ends:
                each.send(commands)
            self.cycles += 1


def run_asyncio(cycle: Cycle, seconds: float) -> Window:
    async def main(timer: PeriodicTimer, deadline: DeadlineTimer) -> Window:
        loop = asyncio.get_running_loop()

        def tick() -> None:
            if timer.expirations():
                cycle.open(deadline)

        loop.add_reader(timer.fileno(), tick)
        loop.add_reader(deadline.fileno(), deadline.expired)
        for end in cycle.ends:
            loop.add_reader(end.fileno(), cycle.take, end)
        await asyncio.sleep(SETTLE)
        start = (time.process_time(), cycle.cycles, cycle.misses)
        await asyncio.sleep(seconds)
        return time.process_time(), start, cycle.cycles, cycle.misses

    with PeriodicTimer(cycle.period) as timer, DeadlineTimer() as deadline:
        return asyncio.run(main(timer, deadline))


def run_plain(cycle: Cycle, seconds: float) -> Window:
    with PeriodicTimer(cycle.period) as timer, DeadlineTimer() as deadline:
        os.set_blocking(timer.fileno(), True)
        by_fd = {end.fileno(): end for end in cycle.ends}
        poller = select.poll()
        for fd in by_fd:
            poller.register(fd, select.POLLIN)
        begin = time.monotonic()
        start = None
        while True:
            os.read(timer.fileno(), 8)  # the tick
            now = time.monotonic()
            if start is None and now >= begin + SETTLE:
                start = (time.process_time(), cycle.cycles, cycle.misses)
            if now >= begin + SETTLE + seconds:
                return time.process_time(), start, cycle.cycles, cycle.misses
            cycle.open(deadline)
            due = now + DEADLINE * cycle.period
            while cycle.waiting:
                left = due - time.monotonic()
                ready = poller.poll(max(left, 0.0) * 1e3) if left > 0 else []
                if not ready:
                    break
                for fd, _ in ready:
                    cycle.take(by_fd[fd])


def tick_cost(rate: float, seconds: float) -> float:
    """CPU us per wake-up of a thread that only waits for the periodic timerfd's ticks."""
    with realtime(CORE), PeriodicTimer(1.0 / rate) as timer:
        os.set_blocking(timer.fileno(), True)
        ticks, end, begin = 0, time.monotonic() + seconds, time.process_time()
        while time.monotonic() < end:
            os.read(timer.fileno(), 8)
            ticks += 1
        return round((time.process_time() - begin) * 1e6 / ticks, 1)


def measure(way: str, rate: float, seconds: float, buses: int, drives_n: int) -> dict:
    pairs = [bus_pair() for _ in range(buses)]
    child = os.fork()
    if child == 0:  # the drives
        for core_end, _ in pairs:
            core_end.close()
        drives([d for _, d in pairs], drives_n // buses)
        os._exit(0)
    for _, drive_end in pairs:
        drive_end.close()
    try:
        cycle = Cycle([c for c, _ in pairs], drives_n // buses, 1.0 / rate)
        runner: Callable = run_asyncio if way == "asyncio" else run_plain
        with realtime(CORE):
            end, (begin, cycles0, misses0), cycles, misses = runner(cycle, seconds)
    finally:
        for core_end, _ in pairs:
            core_end.close()
        os.waitpid(child, 0)
    n = cycles - cycles0
    return {
        "cycles": n,
        "core_us_per_cycle": round((end - begin) * 1e6 / n, 1),
        "missed_deadlines": misses - misses0,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--json", action="store_true", help="one JSON object only")
    parser.add_argument("--seconds", type=float, default=5.0)
    parser.add_argument("--rate", type=float, default=1000.0, help="Hz")
    parser.add_argument("--buses", type=int, default=2)
    parser.add_argument("--drives", type=int, default=8, help="split evenly over the buses")
    args = parser.parse_args()
    if args.buses < 1 or args.drives < args.buses or args.drives % args.buses:
        parser.error("--drives must be a positive multiple of --buses")
    out = {"rate_hz": args.rate, "buses": args.buses, "drives": args.drives}
    for way in ("asyncio", "plain"):
        out[way] = measure(way, args.rate, args.seconds, args.buses, args.drives)
    out["tick_us"] = tick_cost(args.rate, args.seconds)
    if args.json:
        print(json.dumps(out))
        return
    for way in ("asyncio", "plain"):
        f = out[way]
        print(
            f"{way:8s} {f['core_us_per_cycle']:7.1f} us of CPU a cycle, "
            f"{f['missed_deadlines']} missed deadlines of {f['cycles']} cycles"
        )
    print(f"tick     {out['tick_us']:7.1f} us of CPU a wake-up of the timer alone")


if __name__ == "__main__":
    main()
