"""The guest's JUnit report read back as the host's verdict, reruns included: a test run
again (host_timing, pytest-rerunfailures) is in the report once per run."""

from __future__ import annotations

import subprocess
import sys
import textwrap
from pathlib import Path

import uml
from guest_suite import read_junit

MODULE = textwrap.dedent(
    """
    from pathlib import Path

    import pytest

    FLAG = Path(__file__).with_suffix(".ran")

    @pytest.mark.flaky(reruns=1)
    def test_fails_once():
        first = not FLAG.exists()
        FLAG.touch()
        assert not first, "the first run fails"

    @pytest.mark.flaky(reruns=1)
    def test_always_fails():
        assert False, "every run fails"

    def test_passes():
        pass
    """
)


def test_a_rerun_is_read_as_its_last_run(tmp_path: Path) -> None:
    (tmp_path / "test_reruns.py").write_text(MODULE)
    junit = tmp_path / "junit.xml"
    subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", f"--junitxml={junit}"],
        cwd=tmp_path,
        capture_output=True,
        timeout=120,
    )
    run = uml.GuestRun(exit_code=1, output="", boot_seconds=0.0, total_seconds=0.0, timed_out=False)
    suite = read_junit(junit, run)
    assert sorted(suite.passed) == ["test_reruns::test_fails_once", "test_reruns::test_passes"]
    assert list(suite.failed) == ["test_reruns::test_always_fails"]
    assert suite.failed["test_reruns::test_always_fails"].startswith("AssertionError")
    assert suite.skipped == []
