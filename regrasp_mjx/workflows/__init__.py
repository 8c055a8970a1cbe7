"""Layer 6, runs: the training host loop, its checks before the work and its folder's outputs,
distillation, the shipped recipes as data, what the notebooks compute and draw, pictures of the scene."""
