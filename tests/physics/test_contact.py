"""Issue 7: a flying ball, contact as an LCP at the velocity level (neuromotor.physics.contact).

Physics asserted: complementarity of every contact at every step, Newton restitution of a
dropped ball, resting contact carrying the weight, Coulomb sliding that ends in rolling at 5/7 of
the initial speed, conservation of linear momentum when the ball hits a free-floating body,
gradients through an impact against central differences, and a character on the embedded clip
that is hit, deflects, recovers, while the ball rebounds.
"""

import pathlib

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from neuromotor.physics import contact as ct
from neuromotor.studies import ball_hit as sb
from neuromotor.config import ConfigError, SimulationConfig, simulation_config
from neuromotor.physics.dynamics import Params, SimModel, SimulationDiverged, StepOptions
from neuromotor.rotations import quat_to_matrix, rotation_error
from neuromotor.studies.record import run_arrays
from neuromotor.studies.simulate import body_lookup, load_character, prepare, run

H = 1.0 / 120.0
G = 9.81


def _tiny_bvh(path: pathlib.Path, frames: int = 61, dt: float = 1.0 / 30.0) -> pathlib.Path:
    """A post (root, 0.4 m bone) with a swinging arm (0.5 m) on top, root 1 m above the ground."""
    lines = ["HIERARCHY", "ROOT Base", "{", "  OFFSET 0 0 0",
             "  CHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation",
             "  JOINT Arm", "  {", "    OFFSET 0 0.4 0", "    CHANNELS 3 Zrotation Xrotation Yrotation",
             "    End Site", "    {", "      OFFSET 0 0.5 0", "    }", "  }", "}", "MOTION",
             f"Frames: {frames}", f"Frame Time: {dt}"]
    for i in range(frames):
        t = i * dt
        lines.append(f"0 1.0 0 0 0 0 {20 * np.sin(2 * t):.6f} {5 * np.sin(3 * t):.6f} 0")
    path.write_text("\n".join(lines) + "\n")
    return path


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    path = _tiny_bvh(tmp_path_factory.mktemp("tiny") / "post.bvh")
    character, traj = load_character(path, units="m")
    setup = prepare(SimulationConfig(clip=str(path), units="m", duration=1.2), character, traj)
    return setup, ct.fit_capsules(character)


def _stack(balls):
    return jax.tree_util.tree_map(lambda *x: jnp.stack(x), *balls)


BATCH = {  # name -> ball; all share one compiled, vmapped rollout on the tiny model
    "drop": ct.make_ball(0.1, 0.5, (3.0, 1.0, 0.0), velocity=(0, 0, 0), restitution=0.8, friction=0.5),
    "rest": ct.make_ball(0.1, 0.5, (3.0, 0.5, 0.0), velocity=(0, 0, 0), restitution=0.0, friction=0.5),
    "slide": ct.make_ball(0.1, 0.5, (3.0, 0.1, 0.0), velocity=(3.0, 0, 0), restitution=0.0, friction=0.3),
    "hit": ct.make_ball(0.1, 0.5, (-1.0, 1.6, 0.0), velocity=(8.0, 0, 0), restitution=0.5, friction=0.5,
                        launch=0.2),
    "blowup": ct.make_ball(0.1, 0.5, (9.0, 3.0, 0.0), velocity=(0, 5000.0, 0), launch=0.5),
}


@pytest.fixture(scope="module")
def batch(tiny):
    setup, caps = tiny
    out = ct.batched_simulate_contact(setup.sim_model, setup.params,
                                      ct.ContactScene(_stack(list(BATCH.values())), caps, ct.ContactSettings()))
    return {name: jax.tree_util.tree_map(lambda x, i=i: x[i], out) for i, name in enumerate(BATCH)}


