"""Balance of the neuromotor kind (issue 38): a delayed postural loop on the whole body's lean,
acting at the ankles and hips, the standing feedforward that lets the legs carry the trunk, and
an optional assist.

Standing feedforward. The capture's inverse dynamics is computed with the pelvis held (the
paper's driven root): it knows nothing of the feet carrying the body. For a free root we add
the static inverse dynamics of the held pose with the weight on the feet: the ground carries
``m g`` under the feet, split between them so that the whole-body moment about the COM is zero
(each foot's centre of pressure at the centre of its lowest polyhedron vertices, moved by one
common horizontal offset that puts the COM's projection on the line between them). Every joint
above a foot then gets the extra torque on its child ``-sum_f (p_f - o_j) x F_f`` (o_j the
joint, p_f and F_f the foot's centre of pressure and force). It is computed once on the
initial pose and held in each joint's parent frame (``Balance.support``), so it turns with
the limbs.

Postural loop. With ``c`` the whole-body COM, ``a`` the midpoint of the ankles, ``H`` the COM's
height over them, ``up`` the vertical and ``m g H`` the body's gravitational stiffness, the
lean vector is the horizontal part of ``(c - a) / H`` (rad, small angles; minus the reference
pose's), its rate the COM's horizontal velocity over H. The ankles (the shank->foot joints,
shared equally) produce, on the bodies above them,

    T_ankle = -m g H [ kp lean(t - d) + kd lean_rate(t - d) ]  x-ed with up  (i.e. -m g H up x (...))

and the hips (pelvis->thigh joints) on the pelvis ``-m g H [ hip_kp tilt(t - d) + hip_kd
tilt_rate(t - d) ]`` with ``tilt`` the rotation vector taking the pelvis's reference up axis to
its present one (horizontal part). This is Peterka's (2002, J. Neurophysiol. 88:1097)
independent-channel model of quiet standing: sway as a delayed PD of body lean, with stiffness
``K_P ~ 1.2-1.5 m g h`` per rad (just above the gravitational stiffness, the loop's threshold),
damping ``K_D ~ 0.3-0.4 m g h`` s and a lumped time delay of ~100-200 ms (Peterka fits about
170 ms); the ankle-stiffness account of quiet standing is Winter et al. 1998 (J. Neurophysiol.
80:1211), and the automatic postural responses start 100-150 ms after a support perturbation
(Horak & Nashner 1986, J. Neurophysiol. 55:1369). The delayed signals live in a history buffer
in the scan carry and are read with the reflex's linear interpolation
(:func:`neuromotor.physics.reflex.delayed`), so the rollout is differentiable in the delay as
well as in the gains. All parameters are array leaves (jit, vmap, grad).

Assist (off by default, ``assist = 0``): a spring-damper force on the pelvis toward its
captured position, ``F = M (k (x_ref - x) - 2 sqrt(k) v)`` (M the whole body's mass, k in
1/s^2). It is a function of the state alone; the run reports its impulse.
"""

from __future__ import annotations

from collections.abc import Sequence

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from neuromotor.model.skeleton import Model
from neuromotor.physics.reflex import History, delayed, history_steps, push
from neuromotor.physics.system import State
from neuromotor.rotations import mtv, mv, quat_to_matrix

KP = 1.3  # m g H per rad: Peterka 2002, 1.2-1.5
KD = 0.35  # m g H s per rad: Peterka 2002, 0.3-0.4 s
HIP_KP = 0.5  # m g H per rad: the pelvis held upright (a hip strategy)
HIP_KD = 0.15  # m g H s per rad
DELAY = 0.15  # s: Peterka's lumped delay 100-200 ms; automatic postural responses 100-150 ms
MAX_DELAY = 0.3  # s: the history buffer covers delays up to this


