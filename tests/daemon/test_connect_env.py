"""$CDPRD_CONNECT: the endpoint every command-line client uses without --connect (a
daemon on another port, as the bring-up guide's test runs one); --connect still wins."""

from __future__ import annotations

import pytest

from daemon.cli import main
from daemon.interface.client import CONNECT_ENV, DEFAULT_CONNECT, default_connect
from tests.loopback import free_port


def test_the_default_endpoint_comes_from_the_environment(monkeypatch) -> None:
    monkeypatch.delenv(CONNECT_ENV, raising=False)
    assert default_connect() == DEFAULT_CONNECT
    monkeypatch.setenv(CONNECT_ENV, "tcp/127.0.0.1:17448")
    assert default_connect() == "tcp/127.0.0.1:17448"


@pytest.mark.parametrize("given", [False, True])
def test_a_client_command_connects_where_it_is_told(monkeypatch, capsys, given: bool) -> None:
    """Nothing listens on either port: the refusal names the endpoint it tried."""
    env, option = f"tcp/127.0.0.1:{free_port()}", f"tcp/127.0.0.1:{free_port()}"
    monkeypatch.setenv(CONNECT_ENV, env)
    argv = ["status", "--timeout", "1"] + (["--connect", option] if given else [])
    assert main(argv) == 3
    err = capsys.readouterr().err
    assert (option if given else env) in err
    assert (env if given else option) not in err
