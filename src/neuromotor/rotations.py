"""Rotation algebra in JAX: quaternions (w, x, y, z), matrices, Euler angles in any BVH order.

BVH convention: a joint with rotation channels in file order (a1, a2, a3) has local rotation
``R = R_a1(t1) @ R_a2(t2) @ R_a3(t3)`` mapping child-frame vectors to the parent frame.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

AXIS = {"X": 0, "Y": 1, "Z": 2}
# Tait-Bryan orders whose axis sequence is a cyclic permutation of XYZ have parity +1.
_CYCLIC = {"XYZ", "YZX", "ZXY"}


def order_parity(order: str) -> int:
    """+1 for XYZ, YZX, ZXY; -1 for XZY, ZYX, YXZ."""
    if sorted(order) != ["X", "Y", "Z"]:
        raise ValueError(f"rotation order must be a permutation of XYZ, got {order!r}")
    return 1 if order in _CYCLIC else -1


def skew(v: Float[Array, "... 3"]) -> Float[Array, "... 3 3"]:
    """Cross-product matrix: skew(a) @ b == cross(a, b)."""
    x, y, z = v[..., 0], v[..., 1], v[..., 2]
    o = jnp.zeros_like(x)
    return jnp.stack([jnp.stack([o, -z, y], -1), jnp.stack([z, o, -x], -1), jnp.stack([-y, x, o], -1)], -2)


def vee(m: Float[Array, "... 3 3"]) -> Float[Array, "... 3"]:
    """Inverse of skew for the antisymmetric part of m."""
    return 0.5 * jnp.stack([m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0], m[..., 1, 0] - m[..., 0, 1]], -1)


def axis_rotation(axis: int, angle: Float[Array, ...]) -> Float[Array, "... 3 3"]:
    """Rotation by ``angle`` (rad) about coordinate axis 0, 1 or 2."""
    c, s = jnp.cos(angle), jnp.sin(angle)
    o, i = jnp.zeros_like(angle), jnp.ones_like(angle)
    if axis == 0:
        rows = [[i, o, o], [o, c, -s], [o, s, c]]
    elif axis == 1:
        rows = [[c, o, s], [o, i, o], [-s, o, c]]
    else:
        rows = [[c, -s, o], [s, c, o], [o, o, i]]
    return jnp.stack([jnp.stack(r, -1) for r in rows], -2)


def euler_to_matrix(angles: Float[Array, "... 3"], order: str) -> Float[Array, "... 3 3"]:
    """``R_a1(t1) R_a2(t2) R_a3(t3)`` for the axis order, e.g. ``"ZXY"``."""
    r = axis_rotation(AXIS[order[0]], angles[..., 0])
    r = mm(r, axis_rotation(AXIS[order[1]], angles[..., 1]))
    return mm(r, axis_rotation(AXIS[order[2]], angles[..., 2]))


def _euler_parts(entry, order: str, reference: Float[Array, "... 3"] | None):
    """Euler angles of the matrix whose entry (a, b) is ``entry(a, b)``, component by component
    (see :func:`matrix_to_euler`): ``((t1, t2, t3), (cos t1, sin t1, cos t2, sin t2))``, the
    cosines and sines read from the matrix, not from the angles."""
    i, j, k = (AXIS[a] for a in order)
    s = order_parity(order)
    r_ik, r_jk, r_kk = entry(i, k), entry(j, k), entry(k, k)
    # cos t2 of the first solution. Not jnp.hypot: its tangent, fused with the quaternion entries
    # of euler_angles_and_rates, came out wrong from XLA:CPU at -O0 without fusion emitters (the
    # tests' compile flags); a square root of a masked sum is the same value here (entries <= 1).
    h2 = r_jk * r_jk + r_kk * r_kk
    hyp = jnp.where(h2 > 0, jnp.sqrt(jnp.where(h2 > 0, h2, 1.0)), 0.0)
    # atan2 rather than arcsin: near lock sin(t2) rounds to 1 but cos(t2) is still resolved.
    a = jnp.arctan2(-s * r_jk, r_kk)
    b = jnp.arctan2(s * r_ik, hyp)
    c = jnp.arctan2(-s * entry(i, j), entry(i, i))
    safe = jnp.where(hyp > 0, hyp, 1.0)
    cos1, sin1, cos2, sin2 = r_kk / safe, -s * r_jk / safe, hyp, s * r_ik
    if reference is None:
        return (a, b, c), (cos1, sin1, cos2, sin2)
    ref1, ref2, ref3 = reference[..., 0], reference[..., 1], reference[..., 2]
    near = lambda x, r: r + wrap_angle(x - r)
    # Of (t1, t2, t3) and (t1 + pi, pi - t2, t3 + pi), the one nearest the reference.
    a1, b1, c1 = near(a, ref1), near(b, ref2), near(c, ref3)
    a2, b2, c2 = near(a + jnp.pi, ref1), near(jnp.pi - b, ref2), near(c + jnp.pi, ref3)
    first = (a1 - ref1) ** 2 + (b1 - ref2) ** 2 + (c1 - ref3) ** 2 <= (a2 - ref1) ** 2 + (b2 - ref2) ** 2 + (
        c2 - ref3
    ) ** 2
    t1, t2, t3 = jnp.where(first, a1, a2), jnp.where(first, b1, b2), jnp.where(first, c1, c2)
    cos1, sin1, cos2 = jnp.where(first, cos1, -cos1), jnp.where(first, sin1, -sin1), jnp.where(first, cos2, -cos2)
    # Gimbal lock: R depends on t1 + s' t3 only; keep t1 at the reference, and read t3 from
    # column k1 of R_k(t3) = R_a2(t2)^T R_a1(t1)^T R (a vector orthogonal to axis k).
    locked = jnp.abs(cos2) < 1e-7
    cr, sr = jnp.cos(ref1), jnp.sin(ref1)
    k1, k2 = (k + 1) % 3, (k + 2) % 3
    col = _unrotate(j, cos2, sin2, _unrotate(i, cr, sr, [entry(0, k1), entry(1, k1), entry(2, k1)]))
    t3_locked = near(jnp.arctan2(col[k2], col[k1]), ref3)
    return (
        (jnp.where(locked, ref1, t1), t2, jnp.where(locked, t3_locked, t3)),
        (jnp.where(locked, cr, cos1), jnp.where(locked, sr, sin1), cos2, sin2),
    )


def _unrotate(axis: int, c, s, v: list) -> list:
    """The components of ``R^T v``, R the rotation about coordinate ``axis`` with cosine c and sine s."""
    p, q = (axis + 1) % 3, (axis + 2) % 3
    out = list(v)
    out[p] = c * v[p] + s * v[q]
    out[q] = c * v[q] - s * v[p]
    return out


def matrix_to_euler(
    r: Float[Array, "... 3 3"], order: str, reference: Float[Array, "... 3"] | None = None
) -> Float[Array, "... 3"]:
    """Euler angles (t1, t2, t3) with ``euler_to_matrix(angles, order) == r``.

    Of the two solutions (t1, t2, t3) and (t1 + pi, pi - t2, t3 + pi) the one nearest
    ``reference`` (after wrapping) is returned, and each angle is shifted by multiples of 2 pi
    to lie within pi of the reference: simulated angles then compare directly with the mocap's
    unwrapped ones. Near gimbal lock (|cos t2| < 1e-7) only t1 + s t3 is determined; t1 is
    then taken from the reference so the result stays continuous.
    """
    angles, _ = _euler_parts(lambda a, b: r[..., a, b], order, reference)
    return jnp.stack(angles, -1)


def euler_angles_and_rates(entry, w: Float[Array, "... 3"], order: str, reference: Float[Array, "... 3"] | None = None):
    """The Euler angles of :func:`matrix_to_euler`, of the matrix R whose entry (a, b) is
    ``entry(a, b)``, and their rates for ``w``, the angular velocity in the frame R maps into.

    ``w = t1' e_a1 + t2' R_a1 e_a2 + t3' R_a1 R_a2 e_a3``; turned back by ``R_a1(t1)`` it reads
    ``u = t1' e_a1 + t2' e_a2 + t3' (cos t2 e_a3 + s sin t2 e_a1)`` (s: the order's parity), so
    the rates need no 3x3 solve, and the cosines and sines come from R itself. Singular at
    gimbal lock, like the Euler axes. Returns ``(angles (..., 3), rates (..., 3))``.
    """
    angles, (cos1, sin1, cos2, sin2) = _euler_parts(entry, order, reference)
    i, j, k = (AXIS[a] for a in order)
    u = _unrotate(i, cos1, sin1, [w[..., 0], w[..., 1], w[..., 2]])
    t3 = u[k] / cos2
    return jnp.stack(angles, -1), jnp.stack([u[i] - order_parity(order) * sin2 * t3, u[j], t3], -1)


def wrap_angle(x: Float[Array, ...]) -> Float[Array, ...]:
    """Map angles to (-pi, pi]."""
    return x - 2.0 * jnp.pi * jnp.ceil((x - jnp.pi) / (2.0 * jnp.pi))


def euler_axes(
    parent_rot: Float[Array, "... 3 3"], angles: Float[Array, "... 3"], order: str
) -> Float[Array, "... 3 3"]:
    """World-frame Euler axes h_1, h_2, h_3 (rows) of joints (the rows of H, Eq. 4), batched.

    The relative angular velocity of the child is ``sum_i h_i thetadot_i``:
    h_1 = R_p e_a1, h_2 = R_p R_a1(t1) e_a2, h_3 = R_p R_a1(t1) R_a2(t2) e_a3.
    """
    a0, a1, a2 = (AXIS[c] for c in order)
    r1 = mm(parent_rot, axis_rotation(a0, angles[..., 0]))
    r2 = mm(r1, axis_rotation(a1, angles[..., 1]))
    return jnp.stack([parent_rot[..., :, a0], r1[..., :, a1], r2[..., :, a2]], -2)


# ---------------------------------------------------------------- 3-vectors and 3x3 matrices
# Written out component by component. On a CPU a simulation step of this size is bound by the
# number of XLA kernels, not by flops: ``a @ b`` on 3x3 matrices becomes a ``dot`` kernel of its
# own and ``jnp.sum(.., -1)`` a reduction, each breaking the fusion of the elementwise work around
# it. Slices, products and sums of components fuse into a few loop kernels, tangents included.


def dot(a: Float[Array, "... 3"], b: Float[Array, "... 3"]) -> Float[Array, ...]:
    return a[..., 0] * b[..., 0] + a[..., 1] * b[..., 1] + a[..., 2] * b[..., 2]


def cross(a: Float[Array, "... 3"], b: Float[Array, "... 3"]) -> Float[Array, "... 3"]:
    return jnp.stack(
        [
            a[..., 1] * b[..., 2] - a[..., 2] * b[..., 1],
            a[..., 2] * b[..., 0] - a[..., 0] * b[..., 2],
            a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0],
        ],
        -1,
    )


def mv(m: Float[Array, "... 3 3"], x: Float[Array, "... 3"]) -> Float[Array, "... 3"]:
    """m x."""
    return m[..., :, 0] * x[..., 0, None] + m[..., :, 1] * x[..., 1, None] + m[..., :, 2] * x[..., 2, None]


def mtv(m: Float[Array, "... 3 3"], x: Float[Array, "... 3"]) -> Float[Array, "... 3"]:
    """m^T x."""
    return m[..., 0, :] * x[..., 0, None] + m[..., 1, :] * x[..., 1, None] + m[..., 2, :] * x[..., 2, None]


def mm(a: Float[Array, "... 3 3"], b: Float[Array, "... 3 3"]) -> Float[Array, "... 3 3"]:
    """a b."""
    return (
        a[..., :, 0, None] * b[..., None, 0, :]
        + a[..., :, 1, None] * b[..., None, 1, :]
        + a[..., :, 2, None] * b[..., None, 2, :]
    )


def mmt(a: Float[Array, "... 3 3"], b: Float[Array, "... 3 3"]) -> Float[Array, "... 3 3"]:
    """a b^T."""
    return (
        a[..., :, 0, None] * b[..., None, :, 0]
        + a[..., :, 1, None] * b[..., None, :, 1]
        + a[..., :, 2, None] * b[..., None, :, 2]
    )


def inv3(a: Float[Array, "... 3 3"]) -> Float[Array, "... 3 3"]:
    """a^-1 as adjugate over determinant (rows of the adjugate are cross products of columns)."""
    c0, c1, c2 = a[..., :, 0], a[..., :, 1], a[..., :, 2]
    r0, r1, r2 = cross(c1, c2), cross(c2, c0), cross(c0, c1)
    return jnp.stack([r0, r1, r2], -2) / dot(c0, r0)[..., None, None]


# ---------------------------------------------------------------- quaternions (w, x, y, z)


def quat_mul(p: Float[Array, "... 4"], q: Float[Array, "... 4"]) -> Float[Array, "... 4"]:
    pw, pv, qw, qv = p[..., 0], p[..., 1:], q[..., 0], q[..., 1:]
    w = pw * qw - dot(pv, qv)
    v = pw[..., None] * qv + qw[..., None] * pv + cross(pv, qv)
    return jnp.concatenate([w[..., None], v], -1)


def quat_conj(q: Float[Array, "... 4"]) -> Float[Array, "... 4"]:
    return jnp.concatenate([q[..., :1], -q[..., 1:]], -1)


def quat_normalize(q: Float[Array, "... 4"]) -> Float[Array, "... 4"]:
    return q / jnp.linalg.norm(q, axis=-1, keepdims=True)


def quat_to_matrix(q: Float[Array, "... 4"]) -> Float[Array, "... 3 3"]:
    entry = quat_entries(q)
    return jnp.stack([jnp.stack([entry(a, b) for b in range(3)], -1) for a in range(3)], -2)


def matrix_to_quat(m: Float[Array, "... 3 3"]) -> Float[Array, "... 4"]:
    """Rotation matrix to unit quaternion with w >= 0 (branch on the largest diagonal term)."""
    tr = m[..., 0, 0] + m[..., 1, 1] + m[..., 2, 2]
    cands = jnp.stack(
        [
            jnp.stack(
                [1 + tr, m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0], m[..., 1, 0] - m[..., 0, 1]], -1
            ),
            jnp.stack(
                [
                    m[..., 2, 1] - m[..., 1, 2],
                    1 + 2 * m[..., 0, 0] - tr,
                    m[..., 0, 1] + m[..., 1, 0],
                    m[..., 0, 2] + m[..., 2, 0],
                ],
                -1,
            ),
            jnp.stack(
                [
                    m[..., 0, 2] - m[..., 2, 0],
                    m[..., 0, 1] + m[..., 1, 0],
                    1 + 2 * m[..., 1, 1] - tr,
                    m[..., 1, 2] + m[..., 2, 1],
                ],
                -1,
            ),
            jnp.stack(
                [
                    m[..., 1, 0] - m[..., 0, 1],
                    m[..., 0, 2] + m[..., 2, 0],
                    m[..., 1, 2] + m[..., 2, 1],
                    1 + 2 * m[..., 2, 2] - tr,
                ],
                -1,
            ),
        ],
        -2,
    )
    diag = jnp.stack([tr, m[..., 0, 0], m[..., 1, 1], m[..., 2, 2]], -1)
    best = jnp.argmax(diag, -1)
    q = jnp.take_along_axis(cands, best[..., None, None], -2)[..., 0, :]
    q = quat_normalize(q)
    return jnp.where(q[..., :1] < 0, -q, q)  # (a select of +-q, not of +-1.0: no float64 constant in float32)


def quat_rotate(q: Float[Array, "... 4"], v: Float[Array, "... 3"]) -> Float[Array, "... 3"]:
    """``quat_to_matrix(q) v`` for a unit q, without the matrix: ``v + w t + u x t``, ``t = 2 u x v``."""
    u = q[..., 1:]
    t = 2.0 * cross(u, v)
    return v + q[..., :1] * t + cross(u, t)


def quat_entries(q: Float[Array, "... 4"]):
    """``entry(a, b)``: the entry (a, b) of ``quat_to_matrix(q)`` alone (a component array)."""
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    rows = (
        (lambda: 1 - 2 * (y * y + z * z), lambda: 2 * (x * y - w * z), lambda: 2 * (x * z + w * y)),
        (lambda: 2 * (x * y + w * z), lambda: 1 - 2 * (x * x + z * z), lambda: 2 * (y * z - w * x)),
        (lambda: 2 * (x * z - w * y), lambda: 2 * (y * z + w * x), lambda: 1 - 2 * (x * x + y * y)),
    )
    return lambda a, b: rows[a][b]()


def quat_exp(w: Float[Array, "... 3"]) -> Float[Array, "... 4"]:
    """Unit quaternion of the rotation vector w (angle |w| about w / |w|), smooth at 0."""
    theta2 = dot(w, w)
    theta = jnp.sqrt(jnp.where(theta2 > 1e-24, theta2, 1.0))
    small = theta2 < 1e-12
    half_sinc = jnp.where(small, 0.5 - theta2 / 48.0, jnp.sin(0.5 * theta) / theta)
    cos_half = jnp.where(small, 1.0 - theta2 / 8.0, jnp.cos(0.5 * theta))
    return jnp.concatenate([cos_half[..., None], half_sinc[..., None] * w], -1)


def quat_turn(q: Float[Array, "... 4"], w: Float[Array, "... 3"]) -> Float[Array, "... 4"]:
    """q turned by the world-frame rotation vector w: ``normalize(exp(w) q)`` (the retraction
    every position update and post-stabilization step uses)."""
    return quat_normalize(quat_mul(quat_exp(w), q))


def quat_log(q: Float[Array, "... 4"]) -> Float[Array, "... 3"]:
    """Rotation vector of a unit quaternion (shortest rotation: q and -q give the same)."""
    q = jnp.where(q[..., :1] < 0, -q, q)
    w, v = q[..., 0], q[..., 1:]
    s2 = dot(v, v)
    s = jnp.sqrt(jnp.where(s2 > 1e-24, s2, 1.0))
    angle = 2.0 * jnp.arctan2(s, w)
    scale = jnp.where(s2 > 1e-24, angle / s, 2.0 / w)
    return scale[..., None] * v


def right_jacobian_inv(e: Float[Array, "... 3"]) -> Float[Array, "... 3 3"]:
    """Inverse right Jacobian of SO(3) at the rotation vector e (|e| <= pi):
    ``log(exp(e) exp(d)) = e + Jr^-1(e) d + O(d^2)``, ``Jr^-1 = 1 + [e]x / 2 + beta [e]x^2`` with
    ``beta = 1/|e|^2 - cot(|e|/2) / (2 |e|)`` (its series below |e| = 1e-2: smooth at 0)."""
    t2 = dot(e, e)
    small = t2 < 1e-4
    t = jnp.sqrt(jnp.where(small, 1.0, t2))
    half = 0.5 * t
    beta = jnp.where(
        small,
        1.0 / 12.0 + t2 / 720.0 + t2 * t2 / 30240.0,
        1.0 / jnp.where(small, 1.0, t2) - jnp.cos(half) / (2.0 * t * jnp.sin(half)),
    )
    k = skew(e)
    eye = jnp.eye(3, dtype=e.dtype)
    return eye + 0.5 * k + beta[..., None, None] * mm(k, k)


def rotation_error(r_a: Float[Array, "... 3 3"], r_b: Float[Array, "... 3 3"]) -> Float[Array, "... 3"]:
    """World-frame rotation vector e with exp(e) r_b = r_a."""
    return quat_log(matrix_to_quat(mmt(r_a, r_b)))


def continuous_angles(theta, reference=None) -> np.ndarray:
    """(T, n) angles made continuous in time (``np.unwrap`` along axis 0), each column then
    shifted by a whole number of turns so that its first sample is the branch nearest
    ``reference[0]`` (e.g. the mocap's angles; default: the wrapped first sample). NumPy."""
    theta = np.unwrap(np.asarray(theta, dtype=np.float64), axis=0)
    if theta.shape[0] == 0:
        return theta
    first = theta[0]
    target = (
        np.arctan2(np.sin(first), np.cos(first)) if reference is None else np.asarray(reference, dtype=np.float64)[0]
    )
    turns = np.round((first - target) / (2 * np.pi))
    return theta - 2 * np.pi * turns
