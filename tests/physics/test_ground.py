"""Issue 38 (first part): the ground under the bodies, and a free root.

The ground is the plane ``up . x = height``; its contacts are the lowest vertices of the bodies'
polyhedra, as LCP rows with friction in the same contact step as the ball's
(:mod:`neuromotor.physics.contact.ground`). Physics asserted:

* a box at rest on the ground for 10 s: the normal impulses / h sum to m g (to 1e-9, measured
  1e-15) at every step, and it neither drifts (< 1e-6 m; measured 1e-18 m) nor jitters;
* a box sliding at v0 = 4 m/s with mu = 0.3: it decelerates at mu g (to 1 %, measured 1e-12)
  and stops after v0^2 / (2 mu g) (to 1 %; measured -0.61 %, which is the first-order step's
  v0 h / 2: the discrete stop distance v0^2 / (2 mu g) - v0 h / 2 holds to 1e-4 m);
* a box dropped flat from 0.2 m: it lands at t = sqrt(2 * 0.2 / g) inside a step, no vertex of
  any stored state is below the plane by more than 1e-9 m (measured 0), and it does not bounce
  (zero restitution: the vertical velocity is 0 from the landing step on); dropped tilted, it
  lands on a corner, turns onto a face and comes to rest there, never below the plane by more
  than 1e-9 m, its centre never rising faster than 1e-4 m/s (measured 3e-6 m/s);
* a ball dropped on the box resting on the ground: two sources of contact in one LCP, and the
  ground under the box carries the box and the ball (to 1e-9);
* a free skeleton in flight (the embedded clip's character, root free, gravity on, the ground
  50 m below): linear momentum changes by the gravity impulse M g t only (to 1e-9 relative;
  measured 4e-15), and the angular momentum about the centre of mass stays within 1e-3 kg m^2/s
  over 0.5 s of the clip's motion (measured 2.4e-4; it halves with h, the step's first-order error).

The box is a two-body model (the code needs a joint): a 6 kg box at the root with a 0.5 kg cube
welded inside it (``driven_joints``), both centred on the same point, so the pair is one rigid
box of 6.5 kg.
"""

from __future__ import annotations

import dataclasses
import json
import pathlib
import re

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from neuromotor.config import ConfigError, SimulationConfig, simulation_config
from neuromotor.config.parse import fit_spec, sweep_spec
from neuromotor.model import polyhedron as poly
from neuromotor.physics import contact as ct
from neuromotor.physics.dynamics import SimModel
from neuromotor.physics.system import world_inertia
from neuromotor.rotations import quat_exp, quat_mul, quat_to_matrix
from neuromotor.studies.ground import capture_floor, foot_bodies, ground_scene
from neuromotor.studies.record import provenance, run_arrays
from neuromotor.studies.simulate import load_character, prepare, run

H = 1.0 / 120.0
G = 9.81
HALF = np.array([0.2, 0.1, 0.15])  # the box's half extents (m)
M_BOX, M_CORE, CORE = 6.0, 0.5, 0.02
MASS = M_BOX + M_CORE
SECONDS = 10.0


def _box_inertia(m, half):
    a, b, c = half
    return m / 3.0 * np.diag([b * b + c * c, a * a + c * c, a * a + b * b])


def _box_bvh(path: pathlib.Path, seconds: float) -> pathlib.Path:
    frames = int(round(seconds * 30)) + 2
    lines = ["HIERARCHY", "ROOT Box", "{", "  OFFSET 0 0 0",
             "  CHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation",
             "  JOINT Core", "  {", "    OFFSET 0 0 0", "    CHANNELS 3 Zrotation Xrotation Yrotation",
             "    End Site", "    {", "      OFFSET 0 0.05 0", "    }", "  }", "}", "MOTION",
             f"Frames: {frames}", "Frame Time: 0.0333333333"]
    lines += [f"0 {HALF[1]} 0 0 0 0 0 0 0"] * frames
    path.write_text("\n".join(lines) + "\n")
    return path


@pytest.fixture(scope="module")
def box(tmp_path_factory):
    """The box at rest on the plane y = 0 (free root, the core welded), its shapes and gains."""
    path = _box_bvh(tmp_path_factory.mktemp("box") / "box.bvh", SECONDS)
    character, traj = load_character(path, units="m")
    model = eqx.tree_at(lambda m: (m.mass, m.inertia, m.com, m.gravity), character.model, (
        jnp.array([M_BOX, M_CORE]),
        jnp.asarray(np.stack([_box_inertia(M_BOX, HALF), _box_inertia(M_CORE, [CORE] * 3)])),
        jnp.zeros((2, 3)), jnp.array([0.0, -G, 0.0])))
    shapes = (poly.box(HALF), poly.box(CORE))
    character = dataclasses.replace(character, model=model, shapes=shapes)
    setup = prepare(SimulationConfig(clip=str(path), units="m", duration=SECONDS, driven_joints=["Core"]),
                    character, traj)
    sim = SimModel(model, setup.ref, dataclasses.replace(setup.options, free_root=True))
    # The welded core has no muscle (its reference torque is 0: the gain scale would be inf).
    gains = dataclasses.replace(setup.gains, scale=jnp.ones(3), ks=jnp.zeros(()), kd=jnp.zeros(()))
    return sim, dataclasses.replace(setup.params, gains=gains), shapes, character


