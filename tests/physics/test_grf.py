"""Contact-aware inverse dynamics (physics/grf.py, studies/residuals.py; issue 38): the driven
root's wrench is the whole body's momentum rate less gravity, ground reaction forces inside the
friction pyramid explain it where the feet touch, the residual is what they leave (all of it in
flight), the discrete inverse with the forces applied leaves exactly that residual on the root,
and the figures reach RUN.npz and the OpenSim files. On the shipped walk (conftest CLIPS):
standing at 1.0 s, and 4.6-4.8 s, where the left foot leaves the ground."""

from __future__ import annotations

import json
import xml.etree.ElementTree as ET

import numpy as np
import pytest

from conftest import CLIPS
from neuromotor.io import opensim as nos
from neuromotor.io.runfile import RESIDUAL_FIELDS, RunFileError, read_run, write_run
from neuromotor.model.kinematics import grid_poses_jit, still_trajectory
from neuromotor.model.load import load_character
from neuromotor.physics import grf
from neuromotor.physics.dynamics import StepOptions, make_reference
from neuromotor.rotations import matrix_to_quat
from neuromotor.studies import residuals as rs
from neuromotor.studies.ground import foot_bodies, friction_axes

STEPS = 24  # one window length for every case: the programs compile once
STAND, WALK = 1.0, 4.6  # s: both feet flat; the left foot lifts off at about 4.75 s


@pytest.fixture(scope="module")
def walk():
    path = CLIPS["walk"]
    if not path.exists():
        pytest.fail(f"shared mocap clip missing: {path}")
    character, traj = load_character(path)
    options = StepOptions(n_steps=STEPS)
    return character, traj, options, rs.capture_floor(character, traj)


def residuals_of(walk, t0, still=False, floor=None):
    character, traj, options, clip_floor = walk
    if still:
        traj = still_trajectory(traj, t0)
    ref = make_reference(character.model, traj, t0, options)
    floor = (rs.capture_floor(character, traj) if still else clip_floor) if floor is None else floor
    return rs.capture_residuals(character, traj, ref, options, floor), ref, traj


@pytest.fixture(scope="module")
def stepping(walk):
    return residuals_of(walk, WALK)


def test_standing_pose_grfs_carry_the_body_weight(walk):
    """A held standing pose: the root must carry exactly the weight (up, no moment about the
    COM); both feet touch, and their forces sum to it with zero residual (1e-6 of the weight)."""
    res, _, _ = residuals_of(walk, STAND, still=True)
    character = walk[0]
    feet = foot_bodies(character)
    assert len(feet) == 2
    weight = np.zeros(6)
    weight[:3] = res.weight * res.up
    np.testing.assert_allclose(res.required, np.broadcast_to(weight, res.required.shape), atol=1e-9 * res.weight)
    body, active = np.asarray(res.contacts.body), np.asarray(res.contacts.active)
    for foot in feet:  # both feet touch at every step and bear a real share
        assert np.all((active & (body == foot)).any(1))
        share = np.where((body == foot)[..., None], res.ground.force, 0.0).sum(1) @ res.up
        assert np.all(share > 0.1 * res.weight)
    total = res.ground.force.sum(1)
    assert np.abs(total - res.weight * res.up).max() <= 1e-6 * res.weight
    assert np.abs(res.residual[:, :3]).max() <= 1e-6 * res.weight
    assert np.abs(res.residual[:, 3:]).max() <= 1e-6 * res.weight * res.stature
    summary = rs.residual_summary(res)
    assert summary["contact_fraction"] == 1.0 and summary["flight_fraction"] == 0.0
    assert summary["force_peak_pct_bw"] <= 1e-4


