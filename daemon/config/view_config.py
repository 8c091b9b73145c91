"""The `view:` config section: the live 3-D view over the Foxglove WebSocket protocol
(DESIGN §17), served by the companion process, never by the control cycle.

Off unless `enabled: true`.  It listens on 127.0.0.1 only; a host off loopback is
refused unless `expose: true` is set, the same explicit choice as zenoh's (anyone who
reaches the port sees the robot).  Web pages are let in only from `allowed_origins`
(default: Foxglove's web app), and requests only with a Host header naming the bound
address, localhost or one of `allowed_hosts` (daemon.process.view_gate says why).
`rate_hz` is how often the scene is drawn: live, and in the telemetry recording's
standard Foxglove channels (recording.telemetry), whether or not the live view is on.
"""

from __future__ import annotations

import ipaddress
import re
from typing import Annotated

from pydantic import Field, field_validator, model_validator

from cdpr.description import PositiveFloat, StrictModel
from daemon.config.zenoh_config import loopback_host

DEFAULT_VIEW_PORT = 8765  # Foxglove's usual port for a live connection
FOXGLOVE_ORIGINS = ("https://app.foxglove.dev",)  # Foxglove's web app
_ORIGIN = r"[a-z][a-z0-9+.\-]*://([a-z0-9\-]+(\.[a-z0-9\-]+)*|\[[0-9a-f:.]+\])(:[0-9]{1,5})?"


class ViewConfig(StrictModel):
    """The `view:` section of a daemon config (every key optional)."""

    enabled: bool = False
    """Serve the live view (the telemetry recording's scene does not need it)."""
    host: str = Field("127.0.0.1", min_length=1, max_length=253)
    """The address the view listens on; off loopback only with expose."""
    port: Annotated[int, Field(ge=0, le=65535)] = DEFAULT_VIEW_PORT
    """0: any free port (the companion logs the one it got)."""
    expose: bool = False
    """Allow a host off loopback: an explicit network choice."""
    rate_hz: PositiveFloat = Field(30.0, le=200.0)
    """Hz: how often the scene is drawn, live and in the telemetry recording."""
    allowed_origins: tuple[str, ...] = Field(FOXGLOVE_ORIGINS, max_length=64)
    """The web origins (scheme://host[:port]) whose pages may connect; a client that
    sends no Origin (not a web page: Foxglove's desktop app, scripts) always may."""
    allowed_hosts: tuple[str, ...] = Field((), max_length=64)
    """Host header names accepted besides the bound address and localhost (an exposed
    view reached by a name); any other Host is refused (DNS rebinding)."""

    @field_validator("host")
    @classmethod
    def _plain_host(cls, host: str) -> str:
        return _host(host)

    @field_validator("allowed_hosts")
    @classmethod
    def _plain_hosts(cls, hosts: tuple[str, ...]) -> tuple[str, ...]:
        return tuple(_host(host) for host in hosts)

    @field_validator("allowed_origins")
    @classmethod
    def _origins(cls, origins: tuple[str, ...]) -> tuple[str, ...]:
        for origin in origins:
            if not re.fullmatch(_ORIGIN, origin):
                raise ValueError(
                    f"{origin[:100]!r} is not a web origin: scheme://host[:port] in lower "
                    "case, no path, no trailing '/' (e.g. https://app.foxglove.dev)"
                )
        return origins

    @property
    def gate_hosts(self) -> tuple[str, ...]:
        """The Host names the view answers to: its address, localhost, allowed_hosts."""
        return (self.host, "localhost", *self.allowed_hosts)

    @model_validator(mode="after")
    def _placement(self) -> ViewConfig:
        if not self.expose and not loopback_host(self.host):
            raise ValueError(
                f"the host {self.host!r} is not on loopback; serving the live view on a "
                "network is an explicit choice: set view.expose: true, or use 127.0.0.1"
            )
        return self


def _host(host: str) -> str:
    if any(c.isspace() or c in "/:[]" for c in host) and not _ipv6(host):
        raise ValueError(f"{host!r} is not a host name or address (no scheme, no port)")
    return host


def _ipv6(host: str) -> bool:
    try:
        return ipaddress.ip_address(host).version == 6
    except ValueError:
        return False
