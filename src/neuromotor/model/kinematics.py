"""Kinematics of the mocap: joint angles, cubic splines in time, forward kinematics.

Spline coordinates of the mocap, ``q = [root_pos (3), root_quat (4), quat_k (4) per joint]``:
the root joint's position, then the local rotation of the root and of every non-root joint as a
quaternion made sign-continuous over time. A cubic spline through the frames gives q, qdot and
qddot at any time (Section 5.1: "fitting a cubic spline to the position data, and then finding
the second derivative"); quaternions are normalized inside forward kinematics. Splining
rotations rather than Euler channels matters near gimbal lock: real clips (the knees of the
MocapBank clip) jump 100-150 degrees in two Euler channels between frames while the rotation
itself barely moves, and a spline through such jumps invents huge accelerations.

Body velocities and accelerations follow from forward kinematics by the exact chain rule (the
product rule through every joint composition, with ``jax.jvp`` for the normalized quaternions),
not by finite differences of body poses. Joint angles theta (every rotation channel of
every non-root joint, radians) are the BVH Euler decomposition of the splined rotations,
unwrapped across +-180 degrees by continuity with the file's own (unwrapped) channels.
"""

from __future__ import annotations

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float
from scipy.interpolate import CubicSpline

from neuromotor import compiler
from neuromotor.model.bvh import BvhClip, BvhError
from neuromotor.model.skeleton import Model
from neuromotor.rotations import euler_to_matrix, matrix_to_euler, matrix_to_quat, mm, mmt, mv, quat_to_matrix, vee


class Spline(eqx.Module):
    """Piecewise cubic on a uniform grid ``t0 + k dt`` (coefficients from scipy, evaluated in JAX)."""

    t0: Float[Array, ""]
    dt: Float[Array, ""]
    coeffs: Float[Array, "4 K D"]  # highest power first, per interval

    @classmethod
    def fit(cls, times: np.ndarray, values: np.ndarray, bc_type: str = "not-a-knot") -> Spline:
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
    rot = rotating_joints(model)
    cols = [list(clip.joints[k].rotation_columns) for k in rot]
    angles = np.asarray(clip.motion, dtype=np.float64)[:, np.array(cols, dtype=np.int64).reshape(-1, 3)]
    quat = np.array(_euler_to_quats(jnp.asarray(angles), tuple(clip.joints[k].rotation_order for k in rot)))
    # Sign continuity: q and -q are the same rotation; keep neighbours on one side.
    signs = np.cumprod(np.where(np.sum(quat[1:] * quat[:-1], -1) < 0, -1.0, 1.0), axis=0)
    quat[1:] *= signs[..., None]
    pos = np.asarray(clip.motion[:, list(root.translation_columns)], dtype=np.float64)
    return np.concatenate([pos, quat.reshape(quat.shape[0], -1)], axis=1)


@functools.partial(compiler.jit, static_argnames="orders")
def _euler_to_quats(angles_deg: Float[Array, "T R 3"], orders: tuple[str, ...]) -> Float[Array, "T R 4"]:
    """Quaternions of the BVH Euler channels (degrees) of R joints, one batched call per
    rotation order (one small program instead of dozens of eagerly compiled ops)."""
    ang = jnp.deg2rad(angles_deg)
    parts, idx = [], []
    for order in dict.fromkeys(orders):
        rows = np.array([r for r, o in enumerate(orders) if o == order])
        parts.append(matrix_to_quat(euler_to_matrix(ang[:, rows], order)))
        idx.append(rows)
    out = jnp.concatenate(parts, 1)
    return out if len(parts) == 1 else out[:, np.argsort(np.concatenate(idx))]


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


def still_trajectory(traj: Trajectory, time: float) -> Trajectory:
    """The capture held still at clip ``time`` (s): q(t) = q(time) and the angle reference at
    ``time`` for every t, qd = qdd = 0, so the inverse dynamics of it is the static pose's
    (gravity holding) and a driven body holds the pose. The one construction of ``[sim] still``."""

    def constant(spline: Spline) -> Spline:
        value = spline(jnp.asarray(time, spline.coeffs.dtype))
        coeffs = jnp.zeros((4, 1, value.shape[-1]), spline.coeffs.dtype).at[3, 0].set(value)
        return Spline(jnp.asarray(0.0, spline.t0.dtype), jnp.asarray(1.0, spline.dt.dtype), coeffs)

    return Trajectory(constant(traj.spline), constant(traj.angle_spline), traj.duration)


