"""Issue 38: the stepping of neuromotor.physics.balance (off by default; see docs/balance.md,
"Stepping"). The machinery on the standing pose: the [balance] keys, idle in the quiet pose, the
trigger and the step's target, the 2-link IK and the retargeted reference, vmap over parameters
and gradients with respect to the stepping parameters; and one rollout: a backward push lifts
the swing foot and puts it down behind."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from neuromotor.config import ConfigError, simulation_config
from neuromotor.physics.balance import (
    balance_torques,
    empty_posture,
    joint_origins,
    leg_ik,
    swing_path,
    swing_reference,
)
from neuromotor.rotations import quat_to_matrix
from neuromotor.studies.standing import standing_setup


@pytest.fixture(scope="module")
def setups():
    on = standing_setup(0.05, balance={"stepping": True})
    off = standing_setup(0.05, balance={"stepping": False})
    return on, off


def machine(setup, bal, n, state=None):
    """``n`` calls of the balance loop on a fixed state: (torques of the last call, posture)."""
    state = setup.ref.init if state is None else state
    posture = empty_posture(bal, jnp.float64)
    for _ in range(n):
        torque, posture = balance_torques(setup.model, bal, state, posture, setup.options.h)
    return torque, posture


def test_stepping_config():
    assert simulation_config({"sim": {"root": "free"}}, "x").balance.stepping is False  # off by default
    spec = simulation_config({"balance": {"stepping": True, "swing_time": 0.3, "max_step": 0.4}}, "x").balance
    assert spec.stepping and spec.swing_time == 0.3 and spec.values()["stepping"]["max_step"] == 0.4
    assert spec.values()["stepping"]["margin"] == spec.step_margin
    assert simulation_config({}, "x").balance.values()["stepping"] is None
    bad = [
        ({"balance": {"stepping": "yes"}}, "balance.stepping"),
        ({"balance": {"swing_time": 0.0}}, "balance.swing_time"),
        ({"balance": {"step_margin": -0.1}}, "balance.step_margin"),
        ({"balance": {"weight_shift": "slow"}}, "balance.weight_shift"),
        ({"balance": {"step_crouch": -0.01}}, "balance.step_crouch"),
    ]
    for data, field in bad:
        with pytest.raises(ConfigError, match=f"field '{field}'"):
            simulation_config(data, "x.toml")


def test_idle_in_the_quiet_pose(setups):
    """The standing pose's capture point is within the margin: the machine stays idle and the
    torques are those of the loop without stepping."""
    on, off = setups
    t_on, p_on = machine(on, on.gains.balance, 30)
    t_off, _ = machine(off, off.gains.balance, 30)
    assert float(p_on.step.t) == -1.0 and float(p_on.step.count) == 0.0
    np.testing.assert_allclose(t_on, t_off, atol=1e-12)
    rel_rot, rel_quat, rel_omega = reference(on, on.gains.balance, p_on)  # the reference untouched
    ref, c = on.sim_model.ref, np.asarray(on.model.topology.child)
    np.testing.assert_array_equal(rel_rot, ref.rel_rot[0][c])
    np.testing.assert_array_equal(rel_quat, ref.rel_quat[0])
    np.testing.assert_array_equal(rel_omega, ref.rel_omega[0][c])


def eager(setup, margin=0.0):
    bal = setup.gains.balance
    return dataclasses.replace(bal, stepping=dataclasses.replace(bal.stepping, margin=jnp.asarray(margin)))


def reference(setup, bal, posture, state=None):
    """The legs' retargeted reference (per joint) after the machine's calls."""
    state = setup.ref.init if state is None else state
    ref, c = setup.sim_model.ref, np.asarray(setup.model.topology.child)
    return swing_reference(
        setup.model, bal, state, posture.step, ref.rel_rot[0][c], ref.rel_quat[0], ref.rel_omega[0][c]
    )


def test_trigger_and_target(setups):
    """With a zero margin the machine steps at once: the weight shift first (the clock below
    weight_shift, the stance leg's reference moved, the swing foot's anchor at most max_step
    away), and nothing is held until the step ends."""
    on, _ = setups
    bal = eager(on)
    _, p = machine(on, bal, 5)
    step, sp = p.step, bal.stepping
    assert float(step.count) == 1.0 and 0.0 < float(step.t) < float(sp.weight_shift)
    f = int(step.swing)
    moved = float(jnp.linalg.norm(step.anchor[f] - step.start))
    assert 0.0 < moved <= float(sp.max_step) + 1e-12
    assert float(jnp.max(step.held)) == 0.0
    rel_rot, _, _ = reference(on, bal, p)
    c = np.asarray(on.model.topology.child)
    base = on.sim_model.ref.rel_rot[0][c]
    hip = sp.legs[1 - f][0]
    assert float(jnp.abs(rel_rot[hip] - base[hip]).max()) > 1e-3  # the stance hip moves the pelvis over
    others = np.setdiff1d(np.arange(len(c)), np.asarray(sp.legs).ravel())
    np.testing.assert_array_equal(rel_rot[others], base[others])


def test_leg_ik_is_exact(setups):
    """Forward kinematics of the IK's thigh and shank puts the ankle on reachable targets to
    1e-9, both legs, targets around the standing ankle; beyond reach the leg points at it."""
    on, _ = setups
    sp, model, state = on.gains.balance.stepping, on.model, on.ref.init
    rot = quat_to_matrix(state.quat)
    origin = joint_origins(model, state.pos, rot)
    c = np.asarray(model.topology.child)
    rel = on.sim_model.ref.rel_rot[0][c]
    rng = np.random.default_rng(3)
    for f, (hip, knee, _) in enumerate(sp.legs):
        r_p, o_h = rot[sp.parents[f]], origin[hip + 1]
        ankle = origin[hip + 3]
        kl, al = sp.knee_local[f], sp.ankle_local[f]
        for dx in rng.uniform(-0.25, 0.25, (6, 3)) * np.array([1.0, 0.0, 1.0]) + np.array([0.0, 0.12, 0.0]):
            target = ankle + jnp.asarray(dx)
            thigh, shank = leg_ik(kl, al, rel[hip], rel[knee], r_p.T @ (target - o_h))
            reached = o_h + r_p @ thigh @ (kl + shank @ al)
            np.testing.assert_allclose(reached, target, atol=1e-9)
        far = o_h + jnp.asarray([0.4, -0.9, 0.3])
        thigh, shank = leg_ik(kl, al, rel[hip], rel[knee], r_p.T @ (far - o_h))
        reached = o_h + r_p @ thigh @ (kl + shank @ al)
        u, v = reached - o_h, far - o_h
        assert float(jnp.linalg.norm(jnp.cross(u, v))) < 1e-9 * float(jnp.linalg.norm(v))
        assert float(jnp.linalg.norm(u)) < float(jnp.linalg.norm(kl) + jnp.linalg.norm(al))


def test_swing_reference_follows_the_path(setups):
    """In mid-swing the swing leg's retargeted hip and knee put its ankle on the path's goal (from
    the actual hip) to 1e-9, lifted above its lift-off point, and the ankle's target keeps the
    sole's standing orientation."""
    on, _ = setups
    bal = eager(on)
    sp, model, state = bal.stepping, on.model, on.ref.init
    h = on.options.h
    n = int(round(float(sp.weight_shift + 0.5 * sp.swing_time) / h))
    _, p = machine(on, bal, n)
    f = int(p.step.swing)
    rel_rot, rel_quat, _ = reference(on, bal, p)
    np.testing.assert_allclose(quat_to_matrix(rel_quat), rel_rot, atol=1e-12)
    goal, _ = swing_path(model, sp, p.step)
    rot = quat_to_matrix(state.quat)
    origin = joint_origins(model, state.pos, rot)
    hip, knee, ankle = sp.legs[f]
    r_thigh = rot[sp.parents[f]] @ rel_rot[hip]
    reached = origin[hip + 1] + r_thigh @ (sp.knee_local[f] + rel_rot[knee] @ sp.ankle_local[f])
    np.testing.assert_allclose(reached, goal, atol=1e-9)
    up = -model.gravity / jnp.linalg.norm(model.gravity)
    assert float((goal - p.step.start) @ up) > 0.5 * float(sp.lift)
    foot = r_thigh @ rel_rot[knee] @ rel_rot[ankle]
    np.testing.assert_allclose(foot, sp.foot_rot[f], atol=1e-12)


