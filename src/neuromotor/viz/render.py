"""Off-screen pictures of a run: a Figure-2 filmstrip, a side-by-side video, and plots.

    render_run("run.npz", "filmstrip.png", frames=6)   # top row original, bottom row perturbed
    render_run("run.npz", "video.mp4")                 # or .gif: both characters side by side
    plot_run("run.npz", "plots.png")                   # deviation and joint angles vs time

Everything reads the RUN.npz contract of :mod:`neuromotor.io.runfile` (which fields, their
shapes, which are optional), written by :func:`neuromotor.studies.record.run_arrays`. The work is
split by job: :mod:`~neuromotor.viz.data` reads, :mod:`~neuromotor.viz.scene` prepares a run for
drawing, :mod:`~neuromotor.viz.camera` picks the view, :mod:`~neuromotor.viz.geometry` builds the
meshes, :mod:`~neuromotor.viz.filmstrip` and :mod:`~neuromotor.viz.video` draw, and
:mod:`~neuromotor.viz.plots` plots; :mod:`~neuromotor.viz.style` holds sizes and colours.

3-D pictures use pyvista/VTK off screen through EGL and Mesa, so no display and no GPU are needed
(Debian packages ``libegl1 libegl-mesa0 libgl1-mesa-dri``; see ``.ci/install_system_deps.sh``).
This module sets ``VTK_DEFAULT_OPENGL_WINDOW=vtkEGLRenderWindow`` before VTK is imported unless
the variable is already set.

Drawing conventions (also in docs/rendering.md):

* Each body is drawn as the mass model's own convex polyhedron, moved by its pose: a vertex v of
  body b is at ``body_pos[t, b] + R(body_quat[t, b]) @ v``. All bodies of a figure are one mesh
  whose points are recomputed per frame. Bones that carry no body (``skeleton_edge_body`` -1:
  fingers, toes, face) are thin capsules (radius at most ``DETAIL_RADIUS_M``). A run without
  shapes (an older RUN.npz) is drawn as capsules of radius ``skeleton_radii`` for every
  bone, joints as spheres slightly wider than the thickest bone meeting there.
* The external force is an arrow whose tip stops 1 cm outside the body surface at the point of
  application and which points along the force; its length is ``|F| / FORCE_SCALE_N_PER_M``
  metres (1 m per 500 N). It is drawn only while ``|F|`` exceeds 1% of its peak.
* The balance assist (RUN.npz ``assist_force`` at ``assist_point``, runs with ``[balance]
  assist`` on) is a purple arrow from the pelvis's COM along its force, at the same scale,
  labelled "assist X N (not physics)": help is never drawn as physics.
* The camera looks at the character's front: its horizontal direction is the facing direction
  (``facing``, else :func:`facing_from_skeleton`) turned by ``CAMERA_AZIMUTH_DEG`` (40 degrees)
  about the up axis, to the side that sees the hit most side-on (on a tie, the side the hit comes
  from), and it is raised by ``CAMERA_ELEVATION_DEG`` (12 degrees); see :func:`camera_view`. The
  picture is therefore the same whatever the up axis and heading. Parallel projection keeps the
  scale identical in every panel.

Outputs are written to a temporary file beside the target and renamed, so a failed render never
leaves a partial file. Bad input raises :class:`RenderError` (a ``ValueError``) naming the file
and the field.
"""

from __future__ import annotations

import os
import pathlib

os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")

from neuromotor.atomic import atomic_path
from neuromotor.model.facing import facing_direction, facing_from_skeleton  # noqa: F401
from neuromotor.viz.camera import camera_view  # noqa: F401
from neuromotor.viz.data import RenderError, load_run  # noqa: F401
from neuromotor.viz.filmstrip import render_filmstrip
from neuromotor.viz.plots import plot_run  # noqa: F401
from neuromotor.viz.scene import Scene
from neuromotor.viz.style import (  # noqa: F401
    CAMERA_AZIMUTH_DEG,
    CAMERA_ELEVATION_DEG,
    DETAIL_RADIUS_M,
    FORCE_SCALE_N_PER_M,
    IMAGE_EXTENSIONS,
    PANEL_SIZE,
    VIDEO_EXTENSIONS,
    VIDEO_FPS,
    VIDEO_SIZE,
)
from neuromotor.viz.video import render_video, video_sample_times


def render_run(
    run_path, out_path, frames: int = 6, progress: bool = True, ghost: bool = True, stage=None
) -> pathlib.Path:
    """Render a RUN.npz by the extension of ``out_path``.

    ``.png``: a Figure-2 filmstrip, ``frames`` panels per row (top: original motion, bottom:
    perturbed), ``PANEL_SIZE`` pixels each, at instants spread from just before the hit until
    the deviation has mostly decayed; with ``ghost`` the original is also drawn, pale, behind
    the perturbed figure so that small deviations show. ``.mp4`` / ``.gif``: a real-time video (30 / 25 fps) of
    ``VIDEO_SIZE`` pixels with the original (light, on the left) beside the perturbed motion
    (and, with ``ghost``, pale behind it). ``stage``: called with a line of text as each stage
    begins (the CLI's progress lines).
    """
    stage = stage or (lambda text: None)
    out = pathlib.Path(out_path)
    ext = out.suffix.lower()
    if ext not in IMAGE_EXTENSIONS + VIDEO_EXTENSIONS:
        raise RenderError(
            f"{out}: unknown output extension {out.suffix!r}; "
            f"use one of {', '.join(IMAGE_EXTENSIONS + VIDEO_EXTENSIONS)}"
        )
    if ext == ".png" and (int(frames) != frames or frames < 1):
        raise RenderError(f"{out}: frames must be a positive integer, got {frames!r}")
    stage(f"loading run {run_path}")
    scene = Scene(load_run(run_path))
    with atomic_path(out) as tmp:
        if ext == ".png":
            stage(f"rendering a {int(frames)}-panel filmstrip")
            render_filmstrip(scene, tmp, int(frames), ghost=ghost)
        else:
            n = len(video_sample_times(scene.time, VIDEO_FPS[ext]))
            stage(f"rendering and encoding {n} video frames")
            render_video(scene, tmp, ext, progress=progress, ghost=ghost)
        stage(f"writing {out}")
    return out
