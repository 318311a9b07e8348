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

Stepping (``Balance.stepping``; off by default: it lifts and places the foot but does not yet
recover a push that falls without it, docs/balance.md). A state machine in the carry
(:class:`StepState`). From the delayed lean, the capture point ``x_cp = x_com + v / omega0``,
``omega0 = sqrt(g / H)`` (Hof, Gazendam & Sinke 2005, J. Biomech. 38:1); when idle and ``x_cp`` is
more than ``margin`` beyond the segment between the soles, the foot on its side of the midline
steps. The step moves the paper's reference, so that the legs' own stiff feedback makes it
(:func:`swing_reference`, applied to the controller's targets before the stiff forces): for
``weight_shift`` the pelvis moves over the stance foot (each leg's reference hip->ankle vector
turned about its foot, 2-link IK of hip and knee, ``crouch`` lower), the loop drops the lean
across the feet and its ankle torque goes to the loaded swing foot; then over ``swing_time`` the
swing ankle follows a smoothstep path, lifted by ``lift sin(pi s)``, to its lift-off position
plus the capture point's excess (brought forward by the loop's delay, ``exp(omega0 delay)``)
plus ``offset`` (at most ``max_step``), its hip and knee from the IK of the path, its ankle
keeping the sole's standing orientation; the swing leg drops its share of the standing
feedforward, the stance leg takes the whole weight on its sole. After landing both feet hold
where they are (IK to each anchor at the reference's leg length: the new stance is kept, the
capture's foot placement is not restored) and the weight and the loop come back over ``blend``.

Assist (off by default, ``assist = 0``): a spring-damper force on the pelvis toward its
captured position, ``F = M (k (x_ref - x) - 2 sqrt(k) v)`` (M the whole body's mass, k in
1/s^2). It is a function of the state alone; the run reports its impulse.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from neuromotor.model.skeleton import Model
from neuromotor.physics.reflex import History, delayed, history_steps, push
from neuromotor.physics.system import State
from neuromotor.rotations import matrix_to_quat, mtv, mv, quat_exp, quat_normalize, quat_to_matrix, vee

KP = 1.3  # m g H per rad: Peterka 2002, 1.2-1.5
KD = 0.35  # m g H s per rad: Peterka 2002, 0.3-0.4 s
HIP_KP = 0.5  # m g H per rad: the pelvis held upright (a hip strategy)
HIP_KD = 0.15  # m g H s per rad
DELAY = 0.15  # s: Peterka's lumped delay 100-200 ms; automatic postural responses 100-150 ms
MAX_DELAY = 0.3  # s: the history buffer covers delays up to this
# Stepping (module docstring, "Stepping"); our choices unless noted.
STEP_MARGIN = 0.06  # m: the capture point this far beyond the feet's support segment triggers a step
STEP_OFFSET = 0.05  # m: the foot lands this far beyond the capture point (the constant offset b of Hof 2008)
MAX_STEP = 0.45  # m: longest step (ankle displacement)
SWING_TIME = 0.25  # s: swing duration (human single-support of a reactive step ~0.3-0.4 s)
STEP_LIFT = 0.05  # m: peak foot clearance
WEIGHT_SHIFT = 0.15  # s: the anticipatory weight shift onto the stance foot before lift-off
SHIFT_FRACTION = 1.0  # of the half stance width: the pelvis's move over the stance foot
STEP_CROUCH = 0.03  # m: the stance leg lowers the pelvis this much while the other swings
REACH = 0.995  # the IK's longest hip-ankle distance, a fraction of the leg's length
STEP_BLEND = 0.3  # s: after landing, the weight moves back onto both feet over this


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
    # Stepping (None when off): array leaves, and the static legs.
    stepping: Stepping | None = None


class Stepping(eqx.Module):
    """The stepping parameters (array leaves), each foot's sole in its frame, the support
    shift of single stance and the legs' joints (module docstring, "Stepping")."""

    margin: Float[Array, ""]  # m
    offset: Float[Array, ""]  # m
    max_step: Float[Array, ""]  # m
    swing_time: Float[Array, ""]  # s
    lift: Float[Array, ""]  # m
    weight_shift: Float[Array, ""]  # s
    shift_fraction: Float[Array, ""]  # of the way from the soles' midpoint to the stance sole
    crouch: Float[Array, ""]  # m: the pelvis lowered in single stance
    blend: Float[Array, ""]  # s
    sole_local: Float[Array, "2 3"]  # each foot's point of support, foot frame, from its COM
    shift: Float[Array, "2 C 3"]  # support torques with foot f alone minus both feet (parent frame)
    knee_local: Float[Array, "2 3"]  # the knee from the hip, thigh frame
    ankle_local: Float[Array, "2 3"]  # the ankle from the knee, shank frame
    foot_rot: Float[Array, "2 3 3"]  # each foot's standing orientation (world)
    legs: tuple[tuple[int, int, int], ...] = eqx.field(static=True)  # per foot: hip, knee, ankle joints
    parents: tuple[int, ...] = eqx.field(static=True)  # per foot: the thigh's parent body


class StepState(eqx.Module):
    """The stepping state machine in the scan carry. ``t`` < 0: idle; 0 <= t < weight_shift: the
    weight moves onto the stance foot; then for swing_time the foot ``swing`` (0: first foot, 1:
    second) in the air; after: landed, blending back."""

    t: Float[Array, ""]  # s since the step started; -1 when idle
    swing: Float[Array, ""]  # 0 or 1
    start: Float[Array, " 3"]  # the swing ankle at lift-off (world)
    anchor: Float[Array, "2 3"]  # each foot's ankle target (world); the swing foot's: where it lands
    held: Float[Array, " 2"]  # 1: the foot's reference is the IK to its anchor (it stepped)
    count: Float[Array, ""]  # steps taken


class Posture(eqx.Module):
    """The balance loop's carry: the delayed signals' history and the stepping state."""

    history: History
    step: StepState | None = None


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


def support_torques(model: Model, state: State, feet: Sequence[int], soles=None, loads=None) -> Float[Array, "C 3"]:
    """The standing feedforward of every joint in its parent's frame (module docstring);
    ``loads``: ``(points, forces)`` on the feet instead of :func:`foot_forces`'s."""
    rot = quat_to_matrix(state.quat)
    points, forces = foot_forces(model, state, feet, soles) if loads is None else loads
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
    stepping: dict | None = None,
) -> Balance:
    """A :class:`Balance` for the pose ``state`` (the standing reference), ``feet`` (body
    indices: their joints are the ankles) and ``hips`` (joint indices, pelvis->thigh); ``soles``
    (F, 3): each foot's point of support in ``state`` (world; None: under the ankle);
    ``stepping``: the stepping parameters (:func:`make_stepping`'s keywords; None: no stepping)."""
    feet = tuple(int(b) for b in feet)
    if not feet:
        raise ValueError("balance needs at least one foot")
    up, rot = up_of(model), quat_to_matrix(state.quat)
    ankle = jnp.mean(joint_origins(model, state.pos, rot)[jnp.asarray(feet)], 0)
    rel = whole_com(model, state.pos) - ankle
    height = jnp.dot(rel, up)
    f = lambda x: jnp.asarray(x, jnp.float64)
    step = None if stepping is None else make_stepping(model, state, feet, soles, **stepping)
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
        step,
    )


