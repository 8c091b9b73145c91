"""The bring-up guide (docs/guide/bring-up.md) followed on the simulator as written.

Runnable commands are the lines of its ```console blocks that start with "$ cdprd ";
the lines under one, up to the next "$ " line or the block's end, are what it prints on
success.  Hardware-only commands sit in ```text blocks and are not run.  The test runs
every runnable command in the guide's order with the same argv (`cdprd` as
`python -m daemon.cli`): `cdprd run` starts the daemon in the background (as "a second
terminal"; stopped at the end, or on a failure), every other command runs to its end and
must exit 0 and print each shown line.  A shown line is matched against the whole
lines of the command's output (stdout and stderr; the daemon's log for `cdprd run`):
"..." stands for any text, every number for any number (offsets, times and residuals
differ from run to run), the rest must be as shown; a line that is only "..." is not
matched.

The commands run from a scratch copy of the checkout's root: `config/` copied (the
calibration writes its robot file and round file beside them), `docs/` linked (the
flight's path file), the packages imported from this checkout (PYTHONPATH).  In the
copy, the one substitution: the rehearsal config's zenoh port 7448 becomes a free one,
and the client commands find it through CDPRD_CONNECT, so that a daemon on 7448 (or a
parallel test) does not collide with this one.
"""

from __future__ import annotations

import os
import re
import shlex
import shutil
import subprocess
import time
from dataclasses import dataclass
from pathlib import Path

import pytest

from tests.loopback import free_port
from tests.processes import ROOT, cdprd, connect, finish, start_daemon

GUIDE = ROOT / "docs" / "guide" / "bring-up.md"
REHEARSAL = "config/reference8-bring-up.yaml"
GUIDE_PORT = "tcp/127.0.0.1:7448"
# the steps the guide must keep (each a cdprd subcommand it runs)
STEPS = {"check-config", "tune", "run", "status", "pretension", "goto", "disable", "home"}
STEPS |= {"enable", "calibrate", "send", "hold"}
NUMBER = re.compile(r"[-+]?\d+(?:\.\d+)?(?:e[-+]?\d+)?")
COMMAND_TIMEOUT = 600.0  # s: calibrate flies 30 poses (~2 min on a quiet host)
LOG_TIMEOUT = 30.0  # s for the daemon's log to show what the guide shows
START_TIMEOUT = 90.0  # s for it to answer (its companion starts slowly on a busy host)


@dataclass
class Command:
    """One runnable command of the guide: its argv after `cdprd`, the output lines shown
    under it, and where it is (for messages)."""

    argv: list[str]
    shown: list[str]
    line: int

    def __str__(self) -> str:
        return f"line {self.line}: cdprd {shlex.join(self.argv)}"


def console_commands(text: str) -> list[Command]:
    """The `$ cdprd` commands of `text`'s ```console blocks with the lines shown under
    each (module docstring); AssertionError on a console line that is not one."""
    commands: list[Command] = []
    inside = False
    for number, line in enumerate(text.splitlines(), 1):
        if line.startswith("```"):
            inside = line.strip() == "```console"
            continue
        if not inside:
            continue
        if line.startswith("$ "):
            argv = shlex.split(line[2:], comments=True)
            assert argv[0] == "cdprd", f"line {number}: only cdprd commands run here: {line}"
            commands.append(Command(argv[1:], [], number))
        else:
            assert commands and commands[-1].line < number, f"line {number}: output first"
            commands[-1].shown.append(line)
    return commands


def pattern(shown: str) -> re.Pattern[str]:
    """A shown line as a pattern for one whole line of output: "..." any text, a number
    any number."""

    def literal(part: str) -> str:
        pieces = NUMBER.split(part)
        return NUMBER.pattern.join(re.escape(p) for p in pieces)

    return re.compile(".*".join(literal(part) for part in shown.rstrip().split("...")))


def missing(shown: list[str], output: str) -> list[str]:
    """The shown lines that no line of `output` matches."""
    lines = [line.rstrip() for line in output.splitlines()]
    return [
        s
        for s in shown
        if s.strip() != "..." and not any(pattern(s).fullmatch(line) for line in lines)
    ]


