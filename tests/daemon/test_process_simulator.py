"""The demo's simulator in a process of its own (daemon.cli.simulated.ProcessSimulator):
its drives boot and answer on the socket pair, its truth comes stamped on this host's
monotonic clock, SIGTERM ends it cleanly, and a killed daemon leaves no simulator behind."""

from __future__ import annotations

import asyncio
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

from daemon.cli.simulated import ProcessSimulator
from daemon.config import load_config

ROOT = Path(__file__).resolve().parents[2]
CONFIG = ROOT / "config" / "reference8-cia402.yaml"
pytestmark = pytest.mark.timeout(90)


def test_the_simulator_process_boots_its_drives_and_logs_the_truth() -> None:
    async def scenario() -> None:
        simulator = ProcessSimulator(load_config(CONFIG), CONFIG)
        await simulator.start()
        try:
            bus = simulator.daemon_bus
            heard: set[int] = set()
            end = time.monotonic() + 5.0
            while len(heard) < 8 and time.monotonic() < end:
                await asyncio.sleep(0.05)
                heard |= {m.arbitration_id - 0x700 for m in bus.drain() if m.arbitration_id > 0x700}
            assert heard == set(range(1, 9)), f"heartbeats of nodes {sorted(heard)}"
            await asyncio.sleep(0.2)
        finally:
            await simulator.stop()
        assert simulator.process.returncode == 0
        assert len(simulator.truth) >= 5
        last = simulator.truth[-1]
        assert abs(last["monotonic"] - time.monotonic()) < 2.0  # the same clock as ours
        assert len(last["tensions"]) == 8 and min(last["tensions"]) > 0.0
        stamps = [r["monotonic"] for r in simulator.truth]
        assert stamps == sorted(stamps)

    asyncio.run(scenario())


def test_a_killed_daemon_leaves_no_simulator_behind() -> None:
    script = textwrap.dedent(
        f"""
        import asyncio, os, signal
        from pathlib import Path
        from daemon.cli.simulated import ProcessSimulator
        from daemon.config import load_config

        async def main():
            path = Path({str(CONFIG)!r})
            simulator = ProcessSimulator(load_config(path), path)
            await simulator.start()
            print(simulator.process.pid, flush=True)
            os.kill(os.getpid(), signal.SIGKILL)

        asyncio.run(main())
        """
    )
    run = subprocess.run(
        [sys.executable, "-c", script], cwd=ROOT, capture_output=True, text=True, timeout=60
    )
    assert run.returncode == -9, run.stderr
    child = int(run.stdout.split()[0])
    end = time.monotonic() + 10.0
    while _alive(child) and time.monotonic() < end:
        time.sleep(0.05)
    assert not _alive(child), f"the simulator (pid {child}) outlived its daemon"


def _alive(pid: int) -> bool:
    """Whether `pid` runs (a zombie, reaped by init soon, does not)."""
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except FileNotFoundError:
        return False
    return state != "Z"
