"""qnav on-robot controller.

Owns the robot's interface definitions that the ground station and the sim import: robot geometry
and sensor layout (`robot_spec`), the policy kinds with their reference state encoders (`kinds`),
the CAN database and the policy file format. Stdlib plus python-can / cantools / pymavlink /
pyserial only: no numpy, nothing from `ground_station` or `sim_bridge`.
"""

__version__ = "0.1.0"
