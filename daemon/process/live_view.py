"""The live view (DESIGN §17): a Foxglove WebSocket server (foxglove-sdk) in the companion
process, serving the scene's standard channels (daemon.process.scene) to Foxglove or any
client of the protocol.  The sdk's server runs on threads of its own; `log_messages`
hands it encoded messages, each sent only to the clients subscribed to its channel (a
slow client loses its oldest messages, never holds anything up)."""

from __future__ import annotations

import logging
from collections.abc import Sequence

import foxglove

from daemon.config.view_config import ViewConfig
from daemon.process.scene import standard_channels

log = logging.getLogger("cdprd")

BACKLOG = 256  # messages queued per client before the oldest are dropped


class ViewError(Exception):
    """The server could not start (e.g. the port is in use)."""


class LiveView:
    """The Foxglove WebSocket server of `settings`, named `name` (the robot's)."""

    def __init__(self, settings: ViewConfig, name: str) -> None:
        self._context = foxglove.Context()
        try:
            self._server = foxglove.start_server(
                name=f"cdprd {name}",
                host=settings.host,
                port=settings.port,
                context=self._context,
                message_backlog_size=BACKLOG,
            )
        except RuntimeError as exc:  # the sdk's FoxgloveError, e.g. the port in use
            raise ViewError(
                f"view: cannot serve on {settings.host}:{settings.port}: {exc}"
            ) from None
        self.host = settings.host
        self.port = self._server.port
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
        for channel in self._channels.values():
            channel.close()
        self._server.stop()
