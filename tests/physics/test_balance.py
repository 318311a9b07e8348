"""Issue 38: balance. The standing feedforward carries the body on the feet (statics), the
postural loop's torques oppose the lean, the [balance] table, quiet standing on a free root
without falling, and gradients of a sway metric with respect to the balance gains against
central differences."""

from __future__ import annotations

import base64
import dataclasses
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from neuromotor.config import ConfigError, simulation_config
from neuromotor.physics.balance import (
    balance_torques as torques_of,
    empty_posture,
    foot_forces,
    joint_origins,
    posture_signals,
    whole_com,
)
from neuromotor.physics.contact import simulate_contact, simulate_contact_jit
from neuromotor.physics.dynamics import Params
from neuromotor.studies.balance import balance_metrics, hip_joints
from neuromotor.studies.ground import foot_bodies, ground_scene
from neuromotor.studies.standing import standing_setup


@pytest.fixture(scope="module")
def standing():
    """1.5 s of quiet standing (the clip's most upright frame, free root, ground, balance on)."""
    setup = standing_setup(1.5)
    out = simulate_contact_jit(setup.sim_model, setup.params, ground_scene(setup.ground))
    return setup, out


def test_balance_config():
    free = simulation_config({"sim": {"root": "free"}}, "x.toml")
    assert free.balance_on  # on with a free root on the ground
    assert not simulation_config({}, "x.toml").balance_on  # the paper: driven root, no balance
    assert not simulation_config({"sim": {"root": "free"}, "balance": {"enabled": False}}, "x").balance_on
    spec = simulation_config({"balance": {"kp": 1.4, "delay": 0.2, "assist": 5.0}}, "x").balance
    assert (spec.kp, spec.delay, spec.assist, spec.kd) == (1.4, 0.2, 5.0, 0.35)
    bad = [
        ({"balance": {"kp": -1.0}}, "balance.kp"),
        ({"balance": {"delay": 0.5, "max_delay": 0.3}}, "balance.delay"),
        ({"balance": {"max_delay": 2.0}}, "balance.max_delay"),
        ({"balance": {"gain": 1.0}}, "balance.gain"),
        ({"balance": {"enabled": "yes"}}, "balance.enabled"),
    ]
    for data, field in bad:
        with pytest.raises(ConfigError, match=f"field '{field}'"):
            simulation_config(data, "x.toml")


def test_labels_and_statics(standing):
    setup, _ = standing
    model, state, bal = setup.model, setup.ref.init, setup.gains.balance
    names = model.body_names
    assert [names[b] for b in bal.feet] == ["LeftAnkle", "RightAnkle"]
    assert [names[j + 1] for j in hip_joints(setup.character)] == ["LeftHip", "RightHip"]
    # The feet carry the weight with no moment about the COM (horizontal components).
    up = -model.gravity / jnp.linalg.norm(model.gravity)
    points, forces = foot_forces(model, state, foot_bodies(setup.character))
    weight = jnp.sum(model.mass) * jnp.linalg.norm(model.gravity)
    np.testing.assert_allclose(forces.sum(0), weight * up, rtol=1e-12)
    moment = jnp.cross(points - whole_com(model, state.pos), forces).sum(0)
    np.testing.assert_allclose(moment - (moment @ up) * up, 0.0, atol=1e-9)
    assert float(bal.height) > 0.5


def test_loop_opposes_the_lean(standing):
    setup, _ = standing
    model, bal = setup.model, dataclasses.replace(setup.gains.balance, delay=jnp.asarray(0.0))
    state = setup.ref.init
    up = -model.gravity / jnp.linalg.norm(model.gravity)
    fwd = jnp.asarray(setup.character.anatomy.forward, jnp.float64)
    moved = dataclasses.replace(state, vel=state.vel + 0.1 * fwd)  # the COM moves forward
    hist = empty_posture(bal, jnp.float64)
    base, _ = torques_of(model, bal, state, hist, setup.options.h)
    tq, _ = torques_of(model, bal, moved, hist, setup.options.h)
    extra = tq - base
    assert float(jnp.linalg.norm(posture_signals(model, bal, moved)[1][0])) > 0
    # The torque on the shanks (-T of the ankle joints) pitches the body backwards:
    # its component along up x forward is negative of gravity's (which is + along it for a forward lean).
    on_shanks = -extra[jnp.asarray(bal.ankles)].sum(0)
    assert float(on_shanks @ jnp.cross(up, fwd)) < 0