def leg_joints(model: Model, foot: int) -> tuple[int, ...]:
    """The joints from the pelvis down to ``foot``'s parent (the hip, the knee...), not the ankle."""
    out, b = [], model.body_parent[foot]
    while b > 0:
        out.append(b - 1)
        b = model.body_parent[b]
    return tuple(reversed(out))


def make_stepping(
    model: Model,
    state: State,
    feet: Sequence[int],
    soles,
    margin=STEP_MARGIN,
    offset=STEP_OFFSET,
    max_step=MAX_STEP,
    swing_time=SWING_TIME,
    lift=STEP_LIFT,
    weight_shift=WEIGHT_SHIFT,
    shift_fraction=SHIFT_FRACTION,
    crouch=STEP_CROUCH,
    blend=STEP_BLEND,
) -> Stepping:
    """:class:`Stepping` for two ``feet`` standing in ``state`` on ``soles`` (2, 3; world); each
    leg must be a hip, a knee and an ankle (the 2-link IK)."""
    if len(feet) != 2:
        raise ValueError(f"stepping needs two feet, got {len(feet)}")
    chains = [leg_joints(model, b) + (b - 1,) for b in feet]
    if any(len(leg) != 3 for leg in chains):
        raise ValueError(f"stepping needs legs of hip, knee and ankle joints, got {chains}")
    legs = tuple((leg[0], leg[1], leg[2]) for leg in chains)
    rot = quat_to_matrix(state.quat)
    idx = jnp.asarray(feet)
    soles = joint_origins(model, state.pos, rot)[idx] if soles is None else jnp.asarray(soles)
    sole_local = jnp.einsum("fji,fj->fi", rot[idx], soles - state.pos[idx])
    both = support_torques(model, state, feet, soles)
    # Single stance on foot f: the weight on f's sole alone (the swing leg carries nothing; the
    # weight shift brings the COM over that sole).
    weight = jnp.sum(model.mass) * jnp.linalg.norm(model.gravity) * up_of(model)[None]
    shift = jnp.stack(
        [support_torques(model, state, (b,), loads=(soles[i : i + 1], weight)) - both for i, b in enumerate(feet)]
    )
    origin = joint_origins(model, state.pos, rot)
    thigh, shank = np.asarray([leg[0] + 1 for leg in legs]), np.asarray([leg[1] + 1 for leg in legs])
    knee_local = mtv(rot[thigh], origin[shank] - origin[thigh])
    ankle_local = mtv(rot[shank], origin[idx] - origin[shank])
    f = lambda x: jnp.asarray(x, jnp.float64)
    return Stepping(
        f(margin),
        f(offset),
        f(max_step),
        f(swing_time),
        f(lift),
        f(weight_shift),
        f(shift_fraction),
        f(crouch),
        f(blend),
        sole_local,
        shift,
        knee_local,
        ankle_local,
        rot[idx],
        legs,
        tuple(int(model.body_parent[b]) for b in thigh),
    )


