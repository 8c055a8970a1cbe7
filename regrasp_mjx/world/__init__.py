"""Layer 2, the scene and its problems: the MJCF and its exact capsule distances, the continuous
collision test, the true needle, the start and goal distributions, test sets."""
