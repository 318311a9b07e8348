"""Kinematics of the mocap: joint angles, cubic splines in time, forward kinematics.

Spline coordinates of the mocap, ``q = [root_pos (3), root_quat (4), quat_k (4) per joint]``:
the root joint's position, then the local rotation of the root and of every non-root joint as a
quaternion made sign-continuous over time. A cubic spline through the frames gives q, qdot and
qddot at any time (Section 5.1: "fitting a cubic spline to the position data, and then finding
the second derivative"); quaternions are normalized inside forward kinematics. Splining
rotations rather than Euler channels matters near gimbal lock: real clips (the knees of the
MocapBank clip) jump 100-150 degrees in two Euler channels between frames while the rotation
itself barely moves, and a spline through such jumps invents huge accelerations.

Body velocities and accelerations follow from forward kinematics by ``jax.jvp`` (the exact chain
rule), not by finite differences of body poses. Joint angles theta (every rotation channel of
every non-root joint, radians) are the BVH Euler decomposition of the splined rotations,
unwrapped across +-180 degrees by continuity with the file's own (unwrapped) channels.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float
from scipy.interpolate import CubicSpline

from .bvh import BvhClip
from .rotations import euler_to_matrix, matrix_to_euler, matrix_to_quat, quat_to_matrix, vee
from .skeleton import Model


class Spline(eqx.Module):
    """Piecewise cubic on a uniform grid ``t0 + k dt`` (coefficients from scipy, evaluated in JAX)."""

    t0: Float[Array, ""]
    dt: Float[Array, ""]
    coeffs: Float[Array, "4 K D"]  # highest power first, per interval

    @classmethod
    def fit(cls, times: np.ndarray, values: np.ndarray, bc_type: str = "not-a-knot") -> "Spline":
        cs = CubicSpline(times, values, axis=0, bc_type=bc_type)
        dt = float(times[1] - times[0])
        return cls(jnp.asarray(float(times[0])), jnp.asarray(dt), jnp.asarray(cs.c))

    @property
    def t_end(self) -> Float[Array, ""]:
        return self.t0 + self.dt * self.coeffs.shape[1]

    def _locate(self, t):
        k = jnp.clip(jnp.floor((t - self.t0) / self.dt).astype(jnp.int32), 0, self.coeffs.shape[1] - 1)
        s = t - (self.t0 + k * self.dt)
        return self.coeffs[:, k], s

    def __call__(self, t: Float[Array, ""], derivative: int = 0) -> Float[Array, " D"]:
        c, s = self._locate(t)
        if derivative == 0:
            return ((c[0] * s + c[1]) * s + c[2]) * s + c[3]
        if derivative == 1:
            return (3.0 * c[0] * s + 2.0 * c[1]) * s + c[2]
        if derivative == 2:
            return 6.0 * c[0] * s + 2.0 * c[1]
        raise ValueError("derivative must be 0, 1 or 2")


def rotating_joints(model: Model) -> list[int]:
    """Joints with rotation channels (the root first): one quaternion block each in q."""
    return [k for k, order in enumerate(model.joint_order) if order]


def mocap_angles(model: Model, clip: BvhClip) -> np.ndarray:
    """(T, n_all) Euler channels of the non-root joints in radians, unwrapped over time."""
    cols = [c for joint in clip.joints[1:] for c in joint.rotation_columns]
    angles = np.unwrap(np.deg2rad(np.asarray(clip.motion[:, cols], dtype=np.float64)), axis=0)
    if angles.shape[1] != len(model.all_dof_names):
        raise AssertionError("angle layout does not match the model")
    return angles


def mocap_coordinates(model: Model, clip: BvhClip) -> np.ndarray:
    """(T, 3 + 4 * n_rot) spline coordinates of every frame (see the module docstring)."""
    root = clip.joints[0]
    blocks = [np.asarray(clip.motion[:, list(root.translation_columns)], dtype=np.float64)]
    for k in rotating_joints(model):
        joint = clip.joints[k]
        ang = jnp.deg2rad(jnp.asarray(clip.motion[:, list(joint.rotation_columns)]))
        quat = np.array(matrix_to_quat(euler_to_matrix(ang, joint.rotation_order)))
        # Sign continuity: q and -q are the same rotation; keep neighbours on one side.
        signs = np.cumprod(np.where(np.sum(quat[1:] * quat[:-1], -1) < 0, -1.0, 1.0))
        quat[1:] *= signs[:, None]
        blocks.append(quat)
    return np.concatenate(blocks, axis=1)


class Trajectory(eqx.Module):
    """The mocap as a differentiable function of time: q(t), qdot(t), qddot(t)."""

    spline: Spline
    angle_spline: Spline  # unwrapped file channels: branch reference for the decomposition
    duration: Float[Array, ""]

    def q(self, t):
        return self.spline(t, 0)

    def qd(self, t):
        return self.spline(t, 1)

    def qdd(self, t):
        return self.spline(t, 2)

    def angle_reference(self, t):
        return self.angle_spline(t, 0)


def trajectory_from_clip(model: Model, clip: BvhClip) -> Trajectory:
    q = mocap_coordinates(model, clip)
    times = np.arange(q.shape[0]) * clip.frame_time
    if q.shape[0] < 4:
        raise ValueError(f"{clip.path}: need at least 4 frames for a cubic spline, got {q.shape[0]}")
    ref = Spline.fit(times, mocap_angles(model, clip))
    return Trajectory(Spline.fit(times, q), ref, jnp.asarray(times[-1]))


def local_rotations(model: Model, q: Float[Array, " Q"]) -> list:
    """Local rotation matrix of every joint (identity where a joint has no rotation channels)."""
    out = [None] * len(model.joint_names)
    for slot, k in enumerate(rotating_joints(model)):
        quat = q[3 + 4 * slot: 7 + 4 * slot]
        out[k] = quat_to_matrix(quat / jnp.linalg.norm(quat))
    eye = jnp.eye(3, dtype=q.dtype)
    return [eye if r is None else r for r in out]


def joint_angles_from_q(model: Model, q: Float[Array, " Q"], reference: Float[Array, " n_all"]):
    """Euler angles of every non-root rotation channel (n_all), nearest ``reference``."""
    rots = local_rotations(model, q)
    cols = joint_dof_columns(model)
    out = []
    for k, order in enumerate(model.joint_order):
        if model.joint_parent[k] >= 0 and order:
            out.append(matrix_to_euler(rots[k], order, reference[jnp.array(cols[k])]))
    return jnp.concatenate(out) if out else jnp.zeros((0,), q.dtype)


def joint_dof_columns(model: Model) -> list[tuple[int, ...]]:
    """For each joint, the columns of its rotation channels within the ``angles`` block."""
    out, start = [], 0
    for k, order in enumerate(model.joint_order):
        if model.joint_parent[k] < 0:
            out.append(())
            continue
        out.append(tuple(range(start, start + len(order))))
        start += len(order)
    return out


def joint_frames(model: Model, q: Float[Array, " Q"]) -> tuple[Float[Array, "J 3"], Float[Array, "J 3 3"]]:
    """World origin and orientation of every joint frame from spline coordinates q."""
    local = local_rotations(model, q)
    origins, rots = [], []
    for k, parent in enumerate(model.joint_parent):
        if parent < 0:
            origins.append(q[0:3])
            rots.append(local[k])
            continue
        origins.append(origins[parent] + rots[parent] @ model.joint_offset[k])
        rots.append(rots[parent] @ local[k])
    return jnp.stack(origins), jnp.stack(rots)


def body_poses(model: Model, q: Float[Array, " Q"]) -> tuple[Float[Array, "B 3"], Float[Array, "B 3 3"]]:
    """COM positions and orientations of the bodies for coordinates q."""
    origins, rots = joint_frames(model, q)
    idx = jnp.array(model.body_joint)
    rot = rots[idx]
    pos = origins[idx] + jnp.einsum("bij,bj->bi", rot, model.com)
    return pos, rot


def body_kinematics(model: Model, q, qd, qdd):
    """Body pose, velocity and acceleration (world frame) by forward-mode differentiation.

    Returns ``(pos, rot, vel, omega, acc, alpha)``; omega = vee(Rdot R^T) and
    alpha = d omega / dt, both in the world frame.
    """

    def vel_fn(q_, qd_):
        (pos, rot), (vel, rot_dot) = jax.jvp(lambda x: body_poses(model, x), (q_,), (qd_,))
        omega = vee(rot_dot @ jnp.swapaxes(rot, -1, -2))
        return (pos, rot), (vel, omega)

    ((pos, rot), (vel, omega)), (_, (acc, alpha)) = jax.jvp(vel_fn, (q, qd), (qd, qdd))
    return pos, rot, vel, omega, acc, alpha


def skeleton_points(model: Model, origins: Float[Array, "J 3"], rots: Float[Array, "J 3 3"]):
    """Joint origins followed by End Site positions, for drawing: (J + E, 3)."""
    if model.end_site_offset.shape[0] == 0:
        return origins
    idx = jnp.array(model.end_site_joint)
    ends = origins[idx] + jnp.einsum("eij,ej->ei", rots[idx], model.end_site_offset)
    return jnp.concatenate([origins, ends], 0)


def skeleton_edges(model: Model) -> np.ndarray:
    """(E,2) point-index pairs of the bones drawn by :func:`skeleton_points`."""
    n = len(model.joint_names)
    edges = [(p, k) for k, p in enumerate(model.joint_parent) if p >= 0]
    edges += [(j, n + e) for e, j in enumerate(model.end_site_joint)]
    return np.array(edges, dtype=np.int64).reshape(-1, 2)
