"""OpenSim export (neuromotor.io.opensim), checked by OpenSim itself: the model loads and
initializes with our total mass and our body frames, the .mot drives it, and OpenSim's inverse
dynamics on it gives our ``idyn`` generalized forces."""

from __future__ import annotations

import os
import pathlib

import jax.numpy as jnp
import numpy as np
import pytest

from neuromotor import cli
from neuromotor.io import opensim as nos
from neuromotor.model.kinematics import joint_frames
from neuromotor.physics.inverse import idyn_arrays
from neuromotor.rotations import matrix_to_quat, quat_to_matrix
from neuromotor.studies.simulate import load_character

try:
    import opensim as osim
except ImportError:  # optional extra: CI must have it
    if os.environ.get("CI"):
        pytest.fail("opensim is not installed (pip install -e .[test]); CI never skips a format check",
                    pytrace=False)
    pytest.skip("opensim is not installed (pip install -e .[test])", allow_module_level=True)

# The files for OpenSim: the default clip's spline sampled at 480 Hz from 1 s on, as many samples
# as the clip has frames (455, 0.95 s): the same array shapes as `idyn` on the clip's frames (the
# CLI test here, tests/physics/test_inverse_dynamics.py), so that idyn compiles once.
DENSE_HZ, DENSE_START = 480.0, 1.0


@pytest.fixture(scope="module", params=[None, 2], ids=["y_up", "z_up"])
def exported(request, tmp_path_factory):
    """Character (the default clip; its own up axis, Y, or Z forced), its idyn arrays on the DENSE_HZ
    grid, and the OpenSim files written from them."""
    character, traj = load_character(up_axis=request.param)
    folder = tmp_path_factory.mktemp("osim_out")
    dense = DENSE_START + np.arange(character.clip.n_frames) / DENSE_HZ
    arrays = idyn_arrays(character.model, traj, dense)
    files = nos.write_idyn_storage(folder, character, arrays)
    model = osim.Model(str(files["model"]))
    state = model.initSystem()
    return {"character": character, "traj": traj, "arrays": arrays, "files": files, "model": model,
            "state": state}


def _coordinates(model):
    cs = model.getCoordinateSet()
    return cs, [cs.get(i).getName() for i in range(cs.getSize())]


def _vec(v) -> np.ndarray:
    return np.array([v.get(i) for i in range(3)])


def test_model_loads_with_our_mass_and_coordinates(exported):
    model, state, character = exported["model"], exported["state"], exported["character"]
    ours = float(np.sum(character.model.mass))
    assert abs(model.getTotalMass(state) - ours) <= 1e-9 * ours
    _, names = _coordinates(model)
    assert names == list(nos.layout(character.model).coordinates)
    assert model.getNumBodies() == character.model.n_bodies
    bodies, ours_model = model.getBodySet(), character.model
    for b in range(bodies.getSize()):  # mass, COM and inertia about the COM, body frame, as read by OpenSim
        body = bodies.get(b)
        inertia = body.getInertia()
        got = np.concatenate([_vec(inertia.getMoments()), _vec(inertia.getProducts())])
        want = np.asarray(ours_model.inertia[b])[[0, 1, 2, 0, 0, 1], [0, 1, 2, 1, 2, 2]]
        assert body.getName() == nos.osim_name(ours_model.body_names[b])
        assert body.getMass() == pytest.approx(float(ours_model.mass[b]), rel=1e-12)
        assert np.abs(_vec(body.getMassCenter()) - np.asarray(ours_model.com[b])).max() < 1e-12
        assert np.abs(got - want).max() <= 1e-12 * np.abs(want).max()
    g = model.getGravity()
    assert np.allclose([g.get(0), g.get(1), g.get(2)], [0.0, -9.81, 0.0], atol=1e-12)  # Y-up, any clip


