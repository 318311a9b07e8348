"""The character's horizontal facing direction, from its anatomy or estimated from skeleton points.

RUN.npz stores it (``facing``) so that pictures look at the character's front; runs without it
are estimated again from their skeleton points when drawn.
"""

from __future__ import annotations

import numpy as np


def unit(v, fallback):
    n = np.linalg.norm(v)
    return v / n if n > 1e-12 else np.asarray(fallback, float)


def horizontal(v, up):
    v = np.asarray(v, float)
    return v - (v @ up)[..., None] * up


def facing_from_skeleton(points, edges, up_axis: int = 1) -> np.ndarray:
    """The character's horizontal facing direction (a world unit vector perpendicular to the up
    axis), estimated from skeleton points alone, for runs that do not store ``facing``.

    ``points`` (T,P,3) or (P,3), ``edges`` (E,2) parent -> child pairs. The feet are the two
    lowest leaves of the tree (on average over time); the legs are their chains up to the joint
    they share (the pelvis). The left-right axis runs between the two legs' top points (between
    the legs' mean points if the tops coincide), and the facing is horizontal and perpendicular
    to it, on the side the feet point to (leaf minus its parent point: toes, or the foot bone),
    or, when the feet do not tell, the side the root travels to. Averaged over all samples, so a
    walking gait's scissoring cancels. Without two feet it falls back to the travel direction.
    """
    P = np.asarray(points, float)
    if P.ndim == 2:
        P = P[None]
    up = np.eye(3)[int(up_axis)]
    other = np.eye(3)[(int(up_axis) + 2) % 3]
    edges = np.asarray(edges, int).reshape(-1, 2)
    n = P.shape[1]
    parent = np.full(n, -1)
    parent[edges[:, 1]] = edges[:, 0]
    degree = np.bincount(edges.ravel(), minlength=n)
    root = int(np.flatnonzero(parent < 0)[0]) if np.any(parent < 0) else 0
    travel = horizontal(P[-1, root] - P[0, root], up)
    leaves = [i for i in range(n) if degree[i] == 1 and parent[i] >= 0]
    if len(leaves) < 2:
        return unit(travel, other) if np.linalg.norm(travel) > 0.05 else other

    def chain(i):
        out = []
        while i >= 0:
            out.append(i)
            i = parent[i]
        return out[::-1]  # root first

    height = (P @ up).mean(axis=0)
    feet = sorted(leaves, key=lambda i: height[i])[:2]
    a, b = chain(feet[0]), chain(feet[1])
    shared = 0
    while shared < min(len(a), len(b)) and a[shared] == b[shared]:
        shared += 1
    la, lb = a[shared:], b[shared:]
    lateral = horizontal(P[:, la[0]] - P[:, lb[0]], up).mean(axis=0)
    if np.linalg.norm(lateral) < 0.05:
        lateral = horizontal(P[:, la].mean(axis=1) - P[:, lb].mean(axis=1), up).mean(axis=0)
    if np.linalg.norm(lateral) < 1e-6:
        return unit(travel, other) if np.linalg.norm(travel) > 0.05 else other
    forward = unit(np.cross(lateral, up), other)
    toes = sum(horizontal(P[:, f] - P[:, parent[f]], up).mean(axis=0) for f in feet)
    if abs(toes @ forward) > 0.2 * max(float(np.linalg.norm(toes)), 1e-9) and np.linalg.norm(toes) > 0.02:
        return forward if toes @ forward > 0 else -forward
    if abs(travel @ forward) > 0.05:
        return forward if travel @ forward > 0 else -forward
    return forward


def facing_direction(points, edges, up_axis: int = 1, forward=None) -> np.ndarray:
    """``forward`` (a world direction, e.g. from the character's anatomy) made horizontal and
    unit, or :func:`facing_from_skeleton` when it is missing or (nearly) vertical."""
    up = np.eye(3)[int(up_axis)]
    if forward is not None:
        f = horizontal(np.asarray(forward, float).reshape(3), up)
        if np.all(np.isfinite(f)) and np.linalg.norm(f) > 1e-3:
            return f / np.linalg.norm(f)
    return facing_from_skeleton(points, edges, up_axis)


# Directions named in the character's own frame: its facing and the world up axis (the same
# keywords for every perturbation kind's direction and for a fit target's axis).
DIRECTION_KEYWORDS = ("forward", "backward", "left", "right", "up", "down")


def character_axes(character, time: float) -> dict[str, np.ndarray]:
    """World unit vector of every :data:`DIRECTION_KEYWORDS` entry at clip ``time`` (s).

    Up is the anatomy's up axis. Forward is the anatomy's facing (found at its reference frame)
    turned by the root's rotation from that frame to ``time`` (the nearest frame of the clip)
    and made horizontal, so a character that turns during the clip keeps its own forward; left is
    ``up x forward`` (right-handed). A character without anatomy, or whose turned facing is near
    vertical, keeps the anatomy's (or the skeleton's) facing.
    """
    from neuromotor.model.clip_edit import forward_kinematics

    anat, clip = character.anatomy, character.clip
    if anat is None:
        up = np.eye(3)[1]
        pos, _, _ = forward_kinematics(clip, [0])
        edges = [(j.parent, k) for k, j in enumerate(clip.joints) if j.parent >= 0]
        forward = facing_from_skeleton(pos[0], edges, 1)
    else:
        up = np.asarray(anat.up, float)
        frame = int(np.clip(round(float(time) / clip.frame_time), 0, clip.n_frames - 1))
        ref = int(np.clip(anat.reference_frame, 0, clip.n_frames - 1))
        _, rot, _ = forward_kinematics(clip, [ref, frame])
        turned = horizontal(rot[1, 0] @ rot[0, 0].T @ np.asarray(anat.forward, float), up)
        forward = horizontal(np.asarray(anat.forward, float), up)
        if np.linalg.norm(turned) > 0.2:
            forward = turned
        forward = unit(forward, np.eye(3)[(int(np.argmax(np.abs(up))) + 2) % 3])
    left = np.cross(up, forward)
    return {"forward": forward, "backward": -forward, "left": left, "right": -left, "up": up, "down": -up}


def resolve_direction(value, character, time: float, where: str) -> np.ndarray:
    """A direction field's world unit vector: a keyword of :data:`DIRECTION_KEYWORDS` (in the
    character's frame at clip ``time``, :func:`character_axes`) or 3 numbers, not all zero.
    ``where`` names the file and field in the :class:`~neuromotor.errors.ConfigError`."""
    from neuromotor.errors import ConfigError

    if isinstance(value, str):
        if value not in DIRECTION_KEYWORDS:
            raise ConfigError(
                f"{where} = {value!r} is not a direction; use 3 numbers or one of {', '.join(DIRECTION_KEYWORDS)}"
            )
        if character is None:
            raise ConfigError(f"{where} = {value!r}: a keyword direction needs the character (give 3 numbers)")
        return character_axes(character, time)[value]
    v = np.asarray(value, float).reshape(-1)
    if v.shape != (3,) or not np.all(np.isfinite(v)) or not np.linalg.norm(v) > 0:
        raise ConfigError(f"{where} must be 3 numbers, not all zero, or a keyword; got {value!r}")
    return v / np.linalg.norm(v)
