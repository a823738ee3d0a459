"""`python -m ground_station` = `qnav`."""

import sys

from ground_station.cli import main

sys.exit(main())