def empty_posture(balance: Balance, dtype) -> Posture:
    """The loop's initial carry: an empty history, and with stepping an idle state machine."""
    zeros = jnp.zeros((balance.steps, 2, 3), dtype)
    history = History(zeros, zeros)
    if balance.stepping is None:
        return Posture(history)
    z = jnp.zeros((), dtype)
    step = StepState(z - 1.0, z, jnp.zeros(3, dtype), jnp.zeros((2, 3), dtype), jnp.zeros(2, dtype), z)
    return Posture(history, step)


def posture_signals(model: Model, balance: Balance, state: State, origin=None, support=None):
    """``(angle (2, 3), rate (2, 3))``: the lean and the pelvis tilt, and their rates (rad, rad/s);
    the lean measured from ``origin`` (None: the ankles' midpoint). ``support``: the ground's
    motion under the feet, ``(V, Omega or None, pivot or None)`` (None: a still ground); the lean
    rate is then the COM's velocity relative to the ground's at the lean's origin, the rate of
    the lean itself while the feet ride the platform."""
    up, rot = up_of(model), quat_to_matrix(state.quat)
    if origin is None:
        ankle = jnp.mean(joint_origins(model, state.pos, rot)[jnp.asarray(balance.feet)], 0)
    else:
        ankle = origin
    c, v = whole_com(model, state.pos, state.vel)
    lean = horizontal(c - ankle, up) / balance.height - balance.lean0
    if support is not None:
        vel, spin, pivot = support
        v = v - (vel if spin is None else vel + jnp.cross(spin, ankle - pivot))
    lean_rate = horizontal(v, up) / balance.height
    a = mv(rot[0], balance.pelvis_up)
    tilt = jnp.cross(up, a)  # rotation vector taking up to the pelvis's up axis (small angles)
    tilt_rate = horizontal(state.omega[0], up)
    return jnp.stack([lean, tilt]), jnp.stack([lean_rate, tilt_rate])


