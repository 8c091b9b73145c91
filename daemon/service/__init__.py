"""The control service: the cycle on the CAN bus, the safety state machine, the bus port,
its statistics, and the command contract (api) that the interfaces call.  It imports only
cdpr, drivers and daemon.config (a test enforces it): the real-time core's room."""
