"""HIL server: emulated flight processor, supervision, deadlines, telemetry, runs."""
