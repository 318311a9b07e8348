"""From a BVH file to a character: the one recipe (read, understand the skeleton, build the
bodies, spline the motion), shared by the studies (:func:`neuromotor.studies.simulate.prepare`)
and the files that rebuild a run's character from its clip (:mod:`neuromotor.io.export`)."""

from __future__ import annotations

import importlib.resources
import pathlib

from neuromotor.model.anatomy import prepare_clip
from neuromotor.model.kinematics import Trajectory, trajectory_from_clip
from neuromotor.model.skeleton import Character, MassModelOptions, build_character

DEFAULT_CLIP_NAME = "mocapbank_19joint.bvh"


def default_clip_path() -> pathlib.Path:
    """Path of the embedded default clip (MocapBank capture, MIT; see data/README.md)."""
    return pathlib.Path(str(importlib.resources.files("neuromotor") / "data" / DEFAULT_CLIP_NAME))


def load_character(
    path=None,
    units="auto",
    up_axis: int | None = None,
    stature: float | None = None,
    options: MassModelOptions | None = None,
) -> tuple[Character, Trajectory]:
    """Read a clip, understand its skeleton (units, up axis, segments, a virtual root) and build
    the character and its mocap trajectory. ``up_axis`` None: found from the motion."""
    clip, anatomy, source = prepare_clip(path or default_clip_path(), units=units, stature=stature)
    character = build_character(clip, options, up_axis=up_axis, anatomy=anatomy, source_clip=source)
    return character, trajectory_from_clip(character.model, clip)