class Balance(eqx.Module):
    """The postural loop's gains (array leaves), the standing feedforward, the reference lean
    and the static joint indices."""

    kp: Float[Array, ""]  # ankle stiffness, m g H per rad
    kd: Float[Array, ""]  # ankle damping, m g H s per rad
    hip_kp: Float[Array, ""]
    hip_kd: Float[Array, ""]
    delay: Float[Array, ""]  # s
    assist: Float[Array, ""]  # 1/s^2; 0: off
    support: Float[Array, "C 3"]  # standing feedforward per joint, parent frame (N m)
    lean0: Float[Array, " 3"]  # the reference pose's lean (rad, world horizontal)
    pelvis_up: Float[Array, " 3"]  # the vertical in the pelvis's frame, reference pose
    mgh: Float[Array, ""]  # N m per rad
    height: Float[Array, ""]  # H (m)
    ankles: tuple[int, ...] = eqx.field(static=True)  # joint indices (joint c attaches body c + 1)
    hips: tuple[int, ...] = eqx.field(static=True)
    feet: tuple[int, ...] = eqx.field(static=True)  # body indices
    steps: int = eqx.field(static=True)  # history length


def up_of(model: Model) -> Float[Array, " 3"]:
    return -model.gravity / jnp.linalg.norm(model.gravity)


def joint_origins(model: Model, pos, rot) -> Float[Array, "B 3"]:
    return pos - jnp.einsum("bij,bj->bi", rot, model.com)


def whole_com(model: Model, pos, vel=None):
    """The whole body's COM (and its velocity)."""
    w = model.mass / jnp.sum(model.mass)
    c = jnp.einsum("b,bi->i", w, pos)
    return c if vel is None else (c, jnp.einsum("b,bi->i", w, vel))


def horizontal(x, up):
    return x - (x @ up)[..., None] * up


def _subtree_mask(model: Model) -> np.ndarray:
    """in_sub[b, c] = 1 when body c is in body b's subtree."""
    n = model.n_bodies
    sub = np.eye(n)
    for b in reversed(range(1, n)):
        sub[model.body_parent[b]] += sub[b]
    return np.minimum(sub, 1.0)


def foot_forces(model: Model, state: State, feet: Sequence[int], soles=None):
    """Each foot's centre of pressure and vertical force carrying the body statically (see the
    module docstring): ``(points (F, 3), forces (F, 3))``. ``soles`` (F, 3): each foot's point
    of support (world; None: under its ankle)."""
    up, rot = up_of(model), quat_to_matrix(state.quat)
    c = horizontal(whole_com(model, state.pos), up)
    if soles is None:
        soles = joint_origins(model, state.pos, rot)[jnp.asarray(feet)]
    ankle = horizontal(jnp.asarray(soles), up)
    weight = jnp.sum(model.mass) * jnp.linalg.norm(model.gravity)
    if len(feet) == 1:
        share = jnp.ones(1)
        shift = c - ankle[0]
    else:
        a, b = ankle[0], ankle[-1]
        d = b - a
        s = jnp.clip(jnp.dot(c - a, d) / jnp.dot(d, d), 0.0, 1.0)
        share = jnp.zeros(len(feet)).at[0].set(1.0 - s).at[-1].set(s)
        shift = c - (a + s * d)
    return ankle + shift, share[:, None] * weight * up


def support_torques(model: Model, state: State, feet: Sequence[int], soles=None) -> Float[Array, "C 3"]:
    """The standing feedforward of every joint in its parent's frame (module docstring)."""
    rot = quat_to_matrix(state.quat)
    points, forces = foot_forces(model, state, feet, soles)
    origin = joint_origins(model, state.pos, rot)
    child, parent = np.asarray(model.topology.child), np.asarray(model.topology.parent)
    holds = jnp.asarray(_subtree_mask(model)[child][:, np.asarray(feet)])  # (C, F): foot below joint
    lever = points[None, :, :] - origin[child][:, None, :]
    world = -jnp.einsum("cf,cfi->ci", holds, jnp.cross(lever, forces[None]))
    return mtv(rot[parent], world)