def test_vmap_over_stepping_parameters(setups):
    """A batch of two parameter sets equals the two single runs."""
    on, _ = setups
    bal = on.gains.balance
    margins, lifts = jnp.asarray([0.0, 0.5]), jnp.asarray([0.05, 0.08])

    def run(margin, lift):
        b = dataclasses.replace(bal, stepping=dataclasses.replace(bal.stepping, margin=margin, lift=lift))
        torque, posture = machine(on, b, 8)
        return torque, posture.step.t

    batch = jax.vmap(run)(margins, lifts)
    for i in range(2):
        single = run(margins[i], lifts[i])
        np.testing.assert_allclose(batch[0][i], single[0], rtol=1e-12, atol=1e-12)
        assert float(batch[1][i]) == float(single[1])
    assert float(batch[1][0]) >= 0.0 and float(batch[1][1]) == -1.0  # the first steps, the second does not


def test_gradient_of_stepping_parameters(setups):
    """The loop's torques and the retargeted reference early in the swing are differentiable in
    the swing time, the lift, the offset, the weight shift's time and fraction and the crouch
    (the trigger's decision is discrete and has no gradient): jacfwd against central
    differences."""
    on, _ = setups
    bal = on.gains.balance
    names = ("swing_time", "lift", "offset", "weight_shift", "shift_fraction", "crouch")
    x0 = jnp.asarray([float(getattr(bal.stepping, k)) for k in names])
    n = int(round((float(x0[3]) + 0.3 * float(x0[0])) / on.options.h))
    weights = jnp.asarray(np.random.default_rng(0).normal(size=(len(on.model.topology.child), 4)))

    @jax.jit
    def f(x):
        sp = dataclasses.replace(bal.stepping, margin=jnp.asarray(0.0), **dict(zip(names, x, strict=True)))
        b = dataclasses.replace(bal, stepping=sp)
        torque, posture = machine(on, b, n)
        _, rel_quat, rel_omega = reference(on, b, posture)
        return jnp.sum(torque**2) * 1e-4 + jnp.sum(weights * rel_quat) + 1e-2 * jnp.sum(rel_omega)

    grad = jax.jacfwd(f)(x0)
    for i in range(len(names)):
        eps = 1e-6
        e = jnp.zeros(len(names)).at[i].set(eps)
        fd = (f(x0 + e) - f(x0 - e)) / (2 * eps)
        np.testing.assert_allclose(grad[i], fd, rtol=1e-5, err_msg=names[i])
        assert float(jnp.abs(grad[i])) > 1e-6, names[i]


