"""The zenoh interface: the daemon's key space, message schemas and the client planners use."""
