"""The NumPy twin of :mod:`neuromotor.rotations`, for host code (reading and labelling clips,
shaping bodies): same names, same argument order, same conventions, same numbers to round-off,
without JAX dispatch on small arrays.

BVH convention: a joint with rotation channels in file order (a1, a2, a3) has local rotation
``R = R_a1(t1) @ R_a2(t2) @ R_a3(t3)`` mapping child-frame vectors to the parent frame.
"""

from __future__ import annotations

import numpy as np

from neuromotor.rotations import AXIS, order_parity

__all__ = [
    "axis_rotation",
    "euler_to_matrix",
    "matrix_to_euler",
    "quat_conj",
    "quat_exp",
    "quat_log",
    "quat_mul",
    "rotation_angle",
    "wrap_angle",
]


def axis_rotation(axis: int, angle) -> np.ndarray:
    """(..., 3, 3) rotation by ``angle`` (rad) about coordinate axis 0, 1 or 2."""
    c, s = np.cos(angle), np.sin(angle)
    out = np.zeros(np.shape(angle) + (3, 3))
    i, j = (axis + 1) % 3, (axis + 2) % 3
    out[..., axis, axis] = 1.0
    out[..., i, i] = c
    out[..., j, j] = c
    out[..., i, j] = -s
    out[..., j, i] = s
    return out


def euler_to_matrix(angles, order: str) -> np.ndarray:
    """``R_a1(t1) R_a2(t2) R_a3(t3)`` (..., 3, 3) of ``angles`` (..., 3) in radians, e.g. ``"ZXY"``."""
    angles = np.asarray(angles, dtype=np.float64)
    r = axis_rotation(AXIS[order[0]], angles[..., 0])
    r = r @ axis_rotation(AXIS[order[1]], angles[..., 1])
    return r @ axis_rotation(AXIS[order[2]], angles[..., 2])


def wrap_angle(x) -> np.ndarray:
    """Map angles to (-pi, pi]."""
    return x - 2.0 * np.pi * np.ceil((x - np.pi) / (2.0 * np.pi))


def matrix_to_euler(r, order: str, reference=None) -> np.ndarray:
    """Euler angles (..., 3) with ``euler_to_matrix(angles, order) == r``; the rules of
    :func:`neuromotor.rotations.matrix_to_euler`: without ``reference`` the middle angle is in
    [-pi/2, pi/2]; with it, the solution nearest the reference, each angle within pi of it, and
    near gimbal lock (|cos t2| < 1e-7) t1 taken from the reference."""
    r = np.asarray(r, dtype=np.float64)
    i, j, k = (AXIS[a] for a in order)
    s = order_parity(order)
    r_ik, r_jk, r_kk = r[..., i, k], r[..., j, k], r[..., k, k]
    hyp = np.sqrt(r_jk * r_jk + r_kk * r_kk)
    a = np.arctan2(-s * r_jk, r_kk)
    b = np.arctan2(s * r_ik, hyp)
    c = np.arctan2(-s * r[..., i, j], r[..., i, i])
    if reference is None:
        return np.stack([a, b, c], -1)
    ref = np.asarray(reference, dtype=np.float64)
    ref1, ref2, ref3 = ref[..., 0], ref[..., 1], ref[..., 2]
    near = lambda x, q: q + wrap_angle(x - q)
    # Of (t1, t2, t3) and (t1 + pi, pi - t2, t3 + pi), the one nearest the reference.
    a1, b1, c1 = near(a, ref1), near(b, ref2), near(c, ref3)
    a2, b2, c2 = near(a + np.pi, ref1), near(np.pi - b, ref2), near(c + np.pi, ref3)
    first = (a1 - ref1) ** 2 + (b1 - ref2) ** 2 + (c1 - ref3) ** 2 <= (a2 - ref1) ** 2 + (b2 - ref2) ** 2 + (
        c2 - ref3
    ) ** 2
    t1, t2, t3 = np.where(first, a1, a2), np.where(first, b1, b2), np.where(first, c1, c2)
    # Gimbal lock: R depends on t1 + s' t3 only; t1 stays at the reference and t3 is read from
    # column k1 of R_k(t3) = R_a2(t2)^T R_a1(t1)^T R.
    cos2, sin2 = np.where(first, hyp, -hyp), s * r_ik
    locked = np.abs(cos2) < 1e-7
    k1, k2 = (k + 1) % 3, (k + 2) % 3
    col = _unrotate(i, np.cos(ref1), np.sin(ref1), [r[..., 0, k1], r[..., 1, k1], r[..., 2, k1]])
    col = _unrotate(j, cos2, sin2, col)
    t3_locked = near(np.arctan2(col[k2], col[k1]), ref3)
    return np.stack([np.where(locked, ref1, t1), t2, np.where(locked, t3_locked, t3)], -1)


def _unrotate(axis: int, c, s, v: list) -> list:
    """The components of ``R^T v``, R the rotation about coordinate ``axis`` with cosine c and sine s."""
    p, q = (axis + 1) % 3, (axis + 2) % 3
    out = list(v)
    out[p] = c * v[p] + s * v[q]
    out[q] = c * v[q] - s * v[p]
    return out


def rotation_angle(r) -> np.ndarray:
    """Angle (rad, in [0, pi]) of rotation matrices (..., 3, 3)."""
    return np.arccos(np.clip((np.trace(r, axis1=-2, axis2=-1) - 1.0) / 2.0, -1.0, 1.0))


def quat_mul(p, q) -> np.ndarray:
    """Hamilton product of quaternions (..., 4), w x y z."""
    p, q = np.asarray(p, np.float64), np.asarray(q, np.float64)
    w1, v1, w2, v2 = p[..., :1], p[..., 1:], q[..., :1], q[..., 1:]
    return np.concatenate([w1 * w2 - np.sum(v1 * v2, -1, keepdims=True), w1 * v2 + w2 * v1 + np.cross(v1, v2)], -1)


def quat_conj(q) -> np.ndarray:
    q = np.asarray(q, np.float64)
    return np.concatenate([q[..., :1], -q[..., 1:]], -1)


def quat_exp(w) -> np.ndarray:
    """Unit quaternion of the rotation vector w (angle |w| about w / |w|)."""
    w = np.asarray(w, np.float64)
    angle = np.linalg.norm(w, axis=-1, keepdims=True)
    axis = np.divide(w, angle, out=np.zeros_like(w), where=angle > 0)
    return np.concatenate([np.cos(0.5 * angle), np.sin(0.5 * angle) * axis], -1)


def quat_log(q) -> np.ndarray:
    """Rotation vector of a unit quaternion (shortest rotation: q and -q give the same)."""
    q = np.asarray(q, np.float64)
    q = np.where(q[..., :1] < 0, -q, q)
    s = np.linalg.norm(q[..., 1:], axis=-1, keepdims=True)
    angle = 2.0 * np.arctan2(s, q[..., :1])
    return np.divide(angle * q[..., 1:], s, out=np.zeros_like(q[..., 1:]), where=s > 0)
