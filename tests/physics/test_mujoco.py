"""Cross-check against MuJoCo: the MJCF export and our inverse dynamics (Eq. 3) vs ``mj_inverse``.

Conventions (see ``neuromotor.io.mjcf``):

* free joint: qpos = [root joint origin (world), root quaternion w x y z]; qvel = [origin velocity
  (world), angular velocity in the root body's frame]; qacc = [origin acceleration (world),
  R^T alpha] (d/dt (R^T omega) = R^T alpha since omega x omega = 0); generalized force =
  [force at the body origin (world), torque about the body origin (root body frame)], checked
  below on a single free body by an explicit experiment;
* hinges: qpos/qvel/qacc = our Euler angles and their derivatives; generalized force
  Q_i = h_i . T_joint with T_joint = sum_j h_j tau_j (our Eq. 3 multipliers), i.e. A^T A tau per
  joint with A = [h1 h2 h3].
"""

import xml.etree.ElementTree as ET

import jax
import jax.numpy as jnp
import numpy as np
import pytest

mujoco = pytest.importorskip("mujoco")

from conftest import ALL_CLIPS  # noqa: E402
from neuromotor.physics.inverse import mocap_angles, sim_columns, solve_eq3  # noqa: E402
from neuromotor.model.kinematics import body_kinematics  # noqa: E402
from neuromotor.io.mjcf import export_mjcf, model_to_mjcf  # noqa: E402
from neuromotor.studies.simulate import load_character  # noqa: E402

N_FRAMES = 20
RTOL = 1e-6


@pytest.fixture(scope="module", params=sorted(ALL_CLIPS), ids=str)
def loaded(request):
    """Every shipped clip (a CMU conversion with fingers, a ground-marker rig, ...)."""
    return load_character(ALL_CLIPS[request.param])


def test_export_loads_in_mujoco(loaded, tmp_path):
    character, _ = loaded
    model = character.model
    path = export_mjcf(character, tmp_path / "sub" / "character.xml")
    ET.parse(path)  # well-formed XML
    assert not [p for p in path.parent.iterdir() if p.name != path.name]  # no temp file left
    m = mujoco.MjModel.from_xml_path(str(path))
    assert m.nbody == model.n_bodies + 1
    assert m.nv == 6 + model.n_dofs
    assert m.nu == model.n_dofs
    assert m.njnt == 1 + model.n_dofs
    assert abs(float(np.sum(m.body_mass)) - float(model.mass.sum())) < 1e-9
    np.testing.assert_allclose(m.opt.gravity, np.asarray(model.gravity))
    for b, name in enumerate(model.body_names):
        assert abs(m.body(name).mass[0] - float(model.mass[b])) < 1e-12
    for name in model.dof_names:
        assert m.joint(name).type == mujoco.mjtJoint.mjJNT_HINGE
        assert m.actuator(name).gainprm[0] == 100.0
    assert m.jnt_type[0] == mujoco.mjtJoint.mjJNT_FREE
    assert (m.geom_contype == 0).all() and (m.geom_conaffinity == 0).all()


def test_free_joint_force_convention():
    """A free body at rest: mj_inverse's free-joint force for a known acceleration is
    [world force at the body origin, torque about the origin in the body frame]."""
    xml = """<mujoco><option gravity="0 0 0"/><worldbody><body>
      <freejoint/><inertial pos="0.1 -0.2 0.3" mass="2" diaginertia="0.1 0.2 0.3"/>
      </body></worldbody></mujoco>"""
    m = mujoco.MjModel.from_xml_string(xml)
    d = mujoco.MjData(m)
    quat = np.array([0.8, 0.2, -0.4, 0.4])
    quat /= np.linalg.norm(quat)
    d.qpos[:] = [1.0, 2.0, 3.0, *quat]
    d.qacc[:] = [0.0, 0.0, 0.0, 0.0, 0.0, 0.0]
    d.qacc[0:3] = [0.3, -0.7, 1.1]  # pure translation, no rotation
    mujoco.mj_inverse(m, d)
    rot = np.zeros(9)
    mujoco.mju_quat2Mat(rot, quat)
    rot = rot.reshape(3, 3)
    force = 2.0 * d.qacc[0:3]
    lever = rot @ np.array([0.1, -0.2, 0.3])  # origin -> COM, world
    np.testing.assert_allclose(d.qfrc_inverse[0:3], force, atol=1e-12)
    np.testing.assert_allclose(d.qfrc_inverse[3:6], rot.T @ np.cross(lever, force), atol=1e-12)


