"""Write a simulated run back as BVH in the source clip's skeleton, channel orders and units.

Simulated DOFs take the simulated Euler angles and the root takes the simulated root body's
pose (``body_pos``, ``body_quat``: the driven path, a sled's added path, or wherever a free root
went); any channel that is not simulated takes the mocap's values at the simulation times (a
``[sim] still`` run: at the held pose's clip time, ``clip_still``). The frame time is the
simulation step.
"""

from __future__ import annotations

import dataclasses
import pathlib

import jax.numpy as jnp
import numpy as np

from neuromotor.errors import UserError
from neuromotor.io.opensim import root_pose_of_bodies
from neuromotor.io.runfile import EXPORT_FIELDS, read_run
from neuromotor.model.bvh import read_bvh, write_bvh
from neuromotor.model.clip_edit import forward_kinematics
from neuromotor.model.load import load_character
from neuromotor.rotations import continuous_angles, matrix_to_euler

# The root is the simulated one: where the run put it, not where the capture was.
FIELDS = EXPORT_FIELDS + ("body_pos", "body_quat")


def export_bvh(run_path, out_path) -> pathlib.Path:
    run = read_run(run_path, FIELDS)
    units: str | float = str(run["source_units"])
    try:
        units = float(units)
    except ValueError:
        pass
    character, _ = load_character(str(run["source_clip"]), units, int(run["up_axis"]))
    # Written in the file's own skeleton: a virtual root removed for the model is put back.
    clip, model = character.source, character.model
    if tuple(str(n) for n in run["dof_names"]) != model.dof_names:
        raise UserError(f"{run_path}: its DOFs do not match the clip {clip.path}")
    times = np.asarray(run["time"])
    if "clip_still" in run:  # a held pose: the capture at that one clip time, every frame
        times = np.full_like(times, float(run["clip_still"]))
    motion = np.zeros((len(times), clip.n_channels))
    # Every channel from the mocap first (file convention: degrees, metres)...
    frame_times = np.arange(clip.n_frames) * clip.frame_time
    raw = np.asarray(clip.motion, dtype=np.float64)
    for c in range(clip.n_channels):
        col = raw[:, c]
        is_rot = any(c in j.rotation_columns for j in clip.joints)
        if is_rot:
            col = np.rad2deg(np.unwrap(np.deg2rad(col)))
        motion[:, c] = np.interp(times, frame_times, col)
    # ...the root where the simulation put it (below a virtual root: relative to that root's
    # frame, which keeps the file's channels)...
    origin, rot = root_pose_of_bodies(model, run["body_pos"], run["body_quat"])
    _write_root(run_path, clip, motion, model.joint_names[0], origin, rot)
    # ...and the simulated DOFs from the run, continuous in time and starting on the mocap's
    # branch. RUN.npz files store them so already (run_arrays), and then they are written as
    # they are: the exported angle minus RUN.npz theta is exactly 0.
    columns = []
    for name in model.dof_names:
        joint_name, channel = name.rsplit(".", 1)
        joint = clip.joints[clip.joint_index(joint_name)]
        columns.append(joint.rotation_columns[joint.rotation_order.index(channel[0])])
    if columns:
        mocap = np.deg2rad(motion[:, columns])
        theta = continuous_angles(np.asarray(run["theta"], dtype=np.float64), mocap)
        motion[:, columns] = np.rad2deg(theta)
    sim_time = np.asarray(run["time"])
    step = float(sim_time[1] - sim_time[0]) if len(sim_time) > 1 else clip.frame_time
    out = dataclasses.replace(clip, frame_time=step, motion=motion)
    write_bvh(out_path, out)
    return pathlib.Path(out_path)


def _write_root(run_path, clip, motion, name: str, origin, rot) -> None:
    """The model root's channels (in place) from its world pose: origin (T, 3), rotation (T, 3, 3)
    (metres, the clip's world). A joint above it (a virtual root) keeps its channels; the pose is
    written relative to that joint's frame."""
    k = clip.joint_index(name)
    joint = clip.joints[k]
    if joint.parent >= 0:
        pos, rots, _ = forward_kinematics(dataclasses.replace(clip, motion=motion))
        parent_rot, parent_pos = rots[:, joint.parent], pos[:, joint.parent]
        origin = np.einsum("tba,tb->ta", parent_rot, origin - parent_pos)
        rot = np.einsum("tba,tbc->tac", parent_rot, rot)
    if not (joint.translation_columns and joint.rotation_order):
        raise UserError(
            f"{run_path}: the clip's root joint {name!r} has no position or no rotation channels in "
            f"{clip.path}: its simulated pose cannot be written as BVH"
        )
    motion[:, list(joint.translation_columns)] = origin
    ref = jnp.deg2rad(jnp.asarray(motion[:, list(joint.rotation_columns)]))
    ang = matrix_to_euler(jnp.asarray(rot), joint.rotation_order, ref)
    motion[:, list(joint.rotation_columns)] = np.rad2deg(np.asarray(ang))


def reread_angles(bvh_path, units, dof_names) -> np.ndarray:
    """Simulated-DOF channels of a BVH file, radians (used to check a round trip)."""
    clip = read_bvh(bvh_path, units=units)
    cols = []
    for name in dof_names:
        joint_name, channel = str(name).rsplit(".", 1)
        joint = clip.joints[clip.joint_index(joint_name)]
        cols.append(joint.rotation_columns[joint.rotation_order.index(channel[0])])
    return np.deg2rad(np.asarray(clip.motion)[:, cols])