def _complementarity(out: ct.ContactRollout, ball: ct.Ball, caps, settings, model, gap_tol=1e-6):
    c = out.contact
    lam, slack, act = np.asarray(c.normal_impulse), np.asarray(c.slack), np.asarray(c.active)
    gap, gap_imp = np.asarray(c.gap), np.asarray(c.gap_impact)
    scale = max(1.0, lam.max())
    assert lam.min() >= 0.0  # normal impulse >= 0
    assert np.all(lam[~act] == 0.0)  # no impulse without contact
    assert slack[act].min(initial=0.0) >= -1e-9  # post-velocity meets the restitution target
    assert (lam * slack).max() <= 1e-9 * scale  # complementary
    # Positions: no penetration at any step (gaps recomputed from the stored states) ...
    gaps = jax.vmap(lambda p, q, centre: ct.detect(model, caps, settings, ball.radius, centre, p,
                                                   quat_to_matrix(q))[0])(
        out.run.states.pos, out.run.states.quat, out.ball.pos)
    gaps = np.asarray(gaps)
    np.testing.assert_allclose(gaps[:-1], gap[1:], atol=1e-12)  # row j: gap before step j-1..j
    assert gaps.min() >= -gap_tol
    # ... and an impulse only where the surfaces touch at the impact instant.
    assert np.all(np.abs(gap_imp[lam > 0]) <= 1e-3)
    assert (lam * np.abs(gap_imp)).max() <= 1e-3 * scale
    # Friction inside the cone: |f_t| <= mu lam_n.
    imp = np.asarray(c.impulse)
    tang = np.linalg.norm(imp, axis=-1) ** 2 - lam**2
    assert np.all(np.sqrt(np.maximum(tang, 0.0)) <= float(ball.friction) * lam + 1e-9)


@pytest.mark.parametrize("name", ["drop", "rest", "slide", "hit"])
def test_complementarity_every_step(tiny, batch, name):
    setup, caps = tiny
    out = batch[name]
    assert int(out.run.diverged_step) < 0
    _complementarity(out, BATCH[name], caps, ct.ContactSettings(), setup.model)
    assert np.asarray(out.contact.normal_impulse).max() > 0.01  # a contact did happen


def test_dropped_ball_bounces_with_restitution(batch):
    """Newton's law at each bounce: outgoing normal speed = e * incoming, at the impact instant
    reconstructed from the trajectory (gap at the step start and the free velocity)."""
    out, e, r = batch["drop"], 0.8, 0.1
    y, vy = np.asarray(out.ball.pos[:, 1]), np.asarray(out.ball.vel[:, 1])
    ground = np.asarray(out.contact.normal_impulse[:, -1])
    bounces = np.nonzero(ground > 0)[0] - 1  # info row j is the step from j-1 to j
    assert len(bounces) >= 2
    for k in bounces[:2]:
        v_free = vy[k] - H * G
        s = (y[k] - r) / (-H * v_free)  # fraction of the step before the surfaces meet
        assert 0.0 <= s <= 1.0
        v_in = vy[k] - s * H * G
        v_out = vy[k + 1] + (1.0 - s) * H * G
        assert abs(v_out / -v_in - e) <= 0.01 * e
    # The first rebound height follows (e v)^2 / 2g to the accuracy of the time step.
    v_in = np.sqrt(2 * G * 0.9)
    apex = y[bounces[0] + 1: bounces[1]].max() - r
    assert abs(apex - (e * v_in) ** 2 / (2 * G)) <= 2 * H * e * v_in


def test_inelastic_ball_comes_to_rest_and_carries_its_weight(batch):
    out = batch["rest"]
    y, vy = np.asarray(out.ball.pos[:, 1]), np.asarray(out.ball.vel[:, 1])
    lam = np.asarray(out.contact.normal_impulse[:, -1])
    first = np.nonzero(lam > 0)[0][0]
    assert np.all(vy[first:] >= -1e-12) and np.abs(vy[first + 1:]).max() <= 1e-12  # no bounce
    np.testing.assert_allclose(y[first:], 0.1, atol=1e-12)
    np.testing.assert_allclose(lam[first + 1:], 0.5 * G * H, rtol=1e-9)  # impulse = m g h