@pytest.fixture(scope="module")
def ours(loaded):
    """Our Eq. 3 solution and the matching MuJoCo state on N_FRAMES frames (jit once, vmap)."""
    character, traj = loaded
    model = character.model
    times = jnp.linspace(0.02, 0.98, N_FRAMES) * traj.duration
    cols = sim_columns(model)

    def one(t):
        q, qd, qdd = traj.q(t), traj.qd(t), traj.qdd(t)
        theta, theta_dot, theta_ddot = mocap_angles(model, traj, t)
        lam, tau, axes, res = solve_eq3(model, q, qd, qdd, theta[cols])
        pos, rot, _, omega, _, alpha = body_kinematics(model, q, qd, qdd)
        r0 = rot[0]
        quat = q[3:7] / jnp.linalg.norm(q[3:7])
        qpos = jnp.concatenate([q[0:3], quat, theta[cols]])
        qvel = jnp.concatenate([qd[0:3], r0.T @ omega[0], theta_dot[cols]])
        qacc = jnp.concatenate([qdd[0:3], r0.T @ alpha[0], theta_ddot[cols]])
        return dict(qpos=qpos, qvel=qvel, qacc=qacc, lam=lam, tau=tau, axes=axes, rot0=r0, res=res,
                    com_pos=pos, rot=rot)

    out = jax.jit(jax.vmap(one))(times)
    return {k: np.asarray(v) for k, v in out.items()}


def test_inverse_dynamics_matches_mj_inverse(loaded, ours):
    character, _ = loaded
    model = character.model
    m = mujoco.MjModel.from_xml_string(model_to_mjcf(character))
    m.opt.disableflags |= mujoco.mjtDisableBit.mjDSBL_CONTACT
    assert np.all(m.dof_armature == 0) and np.all(m.dof_damping == 0)
    d = mujoco.MjData(m)
    assert ours["res"].max() < 1e-10
    # MuJoCo dof address of each of our DOFs, and each of our bodies' DOF groups.
    dof_adr = np.array([m.joint(name).dofadr[0] for name in model.dof_names])
    groups = [np.array(model.dofs_of_body(b)) for b in range(1, model.n_bodies)]
    assert sorted(dof_adr.tolist()) == list(range(6, m.nv))
    qpos_adr = np.array([m.joint(name).qposadr[0] for name in model.dof_names])

    worst_hinge, worst_root = 0.0, 0.0
    for f in range(N_FRAMES):
        d.qpos[0:7] = ours["qpos"][f, 0:7]
        d.qpos[qpos_adr] = ours["qpos"][f, 7:]
        d.qvel[0:6] = ours["qvel"][f, 0:6]
        d.qvel[dof_adr] = ours["qvel"][f, 6:]
        d.qacc[0:6] = ours["qacc"][f, 0:6]
        d.qacc[dof_adr] = ours["qacc"][f, 6:]
        mujoco.mj_inverse(m, d)
        # The forward kinematics of MuJoCo and ours agree (same joint convention).
        mj_hinge = d.qfrc_inverse[dof_adr]
        tau, axes = ours["tau"][f], ours["axes"][f]
        expected = np.zeros_like(tau)
        for dofs in groups:
            a = axes[dofs].T  # columns h_i
            expected[dofs] = a.T @ (a @ tau[dofs])
        err = np.linalg.norm(mj_hinge - expected) / np.linalg.norm(expected)
        worst_hinge = max(worst_hinge, err)
        lam, r0 = ours["lam"][f], ours["rot0"][f]
        root_expected = np.concatenate([lam[0:3], r0.T @ lam[3:6]])
        err = np.linalg.norm(d.qfrc_inverse[0:6] - root_expected) / np.linalg.norm(root_expected)
        worst_root = max(worst_root, err)
    print(f"\nworst relative error: hinges {worst_hinge:.2e}, root {worst_root:.2e}")
    assert worst_hinge < RTOL, worst_hinge
    assert worst_root < RTOL, worst_root


def test_mujoco_forward_kinematics_matches(loaded, ours):
    """Body poses of MuJoCo at our qpos equal ours (the Euler convention maps exactly)."""
    character, _ = loaded
    model = character.model
    m = mujoco.MjModel.from_xml_string(model_to_mjcf(character))
    d = mujoco.MjData(m)
    qpos_adr = np.array([m.joint(name).qposadr[0] for name in model.dof_names])
    for f in range(N_FRAMES):
        d.qpos[0:7] = ours["qpos"][f, 0:7]
        d.qpos[qpos_adr] = ours["qpos"][f, 7:]
        mujoco.mj_kinematics(m, d)
        for b, name in enumerate(model.body_names):
            np.testing.assert_allclose(d.body(name).xmat.reshape(3, 3), ours["rot"][f, b], atol=1e-9)
            np.testing.assert_allclose(d.body(name).xipos, ours["com_pos"][f, b], atol=1e-9)
