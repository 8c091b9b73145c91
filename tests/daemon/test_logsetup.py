"""Logging set-up: timestamped on a terminal, priority-prefixed for journald."""

from __future__ import annotations

import io
import logging
import os
import re
import socket
import subprocess
import sys
from pathlib import Path

import pytest
from can.interfaces.socketcand.socketcand import convert_ascii_message_to_can_message

from cdpr.description import ConfigError
from daemon.process.logsetup import (
    FloodFilter,
    configure_logging,
    journald_detected,
    parse_level,
    syslog_priority,
)

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(autouse=True)
def restore_root_logger():
    root = logging.getLogger()
    handlers, level = list(root.handlers), root.level
    yield
    for handler in root.handlers:
        if handler not in handlers:
            root.removeHandler(handler)
    root.setLevel(level)


def test_level_names_any_case():
    assert parse_level("debug") == logging.DEBUG
    assert parse_level(" WARNING ") == logging.WARNING
    assert parse_level("Critical") == logging.CRITICAL


@pytest.mark.parametrize("bad", ["verbose", "warn", "", "10"])
def test_unknown_level_is_a_clear_error(bad):
    with pytest.raises(ConfigError, match=r"logging level .* is unknown; use one of: debug, info"):
        configure_logging(bad)


def test_plain_format_has_timestamp_and_level(capsys):
    configure_logging("info", journald=False)
    log = logging.getLogger("daemon.test")
    log.debug("not shown")
    log.info("cycle running at %d Hz", 500)
    log.error("drive 3 fault")
    lines = capsys.readouterr().err.splitlines()
    stamp = r"\d{4}-\d\d-\d\d \d\d:\d\d:\d\d\.\d{3}"
    assert len(lines) == 2
    assert re.fullmatch(rf"{stamp} INFO daemon\.test: cycle running at 500 Hz", lines[0])
    assert re.fullmatch(rf"{stamp} ERROR daemon\.test: drive 3 fault", lines[1])


def test_journald_format_has_priority_prefix_and_no_timestamp(capsys):
    configure_logging("debug", journald=True)
    log = logging.getLogger("daemon.test")
    log.debug("d")
    log.info("i")
    log.warning("w")
    log.error("e")
    log.critical("c")
    assert capsys.readouterr().err.splitlines() == [
        "<7>daemon.test: d",
        "<6>daemon.test: i",
        "<4>daemon.test: w",
        "<3>daemon.test: e",
        "<2>daemon.test: c",
    ]


def test_every_traceback_line_keeps_the_priority(capsys):
    configure_logging("info", journald=True)
    try:
        raise RuntimeError("tension solver failed\nsecond line")
    except RuntimeError:
        logging.getLogger("daemon.test").exception("cycle aborted")
    lines = capsys.readouterr().err.splitlines()
    assert lines[0] == "<3>daemon.test: cycle aborted"
    assert any(line == "<3>Traceback (most recent call last):" for line in lines)
    assert lines[-1] == "<3>second line"
    assert all(line.startswith("<3>") for line in lines)


def test_level_filters_records(caplog):
    configure_logging("warning", journald=False)
    log = logging.getLogger("daemon.test")
    log.info("quiet")
    log.warning("loud")
    assert [r.getMessage() for r in caplog.records] == ["loud"]


def test_second_call_replaces_the_handler(capsys):
    configure_logging("info", journald=False)
    configure_logging("info", journald=True)
    ours = [h for h in logging.getLogger().handlers if h.get_name() == "cdprd"]
    assert len(ours) == 1
    logging.getLogger("daemon.test").info("once")
    assert capsys.readouterr().err == "<6>daemon.test: once\n"


def _python_can_warning() -> None:
    """One warning from python-can's own code (its socketcand client, a bad message)."""
    assert convert_ascii_message_to_can_message("< frame 123 1.0 11") is None