def test_sliding_ball_decelerates_at_mu_g_then_rolls(batch):
    """Coulomb sliding: dv/dt = -mu g; friction spins the ball up until v = omega r, which for a
    solid sphere happens at v = 5/7 v0; then it rolls without slipping."""
    out, mu, r = batch["slide"], 0.3, 0.1
    vx, wz = np.asarray(out.ball.vel[:, 0]), np.asarray(out.ball.omega[:, 2])
    assert vx[0] == 0.0  # at rest before the launch, 3 m/s from the launch step on
    np.testing.assert_allclose(np.diff(vx[:20]), np.r_[3.0, np.zeros(18)] - mu * G * H, rtol=1e-9)
    np.testing.assert_allclose(vx[-10:], 3.0 * 5.0 / 7.0, rtol=1e-9)
    np.testing.assert_allclose(-wz[-10:] * r, vx[-10:], rtol=1e-9)  # rolling contact


def test_ball_hits_arm_and_rebounds(tiny, batch):
    out = batch["hit"]
    names = ct.candidate_names(tiny[1], ct.ContactSettings())
    lam = np.asarray(out.contact.normal_impulse)
    hit = np.nonzero(lam[:, names.index("Arm")] > 0)[0]
    assert hit.size and float(out.run.time[hit[0]]) > 0.2  # not before the launch
    assert float(out.ball.vel[hit[0], 0]) < 0.0 < float(out.ball.vel[hit[0] - 1, 0])  # rebounds
    assert np.all(np.asarray(out.ball.pos[: int(0.2 / H)]) == np.asarray(BATCH["hit"].position))


def test_blowup_names_step_and_ball(tiny, batch):
    setup, _ = tiny
    with pytest.raises(SimulationDiverged, match=r"step 60 .* body 'ball'"):
        ct.check_contact_rollout(setup.model, batch["blowup"])


# ------------------------------------------------------------------ free body: momentum, gradients


@pytest.fixture(scope="module")
def free_body(tiny):
    """Zero gravity, free-floating root: ball (0.5 kg, 6 m/s) hits the post below the arm."""
    setup, caps = tiny
    model = eqx.tree_at(lambda m: m.gravity, setup.model, jnp.zeros(3))
    cfg = StepOptions(h=H, n_steps=40, free_root=True)
    ball = ct.make_ball(0.1, 0.5, (-1.0, 1.15, 0.05), velocity=(6.0, 0.0, 0.0), restitution=0.5, friction=0.4)
    settings = ct.ContactSettings(ground=False)

    def outputs(x):
        b = eqx.tree_at(lambda b: b.speed, ball, x[0])
        g = eqx.tree_at(lambda g: (g.ks, g.kd), setup.gains, (x[1], x[2]))
        out = ct.simulate_contact(SimModel(model, setup.ref, cfg), Params(g, setup.pulses),
                                  ct.ContactScene(b, caps, settings))
        y = jnp.concatenate([out.ball.vel[-1], out.run.states.vel[-1, 0], out.run.states.omega[-1, 1]])
        return y, out

    fn = jax.jit(jax.jacfwd(outputs, has_aux=True))
    x0 = jnp.array([6.0, float(setup.gains.ks), float(setup.gains.kd)])
    return fn, x0, model, ball, caps, settings


def test_free_body_hit_conserves_linear_momentum(free_body):
    fn, x0, model, ball, caps, settings = free_body
    _, out = fn(x0)
    lam = np.asarray(out.contact.normal_impulse)
    assert lam.max() > 1.0  # a real impact
    p = (np.einsum("b,tbi->ti", np.asarray(model.mass), np.asarray(out.run.states.vel))
         + float(ball.mass) * np.asarray(out.ball.vel))
    # Row 0 is before the launch step gives the ball its 3 N s; from then on p is constant.
    np.testing.assert_allclose(p[1] - p[0], [float(ball.mass) * 6.0, 0.0, 0.0], atol=1e-12)
    assert np.abs(p[1:] - p[1]).max() <= 1e-12 * float(ball.mass) * 6.0
    # The ball gave momentum away (it would be conserved trivially without a contact).
    assert float(out.ball.vel[-1, 0]) < 0.0
    _complementarity(out, ball, caps, settings, model)


