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

Stepping (``Balance.stepping``; off by default: it does not lift the foot against the legs'
stiff feedback yet, docs/balance.md). A state machine in the carry (:class:`StepState`). From
the delayed lean, the capture point ``x_cp = x_com + v / omega0``, ``omega0 = sqrt(g / H)``
(Hof, Gazendam & Sinke 2005, J. Biomech. 38:1); when idle and ``x_cp`` is more than ``margin``
beyond the segment between the soles, the foot on its side of the midline swings: its ankle
follows a smoothstep path, lifted by ``lift sin(pi s)``, over ``swing_time`` to its lift-off
position plus the capture point's excess plus ``offset`` (at most ``max_step``), pulled by a
virtual spring-damper made by the leg's joints (Jacobian transpose), and stays held there after
landing. During the swing the swing leg drops its share of the standing feedforward and the
stance ankle takes the loop's torque; both return over ``blend``.

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
# Stepping (module docstring, "Stepping"); our choices unless noted.
STEP_MARGIN = 0.06  # m: the capture point this far beyond the feet's support segment triggers a step
STEP_OFFSET = 0.05  # m: the foot lands this far beyond the capture point (the constant offset b of Hof 2008)
MAX_STEP = 0.45  # m: longest step (ankle displacement)
SWING_TIME = 0.35  # s: swing duration (human single-support of a reactive step ~0.3-0.4 s)
STEP_LIFT = 0.05  # m: peak foot clearance
FOOT_KP = 3000.0  # N/m: the swing ankle's virtual spring
FOOT_KD = 150.0  # N s/m
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
    foot_kp: Float[Array, ""]  # N/m
    foot_kd: Float[Array, ""]  # N s/m
    blend: Float[Array, ""]  # s
    sole_local: Float[Array, "2 3"]  # each foot's point of support, foot frame, from its COM
    shift: Float[Array, "2 C 3"]  # support torques with foot f alone minus both feet (parent frame)
    legs: tuple[tuple[int, ...], ...] = eqx.field(static=True)  # per foot: the joints pelvis->foot, ankle excluded


