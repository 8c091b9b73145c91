"""Bus plumbing for simulated and real setups: the in-process loop bus, the socketcand
server, bus-load accounting and frame-level fault injection."""
