"""Layer 4b, the learning agents on the device: DDPG+BC (``ddpg_bc``) and DAgger distillation (``dagger``)."""