def test_the_loop_measures_the_lean_rate_against_a_moving_platform(standing):
    """The lean is measured from the ankles, which ride the platform, so its rate is the COM's
    velocity relative to the ground's: a body carried along at the platform's velocity has none
    (the loop pushed against the carrying motion itself until 2026-11-29), and one moving
    relative to it has the relative velocity over H."""
    setup, _ = standing
    model, bal, state = setup.model, setup.gains.balance, setup.ref.init
    fwd = jnp.asarray(setup.character.anatomy.forward, jnp.float64)
    carried = dataclasses.replace(state, vel=state.vel + 0.37 * fwd)
    rate = lambda s, support=None: posture_signals(model, bal, s, support=support)[1][0]
    np.testing.assert_allclose(rate(carried), 0.37 * fwd / bal.height, rtol=1e-12)  # a still ground
    still = (jnp.zeros(3), None, None)
    np.testing.assert_allclose(rate(carried, (0.37 * fwd, None, None)), rate(state, still), atol=1e-15)
    np.testing.assert_allclose(rate(carried, (0.3 * fwd, None, None)), 0.07 * fwd / bal.height, rtol=1e-9)
    # A tilting ground: the support's velocity is the plane's at the ankles' midpoint.
    spin, pivot = jnp.asarray([0.0, 0.0, 0.4]), jnp.asarray([0.1, 0.0, 0.2])
    ankles = jnp.mean(joint_origins(model, state.pos, state.rot)[jnp.asarray(bal.feet)], 0)
    turned = dataclasses.replace(state, vel=state.vel + jnp.cross(spin, ankles - pivot))
    np.testing.assert_allclose(rate(turned, (jnp.zeros(3), spin, pivot)), rate(state), atol=1e-15)


def test_quiet_standing(standing):
    setup, out = standing
    m = balance_metrics(setup, out)
    assert not m["fell"], m
    assert m["sway_rms_mm"] < 30.0
    assert int(out.run.diverged_step) < 0


def test_sway_gradient_matches_central_differences(standing):
    setup, _ = standing
    n = 48  # 0.4 s: the loop acts after its 0.15 s delay; the feet stay on the ground
    sim = dataclasses.replace(setup.sim_model, options=dataclasses.replace(setup.options, n_steps=n))
    scene = ground_scene(setup.ground)
    fwd = jnp.asarray(setup.character.anatomy.forward, jnp.float64)
    ref = dataclasses.replace(sim.ref, init=dataclasses.replace(sim.ref.init, vel=sim.ref.init.vel + 0.05 * fwd))
    sim = dataclasses.replace(sim, ref=ref)

    def sway(x):
        bal = dataclasses.replace(setup.gains.balance, kp=x[0], kd=x[1], delay=x[2])
        gains = dataclasses.replace(setup.gains, balance=bal)
        out = simulate_contact(sim, Params(gains, setup.pulses), scene)
        mass = sim.model.mass
        com = jnp.einsum("b,tbi->ti", mass / mass.sum(), out.run.states.pos)
        return jnp.sum((com - com[0]) ** 2), out.contact.active

    # The delay off the grid: the rollout is piecewise linear in it, with kinks at multiples of h.
    x0 = jnp.asarray([1.3, 0.35, 0.155])
    grad = jax.jit(jax.jacfwd(lambda x: sway(x)[0]))(x0)
    f = jax.jit(sway)
    _, active0 = f(x0)
    # eps: PGS's friction polygon has edges where a tangential impulse switches between stick
    # and slide without changing the active set; such kinks lie within ~1e-5 of x0 in kd (there
    # central differences of 1e-5 differ by 2.8e-3, of 3e-7 by 6e-7: docs/balance.md).
    for i, eps in enumerate((1e-5, 1e-6, 1e-6)):
        e = jnp.zeros(3).at[i].set(eps)
        (fp, ap), (fm, am) = f(x0 + e), f(x0 - e)
        assert bool(jnp.all(ap == active0)) and bool(jnp.all(am == active0))  # the contact set is unchanged
        fd = (fp - fm) / (2 * eps)
        np.testing.assert_allclose(grad[i], fd, rtol=1e-3)
    assert float(jnp.abs(grad[0])) > 0


