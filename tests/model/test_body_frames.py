"""The body model depends on the skeleton and the body options, not on which frames a clip holds
(issue 35): a window, a half, the frames reversed or a single frame of a clip give the same
bodies, masses, COMs and inertias, and so does a simulated run written with ``export-bvh`` and
loaded again. What the body does read from the motion is stated in docs/body-model.md; rigs whose
zero pose is not a standing pose are built on their most upright frame, and keep their body in
any part of the clip that holds that frame."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from conftest import ALL_CLIPS
from neuromotor.model.anatomy import prepare_clip
from neuromotor.model.bvh import parse_bvh, read_bvh
from neuromotor.model.skeleton import MassModelOptions, build_character
from synthetic_rigs import make_rig

# Shipped clips whose zero pose is not a standing pose (every bone along its joint's X axis).
FRAME_BUILT = {"bandai_kick_22joint_6ch", "walk_22joint_zyx"}


def subsets(n: int) -> dict[str, np.ndarray]:
    frames = np.arange(n)
    return {"first half": frames[: n // 2], "second half": frames[n // 2:], "window": frames[n // 3: n // 3 + 40],
            "reversed": frames[::-1], "one frame": frames[n // 2: n // 2 + 1]}


def body(raw, options: MassModelOptions | None = None):
    clip, anatomy, source = prepare_clip(raw)
    return build_character(clip, options, anatomy=anatomy, source_clip=source)


def with_frames(raw, frames):
    return dataclasses.replace(raw, motion=raw.motion[np.asarray(frames)])


def assert_same_body(a, b, rtol=1e-12):
    ma, mb = a.model, b.model
    assert mb.body_names == ma.body_names and mb.body_joint == ma.body_joint
    assert b.body_segment == a.body_segment
    scale = float(np.max(np.abs(ma.inertia)))
    np.testing.assert_allclose(mb.mass, ma.mass, rtol=rtol, atol=0)
    np.testing.assert_allclose(mb.com, ma.com, rtol=rtol, atol=rtol * a.anatomy.stature)
    np.testing.assert_allclose(mb.inertia, ma.inertia, rtol=rtol, atol=rtol * scale)
    # The root's offset is where the driven path starts, not a bone.
    np.testing.assert_allclose(mb.joint_offset[1:], ma.joint_offset[1:], rtol=rtol, atol=rtol * a.anatomy.stature)


@pytest.fixture(scope="module", params=sorted(ALL_CLIPS), ids=str)
def shipped(request):
    raw = read_bvh(ALL_CLIPS[request.param], units=1.0)
    return request.param, raw, body(raw)


def test_shipped_clips_standing_in_their_zero_pose_are_built_on_it(shipped):
    name, _, whole = shipped
    assert (whole.anatomy.shape_frame is not None) == (name in FRAME_BUILT)


def test_any_part_of_a_shipped_clip_gives_the_same_body(shipped):
    name, raw, whole = shipped
    parts = subsets(raw.n_frames)
    if name in FRAME_BUILT:
        # Built on the most upright frame (counted in the clip as read, before a skipped bind
        # pose): any part holding it gives the same body.
        ref = whole.anatomy.shape_frame + (raw.n_frames - whole.clip.n_frames)
        frames = np.arange(raw.n_frames)
        parts = {"from it on": frames[ref:], "up to it": frames[:ref + 1], "window": frames[max(ref - 20, 0):ref + 20],
                 "reversed": frames[::-1], "one frame": frames[ref:ref + 1]}
    for what, frames in parts.items():
        assert_same_body(whole, body(with_frames(raw, frames))), what


SYNTHETIC = range(10)


@pytest.mark.parametrize("seed", SYNTHETIC)
def test_any_part_of_a_synthetic_rig_gives_the_same_body(seed):
    """Random names, Euler orders, fingers, toes, face, props, hip links, 6 channels, zero-length
    End Sites, ground-marker roots, Y or Z up and any unit; zero poses that stand, no twist
    joints (recognised from the motion: a single frame cannot show one turning)."""
    rig = make_rig(seed, bent_zero_pose=False, twist=False, hip_link=seed % 2 == 0)
    raw = parse_bvh(rig.text, units=1.0)
    whole = body(raw, MassModelOptions(simulate_extremities=seed % 3 == 0))
    for what, frames in subsets(raw.n_frames).items():
        part = body(with_frames(raw, frames), MassModelOptions(simulate_extremities=seed % 3 == 0))
        assert_same_body(whole, part), what
    assert whole.anatomy.shape_frame is None


@pytest.mark.parametrize("seed", range(3))
def test_a_rig_that_does_not_stand_in_its_zero_pose_keeps_its_body_with_its_upright_frame(seed):
    rig = make_rig(seed, bent_zero_pose=True, twist=False)
    raw = parse_bvh(rig.text, units=1.0)
    whole = body(raw)
    ref = whole.anatomy.shape_frame
    assert ref is not None
    frames = np.arange(raw.n_frames)
    for part in (frames[max(ref - 5, 0): ref + 15], frames[::-1], [ref]):
        assert_same_body(whole, body(with_frames(raw, part)))


def test_inspect_says_what_the_shapes_are_built_on(capsys):
    from neuromotor.cli import main

    assert main(["inspect", str(ALL_CLIPS["mocapbank_19joint"])]) == 0
    assert "shapes    built on the zero pose" in capsys.readouterr().out
    assert main(["inspect", str(ALL_CLIPS["walk_22joint_zyx"]), "--json"]) == 0
    assert '"shape_frame": 0' in capsys.readouterr().out
