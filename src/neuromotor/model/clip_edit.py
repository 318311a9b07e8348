"""Editing a BVH clip on the host (numpy only): forward kinematics of its frames, scaling its
lengths, removing a virtual root, skipping leading bind-pose frames.

Conventions are those of :mod:`neuromotor.model.bvh`: rotation channels are intrinsic Euler angles in
file order, ``p_parent = R @ p_joint + translation``, position channels replace the OFFSET.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from neuromotor.model.bvh import BvhClip
from neuromotor.rotations_np import euler_to_matrix, matrix_to_euler, rotation_angle

__all__ = ["local_motion", "forward_kinematics", "scale_clip", "collapse_virtual_root", "skip_rest_frames"]


def local_motion(clip: BvhClip, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Local rotations (T, J, 3, 3) and translations (T, J, 3) of the given frames."""
    motion = clip.motion[rows]
    T, J = len(rows), len(clip.joints)
    rot = np.broadcast_to(np.eye(3), (T, J, 3, 3)).copy()
    trans = np.zeros((T, J, 3))
    for k, joint in enumerate(clip.joints):
        if joint.rotation_order:
            rot[:, k] = euler_to_matrix(np.deg2rad(motion[:, list(joint.rotation_columns)]), joint.rotation_order)
        cols = joint.translation_columns
        trans[:, k] = motion[:, list(cols)] if cols else joint.offset
    return rot, trans


