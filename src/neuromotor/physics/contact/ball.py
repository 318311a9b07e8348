"""The flying ball: a free rigid sphere (radius r, mass m, inertia 2/5 m r^2) and its state."""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float


class Ball(eqx.Module):
    """The flying ball: every parameter is an array leaf (jit/vmap/grad over speed, mass, ...).

    Before ``launch`` (clip time) the ball hangs at ``position`` at rest (no gravity, no
    contact); the first step with t >= launch starts it at ``speed * direction``, then it flies
    under gravity.
    """

    radius: Float[Array, ""]  # m
    mass: Float[Array, ""]  # kg
    position: Float[Array, " 3"]  # centre at launch (world, m)
    direction: Float[Array, " 3"]  # unit launch direction (world)
    speed: Float[Array, ""]  # m/s
    restitution: Float[Array, ""]  # Newton's coefficient e in [0, 1]
    friction: Float[Array, ""]  # Coulomb coefficient mu
    launch: Float[Array, ""]  # s, clip time

    @property
    def velocity(self) -> Float[Array, " 3"]:
        return self.speed * self.direction

    @property
    def inertia(self) -> Float[Array, ""]:
        """Moment of inertia of a solid sphere about its centre, 2/5 m r^2."""
        return 0.4 * self.mass * self.radius**2

    @property
    def inverse_mass(self) -> Float[Array, " 6"]:
        """Diagonal of the ball's inverse generalized mass (3 linear, 3 angular)."""
        return jnp.concatenate([jnp.full(3, 1.0 / self.mass), jnp.full(3, 1.0 / self.inertia)])


class BallState(eqx.Module):
    pos: Float[Array, " 3"]
    quat: Float[Array, " 4"]
    vel: Float[Array, " 3"]
    omega: Float[Array, " 3"]


def make_ball(
    radius=0.11,
    mass=0.45,
    position=(0.0, 1.0, 0.0),
    velocity=None,
    speed=None,
    direction=None,
    restitution=0.6,
    friction=0.5,
    launch=0.0,
) -> Ball:
    """Build a :class:`Ball` from either ``velocity`` or ``speed`` and ``direction``."""
    if velocity is not None:
        velocity = np.asarray(velocity, np.float64)
        speed = float(np.linalg.norm(velocity))
        direction = velocity / speed if speed > 0 else np.array([1.0, 0.0, 0.0])
    else:
        direction = np.asarray(direction if direction is not None else (1.0, 0.0, 0.0), np.float64)
        norm = float(np.linalg.norm(direction))
        if not norm > 0:
            raise ValueError(f"ball direction must be non-zero, got {direction}")
        direction = direction / norm
        speed = 0.0 if speed is None else float(speed)
    f = lambda x: jnp.asarray(x, jnp.float64)
    return Ball(f(radius), f(mass), f(position), f(direction), f(speed), f(restitution), f(friction), f(launch))


def initial_ball_state(ball: Ball) -> BallState:
    """At rest at its launch position."""
    z = jnp.zeros(3, ball.position.dtype)
    return BallState(ball.position, jnp.array([1.0, 0.0, 0.0, 0.0], ball.position.dtype), z, z)


def never_launched(ball: Ball) -> Ball:
    """The same ball held at its start for ever: the unperturbed run with the same compiled code."""
    return eqx.tree_at(lambda b: b.launch, ball, jnp.full_like(ball.launch, jnp.inf))
