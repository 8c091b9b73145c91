"""Device-side CAN nodes of the simulated drives, one module per protocol."""