def test_required_wrench_is_the_momentum_rate_less_gravity(walk, stepping):
    """The root's wrench in closed form: sum_b m_b (u+ - u) / h - m g, and the root rows'
    multipliers of the discrete inverse (moved to the COM) to round-off."""
    res, ref, _ = stepping
    character, _, options, _ = walk
    model = character.model
    u, h = np.asarray(ref.velocity), options.h
    mass = np.asarray(model.mass)
    momentum = np.einsum("b,sbi->si", mass, u[1:, :, :3] - u[:-1, :, :3]) / h
    np.testing.assert_allclose(res.required[:, :3], momentum - mass.sum() * np.asarray(model.gravity),
                               atol=1e-9 * res.weight)
    zero = np.zeros((STEPS, model.n_bodies, 6))
    tau, lam, kkt = grf.contact_feedforward(model, options, ref, quat_grid(walk, ref), zero)
    assert float(np.max(kkt)) < 1e-10
    np.testing.assert_allclose(tau, np.asarray(ref.tau[:-1]), atol=1e-9 * np.abs(ref.tau).max())  # the driven case
    pos, rot = (np.asarray(a) for a in grid_poses_jit(model, walk[1], ref.time))
    root = np.asarray(grf.root_wrench_about(model, np.asarray(lam)[:, :6], pos[:-1], rot[:-1], res.com))
    np.testing.assert_allclose(root, res.required, atol=1e-8 * res.weight * res.stature)


def quat_grid(walk, ref):
    return matrix_to_quat(grid_poses_jit(walk[0].model, walk[1], ref.time)[1])


def test_grfs_lie_in_the_friction_pyramid(walk, stepping):
    """Every force pushes (normal >= 0) inside the ground's 8-sided pyramid (mu 0.8), turned with
    the foot it acts on as the LCP's is, and acts only at touching vertices; the left foot leaves
    the ground in the window."""
    res, ref, _ = stepping
    force, active = res.ground.force, np.asarray(res.contacts.active)
    assert np.all(force[~active] == 0.0)
    normal = force @ res.up
    tangent = force - normal[..., None] * res.up
    # The LCP's (t1, t2) of each contact: its body's forward axis, at this step's pose.
    rot = np.asarray(grid_poses_jit(walk[0].model, walk[1], ref.time)[1])
    body = np.asarray(res.contacts.body)
    forward = np.einsum("sgij,sgj->sgi", rot[np.arange(body.shape[0])[:, None], body],
                        friction_axes(walk[0], walk[1])[body, 0])
    t1 = forward - (forward @ res.up)[..., None] * res.up
    t1 /= np.linalg.norm(t1, axis=-1, keepdims=True)
    t2 = np.cross(res.up, t1)
    ang = 2 * np.pi * (np.arange(8) + 0.5) / 8  # the octagon's face normals
    faces = np.cos(ang)[:, None] * t1[..., None, :] + np.sin(ang)[:, None] * t2[..., None, :]  # (S, G, 8, 3)
    tol = 1e-9 * res.weight
    assert np.all(normal >= -tol)
    assert np.all(np.einsum("sgfd,sgd->sgf", faces, tangent) <= grf.FRICTION * np.cos(np.pi / 8) * normal[..., None]
                  + tol)
    assert np.linalg.norm(tangent, axis=-1).max() > 1e-3 * res.weight  # friction is used
    left = np.asarray(res.contacts.body) == foot_bodies(walk[0])[0]
    touching = (active & left).any(1)
    assert touching[0] and not touching[-1]


def test_produced_plus_residual_is_required(stepping):
    """The split adds up: the forces' wrench about the COM plus the residual is the required
    wrench, from the point forces and from the per-body force, centre of pressure and free
    torque that RUN.npz and OpenSim get (round-off)."""
    res, _, _ = stepping
    produced = grf.point_wrench(res.ground.force, np.asarray(res.contacts.point), res.com[:, None])
    scale = np.array([res.weight] * 3 + [res.weight * res.stature] * 3)
    assert np.abs((produced + res.residual - res.required) / scale).max() < 1e-12
    bodies = rs.contact_bodies(res)
    force, point, torque = rs.body_loads(res, bodies)
    again = np.concatenate([force.sum(1), (np.cross(point - res.com[:, None], force) + torque).sum(1)], -1)
    assert np.abs((again - produced) / scale).max() < 1e-10
    assert np.abs((point @ res.up) - res.floor).max() < 1e-12  # the centres of pressure are on the floor
    assert np.abs(np.cross(torque, res.up)).max() < 1e-9 * res.weight  # the free torque is about up