def balance_torques(model: Model, balance: Balance, state: State, posture: Posture, h: float, support=None):
    """``(joint torques (C, 3) world, on each joint's child, posture)``: the standing
    feedforward, the delayed postural loop and the stepping torques, this step's signals pushed
    into the history and the state machine advanced (``support``: see :func:`posture_signals`)."""
    step, sp = posture.step, balance.stepping
    origin = None
    if sp is not None:
        assert step is not None  # empty_posture gives stepping its state
        origin = lean_origin(model, balance, sp, state, step)
    angle, rate = posture_signals(model, balance, state, origin, support)
    history = push(posture.history, angle, rate)
    past, past_rate = delayed(history.angle, balance.delay, h), delayed(history.rate, balance.delay, h)
    up = up_of(model)
    extra, share = None, None
    # Torque on the bodies above the ankles (opposes gravity's m g H up x lean) and on the pelvis.
    if sp is None:
        body = -balance.mgh * jnp.cross(up, balance.kp * past[0] + balance.kd * past_rate[0])
    else:
        assert step is not None
        step, extra, share, frontal = stepping_torques(model, balance, sp, state, step, past, past_rate, h, origin)
        lean, lean_rate = past[0] - frontal @ past[0], past_rate[0] - frontal @ past_rate[0]
        body = -balance.mgh * jnp.cross(up, balance.kp * lean + balance.kd * lean_rate)
    pelvis = -balance.mgh * (balance.hip_kp * past[1] + balance.hip_kd * past_rate[1])
    rot = quat_to_matrix(state.quat)
    torque = mv(rot[np.asarray(model.topology.parent)], balance.support)
    if share is None:  # the ops in the order of the loop without stepping (the same program)
        share = jnp.full(len(balance.ankles), 1.0 / len(balance.ankles))
    if extra is not None:
        torque = torque + extra
    # A joint torque acts +T on the child, -T on the parent: the ankle's parent is the shank.
    torque = torque.at[jnp.asarray(balance.ankles)].add(-share[:, None] * body[None])
    if balance.hips:
        torque = torque.at[jnp.asarray(balance.hips)].add(-pelvis / len(balance.hips))
    return torque, Posture(history, step)


def smoothstep(s):
    """``(3 s^2 - 2 s^3, its derivative)`` on s clipped to [0, 1]."""
    s = jnp.clip(s, 0.0, 1.0)
    return s * s * (3.0 - 2.0 * s), 6.0 * s * (1.0 - s)


def sole_world(sp: Stepping, state: State, feet, rot) -> Float[Array, "2 3"]:
    """Each foot's point of support (``Stepping.sole_local``) in the world at ``state``."""
    return state.pos[feet] + jnp.einsum("fij,fj->fi", rot[feet], sp.sole_local)


def capture_excess(model: Model, balance: Balance, sp: Stepping, state: State, lean, rate, origin=None):
    """``(capture point (3,), its horizontal excess beyond the soles' segment (3,), soles (2, 3),
    ankles (2, 3))``, the capture point ``x_com + v_com / omega0`` from the delayed lean
    (measured from ``origin``; None: the ankles' midpoint)."""
    up, rot = up_of(model), quat_to_matrix(state.quat)
    feet = jnp.asarray(balance.feet)
    ankle = joint_origins(model, state.pos, rot)[feet]
    sole = sole_world(sp, state, feet, rot)
    omega0 = jnp.sqrt(jnp.linalg.norm(model.gravity) / balance.height)
    origin = jnp.mean(ankle, 0) if origin is None else origin
    cp = horizontal(origin, up) + balance.height * (lean + balance.lean0 + rate / omega0)
    a, b = horizontal(sole[0], up), horizontal(sole[1], up)
    d = b - a
    s = jnp.clip(jnp.dot(cp - a, d) / jnp.dot(d, d), 0.0, 1.0)
    return cp, cp - (a + s * d), sole, ankle