def _start(sim, lift=0.0, vel=(0.0, 0.0, 0.0), turn=(0.0, 0.0, 0.0)):
    """The box's initial state: lifted, moving, turned (rotation vector) about its centre."""
    init = sim.ref.init
    q = quat_exp(jnp.asarray(turn, jnp.float64))
    return dataclasses.replace(
        init,
        pos=init.pos + jnp.array([0.0, lift, 0.0]),
        quat=jax.vmap(lambda a: quat_mul(q, a))(init.quat),
        vel=jnp.broadcast_to(jnp.asarray(vel, jnp.float64), init.vel.shape),
    )


YAW = np.pi / 8  # the octagon's half sector: along an edge's normal instead of a vertex
TURNED = (np.cos(YAW), 0.0, -np.sin(YAW))  # the box's x axis turned by YAW about up
BOX_AXES = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])  # the box's forward and left axes (its frame)
CASES = {  # name -> (start, friction, friction polygon on the box's axes); one compiled, vmapped 10 s rollout
    "rest": (dict(), 0.8, True),
    "slide": (dict(vel=(4.0, 0.0, 0.0)), 0.3, True),
    "drop": (dict(lift=0.2), 0.8, True),
    "tilted": (dict(lift=0.2, turn=(0.25, 0.1, 0.15)), 0.8, True),
    # The same slide with the box turned about up: along its own x, then on the world's polygon.
    "slide_turned": (dict(vel=tuple(4.0 * np.array(TURNED)), turn=(0.0, YAW, 0.0)), 0.3, True),
    "slide_turned_world": (dict(vel=tuple(4.0 * np.array(TURNED)), turn=(0.0, YAW, 0.0)), 0.3, False),
}


@pytest.fixture(scope="module")
def runs(box):
    sim, params, shapes, _ = box
    ground = ct.make_ground(shapes, 0.0, 0.8, 0.0, axes=BOX_AXES)
    starts = [_start(sim, **kw) for kw, _, _ in CASES.values()]
    stack = lambda xs: jax.tree_util.tree_map(lambda *a: jnp.stack(a), *xs)
    frictions = jnp.array([mu for _, mu, _ in CASES.values()])
    axes = jnp.stack([ground.axes * float(own) for _, _, own in CASES.values()])  # zero: the world's polygon

    def one(init, mu, ax):
        s = eqx.tree_at(lambda s: s.ref.init, sim, init)
        g = eqx.tree_at(lambda g: (g.friction, g.axes), ground, (mu, ax))
        return ct.simulate_contact(s, params, ct.ContactScene(None, None, ct.ContactSettings(), g))

    out = jax.jit(jax.vmap(one))(stack(starts), frictions, axes)
    return ground, {name: jax.tree_util.tree_map(lambda x, i=i: x[i], out) for i, name in enumerate(CASES)}


def _lowest(sim, ground, out):
    states = out.run.states
    return np.asarray(ct.lowest_points(sim.model, ground, states.pos, quat_to_matrix(states.quat), (0,)))


def _weight_ratio(out):
    """Per step, the normal impulses / h over the box's weight."""
    return np.asarray(out.contact.normal_impulse).sum(-1)[1:] / H / (MASS * G)


def test_box_at_rest_carries_its_weight_without_drift(box, runs):
    out = runs[1]["rest"]
    assert int(out.run.diverged_step) < 0
    np.testing.assert_allclose(_weight_ratio(out), 1.0, rtol=1e-9)  # every step
    pos = np.asarray(out.run.states.pos)
    assert out.run.time[-1] - out.run.time[0] >= SECONDS - 1e-9
    assert np.abs(pos - pos[0]).max() < 1e-6  # no drift over 10 s (measured 1e-18 m)
    assert np.abs(np.asarray(out.run.states.vel)).max() < 1e-12  # no jitter
    assert np.abs(np.asarray(out.run.states.omega)).max() < 1e-12
    # The four bottom corners carry it; the slack of each active contact is zero.
    active = np.asarray(out.contact.active)[1:]
    assert np.all(active.sum(-1) == 4)
    assert np.abs(np.asarray(out.contact.slack)[1:][active]).max() < 1e-9
    assert float(np.asarray(out.contact.residual).max()) < 1e-9  # the LCP solved every step


def test_sliding_box_decelerates_at_mu_g_and_stops(runs):
    out, mu, v0 = runs[1]["slide"], 0.3, 4.0
    vx = np.asarray(out.run.states.vel[:, 0, 0])
    x = np.asarray(out.run.states.pos[:, 0, 0])
    sliding = vx[1:] > 1e-9
    acc = np.diff(vx) / H
    stop = int(np.argmin(sliding))  # the step that brings it to rest
    assert 0.9 * v0 / (mu * G) / H < stop < 1.1 * v0 / (mu * G) / H
    np.testing.assert_allclose(acc[:stop - 1], -mu * G, rtol=0.01)
    assert np.abs(acc[:stop - 1] + mu * G).max() < 1e-9  # exact, as Coulomb's law in the LCP says
    assert np.abs(vx[stop + 1:]).max() < 1e-12  # it stays at rest (static friction)
    travel = x[-1] - x[0]
    np.testing.assert_allclose(travel, v0**2 / (2 * mu * G), rtol=0.01)
    np.testing.assert_allclose(travel, v0**2 / (2 * mu * G) - v0 * H / 2, atol=1e-4)  # the first-order step's
    np.testing.assert_allclose(_weight_ratio(out), 1.0, rtol=1e-9)  # friction does not lift it
    assert np.abs(np.asarray(out.run.states.omega)).max() < 1e-9  # nor tip it


