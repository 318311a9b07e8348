"""How pictures look: sizes, colours, the force arrow's scale and the camera's angles. The colours
are the run's one palette (:mod:`neuromotor.io.palette`), shared with the glTF export."""

from __future__ import annotations

from neuromotor.io.palette import (  # noqa: F401  (re-exported: the pictures' colours)
    COLOR_ASSIST,
    COLOR_BALL,
    COLOR_FORCE,
    COLOR_GHOST,
    COLOR_GHOST_JOINT,
    COLOR_ORIGINAL,
    COLOR_ORIGINAL_JOINT,
    COLOR_ORIGINAL_VIDEO,
    COLOR_PERTURBED,
    COLOR_PERTURBED_JOINT,
    GROUND_COLORS,
)

FORCE_SCALE_N_PER_M = 500.0  # arrow length: 1 m per 500 N
FORCE_VISIBLE_FRACTION = 0.01  # draw the arrow while |F| > 1% of its peak
CAMERA_ELEVATION_DEG = 12.0  # camera raised above the horizontal
CAMERA_AZIMUTH_DEG = 40.0  # camera turned this far from the character's facing direction
DETAIL_RADIUS_M = 0.015  # thickest capsule drawn for a bone that carries no body
GHOST_DEPTH_M = 0.05  # the pale original sits this far behind the perturbed figure
VIDEO_SIZE = (640, 360)  # pixels per video frame (width, height)
PANEL_SIZE = (300, 420)  # pixels per filmstrip panel (width, height)
VIDEO_FPS = {".mp4": 30.0, ".gif": 25.0}  # GIF delays are whole centiseconds: 40 ms is exact

IMAGE_EXTENSIONS = (".png",)
VIDEO_EXTENSIONS = (".mp4", ".gif")

GROUND_TILE_M = 0.5