def test_flight_leaves_the_whole_wrench_as_residual(walk):
    """With nothing near the floor (the floor 1 m below the capture's) no vertex touches: no
    force, and the residual is the required wrench itself."""
    res, _, _ = residuals_of(walk, WALK, floor=walk[3] - 1.0)
    assert not np.asarray(res.contacts.active).any() and res.flight.all()
    assert np.all(res.ground.force == 0.0)
    np.testing.assert_array_equal(res.residual, res.required)
    summary = rs.residual_summary(res)
    assert summary["flight_phases"] == 1 and summary["contact_fraction"] == 0.0
    assert summary["flight_force_rms_N"] == pytest.approx(np.sqrt(np.mean(np.sum(res.required[:, :3] ** 2, -1))))


def test_contact_feedforward_leaves_the_residual_on_the_root(walk, stepping):
    """The discrete inverse with the ground reaction forces as known external forces: its root
    rows carry the residual alone (round-off), so a free root misses only that; the ankles'
    torques change (the ground now holds the body up), and the reference takes the new tau."""
    res, ref, traj = stepping
    character, _, options, _ = walk
    model = character.model
    pos, rot = (np.asarray(a) for a in grid_poses_jit(model, traj, ref.time))
    external = grf.body_wrenches(model, res.contacts, res.ground.force, pos)
    tau, lam, kkt = grf.contact_feedforward(model, options, ref, quat_grid(walk, ref), external)
    assert float(np.max(kkt)) < 1e-10
    root = np.asarray(grf.root_wrench_about(model, np.asarray(lam)[:, :6], pos[:-1], rot[:-1], res.com))
    scale = np.array([res.weight] * 3 + [res.weight * res.stature] * 3)
    assert np.abs((root - res.residual) / scale).max() < 1e-9
    assert np.abs(res.residual[:, :3]).max() < 0.5 * np.abs(res.required[:, :3]).max()  # the ground explains most
    changed = np.abs(np.asarray(tau) - np.asarray(ref.tau[:-1])).max(0)
    assert changed.max() > 10.0  # N m: a stance joint's torque
    new, again = rs.ground_reference(character, traj, ref, options, res)  # what a free-root run calls
    assert again is res
    np.testing.assert_allclose(np.asarray(new.tau[:-1]), np.asarray(tau), rtol=0, atol=1e-9 * np.abs(tau).max())
    assert new.activation.shape == ref.activation.shape and not np.allclose(new.activation, ref.activation)


def test_run_file_fields_round_trip_and_are_checked(stepping, tmp_path):
    """The residual fields go into RUN.npz and come back unchanged; runfile checks their shapes,
    that they come together and that the summary is JSON."""
    res, _, _ = stepping
    arrays = rs.residual_arrays(res)
    assert set(arrays) == set(RESIDUAL_FIELDS)
    T = STEPS + 1
    base = {"time": np.arange(T) / 120.0, "theta": np.zeros((T, 3))}
    path = write_run(tmp_path / "RUN.npz", base, arrays)
    back = read_run(path, ("time", "theta"))
    for k, v in arrays.items():
        np.testing.assert_array_equal(back[k], v)
    assert json.loads(str(back["residuals_json"]))["steps"] == STEPS
    broken = [
        ("grf_force", {**arrays, "grf_force": arrays["grf_force"][:, :1]}),
        ("residual_moment", {k: v for k, v in arrays.items() if k != "residual_moment"}),
        ("contact_points", {**arrays, "contact_points": -arrays["contact_points"] - 1}),
        ("residuals_json", {**arrays, "residuals_json": np.asarray("[1]")}),
    ]
    for field, bad in broken:
        path = write_run(tmp_path / f"bad_{field}.npz", base, bad)
        with pytest.raises(RunFileError, match=field):
            read_run(path, ("time", "theta"))