def test_motion_file_drives_the_model_to_our_body_frames(exported):
    """The .mot read back by OpenSim, its first row set on the model: every body frame in
    OpenSim's ground is ours turned by the ground rotation (Y-up), to 1e-12."""
    model, state, character = exported["model"], exported["state"], exported["character"]
    table = osim.TimeSeriesTable(str(exported["files"]["motion"]))
    labels = list(table.getColumnLabels())
    assert labels == list(nos.layout(character.model).coordinates)
    assert table.getTableMetaDataAsString("inDegrees") == "yes"
    assert table.getNumRows() == len(exported["arrays"]["time"])
    row = table.getRowAtIndex(0).to_numpy()
    cs, _ = _coordinates(model)
    for i in range(cs.getSize()):
        c = cs.get(i)
        c.setValue(state, np.deg2rad(row[i]) if c.getMotionType() == 1 else row[i], False)
    model.realizePosition(state)
    origins, rots = joint_frames(character.model, exported["traj"].q(jnp.asarray(DENSE_START)))
    turn = nos.ground_rotation(character.model.gravity)
    bodies = model.getBodySet()
    for b in range(bodies.getSize()):
        frame = bodies.get(b).getTransformInGround(state)
        k = character.model.body_joint[b]
        rot = np.array([[frame.R().get(i, j) for j in range(3)] for i in range(3)])
        assert np.abs(_vec(frame.p()) - turn @ np.asarray(origins[k])).max() < 1e-12
        assert np.abs(rot - turn @ np.asarray(rots[k])).max() < 1e-12


def _speed_order(model, state, n: int) -> np.ndarray:
    """For each coordinate, its index in the state's u (Simbody orders mobilities by tree)."""
    cs = model.getCoordinateSet()
    out = []
    for i in range(n):
        for j in range(n):
            cs.get(j).setSpeedValue(state, 1.0 if j == i else 0.0)
        u = state.getU()
        out.append(int(np.argmax([abs(u.get(j)) for j in range(u.size())])))
    return np.array(out)


def _root_rates(model, arrays):
    """Rates and accelerations of the root's channel angles from its angular velocity and
    acceleration: omega = sum h_i phidot_i, alpha = sum (h_i phiddot_i + hdot_i phidot_i)."""
    order = model.joint_order[0]
    rot = np.asarray(quat_to_matrix(arrays["root_quat"]))
    axes = nos.channel_axes(np.eye(3), nos.euler_angles(rot, order), order)  # rows h_i
    rate = np.linalg.solve(np.swapaxes(axes, -1, -2), arrays["root_ang_vel"][..., None])[..., 0]
    hdot = np.zeros_like(axes)
    hdot[:, 1] = np.cross(rate[:, :1] * axes[:, 0], axes[:, 1])
    hdot[:, 2] = np.cross(rate[:, :1] * axes[:, 0] + rate[:, 1:2] * axes[:, 1], axes[:, 2])
    rhs = arrays["root_ang_acc"] - np.einsum("tij,ti->tj", hdot, rate)
    return rate, np.linalg.solve(np.swapaxes(axes, -1, -2), rhs[..., None])[..., 0]


def _rates(character, arrays):
    """(coordinate rates, accelerations) of the exported model, in layout order."""
    model = character.model
    lay = nos.layout(model)
    sim = list(model.sim_dof_columns)
    qd = nos.motion_values(model, arrays["root_lin_vel"], np.eye(3)[None].repeat(len(arrays["time"]), 0),
                           arrays["theta_dot"][:, sim])
    qdd = nos.motion_values(model, arrays["root_lin_acc"], np.eye(3)[None].repeat(len(arrays["time"]), 0),
                            arrays["theta_ddot"][:, sim])
    rate, acc = _root_rates(model, arrays)
    root = list(lay.body_coordinates[0][:3])
    qd[:, root], qdd[:, root] = rate, acc
    return qd, qdd


