"""A free-standing run (issue 38, docs/balance.md): the clip's most upright frame held still on
a free root on the ground, the postural loop of :mod:`neuromotor.studies.balance` on by default."""

from __future__ import annotations

from neuromotor.config import simulation_config
from neuromotor.model.load import default_clip_path
from neuromotor.studies.simulate import config_character, prepare


def standing_pose(clip=None, top: dict | None = None):
    """``(path, character, traj, still)``: the clip (default: the embedded one) as its config
    loads it (``top``: its top-level keys) and the clip time of its most upright frame."""
    path = str(default_clip_path() if clip is None else clip)
    probe = simulation_config({**(top or {}), "clip": path}, "<standing>")
    character, traj = config_character(probe)
    anatomy = character.anatomy
    assert anatomy is not None, "a standing pose needs the clip's anatomy"
    return path, character, traj, anatomy.reference_frame * character.clip.frame_time


def standing_setup(
    seconds: float,
    h: float = 1.0 / 120.0,
    balance: dict | None = None,
    clip=None,
    root: str = "free",
    ground: dict | None = None,
    top: dict | None = None,
):
    """A free-root run on the ground holding the clip's most upright frame
    (``character.anatomy.reference_frame``) for ``seconds``; ``balance`` and ``ground``: the
    ``[balance]`` and ``[ground]`` tables; ``top``: top-level keys of the clip and body (units,
    up_axis, stature, body_mass, ...)."""
    path, _, _, still = standing_pose(clip, top)
    data = {**(top or {}), "clip": path, "sim": {"root": root, "duration": seconds, "h": h, "still": still}}
    if balance is not None:
        data["balance"] = balance
    if ground is not None:
        data["ground"] = ground
    return prepare(simulation_config(data, "<standing>"))