class Phase(eqx.Module):
    """Where a step is (module docstring, "Stepping"), from its clock: weights in [0, 1]."""

    active: Float[Array, ""]  # bool: a step is under way (weight shift, swing or blend)
    pick: Float[Array, " 2"]  # 1 on the swing foot
    shifting: Float[Array, ""]  # bool: the anticipatory weight shift, before lift-off
    lean: Float[Array, ""]  # the lean target's move onto the stance foot
    single: Float[Array, ""]  # the feedforward's and the ankle torque's move onto the stance foot
    swing: Float[Array, ""]  # the swing leg's reference: 0 the capture's, 1 the IK's
    back: Float[Array, ""]  # after landing: 0 landed, 1 blended back
    s: Float[Array, ""]  # the path's smoothstep
    ds: Float[Array, ""]  # its derivative in the swing's phase
    in_air: Float[Array, ""]  # bool


def phase_of(sp: Stepping, step: StepState) -> Phase:
    t = step.t
    active = t >= 0.0
    tsw = t - sp.weight_shift  # time since lift-off
    w_shift, _ = smoothstep(t / sp.weight_shift)
    ramp, _ = smoothstep(tsw / (0.2 * sp.swing_time))
    back, _ = smoothstep((tsw - sp.swing_time) / sp.blend)
    s, ds = smoothstep(tsw / sp.swing_time)
    on = lambda w: jnp.where(active, w, 0.0)
    return Phase(
        active,
        jnp.stack([1.0 - step.swing, step.swing]),
        active & (tsw < 0.0),
        on(w_shift * (1.0 - back)),
        on(ramp * (1.0 - back)),
        on(ramp),
        on(back),
        s,
        ds,
        active & (tsw >= 0.0) & (tsw < sp.swing_time),
    )


def lean_origin(model: Model, balance: Balance, sp: Stepping, state: State, step: StepState) -> Float[Array, " 3"]:
    """The point the lean is measured from while stepping: the ankles' midpoint with the swing
    ankle held at its lift-off point until landing and blended to its place after, so that the
    moving foot does not move the loop's target."""
    ph = phase_of(sp, step)
    ankle = joint_origins(model, state.pos, quat_to_matrix(state.quat))[jnp.asarray(balance.feet)]
    frozen = step.start[None] + ph.back * (ankle - step.start[None])
    use = (ph.pick > 0.5) & ph.active
    return jnp.mean(jnp.where(use[:, None], frozen, ankle), 0)


def pelvis_shift(model: Model, balance: Balance, sp: Stepping, state: State, step: StepState):
    """The weight shift's move of the pelvis (world, horizontal, m): from the soles' midpoint
    toward the stance sole across the feet's axis, ramped in over ``weight_shift`` and out
    after landing."""
    ph = phase_of(sp, step)
    up, rot = up_of(model), quat_to_matrix(state.quat)
    feet = jnp.asarray(balance.feet)
    sole = horizontal(sole_world(sp, state, feet, rot), up)
    d = sole[1] - sole[0]
    across = d / jnp.sqrt(jnp.dot(d, d))
    lateral = jnp.dot((1.0 - ph.pick) @ sole - 0.5 * (sole[0] + sole[1]), across) * across
    return ph.lean * sp.shift_fraction * lateral


