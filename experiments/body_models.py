"""Picture of the body model of every shipped clip (docs/body_models.png): each clip's polyhedra
in the pose they are built on (the zero pose, or the most upright frame), seen from a three-quarter front view of its facing direction.

    python experiments/body_models.py [CLIP.bvh ...] [-o docs/body_models.png]
"""

import argparse
import os
import pathlib

os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")

import numpy as np  # noqa: E402
import pyvista as pv  # noqa: E402

from neuromotor.model.massmodel import world_frames  # noqa: E402
from neuromotor.studies.simulate import load_character  # noqa: E402
from neuromotor.model.skeleton import joint_offsets  # noqa: E402

SHARED = pathlib.Path(__file__).resolve().parents[2] / "shared" / "mocap"


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("clips", nargs="*", default=sorted(str(c) for c in SHARED.glob("*.bvh")))
    p.add_argument("-o", "--output", default="docs/body_models.png")
    args = p.parse_args()
    plotter = pv.Plotter(off_screen=True, window_size=(400 * len(args.clips), 720), shape=(1, len(args.clips)))
    for i, path in enumerate(args.clips):
        character, _ = load_character(path)
        clip, anat, model = character.clip, character.anatomy, character.model
        pos, rot = world_frames(clip, joint_offsets(clip), anat.shape_frame)
        plotter.subplot(0, i)
        for b, k in enumerate(model.body_joint):
            shape = character.shapes[b]
            faces = np.hstack([np.full((len(shape.faces), 1), 3), shape.faces]).ravel()
            plotter.add_mesh(pv.PolyData(pos[k] + shape.vertices @ rot[k].T, faces), color="#c9a27e")
        up, fwd = anat.shape_up, anat.shape_forward
        view = np.cos(np.radians(35)) * fwd + np.sin(np.radians(35)) * np.cross(up, fwd) + 0.2 * up
        centre = pos[list(model.body_joint)].mean(0)
        plotter.camera_position = [tuple(centre + 6.0 * view), tuple(centre), tuple(up)]
        plotter.camera.parallel_projection = True
        plotter.camera.parallel_scale = 0.68 * anat.stature
        plotter.add_text(f"{pathlib.Path(path).stem[:22]}\n{anat.stature:.2f} m, {np.sum(model.mass):.1f} kg, "
                         f"{model.n_bodies} bodies", font_size=9)
    out = pathlib.Path(args.output)
    out.parent.mkdir(parents=True, exist_ok=True)
    plotter.screenshot(str(out))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
