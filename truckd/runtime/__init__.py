"""The daemon's runtime: rate keeper, systemd notify, Zenoh telemetry, recorder, wiring."""