def test_gradients_through_impact_match_central_differences(free_body):
    """d(final ball velocity, post velocity, arm spin)/d(ball speed, ks, kd): finite, and equal
    to central differences (the perturbation moves the impact inside one step: no switching)."""
    fn, x0, *_ = free_body
    jac, out = fn(x0)
    jac = np.asarray(jac)
    assert np.all(np.isfinite(jac))
    toi = np.asarray(out.contact.toi)[np.asarray(out.contact.normal_impulse) > 0]
    assert np.all((toi > 0.02) & (toi < 0.98))  # away from an impact moving to another step
    steps = np.array([1e-4, 1e-3 * float(x0[1]), 1e-3 * float(x0[2])])
    for i in range(3):
        e = np.zeros(3)
        e[i] = steps[i]
        (_, up), (_, dn) = fn(x0 + e), fn(x0 - e)
        y = lambda o: np.concatenate([o.ball.vel[-1], o.run.states.vel[-1, 0], o.run.states.omega[-1, 1]])
        fd = (y(up) - y(dn)) / (2 * steps[i])
        np.testing.assert_allclose(jac[:, i], fd, rtol=1e-4, atol=1e-6 * np.abs(jac[:, i]).max() + 1e-12)
    assert np.abs(jac[:, 0]).max() > 0.1  # the impact depends on the speed


# ------------------------------------------------------------------ the solver and the shapes


def test_pgs_solves_random_contact_lcps():
    """Random well-conditioned Delassus matrices: the fixed-sweep PGS result satisfies the LCP
    (normal complementarity) and the maximal-dissipation friction law on the polygon."""
    rng = np.random.default_rng(7)
    sides, mu = 8, 0.6
    solve = jax.jit(lambda w, q, a: ct.solve_lcp_pgs(w, q, mu, a, jnp.zeros((3, 3)), sides, 300))
    for _ in range(5):
        j = rng.normal(size=(9, 12))
        w = j @ j.T / 12 + 2.0 * np.eye(9)
        q = rng.normal(size=9)
        active = jnp.array([True, True, False])
        p = np.asarray(solve(jnp.asarray(w), jnp.asarray(q), active))
        vel = (w @ p.reshape(-1) + q).reshape(3, 3)
        assert np.all(p[2] == 0.0)
        for i in range(2):
            lam, wn, ft, wt = p[i, 0], vel[i, 0], p[i, 1:], vel[i, 1:]
            assert lam >= 0 and wn >= -1e-9 and abs(lam * wn) <= 1e-9
            ang = 2 * np.pi * np.arange(sides) / sides
            verts = mu * lam * np.stack([np.cos(ang), np.sin(ang)], -1)
            # f_t minimizes the dissipation <w_t, f> over the polygon (its vertices suffice).
            assert wt @ ft <= (verts @ wt).min() + 1e-9
            normals = np.stack([np.cos(ang + np.pi / sides), np.sin(ang + np.pi / sides)], -1)
            assert (normals @ ft).max() <= mu * lam * np.cos(np.pi / sides) + 1e-12


def test_lcp_residual_is_zero_at_solutions_and_measures_the_distance_otherwise():
    """lcp_residual in closed form on one isotropic contact (W = 2 I): zero at the sticking and
    at the sliding solution, |w_n| at an impulse that leaves the contact approaching; zero on an
    inactive contact; on random LCPs small after 300 PGS sweeps and not after one."""
    w, sides, mu = 2.0 * jnp.eye(3), 8, 0.5
    on = jnp.array([True])
    res = lambda q, p, active=on: float(ct.lcp_residual(w, jnp.asarray(q), mu, active, jnp.asarray([p]), sides)[0])
    assert res([-1.0, 0.0, 0.0], [0.5, 0.0, 0.0]) == 0.0  # lam = -q_n / W_nn, no tangential load
    # Sliding: the sticking force (1.5) is beyond mu lam = 0.25, so f_t = 0.25 against w_t = -2.5.
    assert res([-1.0, -3.0, 0.0], [0.5, 0.25, 0.0]) == pytest.approx(0.0, abs=1e-15)
    assert res([-1.0, 0.0, 0.0], [0.3, 0.0, 0.0]) == pytest.approx(0.4, rel=1e-12)  # w_n = -0.4
    # Friction off the law: f_t = 0.1 while sliding; Proj(0.1 + 0.5 * 2.8) = 0.25, over s = 0.5.
    assert res([-1.0, -3.0, 0.0], [0.5, 0.1, 0.0]) == pytest.approx(0.3, rel=1e-12)
    assert res([-1.0, 0.0, 0.0], [0.3, 0.0, 0.0], jnp.array([False])) == 0.0
    rng = np.random.default_rng(11)
    for _ in range(3):
        j = rng.normal(size=(9, 12))
        wm, q = jnp.asarray(j @ j.T / 12 + 2.0 * np.eye(9)), jnp.asarray(rng.normal(size=9) - 1.0)
        active = jnp.array([True, True, True])
        solve = lambda n: ct.solve_lcp_pgs(wm, q, 0.6, active, jnp.zeros((3, 3)), sides, n)
        assert float(jnp.max(ct.lcp_residual(wm, q, 0.6, active, solve(300), sides))) < 1e-10
        assert float(jnp.max(ct.lcp_residual(wm, q, 0.6, active, solve(1), sides))) > 1e-6


