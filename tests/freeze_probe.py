"""`python -m tests.freeze_probe FILE PARENT`: one thread per CPU, pinned to it at SCHED_FIFO
90, sleeps 2 ms at a time and writes a line `cpu start seconds` to FILE whenever it woke
more than 10 ms after it went to sleep: the CPU was frozen (this host's hypervisor
stops a virtual CPU for 20-130 ms at times, unseen in /proc/stat's steal).  Runs until
killed (tests.host_steal.FreezeWatch), until PARENT (the pid that started it) is gone (a
killed test run must not leave a real-time process behind: one did, for 45 minutes), or
for an hour at most.  Each thread sleeps almost all the time: it cannot starve the
machine."""

from __future__ import annotations

import contextlib
import os
import sys
import threading
import time

SLEEP = 0.002  # s
FROZEN = 0.010  # s: a wake-up this much later than the sleep began
LIFETIME = 3600.0  # s at most


def _watch(cpu: int, out, parent: int) -> None:
    os.sched_setaffinity(0, {cpu})
    # not root: at normal priority, where real-time threads may delay it too
    with contextlib.suppress(OSError):
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(90))
    last = time.monotonic()
    end = last + LIFETIME
    while True:
        time.sleep(SLEEP)
        now = time.monotonic()
        if os.getppid() != parent or now > end:
            os._exit(0)
        if now - last > FROZEN:
            out.write(f"{cpu} {last:.6f} {now - last:.6f}\n")
        last = now


def main() -> None:
    out = open(sys.argv[1], "w", buffering=1)  # noqa: SIM115 (open until killed)
    parent = int(sys.argv[2])  # not getppid() here: the parent may be gone already
    for cpu in sorted(os.sched_getaffinity(0)):
        threading.Thread(target=_watch, args=(cpu, out, parent), daemon=True).start()
    threading.Event().wait()


if __name__ == "__main__":
    main()