def test_friction_turns_with_the_box(runs):
    """The friction polygon is tied to the box's own axes: the slide turned by 22.5 deg about up
    (along its own x) is the slide, turned (velocities to 1e-9 m/s), at exactly mu g; on the
    world's polygon the same turned slide meets an edge instead of a vertex and decelerates at
    cos(22.5 deg) mu g, 7.6 % less."""
    mu, turned = 0.3, np.array(TURNED)
    vel = lambda name: np.asarray(runs[1][name].run.states.vel[:, 0])
    along = vel("slide_turned") @ turned
    np.testing.assert_allclose(along, vel("slide")[:, 0], rtol=0, atol=1e-9)
    np.testing.assert_allclose(vel("slide_turned") - along[:, None] * turned, 0.0, atol=1e-9)  # no sideways drift
    world = vel("slide_turned_world") @ turned
    sliding = world[1:] > 0.5
    np.testing.assert_allclose(np.diff(world)[sliding][1:50] / H, -np.cos(YAW) * mu * G, rtol=1e-6)


def test_dropped_box_lands_without_penetration_or_bounce(box, runs):
    sim = box[0]
    ground, out = runs[0], runs[1]["drop"]
    y, vy = np.asarray(out.run.states.pos[:, 0, 1]), np.asarray(out.run.states.vel[:, 0, 1])
    lam = np.asarray(out.contact.normal_impulse).sum(-1)
    first = int(np.nonzero(lam > 0)[0][0])  # info row j: the step from t_{j-1} to t_j
    # The step's free fall (velocity first, then position) has fallen g h^2 k (k + 1) / 2 after k
    # steps; the impact comes at the fraction s of step k where the straight path of that step
    # meets the plane: t = (k - 1 + s) h, within a step of the continuous sqrt(2 d / g).
    k = first
    gap = 0.2 - G * H**2 * (k - 1) * k / 2
    assert 0.0 < gap <= G * H**2 * k  # the plane is reached within step k, not before
    toi = np.asarray(out.contact.toi)[first][np.asarray(out.contact.active)[first]]
    np.testing.assert_allclose(toi, gap / (G * H**2 * k), rtol=1e-9)
    assert abs((k - 1 + toi[0]) * H - np.sqrt(2 * 0.2 / G)) < H
    low = _lowest(sim, ground, out)
    assert low.min() >= -1e-9  # no penetration at any stored state (measured 0)
    assert np.abs(vy[first:]).max() < 1e-12  # no bounce: at rest from the landing step on
    np.testing.assert_allclose(y[first:], HALF[1], atol=1e-12)
    np.testing.assert_allclose(_weight_ratio(out)[first:], 1.0, rtol=1e-9)  # then it rests


def test_tilted_drop_turns_onto_a_face_and_rests(box, runs):
    sim = box[0]
    ground, out = runs[0], runs[1]["tilted"]
    vy = np.asarray(out.run.states.vel[:, 0, 1])
    lam = np.asarray(out.contact.normal_impulse).sum(-1)
    first = int(np.nonzero(lam > 0)[0][0])
    assert np.asarray(out.contact.active)[first].sum() == 1  # it lands on a corner
    low = _lowest(sim, ground, out)
    assert low.min() >= -1e-9
    assert vy[first:].max() < 1e-4  # it never bounces up (measured 3e-6 m/s)
    # At rest on a face: its centre at the half height, level, and carrying its weight.
    np.testing.assert_allclose(np.asarray(out.run.states.pos[-1, 0, 1]), HALF[1], atol=1e-9)
    up = np.asarray(quat_to_matrix(out.run.states.quat[-1, 0]))[:, 1]
    assert abs(up[1]) > 1 - 1e-9
    assert np.abs(np.asarray(out.run.states.vel[-100:])).max() < 1e-9
    np.testing.assert_allclose(_weight_ratio(out)[-100:], 1.0, rtol=1e-9)


def test_ball_on_the_box_on_the_ground_one_lcp(box):
    """The ball's contacts and the ground's in one LCP: a 1 kg ball dropped onto the box comes to
    rest on it, and the ground under the box then carries both."""
    sim, params, shapes, character = box
    sim = dataclasses.replace(sim, options=dataclasses.replace(sim.options, n_steps=180))
    caps = ct.fit_capsules(character)
    top = HALF[1] + float(jnp.max(caps.radius))  # the box's capsule, over the box's centre
    ball = ct.make_ball(0.1, 1.0, (0.0, top + 0.1 + 0.3, 0.0), velocity=(0, 0, 0), restitution=0.0,
                        friction=0.5, launch=0.0)
    scene = ct.ContactScene(ball, caps, ct.ContactSettings(), ct.make_ground(shapes, 0.0))
    out = ct.simulate_contact_jit(sim, params, scene)
    assert int(out.run.diverged_step) < 0
    nb = scene.n_ball_candidates
    names = ct.scene_candidate_names(sim.model, scene)
    assert names[:nb] == ("Box", "Core", "ground") and names[nb] == "Box@ground[0]"
    lam = np.asarray(out.contact.normal_impulse)
    on_box = lam[:, names.index("Box")]
    assert on_box[1:].max() > 0.1  # the ball hit the box
    np.testing.assert_allclose(on_box[-30:] / H, 1.0 * G, rtol=1e-9)  # it rests on it
    np.testing.assert_allclose(lam[-30:, nb:].sum(-1) / H, (MASS + 1.0) * G, rtol=1e-9)
    np.testing.assert_allclose(np.asarray(out.ball.pos[-1, 1]), top + 0.1, atol=1e-9)


