"""How pictures look: sizes, colours, the force arrow's scale and the camera's angles."""

from __future__ import annotations

FORCE_SCALE_N_PER_M = 500.0   # arrow length: 1 m per 500 N
FORCE_VISIBLE_FRACTION = 0.01  # draw the arrow while |F| > 1% of its peak
CAMERA_ELEVATION_DEG = 12.0  # camera raised above the horizontal
CAMERA_AZIMUTH_DEG = 40.0    # camera turned this far from the character's facing direction
DETAIL_RADIUS_M = 0.015      # thickest capsule drawn for a bone that carries no body
GHOST_DEPTH_M = 0.05         # the pale original sits this far behind the perturbed figure
VIDEO_SIZE = (640, 360)        # pixels per video frame (width, height)
PANEL_SIZE = (300, 420)        # pixels per filmstrip panel (width, height)
VIDEO_FPS = {".mp4": 30.0, ".gif": 25.0}  # GIF delays are whole centiseconds: 40 ms is exact

IMAGE_EXTENSIONS = (".png",)
VIDEO_EXTENSIONS = (".mp4", ".gif")

COLOR_ORIGINAL = (0.52, 0.64, 0.84)       # blue-grey
COLOR_ORIGINAL_JOINT = (0.36, 0.47, 0.68)
COLOR_ORIGINAL_VIDEO = (0.66, 0.76, 0.92)  # lighter, for the original beside the perturbed one
COLOR_GHOST = (0.80, 0.84, 0.90)          # the original, drawn behind the perturbed one
COLOR_GHOST_JOINT = (0.72, 0.77, 0.85)
COLOR_PERTURBED = (0.90, 0.45, 0.20)      # orange
COLOR_PERTURBED_JOINT = (0.62, 0.26, 0.10)
COLOR_FORCE = (0.85, 0.05, 0.05)
COLOR_BALL = (0.95, 0.85, 0.15)
GROUND_COLORS = ((0.93, 0.93, 0.91), (0.84, 0.84, 0.82))
GROUND_TILE_M = 0.5
