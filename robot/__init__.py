"""robot: the probing driver over ur_rtde's interfaces, the simulated arm and controller, the robot-cell script."""