# ------------------------------------------------------------------ a free skeleton in flight


@pytest.fixture(scope="module")
def flight():
    """``neuromotor simulate``'s run of a free root with the ground (50 m below: in flight)."""
    data = {"sim": {"root": "free", "start": 0.95, "duration": 0.5}, "ground": {"height": -50.0}}
    setup = prepare(simulation_config(data, "<test>"))
    result = run(setup)
    assert result.ground is not None and result.ball is None
    return setup, result.ground, result


def test_free_skeleton_in_flight_conserves_momentum(flight):
    setup, out, _ = flight
    assert setup.options.free_root and setup.ground is not None
    model = setup.model
    assert int(out.run.diverged_step) < 0 and np.asarray(out.contact.normal_impulse).max() == 0.0
    mass = np.asarray(model.mass)
    total = mass.sum()
    vel, pos, omega = (np.asarray(a) for a in (out.run.states.vel, out.run.states.pos, out.run.states.omega))
    t = np.asarray(out.run.time) - float(out.run.time[0])
    p = np.einsum("b,tbi->ti", mass, vel)
    drift = p - p[0] - total * np.asarray(model.gravity) * t[:, None]
    assert np.abs(drift).max() <= 1e-9 * np.abs(p).max()  # only gravity changes it
    com = np.einsum("b,tbi->ti", mass, pos) / total
    inertia = np.asarray(jax.vmap(lambda q: world_inertia(model, quat_to_matrix(q)))(out.run.states.quat))
    ang = np.einsum("tbij,tbj->ti", inertia, omega) + np.einsum(
        "b,tbi->ti", mass, np.cross(pos - com[:, None], vel - p[:, None] / total))
    assert np.abs(ang - ang[0]).max() <= 1e-3  # kg m^2/s (measured 2.4e-4)
    # The limbs did move: the joints' angular momenta are far larger than what is left over.
    spins = np.abs(np.einsum("tbij,tbj->tbi", inertia, omega)).max()
    assert spins > 0.01
    # Nothing holds the pelvis: the centre of mass falls freely, by the step's g h^2 k (k + 1) / 2
    # after k steps (g t^2 / 2 = 1.2 m in 0.5 s, plus the first-order step's g h t / 2).
    k = np.arange(len(t))
    fall = np.asarray(model.gravity) * (H**2 * k * (k + 1) / 2)[:, None]
    np.testing.assert_allclose(com - com[0] - p[0] / total * t[:, None], fall, atol=1e-9)


# ------------------------------------------------------------------ config


def test_root_and_ground_config():
    default = prepare(SimulationConfig(duration=0.1))
    assert default.ground is None and not default.options.free_root  # the paper: driven, no ground
    free = simulation_config({"sim": {"root": "free"}}, "x.toml")
    assert free.root == "free" and free.ground_on  # the ground comes with a free root
    assert not simulation_config({"sim": {"root": "free"}, "ground": {"enabled": False}}, "x.toml").ground_on
    assert simulation_config({"ground": {"enabled": True}}, "x.toml").ground_on
    spec = simulation_config({"ground": {"height": 0.1, "friction": 0.5, "contacts_per_body": 4}}, "x").ground
    assert (spec.height, spec.friction, spec.restitution, spec.contacts_per_body) == (0.1, 0.5, 0.0, 4)
    bad = [
        ({"sim": {"root": "floating"}}, "sim.root"),
        ({"ground": {"friction": -0.1}}, "ground.friction"),
        ({"ground": {"restitution": 1.5}}, "ground.restitution"),
        ({"ground": {"enabled": "yes"}}, "ground.enabled"),
        ({"ground": {"contacts_per_body": 0}}, "ground.contacts_per_body"),
        ({"ground": {"height": "floor"}}, "ground.height"),
        ({"ground": {"mu": 0.5}}, "ground.mu"),
        ({"ground": {"pgs_iterations": 0}}, "ground.pgs_iterations"),
        # One LCP with a ball: its sweeps are [ball] pgs_iterations, never two counts.
        ({"ground": {"pgs_iterations": 80}, "ball": {"radius": 0.1, "mass": 1.0, "position": [0.0, 1.0, 2.0],
                                                     "speed": 5.0, "target": "chest", "launch": 0.5}},
         "ground.pgs_iterations"),
    ]
    for data, field in bad:
        with pytest.raises(ConfigError, match=f"field '{field}'"):
            simulation_config(data, "x.toml")
    # The sweep count reaches the ground's scene (and so every run on it); 40 without the key.
    swept = prepare(simulation_config({"sim": {"root": "free", "duration": 0.1}, "ground": {"pgs_iterations": 7}}, "x"))
    assert swept.ground.pgs_iterations == 7 and ground_scene(swept.ground).settings.pgs_iterations == 7
    plain = prepare(simulation_config({"sim": {"root": "free", "duration": 0.1}}, "x"))
    assert ground_scene(plain.ground).settings == ct.ContactSettings()
    cfg = simulation_config({"sim": {"root": "free"}, "perturbation": [{"body": "chest", "magnitude": 1.0}]}, "x")
    sweep_spec({"sweep": {"magnitudes": [1.0]}}, cfg)  # a sweep runs on the ground, and so does a fit
    fit = {"fit": {"target": {"kind": "features", "case": [{"peak_deviation_deg": {"value": 1.0, "sd": 0.5, "source": "illustrative"}}]}}}
    assert fit_spec(fit, cfg).parameters == ("ks", "kd")
    # The postural loop's gains are fitted only where the loop runs.
    loop = {"fit": fit["fit"] | {"parameters": ["ks", "balance_kp", "balance_delay"]}}
    assert fit_spec(loop, cfg).parameters == ("ks", "balance_kp", "balance_delay")
    driven = simulation_config({"perturbation": [{"body": "chest", "magnitude": 1.0}]}, "x")
    off = simulation_config({"sim": {"root": "free"}, "balance": {"enabled": False},
                             "perturbation": [{"body": "chest", "magnitude": 1.0}]}, "x")
    for other in (driven, off):
        with pytest.raises(ConfigError, match=r"field 'fit.parameters\[1\]' = 'balance_kp' needs the postural loop"):
            fit_spec(loop, other)