def test_assist_pulls_the_pelvis_back_and_reports_its_impulse():
    """The assist (off by default) is a spring-damper on the pelvis toward its captured
    position: with the initial state moving sideways, the pelvis ends nearer its target with it
    than without, and the metrics report its impulse."""
    runs = {}
    for k in (0.0, 50.0):
        setup = standing_setup(0.3, balance={"assist": k})
        side = jnp.asarray(np.cross(setup.character.anatomy.up, setup.character.anatomy.forward), jnp.float64)
        init = dataclasses.replace(setup.ref.init, vel=setup.ref.init.vel + 0.1 * side)
        sim = dataclasses.replace(setup.sim_model, ref=dataclasses.replace(setup.ref, init=init))
        out = simulate_contact_jit(sim, setup.params, ground_scene(setup.ground))
        runs[k] = (setup, out)
    off, on = (balance_metrics(*runs[k]) for k in (0.0, 50.0))
    assert "assist_impulse_Ns" not in off
    assert on["assist_impulse_Ns"] > 0 and 0 < on["assist_impulse_pct"] < 100
    drift = {k: float(jnp.linalg.norm(o.run.states.pos[-1, 0] - o.run.states.pos[0, 0])) for k, (_, o) in runs.items()}
    assert drift[50.0] < drift[0.0]


