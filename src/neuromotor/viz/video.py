"""The side-by-side video (.mp4 or .gif): the original motion, lighter, beside the perturbed one,
in real time, the camera following the pair at one zoom."""

from __future__ import annotations

import contextlib
import dataclasses
from typing import Any

import numpy as np

from neuromotor.viz.camera import fit, ghost_offset, set_camera
from neuromotor.viz.geometry import ArrowGeometry, FigureGeometry, add_ground
from neuromotor.viz.scene import Scene
from neuromotor.viz.style import (
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
    VIDEO_FPS,
    VIDEO_SIZE,
)


def video_sample_times(time, fps):
    """Real-time sampling instants of a video of ``time`` at ``fps``."""
    n = int(np.floor((time[-1] - time[0]) * fps + 1e-9)) + 1
    return time[0] + np.arange(n) / fps


def _forking_once(append):
    """``append`` with its first call (where imageio-ffmpeg starts ffmpeg) warning-silenced."""
    started = [False]

    def wrapped(img):
        if started[0]:
            return append(img)
        with _fork_exec_warning_silenced():
            out = append(img)
        started[0] = True
        return out

    return wrapped


@contextlib.contextmanager
def _fork_exec_warning_silenced():
    """Silence JAX's ``os.fork() was called ... JAX is multithreaded`` RuntimeWarning while
    imageio-ffmpeg starts ffmpeg. That start is subprocess.Popen: on Python < 3.12 its C
    fork_exec runs the interpreter's at-fork hooks, where JAX warns; but the child only execs
    ffmpeg (no Python, no JAX runs in it), so the deadlock JAX warns about cannot happen. Only
    that message is filtered, only here."""
    import warnings

    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=r"os\.fork\(\) was called", category=RuntimeWarning)
        yield


def _side_shift(scene: Scene, ks, gap=0.35):
    """Shift of the original beside the perturbed one, on the screen's left: along -right by the
    smallest amount that keeps the two (and the arrow) apart in every frame."""
    shifts = []
    for k in ks:
        a_min = (scene.extent_points(k, "perturbed") @ scene.right).min()
        b_max = (scene.extent_points(k, "original") @ scene.right).max()
        shifts.append(b_max - a_min)
    return (max(shifts) + 2 * scene.pad + gap) * scene.right