def test_run_of_a_free_root_records_the_ground(flight):
    setup, out, result = flight
    m = result.metrics
    assert not m["diverged"] and m["ground_peak_force_N"] == 0.0 and m["ground_contact_fraction"] == 0.0
    arrays = run_arrays(setup, result)
    t, g = len(arrays["time"]), setup.ground.n_slots
    assert arrays["ground_impulse"].shape == (t, g, 3) and arrays["ground_gap"].shape == (t, g)
    assert arrays["ground_body"].shape == (g,) and float(arrays["ground_height"]) == -50.0
    np.testing.assert_allclose(arrays["ground_gap"][0].min(), np.asarray(out.contact.gap)[0].min())
    assert provenance(setup)["root"] == "free" and provenance(setup)["ground"]["height"] == -50.0
    # Each body's friction axes (forward, left) in its frame: recorded as used, orthonormal.
    axes = np.array(provenance(setup)["ground"]["friction_axes"])
    np.testing.assert_array_equal(axes, np.asarray(setup.ground.axes))
    np.testing.assert_allclose(axes @ np.swapaxes(axes, 1, 2), np.broadcast_to(np.eye(2), (g // setup.ground.per_body, 2, 2)),
                               atol=1e-12)


def test_floor_is_the_lowest_foot_point_of_the_capture(flight):
    setup, *_ = flight
    character, traj = setup.character, setup.traj
    floor = capture_floor(character, traj)
    assert [character.model.body_names[b] for b in foot_bodies(character)] == ["LeftAnkle", "RightAnkle"]
    probe = ct.make_ground(character.shapes, floor)
    from neuromotor.model.kinematics import body_poses

    times = jnp.arange(character.clip.n_frames) * character.clip.frame_time
    pos, rot = jax.jit(jax.vmap(lambda t: body_poses(character.model, traj.q(t))))(times)
    low = np.asarray(ct.lowest_points(character.model, probe, pos, rot, foot_bodies(character)))
    assert low.min() == pytest.approx(0.0, abs=1e-12)  # the feet touch it at some frame ...
    assert np.median(low) > 0.0  # ... and are above it at most
    # The default ground of a free root is there; a [ground] height overrides it.
    data = {"sim": {"root": "free", "start": 0.95, "duration": 0.1}}
    on_floor = prepare(simulation_config(data, "<test>"), character, traj)
    assert float(on_floor.ground.height) == pytest.approx(floor, abs=1e-12)
    assert float(setup.ground.height) == -50.0


def test_a_held_pose_stands_on_its_floor():
    """A still run holds one frame: its floor is that frame's lowest foot point, so the pose
    stands on the ground from the first step. The embedded clip's upright frame has its soles
    17.6 mm above the whole clip's floor; on that floor the body used to fall onto its feet in
    the first 0.07 s and the ground's peak force was 4.7 times the body weight."""
    from neuromotor.model.kinematics import body_poses, still_trajectory
    from neuromotor.studies.standing import standing_pose

    path, character, traj, still = standing_pose()
    data = {"clip": path, "sim": {"root": "free", "still": still, "duration": 0.1}}
    setup = prepare(simulation_config(data, "<test>"), character, traj)
    probe = ct.make_ground(character.shapes, 0.0)
    pos, rot = body_poses(character.model, traj.q(jnp.asarray(still)))
    held = float(jnp.min(ct.lowest_points(character.model, probe, pos[None], rot[None], foot_bodies(character))))
    assert float(setup.ground.height) == pytest.approx(held, abs=1e-12)
    assert held - capture_floor(character, traj) > 0.01  # the clip's floor is elsewhere: the rule matters
    assert capture_floor(character, still_trajectory(traj, still)) == pytest.approx(held, abs=1e-12)
    # An explicit height still wins.
    data["ground"] = {"height": 0.0}
    assert float(prepare(simulation_config(data, "<test>"), character, traj).ground.height) == 0.0


# A platform (issue 38): a base motion under a free root moves the ground. Constant acceleration
# a along x from t_0, for 1 s: below mu g the box is carried, above it slides (Coulomb).
PLATFORM_STEPS, PLATFORM_MU = 120, 0.3


def _platform(sim, a):
    """Base-motion pulses of constant acceleration ``a`` (m/s^2, +x) on the grid of ``sim``:
    V_k = a t_k, D_k+1 = D_k + h V_k+1 (the base motion's own update)."""
    t = np.asarray(sim.ref.time[: PLATFORM_STEPS + 1]) - float(sim.ref.time[0])
    vel = np.zeros((t.shape[0], 3))
    vel[:, 0] = a * t
    offset = np.concatenate([np.zeros((1, 3)), H * np.cumsum(vel[1:], 0)])
    return vel, offset


@pytest.fixture(scope="module")
def platform_runs(box):
    """The box on the platform: still (no base motion), a zero base motion, a = 0.2 g and 0.6 g."""
    sim, params, shapes, _ = box
    sim = eqx.tree_at(lambda s: s.options, sim, dataclasses.replace(sim.options, n_steps=PLATFORM_STEPS))
    scene = ct.ContactScene(None, None, ct.ContactSettings(), ct.make_ground(shapes, 0.0, PLATFORM_MU, 0.0))
    still = jax.jit(ct.simulate_contact)(sim, params, scene)
    accels = jnp.array([0.0, 0.2 * G, 0.6 * G])
    motions = [_platform(sim, float(a)) for a in accels]
    vel = jnp.asarray(np.stack([m[0] for m in motions]))
    off = jnp.asarray(np.stack([m[1] for m in motions]))

    def one(v, d):
        pulses = dataclasses.replace(params.pulses, base_velocity=v, base_offset=d)
        return ct.simulate_contact(sim, dataclasses.replace(params, pulses=pulses), scene)

    out = jax.jit(jax.vmap(one))(vel, off)
    moving = [jax.tree_util.tree_map(lambda x, i=i: x[i], out) for i in range(3)]
    return still, moving, np.asarray(vel)


def test_a_still_platform_is_the_still_ground(platform_runs):
    """A zero base motion (another program: vmapped, with the platform's terms) gives the still
    ground's run to round-off; without a base motion the step is the one before platforms
    (``ground_motion`` is None), which the tests above check against the physics."""
    still, (zero, *_), _ = platform_runs
    for a, b in zip(jax.tree_util.tree_leaves(still), jax.tree_util.tree_leaves(zero)):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=0, atol=1e-12)


def test_platform_below_mu_g_carries_the_box(platform_runs):
    _, (_, slow, _), vel = platform_runs
    vx = np.asarray(slow.run.states.vel[:, 0, 0])
    np.testing.assert_allclose(vx, vel[1, :, 0], rtol=0, atol=1e-6)  # sticking from the first step
    assert vx[-1] == pytest.approx(0.2 * G * PLATFORM_STEPS * H, rel=1e-9)
    np.testing.assert_allclose(_weight_ratio(slow), 1.0, rtol=1e-9)
    height = np.asarray(slow.run.states.pos[:, 0, 1])
    assert np.abs(height - HALF[1]).max() < 1e-9  # neither sinks nor lifts


def test_platform_above_mu_g_drags_the_box_by_coulomb_friction(platform_runs):
    _, (_, _, fast), vel = platform_runs
    vx = np.asarray(fast.run.states.vel[:, 0, 0])
    rel = vx - vel[2, :, 0]
    acc = np.diff(rel) / H
    np.testing.assert_allclose(acc, -(0.6 - PLATFORM_MU) * G, rtol=0.01)  # a - mu g, backwards
    np.testing.assert_allclose(np.diff(vx) / H, PLATFORM_MU * G, rtol=0.01)  # friction's mu g forwards
    np.testing.assert_allclose(_weight_ratio(fast), 1.0, rtol=1e-9)


# A tilt (issue 38): the platform turns about a pivot under the box (about z: +x goes up). Below
# the friction angle (tan 10 deg = 0.18 < mu = 0.3) the box turns with it and stays put on it;
# above (tan 30 deg = 0.58) it slides down the slope at g (sin a - mu cos a) once the tilt is held.
TILT_STEPS, TILT_MU, TILT_START, TILT_TIME = 120, 0.3, 0.1, 0.4
TILTS = (0.0, 10.0, 30.0)  # deg


@pytest.fixture(scope="module")
def tilt_runs(box):
    from neuromotor.physics.perturbation import tilt_motion

    sim, params, shapes, _ = box
    sim = eqx.tree_at(lambda s: s.options, sim, dataclasses.replace(sim.options, n_steps=TILT_STEPS))
    ground = ct.make_ground(shapes, 0.0, TILT_MU, 0.0, axes=BOX_AXES)
    scene = ct.ContactScene(None, None, ct.ContactSettings(), ground)
    still = jax.jit(ct.simulate_contact)(sim, params, scene)
    times = np.asarray(sim.ref.time[: TILT_STEPS + 1])
    t0 = float(times[0])
    motions = [
        tilt_motion([dict(direction=[0.0, 0.0, 1.0], magnitude=a, start=t0 + TILT_START, duration=TILT_TIME,
                          shape="half_sine")], times, H, pivot=np.zeros(3))
        for a in TILTS
    ]
    turn, spin = (jnp.asarray(np.stack([m[i] for m in motions])) for i in (0, 1))

    def one(q, w):
        zero = jnp.zeros((TILT_STEPS + 1, 3))
        pulses = dataclasses.replace(params.pulses, base_velocity=zero, base_offset=zero, base_turn=q, base_spin=w,
                                     base_pivot=jnp.zeros(3))
        return ct.simulate_contact(sim, dataclasses.replace(params, pulses=pulses), scene)

    out = jax.jit(jax.vmap(one))(turn, spin)
    return still, [jax.tree_util.tree_map(lambda x, i=i: x[i], out) for i in range(len(TILTS))], sim, ground


def _turned(deg):
    a = np.deg2rad(deg)
    return np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])


