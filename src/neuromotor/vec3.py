"""3-vector, 3x3 and quaternion algebra written out component by component, for the hot loop.

On a CPU a simulation step of this size is bound by the number of XLA kernels, not by flops.
``a @ b`` on 3x3 matrices becomes a ``dot`` kernel of its own and ``jnp.sum(.., -1)`` a
reduction, and each breaks the fusion of the elementwise work around it. The functions here use
only slices, products and sums of components, so XLA fuses long chains of them (and their
forward-mode tangents) into a few loop kernels. They agree with the generic versions in
:mod:`neuromotor.rotations` to round-off.
"""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array, Float


def dot(a: Float[Array, "... 3"], b: Float[Array, "... 3"]) -> Float[Array, "..."]:
    return a[..., 0] * b[..., 0] + a[..., 1] * b[..., 1] + a[..., 2] * b[..., 2]


def cross(a: Float[Array, "... 3"], b: Float[Array, "... 3"]) -> Float[Array, "... 3"]:
    return jnp.stack([a[..., 1] * b[..., 2] - a[..., 2] * b[..., 1],
                      a[..., 2] * b[..., 0] - a[..., 0] * b[..., 2],
                      a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]], -1)


def mv(m: Float[Array, "... 3 3"], x: Float[Array, "... 3"]) -> Float[Array, "... 3"]:
    """m x."""
    return m[..., :, 0] * x[..., 0, None] + m[..., :, 1] * x[..., 1, None] + m[..., :, 2] * x[..., 2, None]


def mtv(m: Float[Array, "... 3 3"], x: Float[Array, "... 3"]) -> Float[Array, "... 3"]:
    """m^T x."""
    return m[..., 0, :] * x[..., 0, None] + m[..., 1, :] * x[..., 1, None] + m[..., 2, :] * x[..., 2, None]


def mm(a: Float[Array, "... 3 3"], b: Float[Array, "... 3 3"]) -> Float[Array, "... 3 3"]:
    """a b."""
    return (a[..., :, 0, None] * b[..., None, 0, :] + a[..., :, 1, None] * b[..., None, 1, :]
            + a[..., :, 2, None] * b[..., None, 2, :])


def mmt(a: Float[Array, "... 3 3"], b: Float[Array, "... 3 3"]) -> Float[Array, "... 3 3"]:
    """a b^T."""
    return (a[..., :, 0, None] * b[..., None, :, 0] + a[..., :, 1, None] * b[..., None, :, 1]
            + a[..., :, 2, None] * b[..., None, :, 2])


def inv(a: Float[Array, "... 3 3"]) -> Float[Array, "... 3 3"]:
    """a^-1 as adjugate over determinant (rows of the adjugate are cross products of columns)."""
    c0, c1, c2 = a[..., :, 0], a[..., :, 1], a[..., :, 2]
    r0, r1, r2 = cross(c1, c2), cross(c2, c0), cross(c0, c1)
    return jnp.stack([r0, r1, r2], -2) / dot(c0, r0)[..., None, None]


# ---------------------------------------------------------------- quaternions (w, x, y, z)


def qmul(p: Float[Array, "... 4"], q: Float[Array, "... 4"]) -> Float[Array, "... 4"]:
    pw, pv, qw, qv = p[..., 0], p[..., 1:], q[..., 0], q[..., 1:]
    w = pw * qw - dot(pv, qv)
    v = pw[..., None] * qv + qw[..., None] * pv + cross(pv, qv)
    return jnp.concatenate([w[..., None], v], -1)


def qconj(q: Float[Array, "... 4"]) -> Float[Array, "... 4"]:
    return jnp.concatenate([q[..., :1], -q[..., 1:]], -1)


def qexp(w: Float[Array, "... 3"]) -> Float[Array, "... 4"]:
    """Unit quaternion of the rotation vector w, smooth at 0 (as ``rotations.quat_exp``)."""
    theta2 = dot(w, w)
    theta = jnp.sqrt(jnp.where(theta2 > 1e-24, theta2, 1.0))
    small = theta2 < 1e-12
    half_sinc = jnp.where(small, 0.5 - theta2 / 48.0, jnp.sin(0.5 * theta) / theta)
    cos_half = jnp.where(small, 1.0 - theta2 / 8.0, jnp.cos(0.5 * theta))
    return jnp.concatenate([cos_half[..., None], half_sinc[..., None] * w], -1)


def qlog(q: Float[Array, "... 4"]) -> Float[Array, "... 3"]:
    """Rotation vector of a unit quaternion, the shortest rotation (as ``rotations.quat_log``)."""
    sign = jnp.where(q[..., 0] < 0, -1.0, 1.0)
    w, v = sign * q[..., 0], sign[..., None] * q[..., 1:]
    s2 = dot(v, v)
    s = jnp.sqrt(jnp.where(s2 > 1e-24, s2, 1.0))
    angle = 2.0 * jnp.arctan2(s, w)
    scale = jnp.where(s2 > 1e-24, angle / s, 2.0 / w)
    return scale[..., None] * v


def qmatrix(q: Float[Array, "... 4"]) -> Float[Array, "... 3 3"]:
    """Rotation matrix of a unit quaternion."""
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    return jnp.stack([
        jnp.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        jnp.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        jnp.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1)], -2)

