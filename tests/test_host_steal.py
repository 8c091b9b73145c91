"""tests.host_steal: the share of CPU time stolen, and how a real-time figure is judged."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest

from tests import host_steal
from tests.host_steal import FreezeWatch, StealMeter

ROOT = Path(__file__).resolve().parent.parent


def metered(monkeypatch: pytest.MonkeyPatch, steal: int, total: int) -> StealMeter:
    """A meter over a block in which `steal` of `total` jiffies were stolen."""
    readings = iter([(100, 10_000), (100 + steal, 10_000 + total)])
    monkeypatch.setattr(host_steal, "_times", lambda: next(readings))
    with StealMeter() as meter:
        pass
    return meter


def test_the_stolen_share_is_that_of_the_block(monkeypatch: pytest.MonkeyPatch) -> None:
    assert metered(monkeypatch, 50, 1000).fraction == pytest.approx(0.05)


def test_a_figure_within_its_bound_passes_whatever_was_stolen(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    metered(monkeypatch, 500, 1000).check(True, "the lag", "fine")


def test_a_missed_bound_fails_on_a_quiet_host(monkeypatch: pytest.MonkeyPatch) -> None:
    meter = metered(monkeypatch, 10, 1000)  # 1 %
    with pytest.raises(AssertionError, match=r"the lag: 4\.5 ms"):
        meter.check(False, "the lag", "4.5 ms")


def test_a_missed_bound_skips_saying_why_on_a_robbed_host(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    meter = metered(monkeypatch, 80, 1000)  # 8 %
    with pytest.raises(pytest.skip.Exception, match=r"the lag: 4.5 ms, with 8.0% .*over 2%"):
        meter.check(False, "the lag", "4.5 ms")


def test_this_host_s_counters_are_read() -> None:
    steal, total = host_steal._times()
    assert 0 <= steal <= total and total > 0  # Linux: /proc/stat's first line


def watched(tmp_path, rows: str) -> FreezeWatch:
    """A watch whose probe noted `rows` (cpu, monotonic start, seconds; one a line)."""
    watch = FreezeWatch()
    watch._file = tmp_path / "freezes.txt"
    watch._file.write_text(rows)
    return watch


def test_the_longest_freeze_is_one_that_overlapped_the_window(tmp_path) -> None:
    watch = watched(tmp_path, "1 10.0 0.100\n0 12.0 0.030\n")
    assert watch.longest(10.05, 11.0) == pytest.approx(0.1)  # began before, ran into it
    assert watch.longest(10.2, 12.01) == pytest.approx(0.03)
    assert watch.longest(10.2, 11.9) == 0.0


def test_a_brake_right_after_a_freeze_skips_naming_both(tmp_path) -> None:
    watch = watched(tmp_path, "1 99.5 0.050\n")
    with pytest.raises(pytest.skip.Exception, match=r"braked \(tracking_error\).* 50 ms"):
        watch.excuse("tracking_error", 100.0)


def test_a_brake_on_a_quiet_host_or_long_after_a_freeze_is_judged(tmp_path) -> None:
    watched(tmp_path, "1 95.0 0.130\n0 99.9 0.015\n").excuse("tracking_error", 100.0)


def test_the_probe_notes_a_frozen_cpu() -> None:
    """SIGSTOP freezes the probe as the hypervisor would freeze its CPU: the probe notes
    the gap (an oversleep by the clock) once it runs again."""
    with FreezeWatch() as watch:
        assert watch._probe is not None
        deadline = time.monotonic() + 10
        while not watch._file.stat().st_size and watch._probe.poll() is None:
            os.kill(watch._probe.pid, signal.SIGSTOP)
            stopped = time.monotonic()
            time.sleep(0.05)
            os.kill(watch._probe.pid, signal.SIGCONT)
            time.sleep(0.05)
            if time.monotonic() > deadline:
                break
        assert watch.longest(stopped - 0.01, stopped + 0.1) >= 0.04, watch.freezes()


def test_a_figure_measured_beside_a_freeze_skips_and_fails_on_a_quiet_host() -> None:
    host_steal.judged(True, 0.5, "the error", "fine")  # within bound: passes whatever froze
    with pytest.raises(pytest.skip.Exception, match=r"the error: 0\.58 mm, .* frozen for 40 ms"):
        host_steal.judged(False, 0.04, "the error", "0.58 mm")
    with pytest.raises(AssertionError, match=r"the error: 0\.58 mm"):
        host_steal.judged(False, 0.015, "the error", "0.58 mm")


def test_the_probe_ends_with_the_process_that_started_it() -> None:
    """A test run killed before FreezeWatch's exit must not leave a real-time process
    behind: the probe ends once its parent is gone."""
    code = (
        "import subprocess, sys; "
        "import os; args = [sys.argv[1], str(os.getpid())]; "
        "p = subprocess.Popen([sys.executable, '-m', 'tests.freeze_probe', *args]); "
        "print(p.pid, flush=True)"
    )
    with tempfile.NamedTemporaryFile(suffix=".txt") as file:
        parent = subprocess.run(
            [sys.executable, "-c", code, file.name], capture_output=True, text=True, cwd=ROOT
        )
        pid = int(parent.stdout.split()[0])
        deadline = time.monotonic() + 10
        while _alive(pid) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert not _alive(pid), "the probe outlived its parent"


def _alive(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as stat:
            return stat.read().split()[2] != "Z"
    except FileNotFoundError:
        return False
