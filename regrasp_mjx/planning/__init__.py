"""Layer 4a, planning on the host: OMPL planners over the CPU MuJoCo checker or the lean one, planned
paths replayed into episodes, a pool of planner processes, demonstration sets planned on all cores."""
