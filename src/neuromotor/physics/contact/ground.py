"""The ground plane and the bodies' contact points on it (issue 38).

The ground is the plane ``up . x = height`` with ``up = -gravity / |gravity|`` (the capture's
up axis; a tilted platform's turned normal instead, ``Ground.normal``). Its contact candidates
are the vertices of each body's mass-model polyhedron (body frame, relative to the joint
origin), by one rule:

* each step, per body, its ``per_body`` nearest vertices are that body's contact slots, ordered
  by vertex index (so a slot keeps its vertex, and its warm start, while the set stays the same);
* of all the bodies' slots, the ``max_contacts`` nearest go into the contact LCP
  (:mod:`neuromotor.physics.contact.step`), beside the ball's contacts.

"Nearest" is by the gap the step would leave without contact, ``g + h min(u, 0)``, with g the
height above the plane at the step start and u the vertex's normal velocity under the step's
contact-free velocity: a vertex about to hit the plane (a heel coming down) goes ahead of one
resting on it. The defaults (8 per body, 16 in all) hold a whole sole (the mass model's foot is
a hull of two rings of 8 vertices) of each foot.

A contact's + side is the body (at the vertex), its - side the static world; the normal is
``up``, and the friction polygon's first tangent is the body's own facing axis in the plane
(``Ground.axes``: each body's forward axis, and its left axis where the forward one stands near
up, fixed in the body): the polygon turns with the foot that stands on it, not with the capture's
axes or the character's first pose. Every parameter of :class:`Ground` except the static counts
is an array leaf (jit, vmap, grad over height, friction, restitution and axes).
"""

from __future__ import annotations

from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from neuromotor.model.skeleton import Model
from neuromotor.physics.contact.detection import up_direction
from neuromotor.rotations import quat_to_matrix

FAR = 1.0e6  # m: the gap of a padding vertex (never the lowest of a body)
DEFAULT_FRICTION = 0.8
DEFAULT_PER_BODY = 8
DEFAULT_MAX_CONTACTS = 16
DEFAULT_PGS_ITERATIONS = 40  # PGS sweeps of a scene of the ground alone (ContactSettings' default)
# m: with a ground under the bodies, a contact (the ball's too) within this gap counts as touching.
# Stacked contacts need it: the contact-free velocity of a ball resting on a body that rests on
# the ground does not close their gap (both fall freely), so by that velocity alone the ball's
# contact would join the LCP only every other step (once it has sunk in).
DEFAULT_MARGIN = 1e-5


class Ground(eqx.Module):
    """The ground plane and the bodies' candidate contact points."""

    height: Float[Array, ""]  # m along up
    friction: Float[Array, ""]  # Coulomb coefficient mu
    restitution: Float[Array, ""]  # Newton's coefficient e (0: no bounce)
    vertices: Float[Array, "B V 3"]  # each body's polyhedron vertices (body frame, from the joint origin), padded
    valid: Bool[Array, "B V"]  # False on padding
    axes: Float[Array, "B 2 3"]  # each body's forward and left axes (body frame; zero: world axes)
    # The plane's unit normal (world); None: up. A tilted platform sets it step by step.
    normal: Float[Array, " 3"] | None = None
    per_body: int = eqx.field(static=True, default=DEFAULT_PER_BODY)  # nearest vertices per body (slots)
    max_contacts: int = eqx.field(static=True, default=DEFAULT_MAX_CONTACTS)  # slots kept per step (nearest)
    margin: float = eqx.field(static=True, default=DEFAULT_MARGIN)  # m: a contact this close is touching
    # PGS sweeps of a scene of the ground alone (with a ball: the ball's ContactSettings rule).
    pgs_iterations: int = eqx.field(static=True, default=DEFAULT_PGS_ITERATIONS)

    @property
    def n_slots(self) -> int:
        return self.vertices.shape[0] * self.per_body

    @property
    def slot_body(self) -> Int[Array, " G"]:
        """Body of each slot (``per_body`` consecutive slots per body)."""
        return jnp.repeat(jnp.arange(self.vertices.shape[0], dtype=jnp.int32), self.per_body)


def make_ground(
    shapes: Sequence,
    height=0.0,
    friction=DEFAULT_FRICTION,
    restitution=0.0,
    per_body: int = DEFAULT_PER_BODY,
    max_contacts: int = DEFAULT_MAX_CONTACTS,
    margin: float = DEFAULT_MARGIN,
    pgs_iterations: int = DEFAULT_PGS_ITERATIONS,
    axes=None,
) -> Ground:
    """A :class:`Ground` for bodies of the given shapes (one polyhedron, or an (N, 3) array of
    points, per body; body frame); ``axes`` (B, 2, 3): each body's forward and left axes in its
    frame, which orient its contacts' friction polygons (None: the world axes' tangents,
    :func:`~neuromotor.physics.contact.detection.tangent_basis`)."""
    verts = [np.asarray(getattr(s, "vertices", s), np.float64).reshape(-1, 3) for s in shapes]
    if not verts or min(len(v) for v in verts) < 1:
        raise ValueError("make_ground needs at least one point per body")
    if per_body < 1 or max_contacts < 1 or pgs_iterations < 1:
        raise ValueError(
            f"per_body, max_contacts and pgs_iterations must be >= 1, got {per_body}, {max_contacts}, {pgs_iterations}"
        )
    n = max(len(v) for v in verts)
    padded = np.zeros((len(verts), n, 3))
    valid = np.zeros((len(verts), n), bool)
    for b, v in enumerate(verts):
        padded[b, : len(v)] = v
        padded[b, len(v) :] = v[0]
        valid[b, : len(v)] = True
    f = lambda x: jnp.asarray(x, jnp.float64)
    return Ground(
        f(height),
        f(friction),
        f(restitution),
        f(padded),
        jnp.asarray(valid),
        f(np.zeros((len(verts), 2, 3)) if axes is None else np.broadcast_to(axes, (len(verts), 2, 3))),
        per_body=min(per_body, n),
        max_contacts=max_contacts,
        margin=margin,
        pgs_iterations=pgs_iterations,
    )