def test_backward_push_lifts_and_places_the_swing_foot():
    """A 15 N s backward pelvis push (a fall without stepping, docs/balance.md): the step
    starts, the swing ankle rises by more than 1.5 cm (the virtual spring of the earlier
    attempt got 1.5 cm at most), moves back by more than 10 cm and is put down (back within 1 cm
    of its standing height) within 12 cm of its target (it lands short: the leg's length)."""
    from neuromotor.physics.contact import simulate_contact
    from neuromotor.physics.dynamics import Params
    from neuromotor.studies.ground import ground_scene

    pert = {"kind": "force", "body": "pelvis", "direction": [1.0, 0.0, 0.0], "magnitude": 15.0 * np.pi / 0.2}
    pert |= {"start": 0.5, "duration": 0.1, "shape": "half_sine"}
    setup = standing_setup(1.3, balance={"stepping": True}, top={"perturbation": [pert]})
    character = setup.character
    fwd = np.asarray(character.anatomy.forward, float)
    pulses = dataclasses.replace(setup.pulses, direction=jnp.asarray(-fwd)[None])
    out = simulate_contact(setup.sim_model, Params(setup.params.gains, pulses), ground_scene(setup.ground))
    assert int(out.run.diverged_step) < 0
    states, model, bal = out.run.states, setup.model, setup.gains.balance

    def replay(posture, state):  # the state machine, from the recorded states
        _, posture = balance_torques(model, bal, state, posture, setup.options.h)
        return posture, (posture.step.count, posture.step.swing, posture.step.anchor)

    first = jax.tree_util.tree_map(lambda x: x[:-1], states)
    _, (count, swing, anchor) = jax.lax.scan(replay, empty_posture(bal, jnp.float64), first)
    stepped = np.nonzero(np.asarray(count) > 0)[0]
    assert stepped.size and float(count[-1]) == 1.0
    f = int(swing[stepped[0]])
    rot = jax.vmap(quat_to_matrix)(states.quat)
    ankle = np.asarray(jax.vmap(lambda p, r: joint_origins(model, p, r))(states.pos, rot))[:, bal.feet[f]]
    up = -np.asarray(model.gravity) / np.linalg.norm(np.asarray(model.gravity))
    height = (ankle - ankle[stepped[0]]) @ up
    peak = int(np.argmax(height))
    assert height[peak] > 0.015
    down = peak + int(np.nonzero(height[peak:] < 0.01)[0][0])
    flat = lambda x: x - np.outer(x @ up, up)
    assert float(-(ankle[down] - ankle[0]) @ fwd) > 0.10
    target = np.asarray(anchor[-1, f])
    assert float(np.linalg.norm(flat((ankle[down] - target)[None]))) < 0.12
