"""Issue 2: skeleton, mass model and inverse dynamics (Eq. 3) on real mocap."""

import json
import subprocess
import sys

import jax.numpy as jnp
import numpy as np
import pytest

from neuromotor.model.bvh import parse_bvh
from neuromotor.physics.inverse import idyn_arrays, inverse_dynamics, mocap_angles, sim_columns
from neuromotor.model.kinematics import body_kinematics, trajectory_from_clip
from neuromotor.studies.simulate import load_character
from neuromotor.model.skeleton import build_character
from neuromotor.physics.system import (
    constraint_jacobian,
    dof_axes,
    external_forces,
    kkt_matrix,
    mass_matrix,
    muscle_jacobian,
)


@pytest.fixture(scope="module")
def loaded(clip_path):
    return load_character(clip_path)


def test_total_mass_is_adult(loaded):
    character, _ = loaded
    model = character.model
    total = float(model.mass.sum())
    assert 50.0 <= total <= 100.0, total
    assert float(model.mass.min()) > 0.05  # no ill-conditioned tiny bodies
    eig = np.linalg.eigvalsh(np.asarray(model.inertia))
    assert eig.min() > 0


def test_walk_detail_is_not_simulated_but_zero_length_hands_and_head_are():
    """The walk clip's toes are extremity detail (no body, DOFs follow the capture); its head and
    hands end in zero-length End Sites yet get their anthropometric segments and DOFs."""
    character, _ = load_character(pytest.importorskip("conftest").CLIPS["walk"])
    model = character.model
    for name in ("LeftToe", "RightToe"):
        assert model.joint_body[model.joint_names.index(name)] == -1
        assert not any(d.startswith(name + ".") for d in model.dof_names)
        assert any(d.startswith(name + ".") for d in model.all_dof_names)
    for name in ("Head", "LeftHand", "RightHand"):
        b = model.joint_body[model.joint_names.index(name)]
        assert b >= 0 and float(model.mass[b]) > 0.2
        assert sum(d.startswith(name + ".") for d in model.dof_names) == 3
    assert model.n_dofs == 3 * (model.n_bodies - 1)


def test_eq3_residual_every_frame(loaded):
    character, traj = loaded
    clip = character.clip
    arrays = idyn_arrays(character.model, traj, np.arange(clip.n_frames) * clip.frame_time)
    assert arrays["kkt_residual"].max() < 1e-10
    T, n_all = len(arrays["time"]), len(character.model.all_dof_names)
    assert arrays["tau"].shape == (T, n_all) and arrays["theta"].shape == (T, n_all)
    assert arrays["joint_torque_world"].shape == (T, len(clip.joints), 3)
    assert np.all(arrays["joint_torque_world"][:, 0] == 0)
    assert arrays["root_wrench"].shape == (T, 6)
    # Root wrench carries the whole body's weight on average (root driven, no floor).
    mean_force = arrays["root_wrench"][:, :3].mean(0)
    weight = float(character.model.mass.sum()) * 9.81
    assert abs(mean_force[1] - weight) < 0.25 * weight


def test_eq1_holds_with_mocap_accelerations(loaded):
    """The KKT matrix of Eq. 1 times [a; lam; tau] reproduces f_ext, and J a + Jdot v = 0."""
    character, traj = loaded
    model = character.model
    t = jnp.asarray(0.37 * float(traj.duration))
    q, qd, qdd = traj.q(t), traj.qd(t), traj.qdd(t)
    _, rot, vel, omega, acc, alpha = body_kinematics(model, q, qd, qdd)
    theta = mocap_angles(model, traj, t)[0][sim_columns(model)]
    axes = dof_axes(model, rot, theta)
    sol = inverse_dynamics(model, traj, t[None])
    a = jnp.concatenate([acc, alpha], -1).reshape(-1)
    x = jnp.concatenate([a, sol.lam[0], sol.tau[0]])
    kkt = kkt_matrix(model, rot, axes)
    top = (kkt @ x)[: 6 * model.n_bodies]
    f = external_forces(model, rot, omega)
    assert float(jnp.linalg.norm(top - f) / jnp.linalg.norm(f)) < 1e-10
    # Velocity-level consistency of the mocap with the ball joints: J v = 0 on joint rows.
    v = jnp.concatenate([vel, omega], -1).reshape(-1)
    jv = constraint_jacobian(model, rot) @ v
    assert float(jnp.max(jnp.abs(jv[6:]))) < 1e-10
    # Blocks of Eq. 1 are the assembled M, J, H.
    n6 = 6 * model.n_bodies
    np.testing.assert_allclose(kkt[:n6, :n6], mass_matrix(model, rot))
    np.testing.assert_allclose(kkt[n6:, :n6], constraint_jacobian(model, rot))
    np.testing.assert_allclose(kkt[:n6, n6 + model.n_constraints:], -muscle_jacobian(model, axes).T)