def test_a_level_tilt_is_the_still_ground(tilt_runs):
    """A zero tilt (the program with the tilt's terms) gives the still ground's run to round-off."""
    still, (zero, *_), _, _ = tilt_runs
    for a, b in zip(jax.tree_util.tree_leaves(still), jax.tree_util.tree_leaves(zero)):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=0, atol=1e-12)


def test_a_tilt_below_the_friction_angle_carries_the_box(tilt_runs):
    _, (_, small, _), sim, ground = tilt_runs
    r = _turned(TILTS[1])
    states = small.run.states
    rot = np.asarray(quat_to_matrix(states.quat[-1, 0]))
    assert np.abs(rot - r).max() < 1e-6  # turned with the platform, not slid or rocked
    np.testing.assert_allclose(np.asarray(states.pos[-1, 0]), r @ np.array([0.0, HALF[1], 0.0]), atol=1e-6)
    # Held on the tilted plane: the ground's impulses / h carry the weight, straight up.
    k = int(round((TILT_START + TILT_TIME + 0.1) / H))
    force = np.einsum("tcj->tj", np.asarray(small.contact.impulse[k:])) / H
    np.testing.assert_allclose(force, np.broadcast_to([0.0, MASS * G, 0.0], force.shape), rtol=0, atol=1e-6)
    # On the plane, never below it by more than 1e-9 m (its normal turned: the gap along it).
    gaps = np.asarray(small.contact.gap)
    assert gaps.min() > -1e-9