def trajectory_from_clip(model: Model, clip: BvhClip) -> Trajectory:
    q = mocap_coordinates(model, clip)
    times = np.arange(q.shape[0]) * clip.frame_time
    if q.shape[0] < 4:
        # A user's file (a single pose, a stub): a one-line error, not a traceback.
        raise BvhError(
            str(clip.path),
            None,
            f"{q.shape[0]} frame(s): the capture is a cubic spline through its frames, so it needs at least 4",
        )
    ref = Spline.fit(times, mocap_angles(model, clip))
    return Trajectory(Spline.fit(times, q), ref, jnp.asarray(times[-1]))


def local_rotations(model: Model, q: Float[Array, " Q"]) -> Float[Array, "J 3 3"]:
    """Local rotation matrix of every joint (identity where a joint has no rotation channels)."""
    return _local_jet(model, (q,))[0]


def _local_jet(model: Model, q_jet: tuple) -> list:
    """Local rotations of every joint and, for a jet ``(q, qd, qdd)``, their first two time
    derivatives (``jax.jvp`` of the batched quaternion-to-matrix map: elementwise, cheap)."""
    st = model.topology
    n_rot = len(st.rotating)
    quats = [x[3 : 3 + 4 * n_rot].reshape(-1, 4) for x in q_jet]

    def rot(u):
        return quat_to_matrix(u / jnp.linalg.norm(u, axis=-1, keepdims=True))

    if len(quats) == 1:
        out = [rot(quats[0])]
    else:

        def rate(u, du):
            return jax.jvp(rot, (u,), (du,))

        (r, r_dot), (_, r_ddot) = jax.jvp(rate, tuple(quats[:2]), tuple(quats[1:]))
        out = [r, r_dot, r_ddot]
    if st.all_rotate:
        return out
    pad = [jnp.eye(3, dtype=out[0].dtype)] + [jnp.zeros((3, 3), out[0].dtype)] * (len(out) - 1)
    return [jnp.concatenate([x, e[None]], 0)[st.local_row] for x, e in zip(out, pad)]


def _jet_mm(a: list, b: list) -> list:
    """Product of two matrix jets by the Leibniz rule: (AB)' = A'B + AB', (AB)'' = A''B + 2A'B' + AB''."""
    out = [mm(a[0], b[0])]
    if len(a) > 1:
        out.append(mm(a[1], b[0]) + mm(a[0], b[1]))
        out.append(mm(a[2], b[0]) + 2.0 * mm(a[1], b[1]) + mm(a[0], b[2]))
    return out


def _frames_jet(model: Model, q_jet: tuple) -> tuple[list, list]:
    """Joint origins and orientations (world) of a jet of coordinates: values only for
    ``(q,)``, values and first two time derivatives for ``(q, qd, qdd)``.

    Forward kinematics as one ``lax.scan`` over the non-root joints in BVH order (parents
    first): ``o = o_p + R_p d`` and ``R = R_p L``, differentiated by the product rule. The same
    operations as a joint-by-joint Python recursion, but one small loop body to compile
    instead of a traced op chain per joint."""
    n = len(model.joint_parent)
    local = jnp.stack(_local_jet(model, q_jet))  # (K, J, 3, 3)
    k_ord = local.shape[0]
    root = jnp.stack([x[0:3] for x in q_jet])  # (K, 3)
    parent = np.array(model.joint_parent)
    roots = np.flatnonzero(parent < 0)
    origins = jnp.zeros((k_ord, n, 3), local.dtype).at[:, roots].set(root[:, None])
    rots = jnp.zeros_like(local).at[:, roots].set(local[:, roots])
    rest = np.flatnonzero(parent >= 0)
    if not len(rest):
        return list(origins), list(rots)

    def step(carry, x):
        origins, rots = carry
        k, p, offset, loc = x
        rot_p = jax.lax.dynamic_index_in_dim(rots, p, 1, keepdims=False)  # (K, 3, 3)
        org_p = jax.lax.dynamic_index_in_dim(origins, p, 1, keepdims=False)
        org = org_p + mv(rot_p, offset)
        rot = jnp.stack(_jet_mm(list(rot_p), list(loc)))
        origins = jax.lax.dynamic_update_index_in_dim(origins, org, k, 1)
        rots = jax.lax.dynamic_update_index_in_dim(rots, rot, k, 1)
        return (origins, rots), None

    xs = (jnp.asarray(rest), jnp.asarray(parent[rest]), model.joint_offset[rest], jnp.moveaxis(local[:, rest], 1, 0))
    (origins, rots), _ = jax.lax.scan(step, (origins, rots), xs)
    return list(origins), list(rots)


