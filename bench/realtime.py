"""What locking the core's memory costs at start-up; prints one JSON object:

- `enter_ms`: enter_realtime with lock_memory only (mlockall(MCL_CURRENT | MCL_FUTURE)),
  after importing what the service imports;
- `rss_before_mb`, `rss_after_mb`, `locked_mb`: VmRSS before and after, VmLck after;
- `thread_start_ms`, `thread_rss_mb`: starting one thread once memory is locked (its
  whole stack becomes resident) and the resident memory it added;
- `warnings`: what enter_realtime could not do (then the figures are not the locked ones).

    python bench/realtime.py
"""

from __future__ import annotations

import json
import threading
import time
from pathlib import Path

import daemon.process.app  # noqa: F401  what the service imports, to be locked
from daemon.config import RealtimeConfig
from daemon.process.realtime import enter_realtime, leave_realtime


def _status_mb(key: str) -> float:
    status = Path("/proc/self/status").read_text()
    return int(status.split(f"{key}:")[1].split()[0]) / 1024


def main() -> None:
    rss_before = _status_mb("VmRSS")
    started = time.perf_counter()
    state = enter_realtime(RealtimeConfig(priority=0, lock_memory=True))
    enter_ms = (time.perf_counter() - started) * 1e3
    rss_after, locked = _status_mb("VmRSS"), _status_mb("VmLck")
    done = threading.Event()
    thread = threading.Thread(target=done.wait)
    started = time.perf_counter()
    thread.start()
    thread_ms = (time.perf_counter() - started) * 1e3
    thread_rss = _status_mb("VmRSS") - rss_after
    done.set()
    thread.join()
    leave_realtime(state)
    figures = {
        "enter_ms": round(enter_ms, 1),
        "rss_before_mb": round(rss_before),
        "rss_after_mb": round(rss_after),
        "locked_mb": round(locked),
        "thread_start_ms": round(thread_ms, 1),
        "thread_rss_mb": round(thread_rss, 1),
        "warnings": state.warnings,
    }
    print(json.dumps(figures))


if __name__ == "__main__":
    main()
