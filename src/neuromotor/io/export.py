"""Write a simulated run back as BVH in the source clip's skeleton, channel orders and units.

Simulated DOFs take the simulated Euler angles; the root (driven along the mocap) and any
channel that is not simulated take the mocap's values at the simulation times (a ``[sim] still``
run: at the held pose's clip time, ``clip_still``). The frame time is the simulation step.
"""

from __future__ import annotations

import dataclasses
import pathlib

import jax
import jax.numpy as jnp
import numpy as np

from neuromotor.errors import UserError
from neuromotor.io.runfile import EXPORT_FIELDS, read_run
from neuromotor.model.bvh import read_bvh, write_bvh
from neuromotor.model.load import load_character
from neuromotor.rotations import continuous_angles, matrix_to_euler, quat_to_matrix


def export_bvh(run_path, out_path) -> pathlib.Path:
    run = read_run(run_path, EXPORT_FIELDS)
    units: str | float = str(run["source_units"])
    try:
        units = float(units)
    except ValueError:
        pass
    character, traj = load_character(str(run["source_clip"]), units, int(run["up_axis"]))
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
    # ...the root exactly on the splined path it was driven along (a virtual root and the
    # joint below it keep the file's channels: together they are that path)...
    root = clip.joints[0]
    if root.name == model.joint_names[0]:
        _write_root(motion, root, np.asarray(jax.vmap(traj.q)(jnp.asarray(times))))
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


def _write_root(motion, root, q):
    """Root channels (in place) from spline coordinates q (T, 7+): position and rotation."""
    motion[:, list(root.translation_columns)] = q[:, 0:3]
    quat = q[:, 3:7] / np.linalg.norm(q[:, 3:7], axis=1, keepdims=True)
    ref = jnp.deg2rad(jnp.asarray(motion[:, list(root.rotation_columns)]))
    ang = matrix_to_euler(quat_to_matrix(jnp.asarray(quat)), root.rotation_order, ref)
    motion[:, list(root.rotation_columns)] = np.rad2deg(np.asarray(ang))


def reread_angles(bvh_path, units, dof_names) -> np.ndarray:
    """Simulated-DOF channels of a BVH file, radians (used to check a round trip)."""
    clip = read_bvh(bvh_path, units=units)
    cols = []
    for name in dof_names:
        joint_name, channel = str(name).rsplit(".", 1)
        joint = clip.joints[clip.joint_index(joint_name)]
        cols.append(joint.rotation_columns[joint.rotation_order.index(channel[0])])
    return np.deg2rad(np.asarray(clip.motion)[:, cols])