def joint_angles_from_q(model: Model, q: Float[Array, " Q"], reference: Float[Array, " n_all"]):
    """Euler angles of every non-root rotation channel (n_all), nearest ``reference``."""
    st = model.topology
    if not st.euler:
        return jnp.zeros((0,), q.dtype)
    rots = local_rotations(model, q)
    out = jnp.zeros((st.n_all,), q.dtype)
    for order, joints, cols in st.euler:  # usually one rotation order per skeleton
        part = matrix_to_euler(rots[joints], order, reference[cols]).reshape(-1)
        # Columns are assigned in joint order, so a single group is already in place.
        out = part if cols.size == st.n_all else out.at[cols.reshape(-1)].set(part)
    return out


def joint_dof_columns(model: Model) -> list[tuple[int, ...]]:
    """For each joint, the columns of its rotation channels within the ``angles`` block."""
    return list(model.topology.dof_columns)


def joint_frames(model: Model, q: Float[Array, " Q"]) -> tuple[Float[Array, "J 3"], Float[Array, "J 3 3"]]:
    """World origin and orientation of every joint frame from spline coordinates q."""
    (origins,), (rots,) = _frames_jet(model, (q,))
    return origins, rots


def _body_jet(model: Model, q_jet: tuple) -> tuple[list, list]:
    """Body COM positions and orientations (and their time derivatives) of a coordinate jet."""
    origins, rots = _frames_jet(model, q_jet)
    idx = np.array(model.body_joint)
    rot = [r[idx] for r in rots]
    pos = [o[idx] + mv(r, model.com) for o, r in zip(origins, rot)]
    return pos, rot


def body_poses(model: Model, q: Float[Array, " Q"]) -> tuple[Float[Array, "B 3"], Float[Array, "B 3 3"]]:
    """COM positions and orientations of the bodies for coordinates q."""
    (pos,), (rot,) = _body_jet(model, (q,))
    return pos, rot


def grid_poses(model: Model, traj, times) -> tuple[Float[Array, "T B 3"], Float[Array, "T B 3 3"]]:
    """:func:`body_poses` of a :class:`Trajectory` at each of ``times`` (T,), vmapped."""
    return jax.vmap(lambda t: body_poses(model, traj.q(t)))(times)


grid_poses_jit = compiler.jit(grid_poses)  # one program (not a per-time loop) for host callers


def body_kinematics(model: Model, q, qd, qdd):
    """Body pose, velocity and acceleration (world frame) by the chain rule through forward
    kinematics (exact: the product rule on each composition, not finite differences).

    Returns ``(pos, rot, vel, omega, acc, alpha)``; omega = vee(Rdot R^T) and
    alpha = d omega / dt = vee(Rddot R^T + Rdot Rdot^T) = vee(Rddot R^T), both in the world
    frame (Rdot Rdot^T is symmetric, and its computed entries are too, so it drops exactly).
    """
    (pos, vel, acc), (rot, rot_dot, rot_ddot) = _body_jet(model, (q, qd, qdd))
    omega = vee(mmt(rot_dot, rot))
    alpha = vee(mmt(rot_ddot, rot))
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
