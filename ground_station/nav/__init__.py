"""Navigation with unmapped obstacles: their definition (`obstacles`: detourable
discs and movers, the configuration-space raster) and the re-planner round what
the robot sees (`replan`); the benchmark's scenario episodes, controllers and
episode loop are in `ground_station.lab.nav`."""