def test_assist_on_a_platform_is_the_force_the_file_and_the_viewer_show(tmp_path):
    """On a moving platform the assist pulls toward the captured path carried along with the
    ground. What RUN.npz records as ``assist_force`` is the force the step applied: the body's
    linear momentum changes by h (M g + F_assist) plus the ground's impulses, to round-off (the
    joints' and the loop's torques are internal). Its impulse is the metrics', and the viewer
    draws it as an arrow |F| / 500 N per m long from the pelvis, and its BVH export moves the
    root with the platform."""
    from neuromotor.studies.record import run_arrays
    from neuromotor.studies.simulate import prepare, run
    from neuromotor.studies.standing import standing_pose
    from neuromotor.viz.html import viewer_data, yup_order

    path, _, _, still = standing_pose()
    base = {"kind": "base", "direction": "backward", "unit": "g", "magnitude": 0.1, "shape": "half_sine",
            "duration": 0.2, "start": 0.1}
    data = {"clip": path, "sim": {"root": "free", "still": still, "duration": 0.5}, "balance": {"assist": 40.0},
            "perturbation": [base]}
    setup = prepare(simulation_config(data, "platform.toml"))
    result = run(setup)
    arrays = run_arrays(setup, result)
    force, h = arrays["assist_force"], setup.options.h
    np.testing.assert_array_equal(arrays["assist_point"], np.asarray(result.perturbed.states.pos[:, 0]))
    mass = np.asarray(setup.model.mass)
    momentum = np.einsum("b,tbi->ti", mass, np.asarray(result.perturbed.states.vel))
    ground = np.asarray(result.ground.contact.impulse).sum(1)[1:]  # the record after each step
    gravity = np.asarray(setup.model.gravity) * mass.sum()
    change = np.diff(momentum, axis=0)
    np.testing.assert_allclose(change, h * (gravity + force[:-1]) + ground, rtol=0, atol=1e-11)
    assert np.abs(h * force[:-1]).max() > 1e3 * 1e-11  # the check sees the assist
    # The target moves with the platform: the same force about the still capture does not balance.
    n, total = force.shape[0], mass.sum()
    platform, platform_vel = (np.asarray(a)[:n] for a in (setup.pulses.base_offset, setup.pulses.base_velocity))
    still = force - 40.0 * total * platform - 2 * np.sqrt(40.0) * total * platform_vel
    assert np.abs(h * (still - force)[:-1]).max() > 1e-4
    impulse = float(np.sum(np.linalg.norm(force[:-1], axis=1)) * h)
    assert result.metrics["assist_impulse_Ns"] == pytest.approx(impulse, rel=1e-12)
    # The contact solve's residual: the metrics are the record's, over the steps with a contact.
    residual, touching = np.asarray(result.ground.contact.residual), np.asarray(result.ground.contact.active)
    assert result.metrics["max_lcp_residual_mps"] == residual.max() > 0.0
    step_max = residual.max(-1)[touching.any(-1)]
    assert result.metrics["lcp_residual_p95_mps"] == pytest.approx(np.percentile(step_max, 95), rel=1e-12)
    assert np.all(residual[~touching] == 0.0)

    # The file says which loop ran: its gains as configured (the assist's included), its feet.
    prov = json.loads(str(arrays["provenance_json"]))["balance"]
    spec = setup.config.balance
    assert {k: prov[k] for k in ("kp", "kd", "hip_kp", "hip_kd", "delay", "assist")} == {
        "kp": spec.kp, "kd": spec.kd, "hip_kp": spec.hip_kp, "hip_kd": spec.hip_kd, "delay": spec.delay,
        "assist": 40.0}
    assert prov["longest_delay"] >= spec.max_delay and prov["stepping"] is False and len(prov["feet"]) == 2

    page = viewer_data(arrays)
    unpack = lambda part: np.frombuffer(base64.b64decode(part["b64"]), "<f4").reshape(part["shape"])
    tail, tip = unpack(page["assist"]["tail"]), unpack(page["assist"]["tip"])
    order = yup_order(int(arrays["up_axis"]))  # the page's frame is Y up
    np.testing.assert_allclose(tip - tail, force[:, order] / 500.0, atol=1e-5)
    np.testing.assert_allclose(tail, arrays["assist_point"][:, order], atol=1e-5)
    # The pictures' ground rides on the platform: the viewer's per sample, the filmstrip's and the
    # video's mesh moved by the platform's displacement (the feet stay on the drawn ground).
    from neuromotor.viz.scene import Scene

    np.testing.assert_allclose(unpack(page["platform"]), arrays["base_offset"][:, order], atol=1e-6)
    scene, k = Scene(arrays), n - 1
    centre = arrays["body_pos"][0, 0]
    moved = np.asarray(scene.ground_mesh(centre, 1.0, k).points) - np.asarray(scene.ground_mesh(centre, 1.0).points)
    np.testing.assert_allclose(moved, np.broadcast_to(arrays["base_offset"][k], moved.shape), atol=1e-9)
    assert np.linalg.norm(arrays["base_offset"][k]) > 0.01


    # The run's BVH puts the root where the simulation did (carried by the platform), not on the
    # held pose: the file's root joint, posed by forward kinematics, is the simulated root body.
    from neuromotor.io.export import export_bvh
    from neuromotor.io.opensim import root_pose_of_bodies
    from neuromotor.io.runfile import save_npz_atomic
    from neuromotor.model.clip_edit import forward_kinematics
    from neuromotor.model.load import load_character

    run_path = save_npz_atomic(tmp_path / "run.npz", arrays)
    units = float(arrays["source_units"])  # metres per file unit, as the run recorded them
    back, _ = load_character(str(export_bvh(run_path, tmp_path / "run.bvh")), units, int(arrays["up_axis"]))
    pos, rot, _ = forward_kinematics(back.source)
    origin, want = root_pose_of_bodies(setup.model, arrays["body_pos"], arrays["body_quat"])
    np.testing.assert_allclose(pos[:, 0], origin, rtol=0, atol=1e-6)  # the file's decimals
    np.testing.assert_allclose(rot[:, 0], want, rtol=0, atol=1e-6)
    assert np.abs(origin - origin[0]).max() > 0.01  # the platform carried it by more than a centimetre


