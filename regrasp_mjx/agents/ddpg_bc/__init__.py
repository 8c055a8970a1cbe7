"""DDPG + behaviour cloning with the Q-filter (Nair et al. 2018), laid out as brax's agents:
``networks`` (actor, critic, inference), ``losses`` (pure loss closures), ``exploration`` (the
rollouts), ``learner`` (one jitted iteration: rollouts, buffer inserts, updates)."""
