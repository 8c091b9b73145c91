"""bench/soak.py's judgement of a drive's lost heartbeat: the machine's (held up) only
where the daemon says it sent none for the consumer time and a CPU froze meanwhile."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

from tests.drivers.test_cia402 import _heartbeat_lost_after
from tests.host_steal import FreezeWatch

ROOT = Path(__file__).resolve().parent.parent
_SPEC = importlib.util.spec_from_file_location("bench_soak", ROOT / "bench" / "soak.py")
assert _SPEC is not None and _SPEC.loader is not None
soak = importlib.util.module_from_spec(_SPEC)
sys.modules[_SPEC.name] = soak
_SPEC.loader.exec_module(soak)


def test_a_lost_heartbeat_is_the_machine_s_only_with_a_silent_host_and_a_frozen_cpu() -> None:
    held = _heartbeat_lost_after(0.08)  # the daemon sent none for 80 ms
    heard_not = _heartbeat_lost_after(0.0)  # sent every cycle; the drive missed them
    watch = FreezeWatch()
    try:
        # cpu, monotonic start, seconds: a 60 ms freeze ending 1 s before the brake at 100 s
        watch._file.write_text("1 98.94 0.060\n0 50.0 0.200\n")
        assert soak.held_up_by(held, 100.0, watch) == 0.06
        assert soak.held_up_by(held, 120.0, watch) is None  # no freeze in the window
        assert soak.held_up_by(heard_not, 100.0, watch) is None
        watch._file.write_text("1 98.94 0.020\n")  # too short for an 80 ms silence
        assert soak.held_up_by(held, 100.0, watch) is None
    finally:
        watch._file.unlink()
