"""The service process around the cycle: serve() (bus, drives, interfaces, signals),
systemd notification, recordings and log set-up."""
