"""The cdprd service: asyncio orchestration, CAN I/O, safety, zenoh, systemd and the CLI."""