def test_inverse_dynamics_solver_matches_idyn(exported):
    """OpenSim's InverseDynamicsSolver at our exact coordinates, rates and accelerations gives our
    generalized forces (idyn's joint torques on each coordinate's axis, root wrench) to 1e-9 of
    the largest (the weight): the two engines agree on the model, not just on a motion."""
    model, state, character, arrays = exported["model"], exported["state"], exported["character"], exported["arrays"]
    lay = nos.layout(character.model)
    theta = arrays["theta"][:, list(character.model.sim_dof_columns)]
    rot = np.asarray(quat_to_matrix(arrays["root_quat"]))
    q = nos.motion_values(character.model, arrays["root_pos"], rot, theta)
    qd, qdd = _rates(character, arrays)
    ours = nos.coordinate_forces(character.model, rot, theta, arrays["joint_torque_world"], arrays["root_wrench"])
    n = len(lay.coordinates)
    u_of = _speed_order(model, state, n)
    solver, cs = osim.InverseDynamicsSolver(model), model.getCoordinateSet()
    theirs = np.zeros_like(ours)
    for t in range(0, len(q), 6):  # every 6th sample keeps the test cheap
        for i in range(n):
            cs.get(i).setValue(state, q[t, i], False)
        for i in range(n):
            cs.get(i).setSpeedValue(state, qd[t, i])
        udot = osim.Vector(n, 0.0)
        for i in range(n):
            udot.set(int(u_of[i]), qdd[t, i])
        tau = solver.solve(state, udot)
        theirs[t] = [tau.get(int(u_of[i])) for i in range(n)]
    rows = slice(0, len(q), 6)
    assert np.abs(theirs[rows] - ours[rows]).max() <= 1e-9 * np.abs(ours).max()


