"""DDPG + behaviour cloning with the Q-filter (Nair et al. 2018), laid out as brax's agents:
``networks`` (actor, critic, inference), ``losses`` (pure loss closures), ``train`` (one jitted
iteration: rollouts, buffer inserts, updates)."""