def forward_kinematics(clip: BvhClip, rows=None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """World joint positions (T, J, 3), rotations (T, J, 3, 3) and End Site positions (T, J, 3)
    (a joint without End Site gets its own position) of frames ``rows`` (default: all)."""
    rows = np.arange(clip.n_frames) if rows is None else np.asarray(rows, dtype=int)
    local_rot, local_trans = local_motion(clip, rows)
    rot = np.empty_like(local_rot)
    pos = np.empty_like(local_trans)
    for k, joint in enumerate(clip.joints):
        p = joint.parent
        if p < 0:
            rot[:, k], pos[:, k] = local_rot[:, k], local_trans[:, k]
        else:
            rot[:, k] = rot[:, p] @ local_rot[:, k]
            pos[:, k] = np.einsum("tab,tb->ta", rot[:, p], local_trans[:, k]) + pos[:, p]
    ends = pos.copy()
    for k, joint in enumerate(clip.joints):
        if joint.end_site is not None:
            ends[:, k] += rot[:, k] @ joint.end_site
    return pos, rot, ends


def scale_clip(clip: BvhClip, factor: float) -> BvhClip:
    """Lengths (OFFSETs, End Sites, position channels) times ``factor``; ``length_scale`` too."""
    factor = float(factor)
    if not (math.isfinite(factor) and factor > 0):
        raise ValueError(f"scale factor must be positive, got {factor!r}")
    motion = clip.motion.copy()
    joints = []
    for joint in clip.joints:
        motion[:, list(joint.translation_columns)] *= factor
        joints.append(
            dataclasses.replace(
                joint,
                offset=joint.offset * factor,
                end_site=None if joint.end_site is None else joint.end_site * factor,
            )
        )
    return dataclasses.replace(clip, joints=tuple(joints), motion=motion, length_scale=clip.length_scale * factor)


def _continuous_euler(order: str, R: np.ndarray, start: np.ndarray) -> np.ndarray:
    """Euler angles (T, 3) radians of R (T, 3, 3), each frame the equivalent solution nearest to
    the previous one (frame 0: nearest to ``start``), so the curves stay continuous."""
    base = matrix_to_euler(R, order)
    alt = np.stack([base[:, 0] + np.pi, np.pi - base[:, 1], base[:, 2] + np.pi], axis=1)
    locked = np.cos(base[:, 1]) < 1e-7  # only t1 +- t3 is defined: the reference rule keeps t1
    out = np.empty_like(base)
    prev = np.asarray(start, dtype=np.float64)
    two_pi = 2.0 * np.pi
    for t in range(len(base)):
        if locked[t]:
            out[t] = prev = matrix_to_euler(R[t], order, prev)
            continue
        best, best_d = None, np.inf
        for cand in (base[t], alt[t]):
            cand = cand + two_pi * np.round((prev - cand) / two_pi)
            d = float(np.abs(cand - prev).sum())
            if d < best_d:
                best, best_d = cand, d
        assert best is not None, "Euler angles are NaN"  # a finite candidate is always nearer than inf
        out[t] = prev = best
    return out


def _subtree_end(clip: BvhClip, k: int) -> int:
    end = k + 1
    while end < len(clip.joints) and _is_below(clip, end, k):
        end += 1
    return end


def _is_below(clip: BvhClip, j: int, k: int) -> bool:
    while j >= 0:
        if j == k:
            return True
        j = clip.joints[j].parent
    return False


def _collapse_once(clip: BvhClip):
    joints = clip.joints
    root = joints[0]
    if not root.translation_columns:
        return None
    if root.end_site is not None and np.linalg.norm(root.end_site) > 0:
        return None
    kids = clip.children(0)
    moving, others = [], []
    for c in kids:
        joint = joints[c]
        if joint.translation_columns:
            moving.append(c)
        else:
            others.append(c)
    if len(moving) != 1:
        return None
    c = moving[0]
    for o in others:  # anything else on the root must be a zero-length leaf (a marker)
        j = joints[o]
        if (
            clip.children(o)
            or np.linalg.norm(j.offset) > 0
            or (j.end_site is not None and np.linalg.norm(j.end_site) > 0)
        ):
            return None
    # Decided on the skeleton alone, not on how far the link moves, so a window of the clip in
    # which the marker stands still is read the same.
    child = joints[c]
    lengths = np.linalg.norm(clip.motion[:, list(child.translation_columns)], axis=1)
    change = float(lengths.max() - lengths.min())

    rows = np.arange(clip.n_frames)
    local_rot, local_trans = local_motion(clip, rows)
    R = local_rot[:, 0] @ local_rot[:, c]
    p = np.einsum("tab,tb->ta", local_rot[:, 0], local_trans[:, c]) + local_trans[:, 0]
    order = child.rotation_order or root.rotation_order
    columns = [p]
    if order:
        start = np.deg2rad(clip.motion[0, list(child.rotation_columns)]) if child.rotation_order else np.zeros(3)
        columns.append(np.rad2deg(_continuous_euler(order, R, start)))
    channels = ("Xposition", "Yposition", "Zposition") + tuple(f"{a}rotation" for a in order)

    keep = list(range(c, _subtree_end(clip, c)))
    new_index = {old: n for n, old in enumerate(keep)}
    new_joints = [dataclasses.replace(child, parent=-1, offset=p[0], channels=channels, channel_start=0)]
    blocks = [np.concatenate(columns, axis=1)]
    column = len(channels)
    for old in keep[1:]:
        j = joints[old]
        new_joints.append(dataclasses.replace(j, parent=new_index[j.parent], channel_start=column))
        blocks.append(clip.motion[:, j.channel_start : j.channel_start + len(j.channels)])
        column += len(j.channels)
    new_clip = dataclasses.replace(clip, joints=tuple(new_joints), motion=np.concatenate(blocks, axis=1))
    removed = (root.name,) + tuple(joints[o].name for o in others)
    warning = (
        f"joint {root.name!r} is a virtual root (its only child {child.name!r} carries its own "
        f"position channels; their length changes by {change:.4g} file units over the clip): removed, "
        f"{child.name!r} is the root now and carries the composed world motion"
    )
    return new_clip, removed, warning


def collapse_virtual_root(clip: BvhClip) -> tuple[BvhClip, tuple[str, ...], tuple[str, ...]]:
    """Remove a ROOT that is only a ground marker: it has position channels, no real bone of its own
    (other children and End Site zero-length or absent), and one child with position channels
    (that child's place is data, not a bone). Decided on the skeleton, whatever the frames.
    The child becomes the ROOT with position channels plus its own rotation order (the root's if it
    has none) and the composed world motion ``R = R_root R_child``, ``p = R_root p_child + p_root``
    (Euler angles kept continuous over time). Repeats while it applies.

    Returns (new clip, names of removed joints, warnings)."""
    removed: list[str] = []
    warnings: list[str] = []
    while True:
        result = _collapse_once(clip)
        if result is None:
            return clip, tuple(removed), tuple(warnings)
        clip, names, warning = result
        removed.extend(names)
        warnings.append(warning)


def skip_rest_frames(clip: BvhClip, max_frames: int = 5) -> tuple[BvhClip, tuple[str, ...]]:
    """Drop leading frames that are not part of the motion: many exporters write the bind pose
    (all channels zero) as frame 1, and the capture jumps away from it at once (CMU's BVH
    conversions: 136 deg in one 1/120 s frame). A leading frame is dropped when some joint turns
    by more than 30 deg and more than 6x the clip's 99th-percentile frame-to-frame turn."""
    if clip.n_frames < 12:
        return clip, ()
    local, _ = local_motion(clip, np.arange(clip.n_frames))
    rel = np.einsum("tjab,tjac->tjbc", local[:-1], local[1:])
    turn = np.degrees(rotation_angle(rel)).max(axis=1)  # (T-1,) largest joint turn per frame
    typical = float(np.percentile(turn[max_frames:], 99))
    drop = 0
    while drop < max_frames and turn[drop] > max(30.0, 6.0 * typical):
        drop += 1
    if drop == 0:
        return clip, ()
    msg = (
        f"{clip.path}: the first {drop} frame{'s' if drop > 1 else ''} jump{'s' if drop == 1 else ''} "
        f"{turn[drop - 1]:.0f} deg to the next (a bind pose, not motion): skipped, the clip starts at "
        f"frame {drop + 1}"
    )
    return dataclasses.replace(clip, motion=clip.motion[drop:]), (msg,)