def stepping_torques(
    model: Model, balance: Balance, sp: Stepping, state: State, step: StepState, past, rate, h, origin=None
):
    """One step of the stepping state machine (module docstring): ``(state machine after this
    step, joint torques (C, 3) world, the ankles' shares of the postural torque (2,), the lean
    target's shift (3,))``."""
    up, rot = up_of(model), quat_to_matrix(state.quat)
    cp, out, sole, ankle = capture_excess(model, balance, sp, state, past[0], rate[0], origin)
    dist = jnp.sqrt(jnp.dot(out, out) + 1e-12)
    go = (step.t < 0.0) & (dist > sp.margin)
    # The swing foot: the one on the capture point's side of the feet's midline (0: the first foot).
    d = horizontal(sole[1] - sole[0], up)
    mid = horizontal(0.5 * (sole[0] + sole[1]), up)
    side = jnp.dot(cp - mid, d)
    swing = jnp.where(go, jnp.where(side > 0.0, 1.0, 0.0), step.swing)
    t = jnp.where(go, 0.0, step.t)
    count = step.count + jnp.where(go, 1.0, 0.0)
    ph = phase_of(sp, StepState(t, swing, step.start, step.anchor, step.held, count))
    # Until lift-off the swing ankle's start and target follow the body: the capture point's
    # excess plus the offset beyond it (at most max_step); frozen from lift-off.
    start = jnp.where(ph.shifting, ph.pick @ ankle, step.start)
    # The delayed excess brought to the present: it grows as exp(omega0 t) about the support's edge.
    omega0 = jnp.sqrt(jnp.linalg.norm(model.gravity) / balance.height)
    move = out * (jnp.exp(omega0 * balance.delay) + sp.offset / dist)
    length = jnp.sqrt(jnp.dot(move, move) + 1e-12)
    move = move * jnp.minimum(1.0, sp.max_step / length)
    aim = jnp.where(ph.shifting & (dist > sp.margin), start + move, ph.pick @ step.anchor)
    anchor = jnp.where((ph.pick[:, None] > 0.5) & ph.shifting, aim[None], step.anchor)
    # The stance foot's anchor follows it until landing: from then both feet hold where they are.
    landed = ph.active & ~ph.shifting & ~ph.in_air
    anchor = jnp.where((ph.pick[:, None] < 0.5) & ph.active & ~landed, ankle, anchor)
    # The weight shift is the legs' (swing_reference): the loop drops its lean across the feet's
    # axis, so that it does not resist the shift.
    stance = 1.0 - ph.pick
    across = d / jnp.sqrt(jnp.dot(d, d))
    frontal = ph.lean * jnp.outer(across, across)
    # From lift-off the swing leg drops its standing feedforward and the stance leg carries it all.
    torque = ph.single * mv(rot[np.asarray(model.topology.parent)], jnp.einsum("f,fci->ci", stance, sp.shift))
    # The loop's ankle torque follows the load: onto the swing foot while the weight shift loads
    # it, then half of it on the stance foot alone.
    apa = 0.5 + ph.lean * (ph.pick - 0.5)
    share = (1.0 - ph.single) * apa + ph.single * stance * 0.5
    # The clock runs while stepping; idle again once landed and blended.
    end = sp.weight_shift + sp.swing_time + sp.blend
    t_next = jnp.where(ph.active, t + h, t)
    done = t_next > end
    t_next = jnp.where(done, -1.0, t_next)
    held = jnp.where(done, 1.0, step.held)
    return StepState(t_next, swing, start, anchor, held, count), torque, share, frontal


def rotation_between(a: Float[Array, " 3"], b: Float[Array, " 3"]) -> Float[Array, "3 3"]:
    """The shortest rotation taking the unit vector ``a`` to ``b`` (not opposite)."""
    q = jnp.concatenate([(1.0 + jnp.dot(a, b))[None], jnp.cross(a, b)])
    return quat_to_matrix(quat_normalize(q))