class StepState(eqx.Module):
    """The stepping state machine in the scan carry. ``t`` < 0: idle; 0 <= t < swing_time: the
    foot ``swing`` (0: first foot, 1: second) in the air; after: landed, blending back."""

    t: Float[Array, ""]  # s since lift-off; -1 when idle
    swing: Float[Array, ""]  # 0 or 1
    start: Float[Array, " 3"]  # the swing ankle at lift-off (world)
    anchor: Float[Array, "2 3"]  # each foot's ankle target (world)
    held: Float[Array, " 2"]  # 1: the foot's ankle is held at its anchor (it stepped)
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
    foot_kp=FOOT_KP,
    foot_kd=FOOT_KD,
    blend=STEP_BLEND,
) -> Stepping:
    """:class:`Stepping` for two ``feet`` standing in ``state`` on ``soles`` (2, 3; world)."""
    if len(feet) != 2:
        raise ValueError(f"stepping needs two feet, got {len(feet)}")
    rot = quat_to_matrix(state.quat)
    idx = jnp.asarray(feet)
    soles = joint_origins(model, state.pos, rot)[idx] if soles is None else jnp.asarray(soles)
    sole_local = jnp.einsum("fji,fj->fi", rot[idx], soles - state.pos[idx])
    both = support_torques(model, state, feet, soles)
    # Single stance on foot f: the other leg's joints (hip, knee, ankle) drop their share of the
    # standing feedforward, so that the swing leg can rise; the stance leg's stiffness carries the rest.
    legs = [leg_joints(model, b) + (b - 1,) for b in feet]
    mask = np.zeros((2, both.shape[0], 1))
    for i in range(2):
        mask[i, list(legs[1 - i])] = 1.0
    shift = -jnp.asarray(mask) * both[None]
    f = lambda x: jnp.asarray(x, jnp.float64)
    return Stepping(
        f(margin),
        f(offset),
        f(max_step),
        f(swing_time),
        f(lift),
        f(foot_kp),
        f(foot_kd),
        f(blend),
        sole_local,
        shift,
        tuple(leg_joints(model, b) for b in feet),
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


def balance_torques(model: Model, balance: Balance, state: State, posture: Posture, h: float):
    """``(joint torques (C, 3) world, on each joint's child, posture)``: the standing
    feedforward, the delayed postural loop and the stepping torques, this step's signals pushed
    into the history and the state machine advanced."""
    angle, rate = posture_signals(model, balance, state)
    history = push(posture.history, angle, rate)
    past, past_rate = delayed(history.angle, balance.delay, h), delayed(history.rate, balance.delay, h)
    up = up_of(model)
    # Torque on the bodies above the ankles (opposes gravity's m g H up x lean) and on the pelvis.
    body = -balance.mgh * jnp.cross(up, balance.kp * past[0] + balance.kd * past_rate[0])
    pelvis = -balance.mgh * (balance.hip_kp * past[1] + balance.hip_kd * past_rate[1])
    rot = quat_to_matrix(state.quat)
    torque = mv(rot[np.asarray(model.topology.parent)], balance.support)
    share = jnp.full(len(balance.ankles), 1.0 / len(balance.ankles))
    step = posture.step
    if balance.stepping is not None:
        assert step is not None  # empty_posture gives stepping its state
        step, extra, share = stepping_torques(model, balance, balance.stepping, state, step, past, past_rate, h)
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


def capture_excess(model: Model, balance: Balance, sp: Stepping, state: State, lean, rate):
    """``(capture point (3,), its horizontal excess beyond the soles' segment (3,), soles (2, 3),
    ankles (2, 3))``, the capture point ``x_com + v_com / omega0`` from the delayed lean."""
    up, rot = up_of(model), quat_to_matrix(state.quat)
    feet = jnp.asarray(balance.feet)
    ankle = joint_origins(model, state.pos, rot)[feet]
    sole = state.pos[feet] + jnp.einsum("fij,fj->fi", rot[feet], sp.sole_local)
    omega0 = jnp.sqrt(jnp.linalg.norm(model.gravity) / balance.height)
    cp = horizontal(jnp.mean(ankle, 0), up) + balance.height * (lean + balance.lean0 + rate / omega0)
    a, b = horizontal(sole[0], up), horizontal(sole[1], up)
    d = b - a
    s = jnp.clip(jnp.dot(cp - a, d) / jnp.dot(d, d), 0.0, 1.0)
    return cp, cp - (a + s * d), sole, ankle


def stepping_torques(model: Model, balance: Balance, sp: Stepping, state: State, step: StepState, past, rate, h):
    """One step of the stepping state machine (module docstring): ``(state machine after this
    step, joint torques (C, 3) world, the ankles' shares of the postural torque (2,))``."""
    up, rot = up_of(model), quat_to_matrix(state.quat)
    origin = joint_origins(model, state.pos, rot)
    cp, out, sole, ankle = capture_excess(model, balance, sp, state, past[0], rate[0])
    dist = jnp.sqrt(jnp.dot(out, out) + 1e-12)
    go = (step.t < 0.0) & (dist > sp.margin)
    # The swing foot: the one on the capture point's side of the feet's midline (0: the first foot).
    d = horizontal(sole[1] - sole[0], up)
    side = jnp.dot(cp - horizontal(0.5 * (sole[0] + sole[1]), up), d)
    swing = jnp.where(go, jnp.where(side > 0.0, 1.0, 0.0), step.swing)
    pick = jnp.stack([1.0 - swing, swing])  # 1 on the swing foot
    start_now = pick @ ankle
    move = out * (1.0 + sp.offset / dist)  # the capture point's excess, plus the offset beyond it
    length = jnp.sqrt(jnp.dot(move, move) + 1e-12)
    move = move * jnp.minimum(1.0, sp.max_step / length)
    start = jnp.where(go, start_now, step.start)
    anchor = jnp.where(go, step.anchor * (1.0 - pick[:, None]) + pick[:, None] * (start_now + move)[None], step.anchor)
    target = pick @ anchor
    t = jnp.where(go, 0.0, step.t)
    held = jnp.where(go, jnp.maximum(step.held, pick), step.held)
    count = step.count + jnp.where(go, 1.0, 0.0)
    # The swing ankle's path: smoothstep from start to target, lifted by lift sin(pi s).
    active = t >= 0.0
    in_air = active & (t < sp.swing_time)
    s, ds = smoothstep(t / sp.swing_time)
    phase = jnp.pi * jnp.clip(t / sp.swing_time, 0.0, 1.0)
    bump = jnp.where(in_air, jnp.sin(phase), 0.0)
    dbump = jnp.where(in_air, jnp.pi * jnp.cos(phase) / sp.swing_time, 0.0)
    goal = start + s * (target - start) + sp.lift * bump * up
    goal_vel = jnp.where(in_air, ds / sp.swing_time, 0.0) * (target - start) + sp.lift * dbump * up
    swinging = pick * jnp.where(in_air, 1.0, 0.0)
    # A stepped foot's ankle is held at its anchor; the swing foot's follows its path.
    goals = jnp.where(swinging[:, None] > 0, goal[None], anchor)
    feet = jnp.asarray(balance.feet)
    force = sp.foot_kp * (goals - ankle) + sp.foot_kd * (swinging[:, None] * goal_vel[None] - state.vel[feet])
    force = force * jnp.maximum(held, swinging)[:, None]
    # The virtual force at the ankle made by the leg's joints (Jacobian transpose): T_j = (p - o_j) x F.
    torque = jnp.zeros_like(origin[1:])
    for f, leg in enumerate(sp.legs):
        joints = jnp.asarray(leg)
        torque = torque.at[joints].add(jnp.cross(ankle[f][None] - origin[joints + 1], force[f][None]))
    # The weight moves onto the stance foot over the swing's first fifth, back after landing.
    w_in, _ = smoothstep(5.0 * t / sp.swing_time)
    w_out, _ = smoothstep((t - sp.swing_time) / sp.blend)
    w = jnp.where(active, w_in * (1.0 - w_out), 0.0)
    stance = 1.0 - pick
    torque = torque + w * mv(rot[np.asarray(model.topology.parent)], jnp.einsum("f,fci->ci", stance, sp.shift))
    share = (1.0 - w) * 0.5 + w * stance
    # The clock runs while stepping; idle again once landed and blended.
    t_next = jnp.where(active, t + h, t)
    t_next = jnp.where(t_next > sp.swing_time + sp.blend, -1.0, t_next)
    return StepState(t_next, swing, start, anchor, held, count), torque, share


def assist_force(model: Model, balance: Balance, state: State, target, target_vel=0.0) -> Float[Array, " 3"]:
    """The assist's force on the pelvis (N) toward ``target`` (its captured COM position, moved
    with a moving ground) and ``target_vel`` (that ground's velocity; 0 on a still one)."""
    k = balance.assist
    mass = jnp.sum(model.mass)
    return mass * (k * (target - state.pos[0]) - 2.0 * jnp.sqrt(jnp.maximum(k, 0.0)) * (state.vel[0] - target_vel))