def _camera_track(scene: Scene, ks, shift, fps, aspect):
    """Focal point per frame (the pair's centre smoothed over about a second, at one height) and
    one parallel scale for the whole video."""
    boxes = []
    for k in ks:
        pts = np.concatenate([scene.extent_points(k, "perturbed"), scene.extent_points(k, "original") - shift])
        boxes.append(scene.box_centre(pts))
    centres = np.asarray(boxes)
    win = max(1, int(round(fps)))  # ~1 s box filter
    pad = np.pad(centres, ((win // 2, win // 2), (0, 0)), mode="edge")
    kernel = np.ones(win) / win
    smooth = np.stack([np.convolve(pad[:, i], kernel, mode="valid")[: len(ks)] for i in range(3)], 1)
    z_mid = 0.5 * (
        scene.ground
        + max(
            float(
                (
                    np.concatenate([scene.extent_points(k, "perturbed"), scene.extent_points(k, "original")]) @ scene.up
                ).max()
            )
            for k in np.unique(ks)
        )
    )
    focals = smooth - (smooth @ scene.up)[:, None] * scene.up + z_mid * scene.up
    half_w = half_h = 0.0
    for k, f in zip(ks, focals):
        pts = np.concatenate(
            [
                scene.extent_points(k, "perturbed"),
                scene.extent_points(k, "original") - shift,
                (f - np.dot(f, scene.up) * scene.up + scene.ground * scene.up)[None],
            ]
        )
        w, h = fit(scene, pts, f)
        half_w, half_h = max(half_w, w), max(half_h, h)
    rmax = scene.pad
    return focals, 1.1 * max(half_h + rmax, (half_w + rmax) / aspect)


@dataclasses.dataclass
class _Actors:
    """What a video frame moves: both figures (and the ghost), the arrows (the force's and the
    balance assist's), the ball, the texts."""

    pert: FigureGeometry
    orig: FigureGeometry
    ghost: FigureGeometry | None
    arrow: ArrowGeometry
    arrow_actor: Any  # pyvista objects
    ball: Any  # pyvista objects
    ball_dirs: np.ndarray | None
    ball_actor: Any  # pyvista objects
    clock: Any  # pyvista objects
    ftext: Any  # pyvista objects
    assist: ArrowGeometry
    assist_actor: Any  # pyvista objects
    atext: Any  # pyvista objects


def _add_actors(pl, scene: Scene, ghost: bool) -> _Actors:
    import pyvista as pv

    g_pert = FigureGeometry(scene)
    g_orig = FigureGeometry(scene)
    g_orig.add(pl, COLOR_ORIGINAL_VIDEO, COLOR_ORIGINAL)
    g_ghost = None
    if ghost:
        g_ghost = FigureGeometry(scene)
        g_ghost.add(pl, COLOR_GHOST, COLOR_GHOST_JOINT, specular=0.0)
    g_pert.add(pl, COLOR_PERTURBED, COLOR_PERTURBED_JOINT)
    arrow = ArrowGeometry()
    arrow_actor = pl.add_mesh(arrow.mesh, color=COLOR_FORCE, smooth_shading=False)
    ball = ball_dirs = ball_actor = None
    if scene.has_ball:
        ball = pv.Sphere(radius=float(scene.d["ball_radius"]), theta_resolution=24, phi_resolution=16)
        ball_dirs = np.asarray(ball.points).copy()
        ball_actor = pl.add_mesh(ball, color=COLOR_BALL, smooth_shading=True)
    pl.add_text("original", position="upper_left", font_size=10, color=COLOR_ORIGINAL_JOINT)
    pl.add_text("perturbed", position="upper_right", font_size=10, color=COLOR_PERTURBED_JOINT)
    clock = pl.add_text("", position="lower_left", font_size=10, color="black")
    ftext = pl.add_text("", position="lower_right", font_size=10, color=COLOR_FORCE)
    assist = ArrowGeometry()
    assist_actor = pl.add_mesh(assist.mesh, color=COLOR_ASSIST, smooth_shading=False)
    assist_actor.SetVisibility(False)
    atext = pl.add_text("", position="upper_edge", font_size=9, color=COLOR_ASSIST)
    return _Actors(
        g_pert,
        g_orig,
        g_ghost,
        arrow,
        arrow_actor,
        ball,
        ball_dirs,
        ball_actor,
        clock,
        ftext,
        assist,
        assist_actor,
        atext,
    )


def _pose_frame(a: _Actors, scene: Scene, k, shift):
    """Move every actor to sample k."""
    a.pert.update(k, "perturbed")
    a.orig.update(k, "original", -shift)
    if a.ghost is not None:
        a.ghost.update(k, "original", ghost_offset(scene))
    on = bool(scene.force_on[k])
    a.arrow_actor.SetVisibility(on)
    if on:
        a.arrow.update(*scene.arrow(k))
    a.ftext.set_text("lower_right", f"force {scene.fmag[k]:.0f} N" if on else "")
    help_on = bool(scene.assist_on[k])
    a.assist_actor.SetVisibility(help_on)
    if help_on:
        a.assist.update(*scene.assist_arrow(k))
    a.atext.set_text("upper_edge", scene.assist_label(k) if help_on else "")
    if a.ball is not None:
        # The ball belongs to the perturbed run: drawn on its (right) half of the frame
        # only, never over the original figure beside it.
        pos = scene.d["ball_pos"][k]
        boundary = (
            0.5 * ((scene.extent_points(k, "original") - shift) @ scene.right).max()
            + 0.5 * (scene.extent_points(k, "perturbed") @ scene.right).min()
        )
        a.ball_actor.SetVisibility(bool(pos @ scene.right - float(scene.d["ball_radius"]) > boundary))
        a.ball.points = a.ball_dirs + pos
    a.clock.set_text("lower_left", f"t = {scene.time[k]:.2f} s")


def _mp4_writer(out_tmp, fps):
    import imageio.v2 as iio2

    writer = iio2.get_writer(
        out_tmp,
        format="FFMPEG",
        mode="I",
        fps=fps,
        codec="libx264",
        quality=7,
        macro_block_size=8,
        ffmpeg_log_level="error",
    )
    writer.append_data = _forking_once(writer.append_data)
    return writer


def render_video(scene: Scene, out_tmp, ext, progress=True, ghost=True):
    """Render and encode the video ``out_tmp`` (``ext`` .mp4 or .gif); returns the frame count."""
    import pyvista as pv
    from tqdm import tqdm

    fps = VIDEO_FPS[ext]
    ks = scene.index_at(video_sample_times(scene.time, fps))
    W, H = VIDEO_SIZE
    aspect = W / H
    shift = _side_shift(scene, ks)
    focals, scale = _camera_track(scene, ks, shift, fps, aspect)
    pl = pv.Plotter(off_screen=True, window_size=(W, H))
    frames = []
    writer = None
    try:
        pl.set_background("white")
        travel = np.ptp(focals @ scene.right) + np.ptp(focals @ np.cross(scene.up, scene.right))
        ground = scene.ground_mesh(focals.mean(axis=0), 3.0 * scale * aspect + travel + 1.0)
        level = np.array(ground.points)
        add_ground(pl, ground)
        actors = _add_actors(pl, scene, ghost)
        writer = _mp4_writer(out_tmp, fps) if ext == ".mp4" else None
        for i, k in enumerate(tqdm(ks, desc=f"rendering {ext[1:]}", unit="frame", disable=not progress)):
            _pose_frame(actors, scene, k, shift)
            if scene.ground_moves:  # a tilt or a platform moves the ground with the run
                ground.points = scene.moved(level, k)
            set_camera(pl, scene, focals[i], scale)
            pl.render()  # screenshot() only renders by itself the first time
            img = pl.screenshot(return_img=True)
            if writer is not None:
                writer.append_data(img)
            else:
                frames.append(img)
        if writer is not None:
            writer.close()
            writer = None
    finally:
        if writer is not None:
            writer.close()
        pl.close()
    if ext == ".gif":
        import imageio.v3 as iio

        iio.imwrite(out_tmp, np.stack(frames), extension=".gif", duration=1000.0 / fps, loop=0)
    return len(ks)
