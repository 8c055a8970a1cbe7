"""Layer 5a, the robot: dVRK PSM kinematics, joint trajectories and their reachability, timed motion at
the PSM's limits and its check along the executed motion, the robot's errors."""
