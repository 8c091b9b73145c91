"""Normal scheduling for what the real-time core starts, and the trampoline that gives it.

`drop_inherited_realtime` puts the calling process back at SCHED_OTHER on every CPU.
Run as a script, ``python -I -S ordinary.py PROGRAM ARG...`` does that, then execs
PROGRAM (a path) with its arguments and the same environment.

Why a trampoline (daemon.process.realtime.spawn_ordinary): posix_spawn is a vfork, which
holds the calling thread, and with it the GIL and so the whole core, until the child
execs.  A child demoted to SCHED_OTHER before that exec queues behind every normal
process for a CPU to get there: 5 ms median and up to 8.6 ms with two CPU hogs on this
2-CPU host (`python bench/spawn_stall.py`, three runs; 17 ms once in a scratch run),
long enough on a busier host for the drives' heartbeat consumers to stop the robot.
Started at SCHED_FIFO priority 1 (above every normal process, below the cycle), the
child reaches its exec at once; this file, run without site or imports beyond os and
sys (~40 ms of CPU at priority 1, never competing with the cycle), then drops to normal
scheduling before PROGRAM starts.
Standard library only, so that it runs by path before any package is importable.
"""

from __future__ import annotations

import contextlib
import os
import sys


def drop_inherited_realtime() -> None:
    """Normal scheduling on every CPU for a process the core spawned (the companion, the
    demo's client): they inherit SCHED_FIFO and the core's CPUs, and must never compete
    with the cycle at its priority.  Lowering one's own priority needs no permission."""
    if os.sched_getscheduler(0) != os.SCHED_OTHER:
        os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
    with contextlib.suppress(OSError):  # CPUs it may not use (a cpuset): keep what it has
        os.sched_setaffinity(0, range(os.cpu_count() or 1))


def main(argv: list[str]) -> int:
    """Drop to normal scheduling and exec argv; 127 (like a shell) if that fails."""
    if not argv:
        print("usage: python -I -S ordinary.py PROGRAM [ARG...]", file=sys.stderr)
        return 2
    drop_inherited_realtime()
    try:
        os.execv(argv[0], argv)
    except OSError as exc:
        print(f"error: cannot run {argv[0]}: {exc.strerror}", file=sys.stderr)
    return 127


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
