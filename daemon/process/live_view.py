"""The live view (DESIGN §17): a Foxglove WebSocket server (foxglove-sdk) in the companion
process, serving the scene's standard channels (daemon.process.scene) to Foxglove or any
client of the protocol.  The sdk's server runs on threads of its own; `log_messages`
hands it encoded messages, each sent only to the clients subscribed to its channel (a
slow client loses its oldest messages, never holds anything up).  Clients reach it
through the gate (daemon.process.view_gate), which refuses web pages of origins not
allowed and Host headers not the view's own."""

from __future__ import annotations

import logging
from collections.abc import Sequence

import foxglove

from daemon.config.view_config import ViewConfig
from daemon.process.scene import standard_channels
from daemon.process.view_gate import INNER_HOST, GateError, ViewGate, inner_tls

log = logging.getLogger("cdprd")

BACKLOG = 256  # messages queued per client before the oldest are dropped


class ViewError(Exception):
    """The server could not start (e.g. the port is in use)."""


class LiveView:
    """The Foxglove WebSocket server of `settings`, named `name` (the robot's)."""

    def __init__(self, settings: ViewConfig, name: str) -> None:
        self._context = foxglove.Context()
        cert, key = inner_tls()
        try:
            self._server = foxglove.start_server(
                name=f"cdprd {name}",
                host=INNER_HOST,
                port=0,
                context=self._context,
                message_backlog_size=BACKLOG,
                tls_cert=cert,
                tls_key=key,
            )
        except RuntimeError as exc:  # the sdk's FoxgloveError
            raise ViewError(f"view: cannot start the Foxglove server: {exc}") from None
        try:
            self._gate = ViewGate(
                settings.host,
                settings.port,
                self._server.port,
                cert,
                settings.allowed_origins,
                settings.gate_hosts,
            )
        except GateError as exc:  # e.g. the port in use
            self._server.stop()
            raise ViewError(
                f"view: cannot serve on {settings.host}:{settings.port}: {exc.strerror}"
            ) from None
        self.host = settings.host
        self.port = self._gate.port
        self._channels = {
            spec.topic: foxglove.Channel(
                spec.topic,
                schema=foxglove.Schema(
                    name=spec.schema_name, encoding=spec.schema_encoding, data=spec.schema_data
                ),
                message_encoding=spec.message_encoding,
                context=self._context,
            )
            for spec in standard_channels()
        }
        log.info("live view on ws://%s:%d (Foxglove WebSocket)", self.host, self.port)

    def log_messages(self, messages: Sequence[tuple[str, bytes]], log_time_ns: int) -> None:
        """Send encoded messages, each (topic, data), to the clients subscribed."""
        for topic, data in messages:
            self._channels[topic].log(data, log_time=log_time_ns)

    def close(self) -> None:
        self._gate.close()
        for channel in self._channels.values():
            channel.close()
        self._server.stop()
