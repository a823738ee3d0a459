"""`qnav` subcommands, one module each (see `ground_station.cli`)."""