def make_balance(
    model: Model,
    state: State,
    feet: Sequence[int],
    hips: Sequence[int],
    h: float,
    kp=KP,
    kd=KD,
    hip_kp=HIP_KP,
    hip_kd=HIP_KD,
    delay=DELAY,
    assist=0.0,
    max_delay: float = MAX_DELAY,
    soles=None,
) -> Balance:
    """A :class:`Balance` for the pose ``state`` (the standing reference), ``feet`` (body
    indices: their joints are the ankles) and ``hips`` (joint indices, pelvis->thigh); ``soles``
    (F, 3): each foot's point of support in ``state`` (world; None: under the ankle)."""
    feet = tuple(int(b) for b in feet)
    if not feet:
        raise ValueError("balance needs at least one foot")
    up, rot = up_of(model), quat_to_matrix(state.quat)
    ankle = jnp.mean(joint_origins(model, state.pos, rot)[jnp.asarray(feet)], 0)
    rel = whole_com(model, state.pos) - ankle
    height = jnp.dot(rel, up)
    f = lambda x: jnp.asarray(x, jnp.float64)
    return Balance(
        f(kp),
        f(kd),
        f(hip_kp),
        f(hip_kd),
        f(delay),
        f(assist),
        support_torques(model, state, feet, soles),
        horizontal(rel, up) / height,
        mtv(rot[0], up),
        jnp.sum(model.mass) * jnp.linalg.norm(model.gravity) * height,
        height,
        tuple(b - 1 for b in feet),
        tuple(int(j) for j in hips),
        feet,
        history_steps(h, max_delay),
    )


def empty_posture(balance: Balance, dtype) -> History:
    zeros = jnp.zeros((balance.steps, 2, 3), dtype)
    return History(zeros, zeros)


def posture_signals(model: Model, balance: Balance, state: State):
    """``(angle (2, 3), rate (2, 3))``: the lean and the pelvis tilt, and their rates (rad, rad/s)."""
    up, rot = up_of(model), quat_to_matrix(state.quat)
    ankle = jnp.mean(joint_origins(model, state.pos, rot)[jnp.asarray(balance.feet)], 0)
    c, v = whole_com(model, state.pos, state.vel)
    lean = horizontal(c - ankle, up) / balance.height - balance.lean0
    lean_rate = horizontal(v, up) / balance.height
    a = mv(rot[0], balance.pelvis_up)
    tilt = jnp.cross(up, a)  # rotation vector taking up to the pelvis's up axis (small angles)
    tilt_rate = horizontal(state.omega[0], up)
    return jnp.stack([lean, tilt]), jnp.stack([lean_rate, tilt_rate])


def balance_torques(model: Model, balance: Balance, state: State, history: History, h: float):
    """``(joint torques (C, 3) world, on each joint's child, history)``: the standing
    feedforward plus the delayed postural loop, this step's signals pushed into ``history``."""
    angle, rate = posture_signals(model, balance, state)
    history = push(history, angle, rate)
    past, past_rate = delayed(history.angle, balance.delay, h), delayed(history.rate, balance.delay, h)
    up = up_of(model)
    # Torque on the bodies above the ankles (opposes gravity's m g H up x lean) and on the pelvis.
    body = -balance.mgh * jnp.cross(up, balance.kp * past[0] + balance.kd * past_rate[0])
    pelvis = -balance.mgh * (balance.hip_kp * past[1] + balance.hip_kd * past_rate[1])
    rot = quat_to_matrix(state.quat)
    torque = mv(rot[np.asarray(model.topology.parent)], balance.support)
    # A joint torque acts +T on the child, -T on the parent: the ankle's parent is the shank.
    torque = torque.at[jnp.asarray(balance.ankles)].add(-body / len(balance.ankles))
    if balance.hips:
        torque = torque.at[jnp.asarray(balance.hips)].add(-pelvis / len(balance.hips))
    return torque, history


def assist_force(model: Model, balance: Balance, state: State, target) -> Float[Array, " 3"]:
    """The assist's force on the pelvis (N) toward ``target`` (its captured COM position)."""
    k = balance.assist
    mass = jnp.sum(model.mass)
    return mass * (k * (target - state.pos[0]) - 2.0 * jnp.sqrt(jnp.maximum(k, 0.0)) * state.vel[0])