def test_zero_length_inner_bone_gets_padded_body():
    text = """HIERARCHY
ROOT Hips
{
  OFFSET 0 0 0
  CHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation
  JOINT Spine
  {
    OFFSET 0 0.3 0
    CHANNELS 3 Zrotation Xrotation Yrotation
    JOINT Twist
    {
      OFFSET 0 0 0
      CHANNELS 3 Zrotation Xrotation Yrotation
      JOINT Neck
      {
        OFFSET 0 0 0
        CHANNELS 3 Zrotation Xrotation Yrotation
        End Site
        {
          OFFSET 0 0.4 0
        }
      }
    }
  }
}
MOTION
Frames: 5
Frame Time: 0.033333
""" + "\n".join("0 1 0 0 0 0 0 0 0 0 0 0 0 0 0" for _ in range(5)) + "\n"
    clip = parse_bvh(text, "zero.bvh", units="m")
    model = build_character(clip).model
    twist = model.joint_body[model.joint_names.index("Twist")]
    assert twist >= 0  # a padded body keeps the chain a proper tree of ball joints
    assert float(model.mass[twist]) > 0.01
    assert model.n_dofs == 3 * (model.n_bodies - 1)
    traj = trajectory_from_clip(model, clip)
    sol = inverse_dynamics(model, traj, jnp.linspace(0.0, 0.1, 4))
    assert float(sol.residual.max()) < 1e-10


def _cli(*args):
    return subprocess.run([sys.executable, "-m", "neuromotor.cli", *args], capture_output=True, text=True)


def test_cli_inspect_json_contract(clip_path):
    out = _cli("inspect", str(clip_path), "--json")
    assert out.returncode == 0, out.stderr
    data = json.loads(out.stdout)
    assert len(data["gravity"]) == 3
    joint = data["joints"][1]
    assert set(joint) >= {"name", "parent", "offset", "channels", "dofs", "body"}
    assert data["joints"][0]["parent"] is None
    body = next(j["body"] for j in data["joints"] if j["body"])
    assert set(body) == {"mass", "com", "inertia"}
    assert 50 < sum(j["body"]["mass"] for j in data["joints"] if j["body"]) < 100


def test_cli_idyn_writes_contract_and_fails_cleanly(tmp_path, clip_path):
    out = tmp_path / "id.npz"
    res = _cli("idyn", str(clip_path), "-o", str(out))
    assert res.returncode == 0, res.stderr
    data = np.load(out)
    for key in ("time", "dof_names", "theta", "theta_dot", "theta_ddot", "tau", "root_pos", "root_quat",
                "root_lin_vel", "root_ang_vel", "root_lin_acc", "root_ang_acc", "joint_torque_world",
                "root_wrench", "kkt_residual"):
        assert key in data, key
    assert data["kkt_residual"].max() < 1e-10
    bad = tmp_path / "bad.bvh"
    bad.write_text(clip_path.read_text()[:-2000])  # truncated motion block
    target = tmp_path / "bad.npz"
    res = _cli("idyn", str(bad), "-o", str(target))
    assert res.returncode != 0
    assert "bad.bvh:" in res.stderr  # names the file and the line
    assert not target.exists()
    assert not list(tmp_path.glob(".bad*"))
