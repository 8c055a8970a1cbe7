"""Layer 5a, the robot: dVRK PSM kinematics, joint trajectories and their reachability, timed motion at the PSM's limits, the robot's errors."""
