"""External perturbations: force pulses and impulses at points on named bodies.

A pulse on body b at body-frame point p (metres, relative to the body's joint origin) applies
the world force ``F(t) = magnitude * direction * shape((t - start) / duration)`` at the moving
point, i.e. force F on the body and torque ``(x_p - c_b) x F`` about its COM. Shapes (unit peak):
``square`` (1 on [0, 1)), ``half_sine`` (sin(pi s) on [0, 1]), ``triangle``. An impulse of
``magnitude`` N s is a square pulse of one time step and magnitude / h newtons, applied in the
step that starts at the grid time nearest ``start``.

Every field is an array leaf with a leading axis P (several pulses per run; the shape too, as an
index into :data:`SHAPES`), so a batch of magnitudes, directions, bodies, start times or shapes is
a ``vmap`` over this container, and runs that differ only in their pulses share one program.
"""

from __future__ import annotations

import dataclasses

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

from neuromotor.rotations import mv

SHAPES = ("square", "half_sine", "triangle")
# Each kind: the fields it reads beside body, point, direction, magnitude and start (the config
# refuses the others), and its magnitude's unit. A force pulse has a shape and duration; an
# impulse acts within one step.
KIND_FIELDS = {"force": ("duration", "shape"), "impulse": ()}
UNITS = {"force": "N", "impulse": "N s"}
KINDS = tuple(KIND_FIELDS)


def acting_interval(kind: str, start: float, duration: float, h: float) -> tuple[float, float]:
    """Clip seconds [t0, t1) a perturbation of ``kind`` pushes: an impulse the one step centred
    on ``start`` (exactly one sample of the time grid falls inside, whatever the round-off of
    t_k = t_0 + k h), a force pulse its ``duration`` from ``start``."""
    if kind == "impulse":
        return start - 0.5 * h, start + 0.5 * h
    return start, start + duration


class ForcePulses(eqx.Module):
    body: Int[Array, " P"]
    point: Float[Array, "P 3"]  # body frame, relative to the joint origin (m)
    direction: Float[Array, "P 3"]  # world, unit
    magnitude: Float[Array, " P"]  # N (peak)
    start: Float[Array, " P"]  # s
    duration: Float[Array, " P"]  # s
    shape: Int[Array, " P"]  # index into SHAPES

    @property
    def count(self) -> int:
        return self.magnitude.shape[-1]


def no_pulses() -> ForcePulses:
    z = jnp.zeros((0,))
    return ForcePulses(
        jnp.zeros((0,), jnp.int32), jnp.zeros((0, 3)), jnp.zeros((0, 3)), z, z, z, jnp.zeros((0,), jnp.int32)
    )


def vector_direction(value, time: float) -> np.ndarray:
    """A direction given as 3 numbers, made unit (keywords need the character: see
    :func:`neuromotor.studies.simulate.direction_lookup`)."""
    if isinstance(value, str):
        raise ValueError(f"direction {value!r} is a keyword of the character's frame: build with its direction_of")
    direction = np.asarray(value, np.float64)
    norm = np.linalg.norm(direction)
    if not norm > 0:
        raise ValueError(f"perturbation direction must be non-zero, got {value}")
    return direction / norm


def build_pulses(specs, model, h: float, body_index, direction_of=vector_direction) -> ForcePulses:
    """The one way from the user's perturbations to the arrays the step consumes.

    ``specs``: mappings with every field of :class:`neuromotor.config.specs.PerturbationSpec`
    (kind, body, point, direction, magnitude, start, duration, shape; the defaults live there,
    not here). ``point`` None is the body's COM (``model.com``); an impulse (N s) becomes a
    square pulse of one step ``h`` and magnitude / h newtons. ``body_index`` maps a name to an
    index; ``direction_of(value, start)`` a direction (3 numbers or a keyword of the character's
    frame, taken at the perturbation's start) to a world unit vector.
    """
    if not specs:
        return no_pulses()
    rows = [_pulse(s, model, h, body_index, direction_of) for s in specs]
    body, point, direction, magnitude, start, duration, shape = zip(*rows)
    return ForcePulses(
        jnp.asarray(body, jnp.int32),
        jnp.asarray(np.stack(point)),
        jnp.asarray(np.stack(direction)),
        jnp.asarray(magnitude),
        jnp.asarray(start),
        jnp.asarray(duration),
        jnp.asarray([SHAPES.index(x) for x in shape], jnp.int32),
    )