def test_capsules_cover_every_polyhedron_vertex():
    character, _ = load_character()
    caps = ct.fit_capsules(character)
    body = np.asarray(caps.body)
    assert sorted(set(body.tolist())) == list(range(character.model.n_bodies))
    for b, shape in enumerate(character.shapes):
        mine = np.nonzero(body == b)[0]
        dist = np.stack([ct.segment_distances(shape.vertices, np.asarray(caps.a[i]), np.asarray(caps.b[i]))
                         - float(caps.radius[i]) for i in mine])
        assert dist.min(0).max() <= 1e-9  # every vertex inside a capsule of its body
        assert dist.min(0).min() >= -float(caps.radius[mine].max()) - 1e-9


# ------------------------------------------------------------------ config


def test_ball_config_errors_name_the_field(tiny):
    good = {"position": [0.0, 1.0, 2.0], "speed": 10.0, "direction": [0.0, 0.0, -1.0]}
    cfg = simulation_config({"ball": good}, "x.toml")
    assert cfg.ball["speed"] == 10.0 and cfg.ball["friction_directions"] == 8
    bad = [
        ({"speed": 1.0, "direction": [1, 0, 0]}, "ball.position"),
        (dict(good, restitution=1.5), "ball.restitution"),
        (dict(good, mass=0.0), "ball.mass"),
        (dict(good, velocity=[1, 0, 0]), "ball.velocity"),
        (dict(good, target="Arm"), "ball.direction"),
        (dict(good, spin=3.0), "ball.spin"),
        (dict(good, friction_directions=3), "ball.friction_directions"),
        ({"position": [0, 1, 2]}, "ball.speed"),
        (dict(good, radius="big"), "ball.radius"),
    ]
    for table, field in bad:
        with pytest.raises(ConfigError, match=f"field '{field}'"):
            simulation_config({"ball": table}, "x.toml")
    setup, _ = tiny
    spec = simulation_config({"ball": {"position": [0, 1, 2], "speed": 5.0, "target": "Elbow"}}, "x.toml").ball
    with pytest.raises(ConfigError, match="unknown body 'Elbow'"):
        sb.ball_setup(spec, setup.character, setup.traj, body_lookup(setup.model, "x.toml"))


def test_aimed_ball_reaches_its_target(tiny):
    """Aiming with gravity compensation: the ballistic path passes through the target's COM."""
    setup, _ = tiny
    pos0, speed = np.array([-2.0, 1.5, 0.5]), 7.0
    d = sb.aim_ball(setup.model, setup.traj, pos0, speed, 1, 0.3)
    from neuromotor.model.kinematics import body_poses

    for t_flight in np.linspace(0.05, 1.0, 400):
        p = pos0 + speed * d * t_flight + 0.5 * np.asarray(setup.model.gravity) * t_flight**2
        target = np.asarray(body_poses(setup.model, setup.traj.q(jnp.asarray(0.3 + t_flight)))[0][1])
        if np.linalg.norm(p - target) < 0.02:
            return
    pytest.fail("the aimed ball never comes within 2 cm of the target COM")


# ------------------------------------------------------------------ the character


