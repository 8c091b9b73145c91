"""How long starting a process holds up the real-time core (daemon.process.ordinary).

    python bench/spawn_stall.py --json [--load 2] [--spawns 30]

The caller runs at SCHED_FIFO 50 (as the core does) beside `--load` CPU-bound processes
at normal priority and starts /bin/true `--spawns` times, each way: `demoted` is a
posix_spawn whose child drops to SCHED_OTHER before its exec (what spawn_ordinary did
before the trampoline); `spawn_ordinary` is the daemon's.  Printed per way: the time
the caller was held (ms: p50, p90, max).  Needs root or RLIMIT_RTPRIO >= 50.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

from daemon.process.realtime import Child, spawn_ordinary

HOG = "import time\nend = time.monotonic() + {}\nwhile time.monotonic() < end: pass"
PAUSE = 0.01  # s between spawns


def demoted(argv: list[str]) -> Child:
    normal = (os.SCHED_OTHER, os.sched_param(0))
    return Child(os.posix_spawn(argv[0], argv, dict(os.environ), scheduler=normal))


def ordinary(argv: list[str]) -> Child:
    return spawn_ordinary(argv, dict(os.environ))


def held(spawn, count: int) -> dict[str, float]:
    """Times (ms) each of `count` spawns held the caller: p50, p90, max."""
    times = []
    for _ in range(count):
        started = time.perf_counter()
        child = spawn(["/bin/true"])
        times.append((time.perf_counter() - started) * 1e3)
        while child.poll() is None:
            time.sleep(0.001)
        time.sleep(PAUSE)
    times.sort()
    pick = lambda q: round(times[min(int(q * len(times)), len(times) - 1)], 3)  # noqa: E731
    return {"p50_ms": pick(0.5), "p90_ms": pick(0.9), "max_ms": round(times[-1], 3)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--json", action="store_true", help="one JSON object only")
    parser.add_argument("--load", type=int, default=2, help="CPU-bound processes beside")
    parser.add_argument("--spawns", type=int, default=30)
    args = parser.parse_args()
    seconds = 2.0 + 2 * args.spawns * (PAUSE + 0.05)
    hogs = [Child(os.posix_spawn(sys.executable, [sys.executable, "-c", HOG.format(seconds)],
                                 dict(os.environ))) for _ in range(args.load)]  # fmt: skip
    try:
        time.sleep(1.0)  # the hogs get going
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(50))
        out = {"load": args.load, "spawns": args.spawns}
        out["demoted"] = held(demoted, args.spawns)
        out["spawn_ordinary"] = held(ordinary, args.spawns)
    finally:
        os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
        for hog in hogs:
            hog.kill()
    print(json.dumps(out) if args.json else json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
