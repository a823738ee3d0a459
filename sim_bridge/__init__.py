"""qnav sim bridge: a pymunk plant that emulates the robot's sensors and
motors on a CAN bus for hardware-in-the-loop runs."""
