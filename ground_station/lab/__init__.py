"""The lab beside the product: benchmarks, fault suites, HIL rigs and research.

`bench/` (`qnav bench ...`), `faults/` (the fault, load and hostile-input
scenarios; `qnav bench faults` and tests/faults), `rigs/` (the lockstep rig,
link emulators, the Ray and vcan rigs, the standalone FTP shell), `nav/` (the
twin's navigation bench: controllers, episodes, the planned stack), `campaign/`
(local and Ray engines, Tune), `study.py` / `sweep.py` (the learning-rate study
and parameter sweeps). As ArduPilot's autotest and nav2's system tests, it sits
beside the product and drives it; nothing in firmware_py, sim_bridge or the rest
of ground_station imports it (tests/test_layering.py), except the thin `qnav
bench`, `qnav study` and `qnav sweep` subcommands that start it.
"""