def leg_ik(knee_local, ankle_local, thigh0, shank0, d, reach=REACH):
    """2-link analytic IK: ``(thigh, shank)``, the thigh's rotation in its parent's frame and the
    shank's in the thigh's, that put the ankle at ``d`` from the hip (the parent's frame),
    changed from the reference's ``(thigh0, shank0)`` by a bend of the knee about its reference
    bending axis and the shortest turn of the hip. ``knee_local``: the knee from the hip in the
    thigh's frame; ``ankle_local``: the ankle from the knee in the shank's frame. Exact for
    ``|d|`` within ``[|l1 - l2|, reach (l1 + l2)]``; clipped to it beyond. Needs a bent
    reference knee (the bending axis)."""
    u0 = thigh0 @ knee_local
    w0 = thigh0 @ (shank0 @ ankle_local)
    l1, l2 = jnp.linalg.norm(knee_local), jnp.linalg.norm(ankle_local)
    n = jnp.cross(u0, w0)
    sin0 = jnp.linalg.norm(n)
    bend0 = jnp.arctan2(sin0, jnp.dot(u0, w0))
    dist = jnp.linalg.norm(d)
    span = jnp.clip(dist, jnp.abs(l1 - l2) * 1.001, reach * (l1 + l2))
    bend = jnp.pi - jnp.arccos((l1 * l1 + l2 * l2 - span * span) / (2.0 * l1 * l2))
    turn = quat_to_matrix(quat_exp(mtv(thigh0, n / sin0) * (bend - bend0)))  # thigh frame
    shank = turn @ shank0
    v = u0 + thigh0 @ (shank @ ankle_local)
    thigh = rotation_between(v / jnp.linalg.norm(v), d / dist) @ thigh0
    return thigh, shank


def swing_path(model: Model, sp: Stepping, step: StepState):
    """``(goal (3,), its velocity (3,))`` of the swing ankle (world): from lift-off a smoothstep
    from ``start`` to its anchor over ``swing_time``, lifted by ``lift sin(pi s)``."""
    up, ph = up_of(model), phase_of(sp, step)
    target = ph.pick @ step.anchor
    phase = jnp.pi * jnp.clip((step.t - sp.weight_shift) / sp.swing_time, 0.0, 1.0)
    bump = jnp.where(ph.in_air, jnp.sin(phase), 0.0)
    dbump = jnp.where(ph.in_air, jnp.pi * jnp.cos(phase) / sp.swing_time, 0.0)
    path = step.start + ph.s * (target - step.start) + sp.lift * bump * up
    path_vel = jnp.where(ph.in_air, ph.ds / sp.swing_time, 0.0) * (target - step.start) + sp.lift * dbump * up
    return path, path_vel


def leg_targets(sp: Stepping, f: int, r_p, thigh0, shank0, shape, g, fixed, x):
    """Leg ``f``'s targets for the hip->ankle vector ``x`` (its parent's frame): ``(thigh and
    shank rotations (2, 3, 3), the foot's in the shank's as a quaternion keeping the sole's
    standing orientation)``; ``x`` is scaled to ``shape``'s length by ``fixed`` and blended from
    ``shape`` by ``g`` (:func:`swing_reference`)."""
    x = x + fixed * (x * jnp.linalg.norm(shape) / jnp.linalg.norm(x) - x)
    thigh, shank = leg_ik(sp.knee_local[f], sp.ankle_local[f], thigh0, shank0, shape + g * (x - shape))
    level = (r_p @ thigh @ shank).T @ sp.foot_rot[f]
    return jnp.stack([thigh, shank]), matrix_to_quat(level)


