"""Layer 6, runs: the training host loop, the shipped recipes as data, what the notebooks compute and draw, pictures of the scene."""
