"""Run selected pytest node ids inside a UML guest and read back its JUnit report."""

from __future__ import annotations

import sys
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from pathlib import Path

import pytest
import uml

SUITE_TEST = "test_vcan_suite_in_uml"
GUEST_NODEIDS = pytest.StashKey[list[str]]()
"""Node ids of the selected vcan tests, for the guest to run (set by conftest)."""
GUEST_SUMMARY = pytest.StashKey[str]()
"""One line on the guest run, for the terminal summary."""


@dataclass
class GuestSuite:
    """What the guest's pytest reported."""

    run: uml.GuestRun
    passed: list[str] = field(default_factory=list)
    skipped: list[str] = field(default_factory=list)
    failed: dict[str, str] = field(default_factory=dict)
    """Test name -> first line of its failure or error message."""

    def summary(self) -> str:
        """E.g. ``6 passed, 0 failed, 0 skipped; boot 1.2 s, total 9.8 s, exit code 0``."""
        boot = (
            f"{self.run.boot_seconds:.1f} s"
            if self.run.boot_seconds is not None
            else "never finished"
        )
        return (
            f"{len(self.passed)} passed, {len(self.failed)} failed, {len(self.skipped)} skipped; "
            f"boot {boot}, total {self.run.total_seconds:.1f} s, exit code {self.run.exit_code}"
            + (" (timed out)" if self.run.timed_out else "")
        )


def nowhere_reason(native_reason: str) -> str | None:
    """With no native vcan0 (``native_reason``): why UML cannot stand in, or ``None``."""
    missing = uml.uml_reason()
    if missing is None:
        return None
    return f"no SocketCAN {uml.CHANNEL} ({native_reason}) and no user-mode-linux: {missing}"


def pytest_command(config: pytest.Config, nodeids: list[str], junit: Path) -> list[str]:
    """The guest's pytest command line: same interpreter, rootdir, ini file and ``-o`` overrides."""
    command = [sys.executable, "-m", "pytest", "-v", "--color=no", "-p", "no:cacheprovider"]
    command += [f"--junitxml={junit}", f"--rootdir={config.rootpath}"]
    if config.inipath is not None:
        command += ["-c", str(config.inipath)]
    for override in config.getoption("override_ini") or []:
        command += ["-o", override]
    # the ini's addopts leave the slow suites out, and every vcan test is one of them
    return [*command, "-m", "vcan", "--", *nodeids]


def read_junit(path: Path, run: uml.GuestRun) -> GuestSuite:
    """Sort the test cases of a JUnit XML report into passed, skipped and failed.  A test
    run again (host_timing) is in the report once per run: its last run is its outcome."""
    outcomes: dict[str, tuple[str, str]] = {}
    for case in ET.parse(path).getroot().iter("testcase"):
        name = "::".join(part for part in (case.get("classname"), case.get("name")) if part)
        problem = case.find("failure")
        if problem is None:
            problem = case.find("error")
        if problem is not None:
            outcomes[name] = ("failed", (problem.get("message") or problem.tag).splitlines()[0])
        elif case.find("skipped") is not None:
            outcomes[name] = ("skipped", "")
        else:
            outcomes[name] = ("passed", "")
    suite = GuestSuite(run=run)
    for name, (outcome, why) in outcomes.items():
        if outcome == "failed":
            suite.failed[name] = why
        else:
            (suite.skipped if outcome == "skipped" else suite.passed).append(name)
    return suite


def run_suite(config: pytest.Config, nodeids: list[str], workdir: Path) -> GuestSuite:
    """Boot UML and run ``nodeids`` there; ``workdir`` holds the JUnit report."""
    junit = workdir / "guest-junit.xml"
    command = pytest_command(config, nodeids, junit)
    run = uml.run_in_uml(command, cwd=config.rootpath, writable=[workdir], echo=sys.stdout)
    suite = read_junit(junit, run) if junit.exists() else GuestSuite(run=run)
    config.stash[GUEST_SUMMARY] = suite.summary()
    return suite
