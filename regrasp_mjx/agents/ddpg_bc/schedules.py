"""The learning rate's and the regularisers' schedules over training (a mixin of ``Learner``)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import optax


class Schedules:
    """Learning rates, the BC coefficient and the action penalty as functions of the update count
    (``Learner`` mixes this in; ``self.config`` is its :class:`~regrasp_mjx.agents.ddpg_bc.config.TrainConfig`)."""

    def _learning_rate(self, lr: float):
        """A constant, or a cosine from ``lr`` to ``lr * lr_decay_to`` over the configured updates."""
        cfg = self.config
        if cfg.lr_decay_to >= 1.0:
            return lr
        return optax.cosine_decay_schedule(lr, decay_steps=cfg.total_updates, alpha=cfg.lr_decay_to)

    def regulariser_scale(self, updates: jax.Array) -> jax.Array:
        """The factor on the BC coefficient (and, with ``action_l2_decay``, on the action penalty)
        after ``updates`` gradient steps: 1, or a cosine from 1 to ``bc_decay_to`` over
        ``bc_decay_epochs`` epochs, then ``bc_decay_to``."""
        cfg = self.config
        if cfg.bc_decay_epochs == 0:
            return jnp.ones((), jnp.float32)
        span = cfg.bc_decay_epochs * cfg.iterations_per_epoch * cfg.updates_per_iteration
        return optax.cosine_decay_schedule(1.0, decay_steps=span, alpha=cfg.bc_decay_to)(updates)

    def bc_coef(self, updates: jax.Array) -> jax.Array:
        return self.config.bc_coef * self.regulariser_scale(updates)

    def action_l2(self, updates: jax.Array) -> jax.Array:
        scale = self.regulariser_scale(updates) if self.config.action_l2_decay else 1.0
        return self.config.action_l2 * scale