def test_python_can_floods_are_one_line_then_a_count():
    """python-can logged a warning per failed connection attempt in a busy loop (444,621
    lines in 11 s): each distinct message passes once per interval, the next one after
    it says how many were held back; other loggers pass untouched."""
    clock = [100.0]
    stream = io.StringIO()
    handler = logging.StreamHandler(stream)
    handler.addFilter(FloodFilter(interval=5.0, clock=lambda: clock[0]))
    root = logging.getLogger()
    root.addHandler(handler)
    root.setLevel(logging.INFO)
    try:
        for _ in range(10_000):
            _python_can_warning()
        for _ in range(3):
            logging.getLogger("cdprd").error("BRAKE [command] stop")
        logging.getLogger("daemon.service.bus_port").warning("CAN send failed: Network is down")
        logging.getLogger("daemon.service.bus_port").warning("CAN send failed: Network is down")
        logging.getLogger("daemon.service.bus_port").warning("CAN receive failed: Network is down")
        clock[0] += 4.9
        _python_can_warning()
        clock[0] += 0.2
        _python_can_warning()
        _python_can_warning()
    finally:
        root.removeHandler(handler)
    lines = stream.getvalue().splitlines()
    missing = "Missing ending character in ascii message: < frame 123 1.0 11"
    assert lines == [
        missing,
        *["BRAKE [command] stop"] * 3,
        "CAN send failed: Network is down",
        "CAN receive failed: Network is down",
        f"{missing} [10000 more in the last 5 s]",
    ]


def test_the_handler_limits_floods(capsys):
    configure_logging("info", journald=False)
    for _ in range(10_000):
        _python_can_warning()
    lines = capsys.readouterr().err.splitlines()
    assert len(lines) == 1 and "can.interfaces.socketcand.socketcand" in lines[0], lines[:3]


def test_syslog_priority_of_custom_levels():
    assert syslog_priority(logging.INFO + 5) == 6
    assert syslog_priority(logging.WARNING + 1) == 4
    assert syslog_priority(logging.CRITICAL + 10) == 2
    assert syslog_priority(1) == 7


def _dev_ino(stream) -> str:
    info = os.fstat(stream.fileno())
    return f"{info.st_dev}:{info.st_ino}"


def test_journal_stream_must_match_the_stream(tmp_path):
    with open(tmp_path / "a", "w") as a, open(tmp_path / "b", "w") as b:
        assert journald_detected(a, {"JOURNAL_STREAM": _dev_ino(a)})
        assert not journald_detected(b, {"JOURNAL_STREAM": _dev_ino(a)})
        # JOURNAL_STREAM is authoritative even under systemd (INVOCATION_ID set)
        assert not journald_detected(b, {"JOURNAL_STREAM": _dev_ino(a), "INVOCATION_ID": "x"})
        assert not journald_detected(a, {})


def test_invocation_id_alone_counts_only_for_a_socket(tmp_path):
    env = {"INVOCATION_ID": "0123456789abcdef"}
    left, right = socket.socketpair()
    with left, right, left.makefile("w") as stream, open(tmp_path / "f", "w") as regular:
        assert journald_detected(stream, env)
        assert not journald_detected(stream, {})
        assert not journald_detected(regular, env)  # StandardError=file:… keeps timestamps
    assert not journald_detected(io.StringIO(), env)  # no file behind it


def test_detection_end_to_end_in_a_child_process(tmp_path):
    """stderr redirected to a file whose dev:inode is in JOURNAL_STREAM, as systemd does."""
    code = (
        "import logging; from daemon.process.logsetup import configure_logging; "
        "configure_logging('info'); logging.getLogger('cdprd').warning('braked')"
    )
    out = tmp_path / "stderr"
    for journal, expected in ((True, "<4>cdprd: braked\n"), (False, " WARNING cdprd: braked\n")):
        with open(out, "w") as stream:
            env = {k: v for k, v in os.environ.items() if k not in ("JOURNAL_STREAM",)}
            if journal:
                env["JOURNAL_STREAM"] = _dev_ino(stream)
            subprocess.run(
                [sys.executable, "-c", code],
                stderr=stream,
                env=env,
                cwd=ROOT,
                check=True,
                timeout=60,
            )
        text = out.read_text()
        assert text.endswith(expected) and (text == expected) == journal