@pytest.fixture(scope="module")
def character_hit():
    """The embedded clip hit in the chest: 1 s window, ball launched 0.05 s after the start."""
    data = {"sim": {"start": 0.95, "duration": 1.0},
            "ball": {"radius": 0.11, "mass": 1.0, "position": [-0.45, 1.45, 4.5], "speed": 14.0,
                     "target": "Chest2", "launch": 1.0, "restitution": 0.6, "friction": 0.5}}
    setup = prepare(simulation_config(data, "<test>"))
    return setup, run(setup)


def test_character_hit_by_ball_reacts_and_recovers(character_hit):
    setup, result = character_hit
    model, out = setup.model, result.ball
    bs = setup.ball
    _complementarity(out, bs.ball, bs.capsules, bs.settings, model)
    lam = np.asarray(out.contact.normal_impulse)
    bodies = np.asarray(ct.candidate_bodies(bs.capsules, bs.settings))
    struck_cand = np.unravel_index(np.argmax(lam), lam.shape)
    struck = int(bodies[struck_cand[1]])
    assert model.body_names[struck] == "Chest2"
    k_hit = int(struck_cand[0])
    # The ball rebounds: its velocity along the throw reverses.
    d = np.asarray(bs.ball.direction)
    assert float(out.ball.vel[k_hit - 1] @ d) > 10.0 and float(out.ball.vel[k_hit] @ d) < -2.0
    # The struck body's orientation deviation from the unperturbed run peaks, then recovers.
    dev = np.linalg.norm(np.asarray(rotation_error(
        quat_to_matrix(result.perturbed.states.quat[:, struck]),
        quat_to_matrix(result.unperturbed.states.quat[:, struck]))), axis=-1)
    assert dev[:k_hit].max() == 0.0  # nothing moves before the impact
    peak = int(np.argmax(dev))
    assert dev[peak] > np.radians(1.0) and k_hit <= peak <= k_hit + int(0.4 / H)
    assert dev[-1] < 0.5 * dev[peak]
    m = result.metrics
    assert not m["diverged"] and m["max_kkt_residual"] < 1e-9 and m["max_constraint_violation"] < 1e-8
    arrays = run_arrays(setup, result)
    t = len(arrays["time"])
    assert arrays["ball_pos"].shape == (t, 3) and arrays["ball_radius"].shape == ()
    n_cand = len(arrays["contact_names"])
    assert arrays["contact_impulse"].shape == arrays["contact_force"].shape == (t, n_cand, 3)
    np.testing.assert_allclose(arrays["contact_force"] * H, arrays["contact_impulse"])


def test_ball_speed_sweep_from_config(tiny):
    """[ball] through prepare, then ball speed as the magnitude of a vmapped sweep: a faster
    ball hits harder and deflects the arm more."""
    setup, _ = tiny
    data = {"clip": str(setup.character.clip.path), "units": "m", "sim": {"duration": 1.2},
            "ball": {"radius": 0.1, "mass": 0.5, "position": [-1.0, 1.6, 0.0], "speed": 8.0,
                     "direction": [1.0, 0.0, 0.0], "launch": 0.2, "restitution": 0.5}}
    s = prepare(simulation_config(data, "<test>"), setup.character, setup.traj)
    assert s.ball.settings == ct.ContactSettings()
    out = sb.sweep_ball_speed(s, [4.0, 6.0, 8.0, 10.0])  # + the base run: the batch fixture's shape
    assert np.all(np.diff(out["peak_impulse_Ns"]) > 0) and out["peak_impulse_Ns"][0] > 0
    assert np.all(np.diff(out["peak_deviation_deg"]) > 0) and out["peak_deviation_deg"][0] > 0.1
    assert np.all(out["time_of_peak_s"] > 0.2)


