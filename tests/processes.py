"""Starting the simulator processes tests need, and stopping the daemon processes they
start the way systemd or an operator would."""

from __future__ import annotations

import re
import signal
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
ANNOUNCED = re.compile(r"serving socketcand on 127\.0\.0\.1:(\d+) channel (\S+)")


def serve_simulator(
    config: Path, *options: str, stderr: int = subprocess.DEVNULL
) -> tuple[subprocess.Popen, int, str]:
    """`python -m sim_bus --config CONFIG OPTIONS` serving its bus over socketcand on a
    free loopback port, text pipes on stdin and stdout: (process, port, channel) once it
    announced them (log lines may come first)."""
    args = [sys.executable, "-m", "sim_bus", "--config", str(config), *options]
    proc = subprocess.Popen(
        [*args, "--serve-socketcand", "127.0.0.1:0"],
        cwd=ROOT,
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        stderr=stderr,
        text=True,
    )
    line = ""
    for _ in range(20):
        line = proc.stdout.readline()
        match = ANNOUNCED.search(line)
        if match:
            return proc, int(match.group(1)), match.group(2)
        if not line:
            break
    proc.kill()
    proc.communicate()
    raise AssertionError(f"the simulator announced no socketcand endpoint: {line!r}")


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
