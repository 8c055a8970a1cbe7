"""Layer 1, foundations: typed configs, frames and poses, atomic files, the multi-process and
GPU-memory helpers, the loops' shared parts, the job scheduler."""
