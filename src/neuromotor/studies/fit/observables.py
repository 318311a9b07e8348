"""Body observables of a fit target (``body_angle``, ``body_position``): a body's turn about an
axis and a body point's displacement along an axis, relative to the world or to another body,
each as the change since the case's onset. Pure JAX and smooth, so the fit differentiates them
through the rollout.

Conventions (``O`` the reference body, the world when there is none: ``R_O = I``, ``x_O = 0``;
``k0`` the onset sample; ``a`` the axis as a world unit vector at onset):

* ``body_angle``: ``R_rel(t) = R_O(t)^T R_B(t)``; the change since onset is
  ``D(t) = R_rel(t) R_rel(k0)^T`` (a rotation written in O's frame); the angle is the twist of
  ``D`` about ``a_O = R_O(k0)^T a`` (swing-twist decomposition ``D = swing * twist``): with
  ``D``'s quaternion ``(w, v)``, ``angle = 2 atan2(s v.a_O, s w)``, ``s = sign(w)``, in
  (-pi, pi], positive by the right-hand rule about the axis. A rotation about ``a_O`` alone gives
  its angle; a rotation common to B and O cancels.
* ``body_position``: the point ``x_P = x_B + R_B p`` (``p`` from the body's COM, in its frame),
  in O's frame ``r(t) = R_O(t)^T (x_P(t) - x_O(t))``; the displacement is
  ``u(t) = a_O . (r(t) - r(k0))``. Which point of O is its origin does not matter: it is a
  constant in O's frame and cancels.
"""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array, Float, Int

from neuromotor.rotations import dot, quat_conj, quat_mul, quat_rotate


def twist_angle(q: Float[Array, "... 4"], axis: Float[Array, "... 3"]) -> Float[Array, ...]:
    """Signed angle (rad) of the twist of the unit quaternion ``q`` (w, x, y, z) about the unit
    ``axis``: ``2 atan2(v.a, w)`` on the branch w >= 0, so q and -q give the same angle."""
    w, va = q[..., 0], dot(q[..., 1:], axis)
    s = jnp.where(w < 0, -1.0, 1.0).astype(q.dtype)
    return 2.0 * jnp.arctan2(s * va, s * w)


def body_angle(
    q_body: Float[Array, "T 4"], q_other: Float[Array, "T 4"], k0: Int[Array, ""], axis: Float[Array, " 3"]
) -> Float[Array, " T"]:
    """The turn (rad) of a body about ``axis`` (world, at onset; fixed in the other body's frame)
    relative to the other body (``q_other``: its world orientations, the identity for the world),
    as the change since sample ``k0``."""
    rel = quat_mul(quat_conj(q_other), q_body)  # R_O^T R_B
    change = quat_mul(rel, quat_conj(rel[k0]))  # R_rel(t) R_rel(k0)^T
    a = quat_rotate(quat_conj(q_other[k0]), axis)  # the axis in O's frame at onset
    return twist_angle(change, a)


def body_displacement(
    pos_body: Float[Array, "T 3"],
    q_body: Float[Array, "T 4"],
    lever: Float[Array, " 3"],
    pos_other: Float[Array, "T 3"],
    q_other: Float[Array, "T 4"],
    k0: Int[Array, ""],
    axis: Float[Array, " 3"],
) -> Float[Array, " T"]:
    """The displacement (m) along ``axis`` (world, at onset; fixed in the other body's frame) of
    the body point ``lever`` (body frame, from its COM at ``pos_body``), relative to the other body
    (``pos_other``/``q_other``; zeros and the identity for the world), as the change since ``k0``."""
    x = pos_body + quat_rotate(q_body, jnp.broadcast_to(lever, pos_body.shape))
    r = quat_rotate(quat_conj(q_other), x - pos_other)
    a = quat_rotate(quat_conj(q_other[k0]), axis)
    return dot(r - r[k0], a)


def identity_quats(n: int, dtype=jnp.float64) -> Float[Array, "n 4"]:
    """``n`` identity quaternions (the world as the reference body)."""
    return jnp.zeros((n, 4), dtype).at[:, 0].set(1.0)
