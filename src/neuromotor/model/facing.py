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
