"""Layer 3, the worlds a policy moves in: the batched MDP in MJX, the same task on CPU MuJoCo, the
lean numba collision test and checker, the one rollout, the shield, the needle-estimate noise."""
