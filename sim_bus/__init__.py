"""Virtual actuators: plant physics, device-side CAN nodes and fault injection."""
