"""Stopping the daemon processes that tests start, the way systemd or an operator would."""

from __future__ import annotations

import signal
import subprocess
import time


def stop_impatiently(proc: subprocess.Popen, timeout: float = 15.0) -> None:
    """SIGTERM every 20 ms until the process exits, as an impatient operator would."""
    end = time.monotonic() + timeout
    while proc.poll() is None and time.monotonic() < end:
        proc.send_signal(signal.SIGTERM)
        time.sleep(0.02)


def finish(proc: subprocess.Popen, terminate: bool = True, timeout: float = 15.0) -> str:
    """SIGTERM (with `terminate`, if still running), then the process's output once it
    exits; killed if it hangs longer than `timeout`."""
    if terminate and proc.poll() is None:
        proc.send_signal(signal.SIGTERM)
    try:
        out, _ = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        out, _ = proc.communicate()
    return out
