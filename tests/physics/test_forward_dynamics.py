"""Issue 3: forward dynamics (Eq. 2), post-stabilization, controller and perturbations."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from conftest import CLIPS
from neuromotor.studies import metrics as mx
from neuromotor.config import DEFAULT_HIT, ConfigError, SimulationConfig, simulation_config
from neuromotor.physics.control import dof_errors
from neuromotor.physics.dynamics import Params, SimModel, SimulationDiverged, check_rollout, rollout
from neuromotor.rotations import euler_to_matrix, matrix_to_euler
from neuromotor.studies.simulate import load_character, prepare, run, simulate_jit

H = 1.0 / 120.0


@pytest.fixture(scope="module")
def bank():
    return load_character(CLIPS["mocapbank"])


def hit(magnitude=400.0, body="Chest2", start=0.5):
    return dict(DEFAULT_HIT, magnitude=magnitude, body=body, start=start)


@pytest.fixture(scope="module")
def hit_setup(bank):
    cfg = SimulationConfig(duration=2.0, perturbations=[hit()])
    return prepare(cfg, *bank)


@pytest.fixture(scope="module")
def hit_result(hit_setup):
    return run(hit_setup)


def test_kkt_residual_and_post_stabilization(hit_result):
    for r in (hit_result.perturbed, hit_result.unperturbed):
        assert float(r.residual.max()) <= 1e-9
        assert float(r.violation.max()) <= 1e-8


def test_one_newton_step_of_post_stabilization(bank, hit_setup, hit_result):
    """``stabilization_steps = 1`` (one projection per step, as Cline & Pai): the Newton step's
    quadratic convergence leaves well under a micrometre at the joints, it does not accumulate
    (each step projects again), and the motion matches two steps far below a degree."""
    cfg = SimulationConfig(duration=2.0, perturbations=[hit()], stabilization_steps=1)
    one = prepare(cfg, *bank)
    assert one.options.stabilization_steps == 1 and hit_setup.options.stabilization_steps == 2
    r1 = check_rollout(one.model, simulate_jit(one.sim_model, one.params))
    r2 = hit_result.perturbed
    v1 = np.asarray(r1.violation)
    # Drift after the position update is ~1e-4 m; one Newton step squares it away.
    assert 1e-12 < v1.max() < 1e-6 and float(r2.violation.max()) < 1e-12
    assert v1[-40:].max() < 2 * v1[:40].max() + 1e-9  # bounded, no growth over the run
    assert float(r1.residual.max()) <= 1e-9
    assert float(jnp.max(jnp.abs(r1.theta - r2.theta))) < 1e-4  # rad


@pytest.mark.parametrize("name", sorted(CLIPS))
def test_unperturbed_replay_tracks_whole_clip(name):
    character, traj = load_character(CLIPS[name])
    setup = prepare(SimulationConfig(), character, traj)  # whole clip, h = 1/120, default gains
    r = check_rollout(setup.model, simulate_jit(setup.sim_model, setup.params))
    err = mx.rms_error_deg(r.theta, setup.ref.theta)
    assert err < 2.0, err
    # Over the first 3 s (issue 14's replay bounds, the window tests/studies/test_every_clip.py uses for the
    # other clips): under 1 deg RMS and every DOF under 3 deg RMS.
    k = int(round(3.0 / setup.options.h)) + 1
    diff = np.degrees(np.angle(np.exp(1j * (np.asarray(r.theta)[:k] - np.asarray(setup.ref.theta)[:k]))))
    assert np.sqrt(np.mean(diff**2)) < 1.0 and np.sqrt(np.mean(diff**2, axis=0)).max() < 3.0
    # The root is exactly on the mocap path (its 6 rows are constraints).
    model = setup.model
    rot0 = jax.vmap(lambda q: q)(r.states.quat)
    from neuromotor.rotations import quat_to_matrix

    origin = r.states.pos[:, 0] - jnp.einsum("tij,j->ti", quat_to_matrix(rot0[:, 0]), model.com[0])
    assert float(jnp.max(jnp.abs(origin - setup.ref.root_origin))) < 1e-8
    assert float(r.violation.max()) <= 1e-8


def test_pulse_deflects_then_recovers(hit_setup, hit_result):
    m = hit_result.metrics
    start = hit_setup.config.perturbations[0]["start"]
    assert m["peak_deviation_deg"] > 1.0
    assert start < m["time_of_peak_s"] < start + 0.6
    assert m["final_error_deg"] < 0.25 * m["peak_deviation_deg"]
    dev = np.asarray(mx.joint_deviation(hit_setup.model, hit_result.perturbed.states.quat,
                                        hit_result.unperturbed.states.quat))
    t = np.asarray(hit_result.perturbed.time)
    np.testing.assert_allclose(dev.max(), m["peak_deviation_deg"], rtol=1e-12)
    # Back below the recovery threshold within 1 s of the hit. (The geodesic d(t) of issue 34
    # rises once more to 0.75 deg at 2.0-2.2 s, above the 0.64 deg threshold: in this 2 s window
    # it has not stayed below yet; the 3 s run recovers for good 1.18 s after the hit, README.)
    assert dev[(t > m["time_of_peak_s"]) & (t < start + 1.0)].min() < m["recovery_threshold_deg"]
    before = t < start
    assert dev[before].max() < 1e-9  # nothing moves before the hit


def test_larger_pulses_give_larger_peaks(hit_setup):
    s = hit_setup
    mags = jnp.array([100.0, 200.0, 400.0])

    def peak(mag):
        p = dataclasses.replace(s.pulses, magnitude=s.pulses.magnitude.at[0].set(mag))
        r = rollout(s.model, s.gains, p, s.ref, s.options)
        return r.theta

    thetas = jax.jit(jax.vmap(peak))(mags)  # one vmapped call over magnitudes
    base = simulate_jit(s.sim_model, Params(s.gains, dataclasses.replace(s.pulses, magnitude=s.pulses.magnitude * 0)))
    base = base.theta
    peaks = [float(mx.deviation(t, base).max()) for t in thetas]
    assert peaks[0] < peaks[1] < peaks[2], peaks


def test_linearly_implicit_survives_where_explicit_diverges(bank):
    character, traj = bank
    setup = prepare(SimulationConfig(h=1.0 / 30.0, duration=2.0), character, traj)
    implicit = simulate_jit(setup.sim_model, setup.params)
    explicit_cfg = dataclasses.replace(setup.options, implicit=False)
    explicit = simulate_jit(SimModel(setup.model, setup.ref, explicit_cfg), setup.params)
    assert int(implicit.diverged_step) == -1
    assert mx.rms_error_deg(implicit.theta, setup.ref.theta) < 5.0
    assert int(explicit.diverged_step) >= 0
    with pytest.raises(SimulationDiverged, match=r"step \d+ \(t = .* s\) in body '"):
        check_rollout(setup.model, explicit)


def test_gains_gradient_matches_central_differences(bank):
    character, traj = bank
    setup = prepare(SimulationConfig(duration=0.3, perturbations=[hit(start=0.1)]), character, traj)

    def loss(log_gains):
        g = dataclasses.replace(setup.gains, ks=jnp.exp(log_gains[0]), kd=jnp.exp(log_gains[1]))
        r = rollout(setup.model, g, setup.pulses, setup.ref, setup.options)
        dev = mx.deviation(r.theta, setup.ref.theta)
        return mx.soft_peak(dev)

    # Reverse mode through the whole scan (forward mode through the rollout is checked against
    # central differences in test_fitting.py, on the fitted features).
    x = jnp.log(jnp.array([400.0, 20.0]))
    value, grad = jax.jit(jax.value_and_grad(loss))(x)
    f = jax.jit(loss)
    assert float(f(x)) == pytest.approx(float(value), rel=1e-12)
    eps = 1e-5
    fd = jnp.array([(f(x.at[i].add(eps)) - f(x.at[i].add(-eps))) / (2 * eps) for i in range(2)])
    assert bool(jnp.all(jnp.abs(fd) > 0))
    np.testing.assert_allclose(grad, fd, rtol=1e-5, atol=1e-9 * float(jnp.abs(fd).max()))


def test_driven_joints_keep_mocap_while_free_arm_reacts(bank):
    character, traj = bank
    names = character.model.body_names
    free = {"LeftShoulder", "LeftElbow", "LeftWrist"}
    driven = [n for n in names[1:] if n not in free]
    cfg = SimulationConfig(duration=1.0, driven_joints=driven,
                           perturbations=[dict(DEFAULT_HIT, body="LeftElbow", magnitude=60.0, start=0.3,
                                               direction=[0.0, 0.0, 1.0], point=[0.0, -0.1, 0.0])])
    setup = prepare(cfg, character, traj)
    res = run(setup)
    dev = np.abs(np.asarray(res.perturbed.theta - res.unperturbed.theta))
    model = setup.model
    arm = [i for i, d in enumerate(model.dof_names) if d.split(".")[0] in free]
    rest = [i for i in range(model.n_dofs) if i not in arm]
    assert dev[:, arm].max() > np.deg2rad(2.0)
    assert dev[:, rest].max() < 1e-6
    assert float(res.perturbed.violation.max()) <= 1e-8


def test_gimbal_lock_decomposition_and_errors_stay_bounded():
    for order in ("ZXY", "ZYX", "XYZ"):
        ref = jnp.array([0.4, jnp.pi / 2 - 1e-9, -0.3])
        r = euler_to_matrix(ref, order)
        ang = matrix_to_euler(r, order, reference=ref)
        np.testing.assert_allclose(euler_to_matrix(ang, order), r, atol=1e-12)
        assert abs(float(ang[0]) - 0.4) < 1e-6  # continuous with the reference at lock
    # Wrapping: a reference near +pi and a decomposition near -pi compare across the seam.
    r = euler_to_matrix(jnp.array([jnp.pi - 0.01, 0.2, 0.1]), "ZXY")
    ang = matrix_to_euler(r, "ZXY", reference=jnp.array([-jnp.pi + 0.02, 0.2, 0.1]))
    assert abs(float(ang[0]) - (-jnp.pi - 0.01)) < 1e-9


def test_dof_errors_near_lock_are_bounded(bank):
    character, _ = bank
    model = character.model
    b = 1
    dofs = model.dofs_of_body(b)
    order = model.joint_order[model.body_joint[b]]
    theta_d = jnp.zeros(model.n_dofs).at[jnp.array(dofs)].set(jnp.array([0.3, jnp.pi / 2 - 1e-6, 0.2]))
    rot = jnp.tile(jnp.eye(3), (model.n_bodies, 1, 1))
    rel_d = jnp.tile(jnp.eye(3), (model.n_bodies, 1, 1)).at[b].set(euler_to_matrix(theta_d[jnp.array(dofs)], order))
    small = euler_to_matrix(jnp.array([0.01, 0.0, 0.0]), "XYZ")
    rot = rot.at[b].set(small @ rel_d[b])
    from neuromotor.physics.system import dof_axes

    axes = dof_axes(model, rot, theta_d)
    d_theta, _ = dof_errors(model, rot, jnp.zeros((model.n_bodies, 3)), axes, rel_d, jnp.zeros((model.n_bodies, 3)))
    assert bool(jnp.all(jnp.isfinite(d_theta)))
    assert float(jnp.abs(d_theta).max()) < 2.0  # bounded, although Euler differences are ill-defined
    torque = sum(axes[i] * d_theta[i] for i in dofs)
    err = -np.array([0.01, 0.0, 0.0])  # the rotation taking the simulated pose back
    assert np.linalg.norm(np.asarray(torque) - err) < 0.2 * 0.01 + 1e-12 or np.dot(torque, err) > 0


def test_config_errors_name_the_field():
    with pytest.raises(ConfigError, match=r"gains\.ks"):
        simulation_config({"gains": {"ks": "stiff"}}, "cfg.toml")
    with pytest.raises(ConfigError, match=r"perturbation\[0\]\.magnitude"):
        simulation_config({"perturbation": [{"body": "Chest"}]}, "cfg.toml")
    with pytest.raises(ConfigError, match=r"sim\.dt"):
        simulation_config({"sim": {"dt": 0.01}}, "cfg.toml")


def test_export_bvh_round_trip(tmp_path, hit_setup, hit_result):
    from neuromotor.io.export import export_bvh, reread_angles
    from neuromotor.studies.record import run_arrays
    from neuromotor.studies.simulate import save_npz_atomic

    run_path = save_npz_atomic(tmp_path / "run.npz", run_arrays(hit_setup, hit_result))
    out = export_bvh(run_path, tmp_path / "out.bvh")
    data = np.load(run_path)
    back = reread_angles(out, "auto", data["dof_names"])
    assert np.abs(back - data["theta"]).max() < 1e-6


def test_an_exported_run_loads_as_the_same_character(tmp_path, bank, hit_setup, hit_result):
    """Issue 35: the run's BVH (2 s of the clip, simulated angles) builds the same body as the
    clip it came from; the body does not depend on which frames a file holds."""
    from neuromotor.io.export import export_bvh
    from neuromotor.studies.record import run_arrays
    from neuromotor.studies.simulate import save_npz_atomic

    run_path = save_npz_atomic(tmp_path / "run.npz", run_arrays(hit_setup, hit_result))
    again, _ = load_character(export_bvh(run_path, tmp_path / "out.bvh"))
    model, back = bank[0].model, again.model
    assert back.body_names == model.body_names
    np.testing.assert_allclose(back.mass, model.mass, rtol=1e-9, atol=0)
    np.testing.assert_allclose(back.com, model.com, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(back.inertia, model.inertia, rtol=1e-9, atol=1e-12)
