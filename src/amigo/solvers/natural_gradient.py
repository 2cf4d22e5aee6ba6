"""Natural-gradient steps: Nesterov momentum on gradients preconditioned by the Fisher
information (a diagonal, or the inverse of a damped full matrix). Used by training; sees
only parameter trees, vectors and matrices."""

from __future__ import annotations

from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp


class FisherMomentum(eqx.Module):
    """Nesterov momentum on Fisher-preconditioned gradients (a diagonal natural gradient).

    ``v <- mu v + g / F``; ``theta <- theta - lr (g / F + mu v)``. ``lr = 1`` is a Newton
    step per parameter for a quadratic loss with a diagonal Hessian.
    """

    velocity: Any
    learning_rate: float = eqx.field(static=True, default=0.5)
    momentum: float = eqx.field(static=True, default=0.6)

    @classmethod
    def init(cls, params: Any, learning_rate: float = 0.5, momentum: float = 0.6) -> FisherMomentum:
        return cls(jax.tree.map(jnp.zeros_like, params), learning_rate, momentum)

    def update(
        self, params: Any, grads: Any, fisher: Any, floor: float = 1e-30
    ) -> tuple[Any, FisherMomentum]:
        """One step; returns ``(new_params, new_optimiser)``."""
        scaled = jax.tree.map(lambda g, f: g / jnp.maximum(f, floor), grads, fisher)
        velocity = jax.tree.map(lambda v, s: self.momentum * v + s, self.velocity, scaled)
        new = jax.tree.map(
            lambda p, s, v: p - self.learning_rate * (s + self.momentum * v),
            params,
            scaled,
            velocity,
        )
        return new, eqx.tree_at(lambda o: o.velocity, self, velocity)

    def update_vector(
        self,
        vector: jax.Array,
        grad: jax.Array,
        preconditioner: jax.Array,
        limit: jax.Array | None = None,
    ) -> tuple[jax.Array, FisherMomentum]:
        """The same step on a flat parameter vector with a full preconditioning matrix
        (the inverse of the damped Fisher matrix): a Gauss-Newton direction. ``limit``
        (same shape) is a trust region: the whole step is shrunk so that no parameter
        moves by more than its limit (far from the optimum a Gauss-Newton step of the
        optics can be wildly non-linear)."""
        scaled = preconditioner @ grad
        velocity = self.momentum * self.velocity + scaled
        delta = self.learning_rate * (scaled + self.momentum * velocity)
        if limit is not None:
            shrink = jnp.minimum(1.0, jnp.min(limit / jnp.maximum(jnp.abs(delta), 1e-30)))
            delta, velocity = delta * shrink, velocity * shrink
        return vector - delta, eqx.tree_at(lambda o: o.velocity, self, velocity)
