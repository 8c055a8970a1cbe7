"""Actor and critic MLPs (paper: 3 hidden layers of 512) and the deterministic policy.

Observations are normalised by brax's running statistics (``brax.training.acme``) and clipped to
+-5 standard deviations (as HER's ``clip_obs``). The actor ends in tanh: actions in [-1, 1].

With ``critics=2`` (ours, TD3's clipped double Q) the critic's parameters carry a leading axis of
two independently initialised critics; ``q`` then returns both estimates, ``[2, ...]``. With
``critic_layer_norm`` (ours) each hidden layer of the critic ends in a layer norm (brax's MLP
``layer_norm``), which bounds the features the critic can extrapolate from at a high replay ratio.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import flax.linen as nn
import jax
import jax.numpy as jnp
from brax.training import networks as brax_networks
from brax.training.acme import running_statistics
from flax import struct

OBS_CLIP = 5.0


@struct.dataclass
class DDPGNetworks:
    """Two flax modules; ``apply`` functions take (params, normaliser state, inputs)."""

    actor: nn.Module = struct.field(pytree_node=False)
    critic: nn.Module = struct.field(pytree_node=False)
    critics: int = struct.field(pytree_node=False, default=1)

    def policy(self, actor_params: Any, normalizer: Any, obs: jax.Array) -> jax.Array:
        return jnp.tanh(self.actor.apply(actor_params, normalize(obs, normalizer)))

    def q(self, critic_params: Any, normalizer: Any, obs: jax.Array, action: jax.Array) -> jax.Array:
        """``Q(s, a)``: ``[...]`` for one critic, ``[critics, ...]`` for several."""
        x = jnp.concatenate([normalize(obs, normalizer), action], axis=-1)
        if self.critics == 1:
            return self.critic.apply(critic_params, x)[..., 0]
        return jax.vmap(self.critic.apply, in_axes=(0, None))(critic_params, x)[..., 0]


def normalize(obs: jax.Array, normalizer: Any) -> jax.Array:
    return running_statistics.normalize(obs, normalizer, max_abs_value=OBS_CLIP)


def make_networks(
    action_size: int, hidden: Sequence[int] = (512, 512, 512), critics: int = 1, critic_layer_norm: bool = False
) -> DDPGNetworks:
    hidden = tuple(int(h) for h in hidden)
    return DDPGNetworks(
        actor=brax_networks.MLP(layer_sizes=hidden + (action_size,), activation=nn.relu),
        critic=brax_networks.MLP(layer_sizes=hidden + (1,), activation=nn.relu, layer_norm=critic_layer_norm),
        critics=critics,
    )


def init_params(nets: DDPGNetworks, key: jax.Array, obs_size: int, action_size: int) -> tuple[Any, Any]:
    k_actor, k_critic = jax.random.split(key)
    actor = nets.actor.init(k_actor, jnp.zeros((1, obs_size)))
    x = jnp.zeros((1, obs_size + action_size))
    if nets.critics == 1:
        critic = nets.critic.init(k_critic, x)
    else:
        critic = jax.vmap(nets.critic.init, in_axes=(0, None))(jax.random.split(k_critic, nets.critics), x)
    return actor, critic