def ground_normal(model: Model, ground: Ground) -> Float[Array, " 3"]:
    """The plane's unit normal: ``up``, or a tilted platform's."""
    return up_direction(model) if ground.normal is None else ground.normal


def friction_references(ground: Ground, body, rot) -> tuple[Float[Array, "K 3"], Float[Array, "K 3"]]:
    """World forward and left axes of the bodies ``body`` (K,) at orientations ``rot`` (B, 3, 3):
    the references of their contacts' friction polygons
    (:func:`~neuromotor.physics.contact.detection.facing_basis`, in this order)."""
    ref = world_axes(ground.axes[body], rot[body])
    return ref[:, 0], ref[:, 1]


def world_axes(axes: Float[Array, "... 2 3"], rot: Float[Array, "... 3 3"]) -> Float[Array, "... 2 3"]:
    """Bodies' friction axes (forward, left; each body's frame) in the world at orientations
    ``rot`` (body to world): the one rule for the ground's contacts and the capture's ground
    reaction forces."""
    return jnp.einsum("...ij,...aj->...ai", rot, axes)


def vertex_heights(model: Model, ground: Ground, pos, rot):
    """World vertices (B, V, 3) and their heights above the plane (B, V; FAR on padding)."""
    local = ground.vertices - model.com[:, None, :]
    world = pos[:, None, :] + jnp.einsum("bij,bvj->bvi", rot, local)
    height = world @ ground_normal(model, ground) - ground.height
    return world, jnp.where(ground.valid, height, FAR)


class GroundSlots(eqx.Module):
    """Every body's ``per_body`` nearest vertices at one configuration (G = B * per_body slots)."""

    vertex: Int[Array, " G"]  # vertex index within its body
    gap: Float[Array, " G"]  # height above the plane (m)
    point: Float[Array, "G 3"]  # the vertex (world)
    reach: Float[Array, " G"]  # the gap the step would leave without contact, g + h min(u, 0) (m)


def ground_slots(model: Model, ground: Ground, pos, rot, velocity=None, h: float = 0.0) -> GroundSlots:
    """The slots of the rule in the module docstring; ``velocity`` (B, 6): the bodies' contact-free
    velocity over the step ([linear, angular], world; None: the heights alone)."""
    world, height = vertex_heights(model, ground, pos, rot)
    key = height
    if velocity is not None:
        lever = world - pos[:, None, :]
        u = (velocity[:, None, :3] + jnp.cross(velocity[:, None, 3:], lever)) @ ground_normal(model, ground)
        key = height + h * jnp.minimum(u, 0.0)
    idx = jnp.sort(smallest(key, ground.per_body), -1)  # (B, k): the nearest, by vertex index
    take = lambda a: jnp.take_along_axis(a, idx, 1).reshape(-1)
    point = jnp.take_along_axis(world, idx[..., None], 1)
    return GroundSlots(idx.reshape(-1), take(height), point.reshape(-1, 3), take(key))


def smallest(key: Float[Array, "... n"], k: int) -> Int[Array, "... k"]:
    """Indices of the ``k`` smallest entries along the last axis, smallest first, ties by lower
    index: ``lax.top_k(-key, k)[1]``, by ranks (pairwise comparisons), which XLA:CPU runs as a
    few fused loops where its sort costs about 0.1 ms a step at these sizes."""
    n = key.shape[-1]
    ids = jnp.arange(n)
    a, b = key[..., :, None], key[..., None, :]  # (.., n, n): entry i against entry j
    before = (b < a) | ((b == a) & (ids[None, :] < ids[:, None]))
    rank = jnp.sum(before, -1)  # entries ahead of each
    hit = rank[..., :, None] == jnp.arange(k)  # (.., n, k)
    return jnp.sum(jnp.where(hit, ids[:, None], 0), -2).astype(jnp.int32)


def vertex_gap(model: Model, ground: Ground, body, vertex, pos_b, quat_b):
    """Height above the plane of one vertex of ``body`` with the body at (pos_b, quat_b)."""
    p = pos_b + quat_to_matrix(quat_b) @ (ground.vertices[body, vertex] - model.com[body])
    return jnp.dot(p, ground_normal(model, ground)) - ground.height


def lowest_points(model: Model, ground: Ground, pos, rot, bodies: Sequence[int] | None = None):
    """The height above the plane of the lowest vertex of ``bodies`` (default: all), per configuration
    (leading axes of ``pos``, ``rot`` are batch axes)."""
    fn = lambda p, r: vertex_heights(model, ground, p, r)[1]
    for _ in range(pos.ndim - 2):
        fn = jax.vmap(fn)
    height = fn(pos, rot)
    if bodies is not None:
        height = height[..., jnp.asarray(list(bodies), jnp.int32), :]
    return jnp.min(height, axis=(-2, -1))
