"""Balance in a run (issue 38): the ``[balance]`` table made into a
:class:`~neuromotor.physics.balance.Balance` (the feet and hips found by the anatomy's labels,
the standing feedforward of the initial pose), falls, COM sway, the COM's response to the
perturbation and the assist's impulse.

The physics is :mod:`neuromotor.physics.balance`.
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import jax.numpy as jnp
import numpy as np

from neuromotor.model.facing import character_axes, horizontal
from neuromotor.model.skeleton import Character
from neuromotor.physics.balance import Balance, assist_force, make_balance
from neuromotor.physics.contact import ContactRollout
from neuromotor.physics.control import joint_torque_magnitude
from neuromotor.physics.dynamics import Reference, assist_target
from neuromotor.physics.system import per_joint_to_dofs
from neuromotor.rotations import quat_to_matrix
from neuromotor.studies.ground import foot_bodies

THIGH = "thigh"
FALL_FRACTION = 0.6  # fell when the COM is below this fraction of its initial height above the ground


def hip_joints(character: Character) -> tuple[int, ...]:
    """The pelvis->thigh joints (joint c attaches body c + 1)."""
    model = character.model
    return tuple(
        b - 1 for b, seg in enumerate(character.body_segment) if seg == THIGH and b > 0 and model.body_parent[b] == 0
    )


SOLE_BAND = 0.01  # m: a foot's support is the centre of its vertices within this of its lowest


def sole_points(character: Character, state, feet) -> np.ndarray:
    """Each foot's point of support in ``state``: the centre of its polyhedron's vertices within
    ``SOLE_BAND`` of its lowest (world)."""
    model = character.model
    up = -np.asarray(model.gravity) / np.linalg.norm(np.asarray(model.gravity))
    out = []
    for b in feet:
        verts = np.asarray(getattr(character.shapes[b], "vertices", character.shapes[b])).reshape(-1, 3)
        rot = np.asarray(quat_to_matrix(state.quat[b]))
        world = np.asarray(state.pos[b]) + (verts - np.asarray(model.com[b])) @ rot.T
        height = world @ up
        out.append(world[height <= height.min() + SOLE_BAND].mean(0))
    return np.stack(out)


def balance_for(character: Character, state, h: float, **values) -> Balance:
    """The :class:`Balance` of ``character`` standing in ``state`` (``values``: kp, kd, hip_kp,
    hip_kd, delay, assist, max_delay, stepping); the feet carry the body at :func:`sole_points`."""
    feet = foot_bodies(character)
    soles = sole_points(character, state, feet)
    if len(feet) != 2:  # stepping needs a left and a right foot
        values = values | {"stepping": None}
    return make_balance(character.model, state, feet, hip_joints(character), h, soles=soles, **values)


def fold_support(model, ref: Reference, balance: Balance) -> tuple[Reference, Balance]:
    """The standing feedforward moved into the reference's feedforward: ``ref`` with
    ``tau + P_L support`` on every grid step and its activation |T_j| recomputed, ``balance``
    with a zero ``support``. The gains' per-DOF scaling stays the capture's (made from the
    driven root's activation), so by the signal dependence of Section 5.2 the legs' feedback
    stiffens with the load they now carry; without it the knees buckle slowly."""
    delta = jnp.einsum("tcij,cj->tci", ref.local_pinv, balance.support)
    tau = ref.tau + per_joint_to_dofs(model, jnp.moveaxis(delta, 0, -1)).T
    axes_rows = per_joint_to_dofs(model, jnp.moveaxis(jnp.swapaxes(ref.local_axes, -1, -2), 0, 2))
    activation = joint_torque_magnitude(model, jnp.moveaxis(axes_rows, 0, 1), tau)
    ref = dataclasses.replace(ref, tau=tau, activation=activation)
    return ref, dataclasses.replace(balance, support=jnp.zeros_like(balance.support))


def com_path(model, pos) -> np.ndarray:
    """The whole body's COM (T, 3) of body positions ``pos`` (T, B, 3)."""
    mass = np.asarray(model.mass)
    return np.einsum("b,tbi->ti", mass / mass.sum(), np.asarray(pos))


def ground_touch(setup, normal_impulse) -> np.ndarray:
    """(T, B): whether each body carries a ground impulse in each step (``normal_impulse``: the
    ground's slots, (T, G))."""
    lam = np.asarray(normal_impulse)
    slot_body = np.asarray(setup.ground.slot_body)
    bodies = np.arange(setup.model.n_bodies)
    return ((lam > 0)[:, :, None] & (slot_body[:, None] == bodies)[None]).any(1)


class StandingTrace(NamedTuple):
    """What the balance metrics read of a run on the ground (a sweep keeps only this per run)."""

    time: np.ndarray  # (T,) s
    com: np.ndarray  # (T, 3) whole-body COM relative to the ground's motion (world, m)
    touch: np.ndarray  # (T, B) bool: the body carries a ground impulse
    root_pos: np.ndarray  # (T, 3) the pelvis's COM (world)
    root_vel: np.ndarray  # (T, 3)
    diverged_step: int
    # The base motion's displacement and velocity (T, 3; None: none): the assist pulls toward
    # the captured path carried along by it (neuromotor.physics.dynamics.balance_stage).
    base_offset: np.ndarray | None = None
    base_velocity: np.ndarray | None = None


def standing_trace(setup, out: ContactRollout, platform=None) -> StandingTrace:
    """The :class:`StandingTrace` of a contact rollout; ``platform`` (T, 3): the ground's
    displacement (a base motion under a free root; None: a still ground)."""
    n, states = out.run.time.shape[0], out.run.states
    com = com_path(setup.model, states.pos) - (0.0 if platform is None else np.asarray(platform)[:n])
    touch = ground_touch(setup, np.asarray(out.contact.normal_impulse)[:, -setup.ground.n_slots :])
    pulses = setup.pulses
    return StandingTrace(
        np.asarray(out.run.time),
        com,
        touch,
        np.asarray(states.pos[:, 0]),
        np.asarray(states.vel[:, 0]),
        int(out.run.diverged_step),
        None if pulses.base_offset is None else np.asarray(pulses.base_offset)[:n],
        None if pulses.base_velocity is None else np.asarray(pulses.base_velocity)[:n],
    )


def _trace(setup, out: ContactRollout | StandingTrace) -> StandingTrace:
    return out if isinstance(out, StandingTrace) else standing_trace(setup, out)


def falls(setup, out: ContactRollout | StandingTrace) -> dict:
    """``fell``, ``fall_time_s`` (clip time, the clock of every time in the metrics; None: never)
    and ``fall_body`` (""): the first step where a body other than a foot carries a ground
    impulse, or the COM drops below ``FALL_FRACTION`` of its initial height above the ground."""
    trace = _trace(setup, out)
    model, ground = setup.model, setup.ground
    feet = foot_bodies(setup.character)
    other = trace.touch & ~np.isin(np.arange(model.n_bodies), feet)[None]
    time = trace.time
    up = -np.asarray(model.gravity) / np.linalg.norm(np.asarray(model.gravity))
    com = trace.com @ up - float(ground.height)
    low = com < FALL_FRACTION * com[0]
    hit = np.nonzero(other.any(-1))[0]
    k_touch = int(hit[0]) if hit.size else None
    k_low = int(np.nonzero(low)[0][0]) if low.any() else None
    if k_touch is None and k_low is None:
        return {"fell": False, "fall_time_s": None, "fall_body": ""}
    if k_touch is not None and (k_low is None or k_touch <= k_low):
        names = sorted(model.body_names[b] for b in np.nonzero(other[k_touch])[0])
        return {"fell": True, "fall_time_s": float(time[k_touch]), "fall_body": ",".join(names)}
    return {"fell": True, "fall_time_s": float(time[k_low]), "fall_body": "(COM low)"}


def facing_axes(setup) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Up (against gravity), the horizontal facing direction and its left (``up x forward``): the
    character's own facing where the run begins (the held pose of a still run), as the
    perturbations' direction keywords and RUN.npz's ``facing`` have it."""
    model, config = setup.model, setup.config
    up = -np.asarray(model.gravity) / np.linalg.norm(np.asarray(model.gravity))
    at = config.start if config.still is None else config.still
    fwd = horizontal(character_axes(setup.character, at)["forward"], up)
    return up, fwd / np.linalg.norm(fwd), np.cross(up, fwd / np.linalg.norm(fwd))


def sway(setup, out: ContactRollout | StandingTrace) -> dict:
    """The COM's horizontal sway about its mean: radial RMS and the ranges along the facing
    direction (AP) and across it (ML), mm; and the radial RMS over the run's second half
    (``sway_rms_late_mm``: after the first settling)."""
    trace = _trace(setup, out)
    _, fwd, side = facing_axes(setup)
    com = trace.com
    d = com - com.mean(0)
    ap, ml = d @ fwd, d @ side
    late = com[com.shape[0] // 2 :]
    late_ap, late_ml = (late - late.mean(0)) @ fwd, (late - late.mean(0)) @ side
    return {
        "sway_rms_mm": float(1000 * np.sqrt(np.mean(ap**2 + ml**2))),
        "sway_range_ap_mm": float(1000 * np.ptp(ap)),
        "sway_range_ml_mm": float(1000 * np.ptp(ml)),
        "sway_rms_late_mm": float(1000 * np.sqrt(np.mean(late_ap**2 + late_ml**2))),
    }


def com_response(setup, out: ContactRollout | StandingTrace, base_com) -> dict:
    """The perturbation's own effect on the COM: the horizontal distance between the run's COM
    (relative to a moving ground) and its unperturbed twin's ``base_com`` (T, 3), at its largest
    (mm), when (s, the run's clock) and at the end (mm). Both runs settle alike from a held pose
    that is not an exact equilibrium, so unlike the sway (about the run's own mean) this does not
    count the settling; before the onset both runs are the same."""
    trace = _trace(setup, out)
    up, _, _ = facing_axes(setup)
    d = trace.com - np.asarray(base_com)[: trace.com.shape[0]]
    dist = 1000 * np.linalg.norm(horizontal(d, up), axis=1)
    k = int(np.argmax(dist))
    return {
        "com_response_peak_mm": float(dist[k]),
        "com_response_time_s": float(trace.time[k]),
        "com_response_final_mm": float(dist[-1]),
    }


def assist_forces(setup, root_pos, root_vel, base_offset=None, base_velocity=None) -> np.ndarray | None:
    """The assist's force on the pelvis per sample (T, 3, N, world) from the pelvis's COM
    position and velocity (T, 3), by the step's own law and target
    (:func:`neuromotor.physics.balance.assist_force`, :func:`neuromotor.physics.dynamics.assist_target`):
    toward the captured path, carried along by a base motion (its displacement and velocity,
    (T, 3) each, or None); None when the assist is off."""
    bal = setup.gains.balance
    if bal is None or float(bal.assist) == 0.0:
        return None
    steps = jnp.arange(np.shape(root_pos)[0])
    target, target_vel = assist_target(setup.model, setup.ref, steps, base_offset, base_velocity)
    return np.asarray(assist_force(setup.model, bal, jnp.asarray(root_pos), jnp.asarray(root_vel), target, target_vel))


def assist_impulse(setup, out: ContactRollout | StandingTrace) -> dict:
    """The assist's impulse (N s, and % of body weight x duration); empty when it is off."""
    trace = _trace(setup, out)
    force = assist_forces(setup, trace.root_pos, trace.root_vel, trace.base_offset, trace.base_velocity)
    if force is None:
        return {}
    n, h = force.shape[0], setup.options.h
    impulse = float(np.sum(np.linalg.norm(force[:-1], axis=-1)) * h)
    weight = float(np.sum(setup.model.mass)) * float(np.linalg.norm(np.asarray(setup.model.gravity)))
    return {"assist_impulse_Ns": impulse, "assist_impulse_pct": 100 * impulse / (weight * h * (n - 1))}


def balance_metrics(setup, out: ContactRollout | StandingTrace, platform=None, base=None) -> dict:
    """Falls, sway, the COM's response against the unperturbed twin (``base``: its COM (T, 3);
    None: not measured) and (when on) the assist's impulse; ``diverged_s``: when the rollout blew
    up (clip time; None: it did not; the states after it are held, so the other figures cover
    the time before). The COM is taken relative to ``platform`` (the ground's displacement, (T, 3); None:
    still)."""
    trace = out if isinstance(out, StandingTrace) else standing_trace(setup, out, platform)
    bad = trace.diverged_step
    when = None if bad < 0 else float(trace.time[bad + 1])
    response = {} if base is None else com_response(setup, trace, base)
    return falls(setup, trace) | sway(setup, trace) | response | assist_impulse(setup, trace) | {"diverged_s": when}