def _dense_stiff_terms(model, blocks):
    """k_stiff (6B,), K and D (6B, 6B) of tree blocks, scattered into the dense layout."""
    n = model.n_bodies
    c, p, b = jnp.arange(1, n), jnp.array(model.body_parent[1:]), jnp.arange(n)

    def dense(diag, up, down):
        out = jnp.zeros((n, 3, n, 3)).at[b, :, b, :].set(diag).at[c, :, p, :].add(up).at[p, :, c, :].add(down)
        return jnp.zeros((n, 6, n, 6)).at[:, 3:, :, 3:].set(out).reshape(6 * n, 6 * n)

    k_stiff = jnp.concatenate([jnp.zeros_like(blocks.k), blocks.k], -1).reshape(-1)
    return k_stiff, dense(blocks.k_diag, blocks.k_up, blocks.k_down), dense(blocks.d_diag, blocks.d_up, blocks.d_down)


def test_tree_stiff_blocks_equal_dense_jacobians(tiny):
    """K, D from the per-joint blocks (tree and null-space solvers, with or without contact)
    equal the dense jacfwd (dense solver): the same Eq. 2."""
    from neuromotor.physics.dynamics import SimModel, reference_inputs
    from neuromotor.physics.stiffness import stiff_blocks, stiff_jacobians
    from neuromotor.physics.system import State

    setup, _ = tiny
    model, ref, k = setup.model, setup.ref, 10
    inputs = reference_inputs(SimModel(model, ref, setup.options), setup.gains, k)
    rng = np.random.default_rng(0)
    from neuromotor.rotations import quat_exp, quat_mul

    quat = quat_mul(quat_exp(jnp.asarray(0.3 * rng.normal(size=(2, 3)))), ref.init.quat)
    omega = ref.init.omega + jnp.asarray(rng.normal(size=(2, 3)))
    state = State(ref.init.pos, quat, ref.init.vel, omega)
    # eager jacfwd would dispatch op by op
    tree_terms = jax.jit(lambda: _dense_stiff_terms(model, stiff_blocks(model, setup.gains, inputs, state)))()
    dense = jax.jit(lambda: stiff_jacobians(model, setup.gains, inputs, quat_to_matrix(quat), omega))()
    dense_terms = (dense.k, dense.kmat, dense.dmat)
    for tree, dense in zip(tree_terms, dense_terms):
        np.testing.assert_allclose(np.asarray(tree), np.asarray(dense), atol=1e-12 * float(jnp.abs(dense).max()))
    assert float(jnp.abs(tree_terms[1]).max()) > 1.0  # K is not trivially zero


@pytest.mark.parametrize("solver", ["dense", "tree"])
def test_contact_step_is_the_same_with_every_solver(tiny, batch, solver):
    """Contact adds its rows to whichever solver of Eq. 2 the run chose: the ball hitting the arm
    with the dense or the tree solver equals the default (null-space) to round-off."""
    import dataclasses

    setup, caps = tiny
    cfg = dataclasses.replace(setup.options, solver=solver)
    out = ct.simulate_contact_jit(SimModel(setup.model, setup.ref, cfg), setup.params,
                                  ct.ContactScene(BATCH["hit"], caps, ct.ContactSettings()))
    ref = batch["hit"]
    assert np.asarray(ref.contact.normal_impulse).max() > 0.01
    for got, want in ((out.run.states.pos, ref.run.states.pos), (out.run.states.omega, ref.run.states.omega),
                      (out.ball.pos, ref.ball.pos), (out.ball.vel, ref.ball.vel),
                      (out.contact.impulse, ref.contact.impulse)):
        np.testing.assert_allclose(np.asarray(got), np.asarray(want), atol=1e-8)


def test_without_contact_the_character_follows_the_plain_step(tiny, batch):
    """A ball that never touches the character leaves Eq. 2 unchanged: the contact step's
    character equals dynamics.rollout (tree solver) to round-off."""
    from neuromotor.studies.simulate import simulate_jit

    setup, _ = tiny
    plain = simulate_jit(setup.sim_model, setup.params)
    out = batch["drop"]  # falls on the ground 3 m away from the post
    np.testing.assert_allclose(np.asarray(out.run.states.pos), np.asarray(plain.states.pos), atol=1e-10)
    np.testing.assert_allclose(np.asarray(out.run.states.omega), np.asarray(plain.states.omega), atol=1e-8)
    np.testing.assert_allclose(np.asarray(out.run.theta), np.asarray(plain.theta), atol=1e-10)