def swing_reference(model: Model, balance: Balance, state: State, step: StepState, rel_rot, rel_quat, rel_omega):
    """The retargeted reference of the legs (module docstring, "Stepping"): ``(rel_rot (C, 3, 3),
    rel_quat (C, 4), rel_omega (C, 3))``, the joints' targets (per joint, parent frame) with each
    leg's hip and knee from the 2-link IK of a hip->ankle vector: the reference's, moved
    by the weight shift (the pelvis over the stance foot), or toward the ankle's goal (the swing
    path, or where it landed) with the sole kept as it stood. Idle legs that never stepped keep
    the reference."""
    sp = balance.stepping
    assert sp is not None  # called with stepping on
    rot = quat_to_matrix(state.quat)
    origin = joint_origins(model, state.pos, rot)
    ph = phase_of(sp, step)
    path, path_vel = swing_path(model, sp, step)
    swinging = (ph.pick > 0.5) & ph.active
    # 0: the reference's shape, 1: the goal (the swing foot from lift-off, the stance foot after landing)
    to_goal = jnp.where(ph.active, ph.pick * ph.swing + (1.0 - ph.pick) * jnp.maximum(step.held, ph.back), step.held)
    on = jnp.where(ph.active, 1.0, step.held)  # 0: the reference untouched
    shift = pelvis_shift(model, balance, sp, state, step)
    for f, (hip, knee, ankle) in enumerate(sp.legs):
        goal = jnp.where(swinging[f], path, step.anchor[f])
        r_p = rot[sp.parents[f]]
        thigh0, shank0 = rel_rot[hip], rel_rot[knee]
        # The reference's hip->ankle vector turned by the weight shift at the leg's length (less
        # the crouch, which lets the swing leg reach further): the legs pivot about the feet.
        ref = thigh0 @ (sp.knee_local[f] + shank0 @ sp.ankle_local[f])
        turned = ref - mtv(r_p, shift)
        shape = turned * (jnp.linalg.norm(ref) - ph.lean * sp.crouch) / jnp.linalg.norm(turned)
        g = to_goal[f]
        # A foot on the ground holds the leg at the reference's length, so that the leg carries
        # the body (an IK to the actual hip would follow it down); the swing foot lands on its path.
        fixed = jnp.where(swinging[f], ph.back, 1.0)
        pose = functools.partial(leg_targets, sp, f, r_p, thigh0, shank0, shape, g, fixed)
        goal_vel = jnp.where(swinging[f], mtv(r_p, path_vel), 0.0)
        (mats, q_level), (dmats, _) = jax.jvp(pose, (mtv(r_p, goal - origin[hip + 1]),), (goal_vel,))
        joints = np.asarray([hip, knee, ankle])
        q0 = rel_quat[joints]
        q_ik = jnp.concatenate([matrix_to_quat(mats), q_level[None]])
        q_ik = jnp.where(jnp.sum(q_ik * q0, -1, keepdims=True) < 0.0, -q_ik, q_ik)
        q = quat_normalize(q0 + on[f] * (q_ik - q0))
        omega = jnp.concatenate([vee(dmats @ jnp.swapaxes(mats, -1, -2)), jnp.zeros((1, 3), mats.dtype)])
        keep = on[f] <= 0.0  # the reference exactly, not a round trip through the IK
        rel_quat = rel_quat.at[joints].set(jnp.where(keep, q0, q))
        rel_rot = rel_rot.at[joints].set(jnp.where(keep, rel_rot[joints], quat_to_matrix(q)))
        rel_omega = rel_omega.at[joints].set(rel_omega[joints] + on[f] * g * (omega - rel_omega[joints]))
    return rel_rot, rel_quat, rel_omega


def assist_force(model: Model, balance: Balance, pos, vel, target, target_vel=None) -> Float[Array, "... 3"]:
    """The assist's force on the pelvis (N) at the pelvis's COM position ``pos`` and velocity
    ``vel`` toward ``target`` (its captured COM position, moved with a moving ground) and
    ``target_vel`` (that ground's velocity; None: a still one); leading axes broadcast (the step
    passes one sample, the run's record all of them)."""
    k = balance.assist
    mass = jnp.sum(model.mass)
    spring = k * (target - pos)
    damping = 2.0 * jnp.sqrt(jnp.maximum(k, 0.0))
    return mass * (spring - damping * (vel if target_vel is None else vel - target_vel))