def tool_agreement(model, character, files, folder) -> tuple[list, float, float]:
    """Run OpenSim's Inverse Dynamics Tool (no low-pass) on our motion file; return our .sto's
    column labels, and over the inner 80 % of the window (spline ends left out) the largest
    difference from our .sto over the body weight and the relative RMS difference."""
    tool = osim.InverseDynamicsTool()
    tool.setModel(model)
    tool.setCoordinatesFileName(str(files["motion"]))
    tool.setLowpassCutoffFrequency(-1)
    time = osim.TimeSeriesTable(str(files["motion"])).getIndependentColumn()
    tool.setStartTime(float(time[0]))
    tool.setEndTime(float(time[-1]))
    tool.setResultsDir(str(folder))
    tool.setOutputGenForceFileName("osim_id.sto")
    assert tool.run()
    theirs = osim.TimeSeriesTable(str(pathlib.Path(folder) / "osim_id.sto"))
    ours = osim.TimeSeriesTable(str(files["forces"]))
    labels, got = list(ours.getColumnLabels()), list(theirs.getColumnLabels())
    a = theirs.getMatrix().to_numpy()[:, [got.index(c) for c in labels]]
    b = ours.getMatrix().to_numpy()
    assert a.shape == b.shape
    inner = slice(len(b) // 10, len(b) - len(b) // 10)
    err = a[inner] - b[inner]
    weight = float(np.sum(character.model.mass)) * 9.81
    return labels, float(np.abs(err).max() / weight), float(np.sqrt(np.mean(err ** 2) / np.mean(b[inner] ** 2)))


def test_inverse_dynamics_tool_on_our_motion_file(exported, tmp_path):
    """OpenSim's Inverse Dynamics Tool (no low-pass) on our .mot gives our inverse_dynamics.sto:
    it fits a quintic GCV spline to the Euler angles sampled at 480 Hz where idyn differentiates
    a cubic spline of the joint quaternions through the 30 Hz frames, whose acceleration has a
    kink at every frame: the accelerations differ near the knots by O(sampling step)
    (docs/opensim.md has the errors at 30, 120 and 480 Hz). Inner 80 % of the window (spline
    ends left out): max error <= 1e-3 of the body weight (measured 3.3e-4), relative RMS
    <= 2e-4 (measured 4.6e-5)."""
    labels, max_err, rms = tool_agreement(exported["model"], exported["character"], exported["files"], tmp_path)
    assert labels == list(nos.layout(exported["character"].model).force_labels)
    assert max_err <= 1e-3 and rms <= 2e-4


def test_run_motion_from_body_poses_equals_the_idyn_motion(exported, tmp_path):
    """``simulate --opensim-dir`` writes its .mot from body poses; on the mocap's own poses it is
    idyn's .mot (same coordinates to 1e-9 deg or m)."""
    character, arrays = exported["character"], exported["arrays"]
    model = character.model
    theta = arrays["theta"][:, list(model.sim_dof_columns)]
    rot = nos.body_rotations(model, np.asarray(quat_to_matrix(arrays["root_quat"])), theta)
    origin = [arrays["root_pos"]]
    for b in range(1, model.n_bodies):  # forward kinematics: o = o_p + R_p d
        p, k = model.body_parent[b], model.body_joint[b]
        origin.append(origin[p] + rot[:, p] @ np.asarray(model.joint_offset[k]))
    pos = np.stack(origin, 1) + np.einsum("tbij,bj->tbi", rot, np.asarray(model.com))
    quat = np.asarray(matrix_to_quat(rot))
    run = {"time": arrays["time"], "theta": theta, "body_pos": pos, "body_quat": quat,
           "theta_unperturbed": theta, "body_pos_unperturbed": pos, "body_quat_unperturbed": quat}
    files = nos.write_run_storage(tmp_path, character, run)
    got, want = (osim.TimeSeriesTable(str(f)) for f in (files["perturbed"], exported["files"]["motion"]))
    assert list(got.getColumnLabels()) == list(want.getColumnLabels())
    assert np.abs(got.getMatrix().to_numpy() - want.getMatrix().to_numpy()).max() < 1e-9  # tables kept alive


@pytest.mark.parametrize("up", [[0, 0, -9.81], [0, 0, 9.81], [-9.81, 0, 0], [0, -9.81, 0], [0, 9.81, 0],
                                [3.0, -4.0, 0.0]])
def test_ground_rotation_takes_up_to_y(up):
    turn = nos.ground_rotation(np.asarray(up))
    assert np.allclose(turn @ turn.T, np.eye(3), atol=1e-14) and np.isclose(np.linalg.det(turn), 1.0)
    assert np.allclose(turn @ np.asarray(up), [0.0, -np.linalg.norm(up), 0.0], atol=1e-12)


def test_cli_export_osim_and_idyn_opensim_dir(tmp_path, capsys):
    """export-osim and idyn --opensim-dir on the embedded clip: the same model, a motion on the
    clip's frames that OpenSim reads, in degrees."""
    out = tmp_path / "model.osim"
    assert cli.main(["export-osim", "-o", str(out)]) == 0
    model = osim.Model(str(out))
    character, _ = load_character()
    total = float(np.sum(character.model.mass))
    assert abs(model.getTotalMass(model.initSystem()) - total) <= 1e-9 * total
    folder = tmp_path / "id"
    assert cli.main(["idyn", "-o", str(tmp_path / "id.npz"), "--opensim-dir", str(folder), "--quiet"]) == 0
    assert sorted(p.name for p in folder.iterdir()) == ["inverse_dynamics.sto", "model.osim", "motion.mot"]
    assert (folder / "model.osim").read_text() == out.read_text()
    storage = osim.Storage(str(folder / "motion.mot"))
    assert storage.getSize() == character.clip.n_frames and storage.isInDegrees()


def test_cli_export_osim_bad_clip_is_one_line_and_writes_nothing(tmp_path, capsys):
    bad = tmp_path / "bad.bvh"
    bad.write_text("HIERARCHY\nROOT Hips\n{\n")
    out = tmp_path / "model.osim"
    assert cli.main(["export-osim", str(bad), "-o", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "bad.bvh" in err and err.startswith("neuromotor export-osim: error:")
    assert not out.exists()
    folder = tmp_path / "id"
    folder.write_text("a file where the folder should be")
    assert cli.main(["idyn", str(bad), "-o", str(tmp_path / "x.npz"), "--opensim-dir", str(folder)]) == 2
    assert "exists and is not a directory" in capsys.readouterr().err
    assert not (tmp_path / "x.npz").exists()


if __name__ == "__main__":  # the figures of docs/opensim.md: python tests/io/test_opensim.py
    import sys
    import tempfile

    character, traj = load_character()
    for hz, start, seconds in ((30.0, 1.0, 13.0), (30.0, 1.0, 3.0), (120.0, 1.0, 3.0), (480.0, 1.0, 0.945)):
        with tempfile.TemporaryDirectory() as folder:
            times = start + np.arange(round(seconds * hz) + 1) / hz
            files = nos.write_idyn_storage(folder, character, idyn_arrays(character.model, traj, times))
            model = osim.Model(str(files["model"]))
            model.initSystem()
            _, max_err, rms = tool_agreement(model, character, files, folder)
        print(f"{hz:5.0f} Hz, t = {times[0]:.2f} .. {times[-1]:.2f} s: max |ID tool - idyn| = {max_err:.2e} "
              f"of the body weight, relative RMS {rms:.2e}", file=sys.stdout, flush=True)


def test_external_loads_enter_opensim_inverse_dynamics_as_our_ground_reaction_forces(tmp_path):
    """The capture's ground reaction forces (issue 38, studies/residuals.py) as OpenSim's
    ExternalLoads: its Inverse Dynamics Tool with them, less without them, is minus their
    generalized forces on the root: their sum on the translations and their moment about the
    root joint's origin on the rotation axes (1e-6 N and N m; measured 1e-8), whatever the
    accelerations OpenSim estimates (the same motion both times). The walk, 4.6-4.8 s, where
    the left foot leaves the ground."""
    from conftest import CLIPS
    from neuromotor.physics.dynamics import StepOptions, make_reference
    from neuromotor.studies import residuals as rs

    character, traj = load_character(CLIPS["walk"])
    model, options = character.model, StepOptions(n_steps=24)
    ref = make_reference(model, traj, 4.6, options)
    arrays = {"time": np.asarray(ref.time), **rs.residual_arrays(rs.capture_residuals(character, traj, ref, options))}
    loads = nos.write_ground_storage(tmp_path, character, arrays)
    osim_model = nos.export_osim(character, tmp_path / "model.osim")
    motion = nos.write_motion(tmp_path / "motion.mot", model, ref.time, ref.root_origin, ref.root_rot, ref.theta)

    def tool_forces(external: bool):
        model_ = osim.Model(str(osim_model))  # kept alive: the tool holds a bare pointer to it
        model_.initSystem()
        tool = osim.InverseDynamicsTool()
        tool.setModel(model_)
        tool.setCoordinatesFileName(str(motion))
        tool.setLowpassCutoffFrequency(-1)
        tool.setStartTime(float(ref.time[0]))
        tool.setEndTime(float(ref.time[-1]))
        if external:
            tool.setExternalLoadsFileName(str(loads["external_loads_setup"]))
        name = f"id_{external}.sto"
        tool.setResultsDir(str(tmp_path))
        tool.setOutputGenForceFileName(name)
        assert tool.run()
        table = osim.TimeSeriesTable(str(tmp_path / name))
        return list(table.getColumnLabels()), np.array(table.getMatrix().to_numpy())

    labels, with_loads = tool_forces(True)
    labels_without, without = tool_forces(False)
    assert labels_without == labels
    diff = with_loads - without
    force = arrays["grf_force"].sum(1)
    assert np.abs(force[:, 1]).max() > 300.0  # N: the feet bear the body
    origin = np.asarray(ref.root_origin)
    moment = (np.cross(arrays["grf_point"] - origin[:, None], arrays["grf_force"]) + arrays["grf_torque"]).sum(1)
    order = model.joint_order[model.body_joint[0]]
    axes = nos.channel_axes(np.eye(3), nos.euler_angles(np.asarray(ref.root_rot), order), order)
    root = nos.layout(model).bodies[0]
    for i, a in enumerate("XYZ"):
        assert np.abs(diff[:, labels.index(f"{root}_{a}position_force")] + force[:, i]).max() < 1e-6
    for i, a in enumerate(order):
        generalized = np.einsum("tj,tj->t", axes[:, i], moment)
        assert np.abs(diff[:, labels.index(f"{root}_{a}rotation_moment")] + generalized).max() < 1e-6
