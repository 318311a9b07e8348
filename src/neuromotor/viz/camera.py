"""Where the camera looks from: the character's facing direction and a three-quarter front view.

The camera's horizontal direction is the facing direction (``facing``, else
:func:`neuromotor.model.facing.facing_from_skeleton`) turned by ``CAMERA_AZIMUTH_DEG`` about the up axis, to the side
that sees the hit most side-on, and raised by ``CAMERA_ELEVATION_DEG`` (:func:`camera_view`);
so the picture is the same whatever the up axis and heading. Parallel projection keeps the
scale identical in every panel.
"""

from __future__ import annotations

import numpy as np

from neuromotor.model.facing import horizontal, unit
from neuromotor.viz.style import CAMERA_AZIMUTH_DEG, CAMERA_ELEVATION_DEG, GHOST_DEPTH_M


def _turn(v, up, angle):
    """Rotate the horizontal vector ``v`` about ``up`` by ``angle`` radians (right-handed)."""
    return np.cos(angle) * v + np.sin(angle) * np.cross(up, v)


def camera_view(facing, up, hit=None, azimuth_deg=CAMERA_AZIMUTH_DEG, elevation_deg=CAMERA_ELEVATION_DEG):
    """Unit vector from the scene towards the camera: the horizontal ``facing`` turned by
    ``azimuth_deg`` about ``up`` (a three-quarter front view), then raised by ``elevation_deg``.

    Of the two turns (counter-clockwise or clockwise about ``up``) it takes the one that sees
    the horizontal ``hit`` direction most side-on, so that the force arrow is long on screen. On
    a tie in that (a push from the side) it takes the one where the force points away from the
    camera, so the arrow starts on the camera's side of the body; on a push from straight in
    front or behind, or without a hit, the counter-clockwise turn.
    """
    up = np.asarray(up, float)
    f = unit(horizontal(facing, up), np.roll(up, 1))
    az = np.radians(azimuth_deg)
    candidates = [_turn(f, up, az), _turn(f, up, -az)]
    best = candidates[0]
    if hit is not None and np.linalg.norm(horizontal(hit, up)) > 1e-9:
        h = unit(horizontal(hit, up), f)
        score = [abs(h @ c) + 0.25 * (h @ c) for c in candidates]
        if score[1] < score[0] - 1e-9:
            best = candidates[1]
    el = np.radians(elevation_deg)
    return np.cos(el) * best + np.sin(el) * up


def ghost_offset(scene):
    """Shift of the ghost along the line of sight: with parallel projection it lands on the same
    pixels, but sits behind the perturbed figure, so only where the two differ does it show."""
    return -GHOST_DEPTH_M * scene.view


def set_camera(pl, scene, focal, scale, distance=20.0):
    pl.camera_position = [tuple(focal + distance * scene.view), tuple(focal), tuple(scene.screen_up)]
    pl.camera.parallel_projection = True
    pl.camera.parallel_scale = scale
    pl.camera.clipping_range = (0.1, 2 * distance + 50.0)


def fit(scene, pts, focal):
    """Half extents (screen right, screen up) of ``pts`` about ``focal``."""
    rel = pts - focal
    return np.abs(rel @ scene.right).max(), np.abs(rel @ scene.screen_up).max()
