"""The colours of a run, one palette for every picture and file that shows it: the filmstrip,
the video and the viewer (:mod:`neuromotor.viz.style` takes them from here) and the glTF export
(:mod:`neuromotor.io.gltf`, which converts them to linear RGB). RGB in [0, 1]."""

from __future__ import annotations

COLOR_ORIGINAL = (0.52, 0.64, 0.84)  # blue-grey
COLOR_ORIGINAL_JOINT = (0.36, 0.47, 0.68)
COLOR_ORIGINAL_VIDEO = (0.66, 0.76, 0.92)  # lighter, for the original beside the perturbed one
COLOR_GHOST = (0.80, 0.84, 0.90)  # the original, drawn behind the perturbed one
COLOR_GHOST_JOINT = (0.72, 0.77, 0.85)
COLOR_PERTURBED = (0.90, 0.45, 0.20)  # orange
COLOR_PERTURBED_JOINT = (0.62, 0.26, 0.10)
COLOR_FORCE = (0.85, 0.05, 0.05)
COLOR_BALL = (0.95, 0.85, 0.15)
COLOR_ASSIST = (0.55, 0.20, 0.75)  # purple: the balance assist's virtual force (help, not physics)
GROUND_COLORS = ((0.93, 0.93, 0.91), (0.84, 0.84, 0.82))