def test_a_tilt_beyond_the_friction_angle_slides_the_box_at_the_coulomb_rate(tilt_runs):
    _, (_, _, steep), _, _ = tilt_runs
    a = np.deg2rad(TILTS[2])
    down = -_turned(TILTS[2])[:, 0]  # down the slope: -R x
    k = int(round((TILT_START + TILT_TIME + 0.1) / H))
    v = np.asarray(steep.run.states.vel[k:, 0]) @ down
    np.testing.assert_allclose(np.diff(v) / H, G * (np.sin(a) - TILT_MU * np.cos(a)), rtol=0.01)
    normal = np.asarray(steep.contact.normal_impulse[k + 1 :]).sum(-1) / H
    np.testing.assert_allclose(normal, MASS * G * np.cos(a), rtol=1e-6)


def test_tilt_config_is_checked():
    """A tilt needs a free root on the ground; a base motion names kind = "tilt" for a tilt's fields."""
    tilt = {"kind": "tilt", "direction": "right", "magnitude": 4.0}
    bad = [
        ({"perturbation": [tilt]}, "perturbation[0].kind"),  # the driven root stands on nothing
        ({"sim": {"root": "free"}, "ground": {"enabled": False}, "perturbation": [tilt]}, "perturbation[0].kind"),
        ({"sim": {"root": "free"}, "perturbation": [{**tilt, "unit": "g"}]}, "perturbation[0].unit"),
        ({"sim": {"root": "free"}, "perturbation": [{**tilt, "pivot": [0.0, 1.0]}]}, "perturbation[0].pivot"),
        ({"sim": {"root": "free"}, "perturbation": [{"kind": "tilt", "magnitude": 4.0}]}, "perturbation[0].direction"),
        # One platform: one pivot for all its tilts; the ball's ground does not tilt.
        ({"sim": {"root": "free"}, "perturbation": [tilt, {**tilt, "pivot": [0.0, 0.0, 0.1]}]}, "perturbation[1].pivot"),
        ({"sim": {"root": "free"}, "perturbation": [tilt], "ball": {"radius": 0.1, "mass": 1.0, "speed": 5.0,
                                                                    "position": [0.0, 1.0, 2.0], "target": "chest"}},
         "perturbation[0].kind"),
        ({"sim": {"root": "free"}, "perturbation": [{"kind": "base", "unit": "g", "magnitude": 0.1, "tilt": 4.0}]},
         "perturbation[0].tilt"),
    ]
    for data, field in bad:
        with pytest.raises(ConfigError, match=rf"field '{re.escape(field)}'"):
            simulation_config(data, "x.toml")
    with pytest.raises(ConfigError, match='kind = "tilt"'):
        simulation_config(bad[-1][0], "x.toml")


