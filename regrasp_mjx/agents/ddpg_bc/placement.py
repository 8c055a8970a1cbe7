"""Where a learner's work runs: whole members per device, or data parallel (a mixin of ``Learner``).

Several devices (``devices`` in the config) share the work in one of two ways (``shard``). With
``members`` (the default when the members divide evenly over the devices), each device holds whole
learners: the leading member axis of every state leaf is split over a one-axis mesh, the iteration
runs under ``shard_map`` with no collectives at all, and each learner computes exactly what it
computes on one device. With ``envs`` they are data parallel: the iteration runs under ``shard_map`` on a
one-axis mesh ``"data"``. Each device rolls out ``num_envs / devices`` environments into its own
slice of the online buffer and samples ``1 / devices`` of every batch from it (and from its copy of
the demonstrations); networks, optimisers and the normaliser are replicated, gradients are averaged
(``pmean``) and normaliser statistics summed (``psum``) across devices, so every replica takes the
same step: the gradient of the whole batch. The buffer's slices are one array sharded along its
length (each device's insert index is the same, as every device adds as many transitions), so a
state's shapes do not depend on the device count. With one device the program has no collectives.
"""

from __future__ import annotations

import jax
import numpy as np
from jax.sharding import Mesh, NamedSharding
from jax.sharding import PartitionSpec as P

from regrasp_mjx.agents.ddpg_bc.config import TrainConfig
from regrasp_mjx.core.config import ConfigError

AXIS = "data"  # the mesh axis the environments and batches are split over


class Placement:
    """The mesh and the placement of a learner's state (``Learner`` mixes this in)."""

    def _init_placement(self, config: TrainConfig) -> None:
        n, self.shard = self.check_devices(config)
        # ``devices``: the data-parallel split (1 when whole members are placed per device)
        self.devices = n if self.shard == "envs" else 1
        self.member_devices = n if self.shard == "members" else 1
        self.axis = AXIS if self.devices > 1 else None  # collectives only with several devices
        self.mesh = Mesh(np.array(jax.devices()[:n]), (AXIS,))
        self.local_envs = config.num_envs // self.devices

    @staticmethod
    def check_devices(cfg: TrainConfig) -> tuple[int, str]:
        """``(devices, shard)``: the device count in use and how the work is split over them; a
        :class:`ConfigError` where the config asks for devices JAX does not see or cannot split."""
        available = jax.devices()  # every process's devices in a distributed run
        n = cfg.devices or len(available)
        if jax.process_count() > 1 and n != len(available):
            raise ConfigError(
                f"devices={cfg.devices} is not accepted in a run of {jax.process_count()} processes: the mesh "
                f"spans every process's devices; accepted: 0 (all) or {len(available)}"
            )
        if n > len(available):
            raise ConfigError(
                f"devices={cfg.devices} is not accepted: JAX sees {len(available)} "
                f"{jax.default_backend()} device(s); accepted: 0 (all) or 1..{len(available)}"
            )
        members = cfg.num_members
        shard = cfg.shard
        if shard == "auto":
            shard = "members" if n > 1 and members % n == 0 else "envs"
        if n == 1:
            return n, "envs"
        if shard == "members":
            if members % n:
                raise ConfigError(
                    f"shard='members' with devices={n} does not divide the {members} learners (seeds x "
                    "settings); accepted: a multiple of the device count, or shard='envs'"
                )
            return n, shard
        for name, value in (
            ("num_envs", cfg.num_envs),
            ("buffer_size", cfg.buffer_size),
            ("demo_chunk", cfg.demo_chunk),
            ("the online part of batch_size", cfg.online_batch),
            ("the demonstration part of batch_size", cfg.demo_batch),
        ):
            if value % n:
                raise ConfigError(
                    f"devices={n} does not divide {name} ({value}); accepted: sizes that split evenly over the devices"
                )
        return n, shard

    def state_specs(self, ts):
        """Partition specs of a state: with whole members per device, every leaf split along its
        leading member axis; data parallel, the online buffer's transitions split along the buffer's
        length (``[seed, 1, length, ...]``) and everything else replicated."""
        if self.member_devices > 1:
            return jax.tree.map(lambda _: P(AXIS), ts)
        specs = jax.tree.map(lambda _: P(), ts)
        experience = jax.tree.map(lambda _: P(None, None, AXIS), ts.online.experience)
        return specs.replace(online=specs.online.replace(experience=experience))

    def state_shardings(self, ts):
        return jax.tree.map(lambda spec: NamedSharding(self.mesh, spec), self.state_specs(ts))

    def place(self, ts):
        """Puts a state (fresh or restored from a checkpoint) on the mesh. Across processes each
        holds the whole host value and gives its own devices their part of it."""
        shardings = self.state_shardings(ts)
        if jax.process_count() == 1:
            return jax.device_put(ts, shardings)

        def put(x, sharding):
            x = np.asarray(x)
            return jax.make_array_from_callback(x.shape, sharding, lambda index: x[index])

        return jax.tree.map(put, ts, shardings)

    def _shard_map(self, fn, in_specs, out_specs):
        # Replication of the outputs given P() is by construction (averaged gradients, summed
        # statistics, keys split before any device index is folded in) and tested, not type-checked.
        return jax.shard_map(fn, mesh=self.mesh, in_specs=in_specs, out_specs=out_specs, check_vma=False)

    def _pmean(self, tree):
        return jax.lax.pmean(tree, self.axis) if self.axis else tree

    def _device_key(self, key: jax.Array) -> jax.Array:
        """A key of this device's own (unchanged with one device, so runs reproduce across versions)."""
        return jax.random.fold_in(key, jax.lax.axis_index(self.axis)) if self.axis else key
