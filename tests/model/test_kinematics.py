"""Batched kinematics and the Eq. 3 assembly against plain joint-by-joint references.

The setup programs (reference kinematics, inverse dynamics of Eq. 3) work on all joints at once:
one quaternion-to-matrix call, one Euler decomposition per rotation order, forward kinematics as
one loop body differentiated by the product rule, and ``[J^T H^T]`` placed by a static gather.
Here they are checked against the straightforward per-joint recursion (with ``jax.jvp`` for the
derivatives) and the dense assembly of :mod:`neuromotor.physics.system`, on both real clips and on a
hand-made skeleton with mixed rotation orders and massless joints with and without channels.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from neuromotor.model.bvh import parse_bvh
from neuromotor.physics.inverse import eq3_matrix, sim_columns, solve_eq3
from neuromotor.model.kinematics import (
    body_kinematics,
    joint_angles_from_q,
    joint_dof_columns,
    joint_frames,
    local_rotations,
    rotating_joints,
    trajectory_from_clip,
)
from neuromotor.rotations import matrix_to_euler, quat_to_matrix, vee
from neuromotor.studies.record import joint_frames_from_state
from neuromotor.studies.simulate import load_character
from neuromotor.model.skeleton import build_character
from neuromotor.physics.system import (
    constraint_jacobian,
    dof_axes,
    external_forces,
    mass_matrix,
    muscle_jacobian,
)

RTOL = 1e-12

MIXED_BVH = """HIERARCHY
ROOT Hips
{
  OFFSET 0 0 0
  CHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation
  JOINT Spine
  {
    OFFSET 0 0.25 0.01
    CHANNELS 3 Xrotation Yrotation Zrotation
    JOINT Neck
    {
      OFFSET 0.01 0.3 0
      CHANNELS 3 Yrotation Zrotation Xrotation
      JOINT Head
      {
        OFFSET 0 0.12 0.02
        End Site
        {
          OFFSET 0 0 0
        }
      }
    }
  }
  JOINT LeftUpLeg
  {
    OFFSET 0.1 -0.05 0
    CHANNELS 3 Zrotation Yrotation Xrotation
    JOINT LeftLeg
    {
      OFFSET 0 -0.42 0.01
      CHANNELS 3 Xrotation Zrotation Yrotation
      JOINT LeftToe
      {
        OFFSET 0.02 -0.4 0.1
        CHANNELS 3 Yrotation Xrotation Zrotation
        End Site
        {
          OFFSET 0 0 0
        }
      }
    }
  }
}
"""


def mixed_clip(n_frames: int = 12):
    """A skeleton with four rotation orders, a massless joint without channels (Head) and a
    massless joint with channels (LeftToe), moving smoothly through large angles."""
    t = np.arange(n_frames)[:, None] / n_frames
    rng = np.random.default_rng(0)
    amp, phase = rng.uniform(20.0, 70.0, (1, 21)), rng.uniform(0.0, 6.0, (1, 21))
    motion = amp * np.sin(2.0 * np.pi * t + phase)
    motion[:, 0:3] = 0.3 * motion[:, 0:3] / 70.0  # root position in metres
    text = MIXED_BVH + f"MOTION\nFrames: {n_frames}\nFrame Time: 0.0333333\n"
    text += "\n".join(" ".join(f"{x:.6f}" for x in row) for row in motion) + "\n"
    return parse_bvh(text, "mixed.bvh", units="m")


@pytest.fixture(scope="module", params=["mixed", "mocapbank", "walk"])
def loaded(request):
    if request.param == "mixed":
        clip = mixed_clip()
        model = build_character(clip).model
        return model, trajectory_from_clip(model, clip)
    character, traj = load_character(pytest.importorskip("conftest").CLIPS[request.param])
    return character.model, traj


def _reference_local(model, q):
    out = [jnp.eye(3, dtype=q.dtype)] * len(model.joint_names)
    for slot, k in enumerate(rotating_joints(model)):
        quat = q[3 + 4 * slot: 7 + 4 * slot]
        out[k] = quat_to_matrix(quat / jnp.linalg.norm(quat))
    return out


def _reference_frames(model, q):
    local = _reference_local(model, q)
    origins, rots = [], []
    for k, parent in enumerate(model.joint_parent):
        if parent < 0:
            origins.append(q[0:3])
            rots.append(local[k])
        else:
            origins.append(origins[parent] + rots[parent] @ model.joint_offset[k])
            rots.append(rots[parent] @ local[k])
    return jnp.stack(origins), jnp.stack(rots)


def _reference_angles(model, q, reference):
    local = _reference_local(model, q)
    cols = joint_dof_columns(model)
    out = [matrix_to_euler(local[k], order, reference[jnp.array(cols[k])])
           for k, order in enumerate(model.joint_order) if model.joint_parent[k] >= 0 and order]
    return jnp.concatenate(out)


def _reference_body_kinematics(model, q, qd, qdd):
    def poses(x):
        origins, rots = _reference_frames(model, x)
        idx = jnp.array(model.body_joint)
        return origins[idx] + jnp.einsum("bij,bj->bi", rots[idx], model.com), rots[idx]

    def vel_fn(q_, qd_):
        (pos, rot), (vel, rot_dot) = jax.jvp(poses, (q_,), (qd_,))
        return (pos, rot), (vel, vee(rot_dot @ jnp.swapaxes(rot, -1, -2)))

    ((pos, rot), (vel, omega)), (_, (acc, alpha)) = jax.jvp(vel_fn, (q, qd), (qd, qdd))
    return pos, rot, vel, omega, acc, alpha


def _close(actual, expected, rtol=RTOL):
    actual, expected = np.asarray(actual), np.asarray(expected)
    assert actual.shape == expected.shape
    scale = max(float(np.max(np.abs(expected))), 1e-300)
    assert float(np.max(np.abs(actual - expected))) <= rtol * scale


def _samples(traj, n=5):
    return jnp.linspace(0.03, 0.97, n) * traj.duration


def test_batched_kinematics_equal_joint_by_joint_recursion(loaded):
    model, traj = loaded
    times = _samples(traj)
    q, qd, qdd = (jax.vmap(f)(times) for f in (traj.q, traj.qd, traj.qdd))
    ref = jax.vmap(traj.angle_reference)(times)

    @jax.jit
    def ours(q, qd, qdd, ref):
        return (jax.vmap(lambda x: local_rotations(model, x))(q), jax.vmap(lambda x: joint_frames(model, x))(q),
                jax.vmap(lambda x, r: joint_angles_from_q(model, x, r))(q, ref),
                jax.vmap(lambda a, b, c: body_kinematics(model, a, b, c))(q, qd, qdd))

    @jax.jit
    def reference(q, qd, qdd, ref):
        return (jax.vmap(lambda x: jnp.stack(_reference_local(model, x)))(q),
                jax.vmap(lambda x: _reference_frames(model, x))(q),
                jax.vmap(lambda x, r: _reference_angles(model, x, r))(q, ref),
                jax.vmap(lambda a, b, c: _reference_body_kinematics(model, a, b, c))(q, qd, qdd))

    for a, b in zip(jax.tree_util.tree_leaves(ours(q, qd, qdd, ref)),
                    jax.tree_util.tree_leaves(reference(q, qd, qdd, ref))):
        _close(a, b)


def test_eq3_assembly_equals_dense_blocks(loaded):
    """[J^T H^T] by static placement is entry for entry the dense assembly, and the solve of
    Eq. 3 matches the one with the dense mass matrix to round-off."""
    model, traj = loaded
    cols = sim_columns(model)

    @jax.jit
    def both(t):
        q, qd, qdd = traj.q(t), traj.qd(t), traj.qdd(t)
        theta = joint_angles_from_q(model, q, traj.angle_reference(t))[cols]
        _, rot, _, omega, acc, alpha = body_kinematics(model, q, qd, qdd)
        axes = dof_axes(model, rot, theta)
        dense = jnp.concatenate([constraint_jacobian(model, rot).T, muscle_jacobian(model, axes).T], 1)
        rhs = mass_matrix(model, rot) @ jnp.concatenate([acc, alpha], -1).reshape(-1)
        x = jnp.linalg.solve(dense, rhs - external_forces(model, rot, omega))
        lam, tau, _, residual = solve_eq3(model, q, qd, qdd, theta)
        return eq3_matrix(model, rot, axes), dense, jnp.concatenate([lam, tau]), x, residual

    for t in _samples(traj, 3):
        ours, dense, x, x_dense, residual = both(t)
        np.testing.assert_array_equal(np.asarray(ours), np.asarray(dense))
        _close(x, x_dense, 1e-10)
        assert float(residual) < 1e-10


def test_joint_frames_from_state_fill_massless_joints():
    """Skeleton drawing: joints with bodies come from the state, massless ones (with or without
    channels, chained) from their parent's frame and the mocap's local rotations."""
    clip = mixed_clip()
    model = build_character(clip).model
    assert model.joint_body[model.joint_names.index("Head")] < 0
    assert model.joint_body[model.joint_names.index("LeftToe")] < 0
    traj = trajectory_from_clip(model, clip)
    q = traj.q(jnp.asarray(0.1))
    origins, rots = _reference_frames(model, q)
    idx = np.array(model.body_joint)
    pos = origins[idx] + jnp.einsum("bij,bj->bi", rots[idx], model.com)
    got_o, got_r = joint_frames_from_state(model, pos, rots[idx], local_rotations(model, q))
    _close(got_o, origins)
    _close(got_r, rots)
