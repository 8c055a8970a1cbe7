"""Host-side planning: OMPL planners over the CPU MuJoCo checker, paths to episodes, a worker pool."""