def test_a_toes_up_tilt_turns_the_standing_feet_with_the_ground():
    """The embedded clip's standing pose on a free root, the ground turned 4 deg toes-up about the
    point under the COM: the feet turn with it and stay on it, the body does not fall, and the
    run's file holds the ground's orientation and pivot as used (the viewer and the pictures
    draw the ground from them)."""
    from neuromotor.io.runfile import check_run
    from neuromotor.rotations import quat_log
    from neuromotor.studies.standing import standing_pose

    path, character, traj, still = standing_pose()
    tilt = {"kind": "tilt", "direction": "right", "magnitude": 4.0, "duration": 0.25, "start": 0.3}
    data = {"clip": path, "sim": {"root": "free", "still": still, "duration": 1.2}, "perturbation": [tilt]}
    setup = prepare(simulation_config(data, "tilt.toml"), character, traj)
    result = run(setup)
    assert not result.metrics["fell"] and not result.metrics["diverged"]
    arrays = run_arrays(setup, result)
    check_run("tilt.npz", arrays)
    pivot, turn = arrays["ground_pivot"], arrays["ground_turn"]
    np.testing.assert_allclose(pivot, setup.tilt_pivot, rtol=0, atol=0)
    up = -np.asarray(setup.model.gravity) / np.linalg.norm(np.asarray(setup.model.gravity))
    assert pivot @ up == pytest.approx(float(setup.ground.height), abs=1e-12)  # on the ground
    right = -np.cross(up, np.asarray(character.anatomy.forward, float))
    right /= np.linalg.norm(right)
    np.testing.assert_allclose(np.asarray(quat_log(jnp.asarray(turn[-1]))), np.deg2rad(4.0) * right, atol=1e-12)
    record = provenance(setup)["perturbations"][0]
    assert record["pivot"] == pytest.approx(list(pivot)) and not record["pivot_given"]
    # Each foot pitched with the ground: against the unperturbed run's at the end, its turn about
    # the right axis is the tilt's 4 deg to 1 deg (measured 4.0 and 4.7: the second foot stands on
    # part of its sole and rolls a little, as it does in the unperturbed run).
    pert, still_run = (np.asarray(r.states.quat) for r in (result.perturbed, result.unperturbed))
    for b in foot_bodies(character):
        rel = quat_mul(jnp.asarray(pert[-1, b]), jnp.asarray(still_run[-1, b]) * jnp.array([1.0, -1.0, -1.0, -1.0]))
        assert np.degrees(np.asarray(quat_log(rel)) @ right) == pytest.approx(4.0, abs=1.0)
    assert np.asarray(result.ground.contact.gap)[1:].min() > -1e-3  # never more than 1 mm into the turned plane
    # The held pose starts on its ground (no drop), and the file has one floor: the ground's is
    # the capture's inverse's (residuals_json).
    assert np.asarray(result.ground.contact.gap)[0].min() == pytest.approx(0.0, abs=1e-9)
    weight = float(np.sum(setup.model.mass)) * float(np.linalg.norm(np.asarray(setup.model.gravity)))
    assert result.metrics["ground_peak_force_N"] < 1.5 * weight
    assert json.loads(str(arrays["residuals_json"]))["floor_m"] == float(arrays["ground_height"])
    # The pictures draw that plane: the perturbed figure's ground turned about the pivot (the
    # original's level), the viewer's with the same quaternions in its own axes.
    from neuromotor.viz.html import viewer_data
    from neuromotor.viz.scene import Scene

    scene = Scene(arrays)
    assert scene.ground == float(setup.ground.height)
    normal = np.asarray(quat_to_matrix(jnp.asarray(turn[-1]))) @ up
    for k, n in ((None, up), (len(turn) - 1, normal)):
        pts = np.asarray(scene.ground_mesh(pivot, 1.0, k).points)
        np.testing.assert_allclose((pts - pivot) @ n, 0.0, atol=1e-5)  # float32 points
    assert viewer_data(arrays)["tilt"]["pivot"] == pytest.approx(list(pivot[[0, 1, 2]]))  # Y up: the same axes


def test_a_rig_without_feet_on_the_ground_is_warned(tmp_path):
    """Every body stands in for a foot on a rig whose labels find none; the run says so (a rig
    with feet does not get the warning). The postural loop, which stands on the feet, is
    refused there, naming the table and how to run without it."""
    from synthetic_rigs import chain_text

    chain = tmp_path / "chain.bvh"
    chain.write_text(chain_text())
    data = {"clip": str(chain), "sim": {"root": "free", "duration": 0.1}}
    with pytest.raises(ConfigError, match=r"^chain\.toml: field 'balance': .*none labelled.*enabled = false"):
        prepare(simulation_config(data, "chain.toml"))
    setup = prepare(simulation_config({**data, "balance": {"enabled": False}}, "chain.toml"))
    assert foot_bodies(setup.character) == tuple(range(setup.model.n_bodies))
    assert [w for w in setup.warnings if "no labelled feet" in w] == [
        "chain.toml: the rig has no labelled feet (see neuromotor inspect): every body counts as a foot for the "
        "ground's floor and the fall rule, so falls are found only by the COM's height"
    ]
    with_feet = prepare(simulation_config({"sim": {"root": "free", "duration": 0.1}}, "<test>"))
    assert not any("no labelled feet" in w for w in with_feet.warnings)
    # A given ground far from the feet is said: inside them, or below them by a drop.
    floor = float(with_feet.ground.height)
    for dz, words in ((0.05, "mm above the feet's lowest point"), (-0.2, "the character drops onto it"), (0.01, None)):
        cfg = simulation_config({"sim": {"root": "free", "duration": 0.1}, "ground": {"height": floor + dz}}, "g.toml")
        said = [w for w in prepare(cfg).warnings if "ground.height" in w]
        assert (len(said) == 1 and words in said[0] and said[0].startswith("g.toml: field 'ground.height'")) if words \
            else not said, (dz, said)
