"""Layer 5b, inference: policy files, the planning programs (JAX and lean numba), queries and plans,
Policy, the grasp library, the closed loops, robustness tables and choices on validation problems."""
