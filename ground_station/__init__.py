"""qnav ground station: maps, training, evaluation, export, MAVLink client,
telemetry monitor. May import `firmware_py` for the shared contracts."""