def _com_distance_mm(setup, result) -> np.ndarray:
    """The horizontal distance (mm) between the perturbed and unperturbed runs' whole-body COM at
    every sample, from their body positions."""
    mass = np.asarray(setup.model.mass) / float(np.sum(setup.model.mass))
    d = np.einsum("b,tbi->ti", mass, np.asarray(result.perturbed.states.pos) - np.asarray(result.unperturbed.states.pos))
    up = -np.asarray(setup.model.gravity) / np.linalg.norm(np.asarray(setup.model.gravity))
    return 1000 * np.linalg.norm(d - np.outer(d @ up, up), axis=1)


def test_com_response_is_the_push_and_not_the_settling():
    """``com_response_*`` is the horizontal distance between the pushed run's COM and its
    unperturbed twin's: recomputed here from the two runs' body positions, and exactly 0 for a
    push of 0 N s, whose sway still counts the held pose's settling (the right sole rolling flat
    moves the COM about 2 cm sideways in the first second)."""
    from neuromotor.studies.simulate import prepare, run
    from neuromotor.studies.standing import standing_pose

    path, character, traj, still = standing_pose()
    push = {"kind": "impulse", "body": "pelvis", "direction": "left", "start": 0.6}
    figures = {}
    for j in (0.0, 8.0):
        data = {"clip": path, "sim": {"root": "free", "still": still, "duration": 1.5},
                "perturbation": [push | {"magnitude": j}]}
        setup = prepare(simulation_config(data, "<test>"), character, traj)
        result = run(setup)
        m = result.metrics
        dist = _com_distance_mm(setup, result)
        assert m["com_response_peak_mm"] == pytest.approx(dist.max(), rel=1e-12, abs=1e-12)
        assert m["com_response_final_mm"] == pytest.approx(dist[-1], rel=1e-12, abs=1e-12)
        assert m["com_response_time_s"] == pytest.approx(float(np.asarray(result.perturbed.time)[dist.argmax()]))
        figures[j] = m
    assert figures[0.0]["com_response_peak_mm"] == 0.0 and figures[0.0]["sway_range_ml_mm"] > 10.0
    pushed = figures[8.0]
    # An 8 N s sideways push moves the COM 9.3 mm off its twin's path, inside the 19.8 mm that the
    # settling already spans sideways: the sway's ML range does not see it.
    assert pushed["com_response_peak_mm"] > 5.0
    assert pushed["sway_range_ml_mm"] == pytest.approx(figures[0.0]["sway_range_ml_mm"], abs=0.5)
    assert pushed["com_response_time_s"] > 0.6  # after the onset


def test_a_ball_on_a_standing_character_reports_falls_sway_and_response():
    """A ball thrown at a free-standing character: the run's metrics have the falls, sway and COM
    response that a push on the ground reports (they were missing with a ball), the response
    against the twin whose ball is never launched."""
    from neuromotor.studies.simulate import prepare, run
    from neuromotor.studies.standing import standing_pose

    path, character, traj, still = standing_pose()
    ball = {"radius": 0.11, "mass": 1.0, "position": [-0.45, 1.45, 4.5], "speed": 14.0, "target": "Chest2",
            "launch": 0.3, "restitution": 0.6, "friction": 0.5}
    data = {"clip": path, "sim": {"root": "free", "still": still, "duration": 1.0}, "ball": ball}
    setup = prepare(simulation_config(data, "<test>"), character, traj)
    result = run(setup)
    m = result.metrics
    assert m["ball_peak_impulse_Ns"] > 1.0 and not m["fell"] and m["fall_time_s"] is None
    for key in ("sway_rms_mm", "sway_range_ap_mm", "sway_range_ml_mm", "sway_rms_late_mm", "diverged_s"):
        assert key in m, key
    dist = _com_distance_mm(setup, result)
    assert m["com_response_peak_mm"] == pytest.approx(dist.max(), rel=1e-12) and dist.max() > 1.0
    assert m["com_response_time_s"] > 0.3  # after the launch