def test_opensim_files_have_the_loads_and_residual_columns(walk, stepping, tmp_path):
    """external_loads.sto has each contact body's force, point and torque (OpenSim's ground
    frame: up is +Y) and external_loads.xml an ExternalForce per body reading them;
    residuals.sto has the residual force, moment and point."""
    res, _, _ = stepping
    character = walk[0]
    arrays = {"time": np.arange(STEPS + 1) / 120.0, **rs.residual_arrays(res)}
    files = nos.write_ground_storage(tmp_path, character, arrays)
    names = [nos.layout(character.model).bodies[b] for b in arrays["grf_body"]]
    assert names == ["LeftFoot", "RightFoot"]

    def table(path):
        lines = path.read_text().splitlines()
        head = lines.index("endheader")
        return lines[head + 1].split("\t"), np.array([[float(x) for x in ln.split("\t")] for ln in lines[head + 2:]])

    labels, data = table(files["external_loads"])
    assert labels == ["time"] + [f"{b}_{k}{a}" for b in names for k in ("force_v", "force_p", "torque_") for a in "xyz"]
    vertical = sum(data[:, labels.index(f"{b}_force_vy")] for b in names)
    np.testing.assert_allclose(vertical, arrays["grf_force"].sum(1) @ res.up, atol=1e-9 * res.weight)
    labels, data = table(files["residuals"])
    assert labels == ["time"] + [f"residual_{k}_{a}" for k in ("force", "moment", "point") for a in "xyz"]
    np.testing.assert_allclose(data[:, 1 + 1], arrays["residual_force"] @ res.up, atol=1e-9)
    xml = ET.parse(files["external_loads_setup"]).getroot()
    forces = xml.findall(".//ExternalForce")
    assert [f.findtext("applied_to_body") for f in forces] == names
    assert xml.findtext(".//datafile") == "external_loads.sto"


def test_contact_thresholds_decide_touching(walk, stepping):
    """A vertex touches when it is both low and slow: stricter thresholds keep a subset."""
    res, ref, traj = stepping
    character, _, options, floor = walk
    model = character.model
    pos, rot = grid_poses_jit(model, traj, ref.time)
    verts, valid = grf.body_vertices(character.shapes)
    strict = grf.capture_contacts(model, verts, valid, pos, rot, floor, options.h, 0.04, 0.1)
    active = np.asarray(res.contacts.active)
    assert np.all(np.asarray(strict.active) <= active) and np.asarray(strict.active).sum() < active.sum()
    height, speed = np.asarray(res.contacts.height), np.asarray(res.contacts.speed)
    np.testing.assert_array_equal(active, (height < grf.CONTACT_HEIGHT) & (speed < grf.CONTACT_SPEED))


def test_simulate_writes_residuals_when_asked(tmp_path):
    """A driven run's RUN.npz has the residuals with ``--residuals`` (and the .sto with
    ``--opensim-dir``), not without: they cost a second inverse problem per step."""
    from neuromotor import cli

    cfg = tmp_path / "c.toml"
    cfg.write_text('[sim]\nstart = 0.5\nduration = 0.3\n[[perturbation]]\nbody = "chest"\nmagnitude = 100.0\nstart = 0.6\n')
    plain, asked = tmp_path / "plain.npz", tmp_path / "asked.npz"
    assert cli.main(["simulate", str(cfg), "-o", str(plain), "--quiet"]) == 0
    assert cli.main(["simulate", str(cfg), "-o", str(asked), "--quiet", "--residuals", "--opensim-dir",
                     str(tmp_path / "osim")]) == 0
    a, b = np.load(plain), np.load(asked)
    assert "residual_force" not in a.files and b["residual_force"].shape == (37, 3)
    np.testing.assert_array_equal(a["theta"], b["theta"])  # the run itself is the same
    assert (tmp_path / "osim" / "residuals.sto").is_file() and (tmp_path / "osim" / "external_loads.xml").is_file()