def _pulse(s, model, h: float, body_index, direction_of) -> tuple:
    """One pulse's fields from one spec (see :func:`build_pulses`)."""
    if s["kind"] not in KINDS:
        raise ValueError(f"perturbation kind must be one of {KINDS}, got {s['kind']!r}")
    direction = direction_of(s["direction"], float(s["start"]))  # host arrays: a sweep builds one per run
    b = body_index(s["body"])
    point = np.asarray(model.com[b] if s["point"] is None else s["point"], np.float64)
    magnitude, start, duration, shape = float(s["magnitude"]), float(s["start"]), float(s["duration"]), s["shape"]
    if s["kind"] == "impulse":  # N s as a square pulse of magnitude / h over its acting step
        start = acting_interval("impulse", start, duration, h)[0]
        magnitude, duration, shape = magnitude / h, h, "square"
    if shape not in SHAPES:
        raise ValueError(f"perturbation shape must be one of {SHAPES}, got {shape!r}")
    return (b, point, direction, magnitude, start, float(duration), shape)


def replace_first(p: ForcePulses, first: ForcePulses) -> ForcePulses:
    """``p`` with pulse 0 replaced by the one pulse ``first`` (the pulse a sweep varies)."""
    return ForcePulses(
        **{
            f.name: np.concatenate(
                [
                    np.asarray(getattr(first, f.name)),  # type: ignore[arg-type]
                    np.asarray(getattr(p, f.name))[1:],
                ]
            )
            for f in dataclasses.fields(p)
        }
    )


def unperturbed(p: ForcePulses) -> ForcePulses:
    """The unperturbed twin: the same pulses at zero magnitude (same shapes, one program)."""
    return dataclasses.replace(p, magnitude=p.magnitude * 0)


def pulse_profile(shape, s):
    """Unit-peak profile at phase ``s`` of shape ``shape`` (an index into SHAPES, or its name)."""
    shape = SHAPES.index(shape) if isinstance(shape, str) else shape
    inside = (s >= 0.0) & (s < 1.0)
    c = jnp.clip(s, 0.0, 1.0)
    val = jnp.select([shape == 0, shape == 1], [jnp.ones_like(s), jnp.sin(jnp.pi * c)], 1.0 - jnp.abs(2.0 * c - 1.0))
    return jnp.where(inside, val, 0.0)


def pulse_forces(p: ForcePulses, t) -> Float[Array, "P 3"]:
    """World force vector of each pulse at time t."""
    if p.count == 0:
        return jnp.zeros((0, 3))
    prof = pulse_profile(p.shape, (t - p.start) / p.duration)
    return (p.magnitude * prof)[:, None] * p.direction


def pulse_wrenches(
    p: ForcePulses, t, n_bodies: int, pos, rot, com
) -> tuple[Float[Array, " 6B"], Float[Array, "B 3"], Float[Array, "P 3"]]:
    """The pulses' wrenches at time t: as a generalized force (6B: each body's force and torque
    about its COM), the force on each body (B, 3), and the pulses' world points (P, 3)."""
    zeros = jnp.zeros((n_bodies, 6), pos.dtype)
    if p.count == 0:
        return zeros.reshape(-1), jnp.zeros((n_bodies, 3), pos.dtype), jnp.zeros((0, 3), pos.dtype)
    force = pulse_forces(p, t)
    lever = mv(rot[p.body], p.point - com[p.body])
    torque = jnp.cross(lever, force)
    gen = zeros.at[p.body, :3].add(force).at[p.body, 3:].add(torque)
    per_body = jnp.zeros((n_bodies, 3), pos.dtype).at[p.body].add(force)
    return gen.reshape(-1), per_body, pos[p.body] + lever
