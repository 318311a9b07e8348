"""Contact detection: the ball against the bodies' capsules and the ground plane.

Candidates are every capsule plus (optionally) the ground, the plane ``up . x = ground_height``
with ``up = -gravity / |gravity|``. For each: the gap, the unit normal from the body to the
ball, the body's surface point, and a tangent basis completing the normal to a frame.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int

from neuromotor.model.skeleton import Model
from neuromotor.physics.contact.shapes import Capsules
from neuromotor.rotations import quat_to_matrix

_TINY = 1e-12


class ContactSettings(eqx.Module):
    """Static settings of contact: candidates (detection) and the LCP solver."""

    friction_directions: int = eqx.field(static=True, default=8)  # N of the friction pyramid (>= 4)
    max_contacts: int = eqx.field(static=True, default=4)  # candidates kept per step (nearest)
    pgs_iterations: int = eqx.field(static=True, default=40)
    position_iterations: int = eqx.field(static=True, default=10)
    restitution_threshold: float = eqx.field(static=True, default=0.25)  # m/s
    ground: bool = eqx.field(static=True, default=True)
    ground_height: float = eqx.field(static=True, default=0.0)


def candidate_bodies(caps: Capsules, settings: ContactSettings) -> Int[Array, " C"]:
    """Body of every contact candidate; -1 for the ground (static world)."""
    extra = jnp.array([-1], jnp.int32) if settings.ground else jnp.zeros((0,), jnp.int32)
    return jnp.concatenate([caps.body, extra])


def on_character(caps: Capsules, settings: ContactSettings) -> Bool[Array, " C"]:
    """Which contact candidates are bodies of the character (the ground is not): the ones a
    ball's hit metrics count."""
    return candidate_bodies(caps, settings) >= 0


def candidate_names(caps: Capsules, settings: ContactSettings) -> tuple[str, ...]:
    return caps.names + (("ground",) if settings.ground else ())


def safe_norm(x):
    """|x| along the last axis, with a zero (not NaN) gradient at x = 0."""
    sq = jnp.sum(x * x, -1)
    safe = jnp.where(sq > 0, sq, 1.0)
    return jnp.where(sq > 0, jnp.sqrt(safe), 0.0)


def capsule_contact(a_w, b_w, rad, centre, ball_r):
    """Sphere against a world capsule: gap, normal (capsule to ball), point on the capsule."""
    seg = b_w - a_w
    t = jnp.clip(jnp.dot(centre - a_w, seg) / jnp.maximum(jnp.dot(seg, seg), _TINY), 0.0, 1.0)
    q = a_w + t * seg
    d = centre - q
    dist = safe_norm(d)
    # Ball centre on the axis (never in practice): any normal will do.
    n = jnp.where(dist > _TINY, d / jnp.maximum(dist, _TINY), jnp.array([0.0, 1.0, 0.0], d.dtype))
    return dist - rad - ball_r, n, q + rad * n


def up_direction(model: Model) -> Float[Array, " 3"]:
    """-gravity / |gravity|; +y (the clips' up axis) in zero gravity."""
    norm = safe_norm(model.gravity)
    return jnp.where(
        norm > 0, -model.gravity / jnp.maximum(norm, _TINY), jnp.array([0.0, 1.0, 0.0], model.gravity.dtype)
    )


def detect(model: Model, caps: Capsules, settings: ContactSettings, ball_radius, centre, pos, rot):
    """Gap (C,), unit normal (C,3) from body to ball, body surface point (C,3) per candidate."""
    bodies = caps.body
    to_world = lambda p: pos[bodies] + jnp.einsum("kij,kj->ki", rot[bodies], p - model.com[bodies])
    gap, n, p = jax.vmap(capsule_contact, (0, 0, 0, None, None))(
        to_world(caps.a), to_world(caps.b), caps.radius, centre, ball_radius
    )
    if settings.ground:
        up = up_direction(model)
        height = jnp.dot(centre, up) - settings.ground_height
        gap = jnp.concatenate([gap, (height - ball_radius)[None]])
        n = jnp.concatenate([n, up[None]])
        p = jnp.concatenate([p, (centre - height * up)[None]])
    return gap, n, p


def single_gap(model: Model, caps: Capsules, settings: ContactSettings, ball_radius, i, pos_b, quat_b, centre):
    """Gap of candidate i with its body at (pos_b, quat_b) and the ball at centre."""
    n_caps = caps.radius.shape[0]
    if settings.ground:
        ground = jnp.dot(centre, up_direction(model)) - settings.ground_height - ball_radius
    else:
        ground = jnp.zeros((), centre.dtype)
    j = jnp.minimum(i, n_caps - 1)
    b = caps.body[j]
    rot = quat_to_matrix(quat_b)
    to_w = lambda p: pos_b + rot @ (p - model.com[b])
    g_cap, _, _ = capsule_contact(to_w(caps.a[j]), to_w(caps.b[j]), caps.radius[j], centre, ball_radius)
    return jnp.where(i >= n_caps, ground, g_cap)


def tangent_basis(n: Float[Array, "... 3"]) -> tuple[Float[Array, "... 3"], Float[Array, "... 3"]]:
    """Two unit tangents completing n to a right-handed frame (n, t1, t2)."""
    helper = jnp.where(
        jnp.abs(n[..., :1]) < 0.57, jnp.array([1.0, 0.0, 0.0], n.dtype), jnp.array([0.0, 0.0, 1.0], n.dtype)
    )
    t1 = jnp.cross(n, helper)
    t1 = t1 / safe_norm(t1)[..., None]
    return t1, jnp.cross(n, t1)


def facing_basis(
    n: Float[Array, "... 3"], *references: Float[Array, " 3"]
) -> tuple[Float[Array, "... 3"], Float[Array, "... 3"]]:
    """Tangents (t1, t2) completing n to a right-handed frame, t1 along the part perpendicular to
    n of the first of ``references`` whose part is longer than 0.1, so that a friction polygon
    built on them is tied to physical directions (up, the character's facing, the ball's flight)
    and not to the capture's world axes: a turned or Z-up copy of a clip gets the same forces.
    :func:`tangent_basis` where no reference has such a part (a zero heading: none given)."""
    t1, _ = tangent_basis(n)
    for ref in reversed(references):  # the first reference wins: it is applied last
        along = ref - jnp.sum(ref * n, -1, keepdims=True) * n
        size = safe_norm(along)[..., None]
        ok = size > 0.1
        t1 = jnp.where(ok, along / jnp.where(ok, size, 1.0), t1)
    return t1, jnp.cross(n, t1)
