"""External perturbations: force pulses and impulses at points on named bodies.

A pulse on body b at body-frame point p (metres, relative to the body's joint origin) applies
the world force ``F(t) = magnitude * direction * shape((t - start) / duration)`` at the moving
point, i.e. force F on the body and torque ``(x_p - c_b) x F`` about its COM. Shapes (unit peak):
``square`` (1 on [0, 1)), ``half_sine`` (sin(pi s) on [0, 1]), ``triangle``. An impulse of
``magnitude`` N s is a square pulse of one time step and magnitude / h newtons, applied in the
step that starts at the grid time nearest ``start``.

Every numeric field is an array leaf with a leading axis P (several pulses per run), so a batch
of magnitudes, directions, bodies or start times is a ``vmap`` over this container.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Float, Int

from neuromotor.rotations import mv

SHAPES = ("square", "half_sine", "triangle")


class ForcePulses(eqx.Module):
    body: Int[Array, " P"]
    point: Float[Array, "P 3"]  # body frame, relative to the joint origin (m)
    direction: Float[Array, "P 3"]  # world, unit
    magnitude: Float[Array, " P"]  # N (peak)
    start: Float[Array, " P"]  # s
    duration: Float[Array, " P"]  # s
    shape: tuple[str, ...] = eqx.field(static=True)

    @property
    def count(self) -> int:
        return len(self.shape)


def no_pulses() -> ForcePulses:
    z = jnp.zeros((0,))
    return ForcePulses(jnp.zeros((0,), jnp.int32), jnp.zeros((0, 3)), jnp.zeros((0, 3)), z, z, z, ())


def pulses(specs: list[dict], body_index) -> ForcePulses:
    """Build from dicts with keys body (name), point, direction, magnitude, start, duration,
    shape; ``body_index`` maps a body name to its index. ``kind='impulse'`` needs ``step``."""
    if not specs:
        return no_pulses()
    cols: dict[str, list] = {k: [] for k in ("body", "point", "direction", "magnitude", "start", "duration")}
    shapes = []
    for s in specs:
        direction = jnp.asarray(s.get("direction", (1.0, 0.0, 0.0)), jnp.float64)
        norm = jnp.linalg.norm(direction)
        if not norm > 0:
            raise ValueError(f"perturbation direction must be non-zero, got {s.get('direction')}")
        magnitude, duration, shape = s["magnitude"], s.get("duration", 0.1), s.get("shape", "half_sine")
        start = float(s.get("start", 0.5))
        if s.get("kind", "force") == "impulse":
            step = s["step"]
            magnitude, duration, shape = magnitude / step, step, "square"
            # Centre the one-step window on ``start`` so that exactly one sample of the time
            # grid falls inside it, whatever the round-off of t_k = t_0 + k h.
            start -= 0.5 * step
        if shape not in SHAPES:
            raise ValueError(f"perturbation shape must be one of {SHAPES}, got {shape!r}")
        cols["body"].append(body_index(s["body"]))
        cols["point"].append(jnp.asarray(s.get("point", (0.0, 0.0, 0.0)), jnp.float64))
        cols["direction"].append(direction / norm)
        cols["magnitude"].append(float(magnitude))
        cols["start"].append(start)
        cols["duration"].append(float(duration))
        shapes.append(shape)
    return ForcePulses(
        jnp.asarray(cols["body"], jnp.int32),
        jnp.stack(cols["point"]),
        jnp.stack(cols["direction"]),
        jnp.asarray(cols["magnitude"]),
        jnp.asarray(cols["start"]),
        jnp.asarray(cols["duration"]),
        tuple(shapes),
    )


def pulse_profile(shape: str, s):
    inside = (s >= 0.0) & (s < 1.0)
    if shape == "square":
        val = jnp.ones_like(s)
    elif shape == "half_sine":
        val = jnp.sin(jnp.pi * jnp.clip(s, 0.0, 1.0))
    else:
        val = 1.0 - jnp.abs(2.0 * jnp.clip(s, 0.0, 1.0) - 1.0)
    return jnp.where(inside, val, 0.0)


def pulse_forces(p: ForcePulses, t) -> Float[Array, "P 3"]:
    """World force vector of each pulse at time t."""
    if p.count == 0:
        return jnp.zeros((0, 3))
    s = (t - p.start) / p.duration
    prof = jnp.stack([pulse_profile(shape, s[i]) for i, shape in enumerate(p.shape)])
    return (p.magnitude * prof)[:, None] * p.direction


def generalized_forces(p: ForcePulses, t, n_bodies: int, pos, rot, com) -> tuple[Float[Array, " 6B"], Float[Array, "B 3"], Float[Array, "P 3"]]:
    """Generalized force of the pulses (6B), per-body force (B,3), and world points (P,3)."""
    zeros = jnp.zeros((n_bodies, 6), pos.dtype)
    if p.count == 0:
        return zeros.reshape(-1), jnp.zeros((n_bodies, 3), pos.dtype), jnp.zeros((0, 3), pos.dtype)
    force = pulse_forces(p, t)
    lever = mv(rot[p.body], p.point - com[p.body])
    torque = jnp.cross(lever, force)
    gen = zeros.at[p.body, :3].add(force).at[p.body, 3:].add(torque)
    per_body = jnp.zeros((n_bodies, 3), pos.dtype).at[p.body].add(force)
    return gen.reshape(-1), per_body, pos[p.body] + lever
