"""The capture daemon: control protocol, telemetry, metrics, systemd integration."""