def scratch_checkout(tmp_path: Path, port: int) -> Path:
    """The directory the commands run from (module docstring), the rehearsal config
    listening on `port`."""
    root = tmp_path / "checkout"
    root.mkdir()
    shutil.copytree(ROOT / "config", root / "config")
    (root / "docs").symlink_to(ROOT / "docs")
    config = root / REHEARSAL
    text = config.read_text()
    assert text.count(GUIDE_PORT) == 1, f"{REHEARSAL} listens on {GUIDE_PORT}"
    config.write_text(text.replace(GUIDE_PORT, f"tcp/127.0.0.1:{port}"))
    return root


def wait_logged(log: Path, shown: list[str], timeout: float) -> list[str]:
    """The shown lines the daemon's log still lacks after at most `timeout` s."""
    end = time.monotonic() + timeout
    while (lacking := missing(shown, log.read_text())) and time.monotonic() < end:
        time.sleep(0.5)
    return lacking


def test_the_guide_marks_its_commands_as_this_test_reads_them() -> None:
    """Fast: the guide's console commands parse, cover every step, start one simulated
    daemon, and each shown line matches itself (so that the slow test can pass)."""
    commands = console_commands(GUIDE.read_text())
    assert not STEPS - {c.argv[0] for c in commands}, "a step of the guide runs no command"
    runs = [c for c in commands if c.argv[0] == "run"]
    assert len(runs) == 1 and "--sim" in runs[0].argv and REHEARSAL in runs[0].argv
    for command in commands:
        assert not missing(command.shown, "\n".join(command.shown)), command


def test_pattern_stands_for_numbers_and_elisions_only() -> None:
    shown = '{"state": "hold", ... "motion_mm": 0.0846, ...}'
    assert pattern(shown).fullmatch('{"state": "hold", "x": 1, "motion_mm": 1e-05, "y": 2}')
    assert not pattern(shown).fullmatch('{"state": "idle", "motion_mm": 0.0846}')
    assert missing(["...", "took 103.1 s"], "took 98.7 s\n") == []


@pytest.mark.slow  # the daemon as processes, a winch tuned, 30 poses flown: minutes
@pytest.mark.host_timing  # flown in real time by three processes on a shared host
@pytest.mark.timeout(1500)
def test_the_bring_up_guide_runs_on_the_simulator_as_written(tmp_path: Path) -> None:
    port = free_port()
    root = scratch_checkout(tmp_path, port)
    env = {
        **os.environ,
        "PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")])),
        "CDPRD_CONNECT": f"tcp/127.0.0.1:{port}",
    }
    log = tmp_path / "daemon.log"
    daemon: subprocess.Popen | None = None
    try:
        for command in console_commands(GUIDE.read_text()):
            if command.argv[0] == "run":
                assert daemon is None, f"{command}: a second daemon"
                assert command.argv[1] == "--config", f"{command}: run --config FILE first"
                config, options = Path(command.argv[2]), command.argv[3:]
                daemon = start_daemon(config, *options, log=log, cwd=root, env=env)
                connect(port, daemon, timeout=START_TIMEOUT).close()
                lacking = wait_logged(log, command.shown, LOG_TIMEOUT)
                assert not lacking, (
                    f"{command}: not in the daemon's log: {lacking}\n{log.read_text()}"
                )
                continue
            done = cdprd(*command.argv, timeout=COMMAND_TIMEOUT, cwd=root, env=env)
            output = done.stdout + done.stderr
            assert done.returncode == 0, f"{command}: exit {done.returncode}\n{output[-3000:]}"
            lacking = missing(command.shown, output)
            assert not lacking, f"{command}: does not print {lacking}\n{output[-3000:]}"
        assert daemon is not None, "the guide starts no daemon"
    finally:
        if daemon is not None:
            out = finish(daemon)
            print(log.read_text() if log.exists() else out)
