"""The Figure-2 filmstrip: two rows of panels (original above, perturbed below) at instants from
just before the hit until the deviation has mostly decayed, one scale for every panel."""

from __future__ import annotations

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
    COLOR_PERTURBED,
    COLOR_PERTURBED_JOINT,
    PANEL_SIZE,
)


def _write_png(path, img):
    import imageio.v3 as iio

    iio.imwrite(path, np.ascontiguousarray(img), extension=".png")


def _framing(scene: Scene, ks, aspect):
    """Per column focal point (centre of both characters, horizontal; one height for all) and
    the one parallel scale that fits every panel."""
    heights = (
        np.concatenate(
            [np.concatenate([scene.extent_points(k, "perturbed"), scene.extent_points(k, "original")]) for k in ks]
        )
        @ scene.up
    )
    z_mid = 0.5 * (scene.ground + heights.max())
    focals = []
    half_w = half_h = 0.0
    for k in ks:
        both = np.concatenate([scene.extent_points(k, "perturbed"), scene.extent_points(k, "original")])
        c = scene.box_centre(both)
        c = c - np.dot(c, scene.up) * scene.up + z_mid * scene.up
        focals.append(c)
        w, h = fit(scene, both, c)
        foot = c - np.dot(c, scene.up) * scene.up + scene.ground * scene.up
        _, hg = fit(scene, foot[None], c)
        half_w, half_h = max(half_w, w), max(half_h, h, hg)
    rmax = scene.pad
    return focals, 1.12 * max(half_h + rmax, (half_w + rmax) / aspect)


def _draw_perturbed(pl, scene: Scene, k, geom, ghost):
    """The perturbed figure at sample k, with the pale original behind it, the force arrow and
    its label, the balance assist's arrow and label (purple), and the ball."""
    import pyvista as pv

    geom.add(pl, COLOR_PERTURBED, COLOR_PERTURBED_JOINT)
    if ghost:
        gg = FigureGeometry(scene).update(k, "original", ghost_offset(scene))
        gg.add(pl, COLOR_GHOST, COLOR_GHOST_JOINT, specular=0.0)
    if scene.force_on[k]:
        arrow = ArrowGeometry()
        arrow.update(*scene.arrow(k))
        pl.add_mesh(arrow.mesh, color=COLOR_FORCE, smooth_shading=False)
        pl.add_text(scene.force_label(k), position="lower_right", font_size=9, color=COLOR_FORCE)
    if scene.assist_on[k]:
        arrow = ArrowGeometry()
        arrow.update(*scene.assist_arrow(k))
        pl.add_mesh(arrow.mesh, color=COLOR_ASSIST, smooth_shading=False)
        pl.add_text(scene.assist_label(k), position="upper_right", font_size=8, color=COLOR_ASSIST)
    if scene.has_ball:
        pl.add_mesh(pv.Sphere(radius=float(scene.d["ball_radius"]), center=scene.d["ball_pos"][k]), color=COLOR_BALL)


def _draw_panel(pl, scene: Scene, k, which, col, ghost):
    """One panel: the ground, the figure ``which`` at sample k, and the labels."""
    geom = FigureGeometry(scene).update(k, which)
    if which == "original":
        geom.add(pl, COLOR_ORIGINAL, COLOR_ORIGINAL_JOINT)
    else:
        _draw_perturbed(pl, scene, k, geom, ghost)
    pl.add_text(f"t = {scene.time[k]:.2f} s", position="upper_left", font_size=10, color="black")
    if col == 0:
        label = which if which == "original" or not ghost else "perturbed (pale: original)"
        pl.add_text(label, position="lower_left", font_size=9, color="black")


def render_filmstrip(scene: Scene, out_tmp, frames: int, ghost: bool = True):
    """Draw ``frames`` columns of the original (top) and perturbed (bottom) figure into the PNG
    ``out_tmp``; returns the image."""
    import pyvista as pv

    times = scene.filmstrip_times(frames)
    ks = scene.index_at(times)
    pw, ph = PANEL_SIZE
    aspect = pw / ph
    focals, scale = _framing(scene, ks, aspect)
    pl = pv.Plotter(shape=(2, frames), off_screen=True, window_size=(pw * frames, ph * 2), border=False)
    try:
        pl.set_background("white")
        for col, (k, c) in enumerate(zip(ks, focals)):
            for row, which in enumerate(("original", "perturbed")):
                pl.subplot(row, col)
                pl.set_background("white")
                # A tilted ground tilts under the perturbed figure; the original stood on it level.
                add_ground(pl, scene.ground_mesh(c, 3.0 * scale * aspect + 1.0, k if which == "perturbed" else None))
                _draw_panel(pl, scene, k, which, col, ghost)
                set_camera(pl, scene, c, scale)
        img = pl.screenshot(return_img=True).copy()
    finally:
        pl.close()
    # Thin separators between panels.
    sep = np.array([190, 190, 190], np.uint8)
    img[ph - 1 : ph + 1, :, :3] = sep
    for c in range(1, frames):
        img[:, c * pw - 1 : c * pw + 1, :3] = sep
    _write_png(out_tmp, img)
    return img
