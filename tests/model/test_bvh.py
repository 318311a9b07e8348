"""Tests of the BVH reader/writer: shipped clips, generated skeletons, generated damage, round trips."""

from __future__ import annotations

import dataclasses
import math
import os
import pickle
import tempfile

import numpy as np
import pytest
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from conftest import CLIPS
from neuromotor.model.bvh import (
    BvhClip,
    BvhError,
    BvhJoint,
    parse_bvh,
    read_bvh,
    rest_pose_positions,
    write_bvh,
)

SETTINGS = settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])

# ----------------------------------------------------------------------------------------------
# Shipped clips

EXPECTED = {
    "mocapbank": dict(
        names=["Hips", "Chest", "Chest2", "LeftCollar", "LeftShoulder", "LeftElbow", "LeftWrist",
               "RightCollar", "RightShoulder", "RightElbow", "RightWrist", "Neck", "Head", "LeftHip",
               "LeftKnee", "LeftAnkle", "RightHip", "RightKnee", "RightAnkle"],
        frames=455, channels=60, order="ZXY",
        root_channels=("Xposition", "Yposition", "Zposition", "Zrotation", "Xrotation", "Yrotation"),
    ),
    "walk": dict(
        names=["Hips", "LeftUpLeg", "LeftLeg", "LeftFoot", "LeftToe", "RightUpLeg", "RightLeg",
               "RightFoot", "RightToe", "Spine", "Spine1", "Spine2", "Neck", "Head", "LeftShoulder",
               "LeftArm", "LeftForeArm", "LeftHand", "RightShoulder", "RightArm", "RightForeArm",
               "RightHand"],
        frames=900, channels=69, order="ZYX",
        root_channels=("Xposition", "Yposition", "Zposition", "Zrotation", "Yrotation", "Xrotation"),
    ),
}


def _clip_key(path) -> str:
    return next(k for k, p in CLIPS.items() if p == path)


def test_shipped_clip_structure(clip_path):
    exp = EXPECTED[_clip_key(clip_path)]
    clip = read_bvh(clip_path)
    assert [j.name for j in clip.joints] == exp["names"]
    assert clip.n_frames == exp["frames"]
    assert clip.n_channels == exp["channels"] == 6 + 3 * (len(exp["names"]) - 1)
    assert clip.frame_time == 0.033333  # kept exactly as written
    assert clip.frame_time == pytest.approx(1 / 30, rel=1e-4)
    assert clip.fps == pytest.approx(30.0, rel=1e-4)
    assert clip.duration == pytest.approx((exp["frames"] - 1) * 0.033333)
    assert clip.length_scale == 0.01  # detected as centimetres
    root = clip.joints[0]
    assert root.parent == -1 and root.channels == exp["root_channels"]
    assert root.translation_columns == (0, 1, 2) and root.rotation_columns == (3, 4, 5)
    for k, joint in enumerate(clip.joints):
        assert joint.rotation_order == exp["order"]
        if k:
            assert 0 <= joint.parent < k and joint.translation_columns == ()
            assert joint.rotation_columns == tuple(range(joint.channel_start, joint.channel_start + 3))
    assert clip.motion.shape == (exp["frames"], exp["channels"])
    assert np.all(np.isfinite(clip.motion))
    # Rest pose: a human of plausible size, in metres.
    pos = rest_pose_positions(clip)
    assert 1.0 < np.linalg.norm(np.ptp(pos, axis=0)) < 2.6


def test_shipped_clip_values():
    walk = read_bvh(CLIPS["walk"])
    np.testing.assert_allclose(walk.joints[0].offset, [-2.24689499, 0.91882057, -4.31625488], rtol=1e-12)
    left_leg = walk.joints[walk.joint_index("LeftLeg")]
    np.testing.assert_allclose(left_leg.offset, [0.435, -0.00000042, 0.0000001], rtol=1e-12)
    assert walk.joints[walk.joint_index("LeftToe")].end_site.tolist() == [0.0, 0.0, 0.0]
    assert walk.children(0) == (1, 5, 9)
    mb = read_bvh(CLIPS["mocapbank"])
    chest = mb.joints[mb.joint_index("Chest")]
    np.testing.assert_allclose(chest.offset, [-0.001728, 0.102870, 0.001254], rtol=1e-12)
    np.testing.assert_allclose(mb.joints[mb.joint_index("LeftWrist")].end_site,
                               [0.014871, -0.139919, 0.011523], rtol=1e-12)
    np.testing.assert_allclose(mb.motion[-1, :3], [-0.473922, 0.941088, 2.305628], rtol=1e-12)
    np.testing.assert_allclose(mb.motion[-1, 3:6], [-3.80, -21.68, 1.69], rtol=1e-12)  # degrees


def test_shipped_clip_round_trip(clip_path, tmp_path):
    clip = read_bvh(clip_path)
    out = tmp_path / "copy.bvh"
    write_bvh(out, clip)
    again = read_bvh(out)
    _assert_clips_match(clip, again)
    assert os.listdir(tmp_path) == ["copy.bvh"]


def test_truncated_shipped_clip_reports_line():
    lines = CLIPS["walk"].read_text().splitlines()
    time_line = next(i for i, l in enumerate(lines, 1) if l.startswith("Frame Time"))
    text = "\n".join(lines[: time_line + 500]) + "\n\n"
    with pytest.raises(BvhError) as info:
        parse_bvh(text, path="walk.bvh")
    err = info.value
    assert err.line == time_line + 500 and err.path == "walk.bvh"
    assert str(err).startswith(f"walk.bvh:{time_line + 500}: ")
    assert "900" in err.message and "500" in err.message and "truncated" in err.message


def _assert_clips_match(a: BvhClip, b: BvhClip, rtol: float = 1e-6, atol: float | None = None) -> None:
    # 8 written decimals: <= 5e-9 file units (positions) or degrees (rotations) of rounding
    atol = 1e-8 * max(1.0, a.length_scale) if atol is None else atol
    assert b.length_scale == a.length_scale
    assert b.frame_time == a.frame_time
    assert len(a.joints) == len(b.joints)
    for ja, jb in zip(a.joints, b.joints):
        assert (ja.name, ja.parent, ja.channels, ja.channel_start) == (jb.name, jb.parent, jb.channels, jb.channel_start)
        np.testing.assert_allclose(jb.offset, ja.offset, rtol=rtol, atol=atol)
        assert (ja.end_site is None) == (jb.end_site is None)
        if ja.end_site is not None:
            np.testing.assert_allclose(jb.end_site, ja.end_site, rtol=rtol, atol=atol)
    assert a.motion.shape == b.motion.shape
    np.testing.assert_allclose(b.motion, a.motion, rtol=rtol, atol=atol)


# ----------------------------------------------------------------------------------------------
# Generated skeletons and an independent serializer

AXES = "XYZ"


@dataclasses.dataclass
class Skel:
    names: list[str]  # words joined by single spaces
    parents: list[int]
    offsets: list[tuple[float, float, float]]  # file units
    channels: list[tuple[str, ...]]  # spelled as they will be written
    end_sites: list[tuple[float, float, float] | None]
    frame_time: float
    motion: list[list[float]]  # file units (positions) / degrees


@dataclasses.dataclass
class Style:
    newline: str
    indent: str
    sep: str
    trailing: str
    blank_tail: int
    brace: str  # "own" line, "same" line after a separator, "glued" to the name
    number: str  # "repr", "fixed", "exp"

    def fmt(self, x: float) -> str:
        return {"repr": repr, "fixed": lambda v: f"{v:.6f}", "exp": lambda v: f"{v:.12e}"}[self.number](float(x))


@dataclasses.dataclass
class Layout:
    """1-based line numbers of the interesting lines of a serialized file."""

    joint: list[int]
    offset: list[int]
    channels: list[int]
    end_offset: dict[int, int]
    close: list[int]
    motion: int
    frames: int
    frame_time: int
    frame: list[int]


def _spell(draw, axis: str, kind: str) -> str:
    return draw(st.sampled_from([f"{axis}{kind}", f"{axis}{kind.capitalize()}", f"{axis}{kind}".upper(),
                                 f"{axis.lower()}{kind}"]))


name_words = st.text(alphabet="abcdefghijklmnopqrstuvwxyzABCDEFGHIJKLMNOPQRSTUVWXYZ0123456789_:.-éß",
                     min_size=1, max_size=8)
joint_names = st.lists(name_words, min_size=1, max_size=2).map(" ".join)
coords = st.floats(-150, 150, allow_nan=False, allow_infinity=False)
offsets3 = st.one_of(st.just((0.0, 0.0, 0.0)), st.tuples(coords, coords, coords))


@st.composite
def channel_lists(draw, root: bool) -> tuple[str, ...]:
    kinds = ["rot", "rot+pos"] + ([] if root else ["none", "pos"])
    kind = draw(st.sampled_from(kinds))
    rot = [_spell(draw, a, "rotation") for a in draw(st.permutations(AXES))]
    pos = [_spell(draw, a, "position") for a in draw(st.permutations(AXES))]
    if kind == "none":
        return ()
    if kind == "rot":
        return tuple(rot)
    if kind == "pos":
        return tuple(pos)
    return tuple(draw(st.sampled_from([pos + rot, rot + pos, None])) or draw(st.permutations(pos + rot)))


@st.composite
def skeletons(draw, max_joints: int = 9) -> Skel:
    n = draw(st.integers(1, max_joints))
    names = draw(st.lists(joint_names, min_size=n, max_size=n, unique=True))
    parents, chain = [-1], [0]
    for i in range(1, n):
        depth = draw(st.integers(1, len(chain)))  # parent: the previous joint or one of its ancestors
        chain = chain[:depth]
        parents.append(chain[-1])
        chain.append(i)
    channels = [draw(channel_lists(root=(i == 0))) for i in range(n)]
    offsets = [draw(offsets3) for _ in range(n)]
    leaves = {i for i in range(n) if i not in parents}
    end_sites = [draw(offsets3) if draw(st.booleans()) or (i in leaves and draw(st.booleans())) else None
                 for i in range(n)]
    n_channels = sum(len(c) for c in channels)
    n_frames = draw(st.integers(1, 4))
    value = st.floats(-720, 720, allow_nan=False, allow_infinity=False)
    motion = draw(st.lists(st.lists(value, min_size=n_channels, max_size=n_channels),
                           min_size=n_frames, max_size=n_frames))
    frame_time = draw(st.sampled_from([0.033333, 1 / 30, 0.008333, 0.01, 1 / 120]) | st.floats(1e-4, 1.0))
    return Skel(names, parents, offsets, channels, end_sites, frame_time, motion)


styles = st.builds(
    Style,
    newline=st.sampled_from(["\n", "\r\n"]),
    indent=st.sampled_from(["\t", "  ", "    ", ""]),
    sep=st.sampled_from([" ", "\t", "  ", " \t "]),
    trailing=st.sampled_from(["", " ", "\t", "  \t"]),
    blank_tail=st.integers(0, 3),
    brace=st.sampled_from(["own", "same", "glued"]),
    number=st.sampled_from(["repr", "fixed", "exp"]),
)


def serialize(skel: Skel, style: Style) -> tuple[list[str], Layout]:
    """Write ``skel`` as BVH lines (no line ends) and record where each item went."""
    s = style.sep
    lines: list[str] = ["HIERARCHY"]
    n = len(skel.names)
    lay = Layout([0] * n, [0] * n, [0] * n, {}, [], 0, 0, 0, [])

    def add(depth: int, text: str) -> int:
        lines.append(style.indent * depth + text)
        return len(lines)

    def opener(depth: int, head: str) -> int:
        if style.brace == "own":
            line = add(depth, head)
            add(depth, "{")
            return line
        return add(depth, head + ("{" if style.brace == "glued" else s + "{"))

    def vec(v) -> str:
        return s.join(style.fmt(x) for x in v)

    stack: list[int] = []

    def close() -> None:
        k = stack.pop()
        depth = len(stack)
        if skel.end_sites[k] is not None:
            opener(depth + 1, f"End{s}Site")
            lay.end_offset[k] = add(depth + 2, f"OFFSET{s}{vec(skel.end_sites[k])}")
            lay.close.append(add(depth + 1, "}"))
        lay.close.append(add(depth, "}"))

    for k in range(n):
        while stack and stack[-1] != skel.parents[k]:
            close()
        depth = len(stack)
        keyword = "ROOT" if k == 0 else "JOINT"
        lay.joint[k] = opener(depth, f"{keyword}{s}{s.join(skel.names[k].split(' '))}")
        lay.offset[k] = add(depth + 1, f"OFFSET{s}{vec(skel.offsets[k])}")
        lay.channels[k] = add(depth + 1, s.join(["CHANNELS", str(len(skel.channels[k])), *skel.channels[k]]))
        stack.append(k)
    while stack:
        close()
    lay.motion = add(0, "MOTION")
    lay.frames = add(0, f"Frames:{s}{len(skel.motion)}")
    lay.frame_time = add(0, f"Frame Time:{s}{skel.frame_time!r}")
    for row in skel.motion:
        lay.frame.append(add(0, vec(row)))
    return lines, lay


def join(lines: list[str], style: Style) -> str:
    body = style.newline.join(line + style.trailing for line in lines)
    return body + style.newline + style.newline * style.blank_tail


def _expected_columns(channels: tuple[str, ...], start: int):
    low = [c.lower() for c in channels]
    order = "".join(c[0].upper() for c in low if c.endswith("rotation"))
    rot = tuple(start + i for i, c in enumerate(low) if c.endswith("rotation"))
    pos = {c[0]: start + i for i, c in enumerate(low) if c.endswith("position")}
    trans = tuple(pos[a] for a in "xyz") if pos else ()
    return order, rot, trans


def check_matches(clip: BvhClip, skel: Skel, style: Style, scale: float) -> None:
    assert clip.length_scale == scale
    assert [j.name for j in clip.joints] == skel.names
    assert [j.parent for j in clip.joints] == skel.parents
    assert clip.frame_time == skel.frame_time
    start = 0
    pos_cols = []
    for k, joint in enumerate(clip.joints):
        assert joint.channels == skel.channels[k]
        assert joint.channel_start == start
        order, rot, trans = _expected_columns(skel.channels[k], start)
        assert (joint.rotation_order, joint.rotation_columns, joint.translation_columns) == (order, rot, trans)
        pos_cols += [start + i for i, c in enumerate(skel.channels[k]) if c.lower().endswith("position")]
        start += len(skel.channels[k])
        want = [float(style.fmt(x)) * scale for x in skel.offsets[k]]
        np.testing.assert_allclose(joint.offset, want, rtol=1e-15, atol=0)
        if skel.end_sites[k] is None:
            assert joint.end_site is None
        else:
            want = [float(style.fmt(x)) * scale for x in skel.end_sites[k]]
            np.testing.assert_allclose(joint.end_site, want, rtol=1e-15, atol=0)
        assert clip.children(k) == tuple(i for i, p in enumerate(skel.parents) if p == k)
        assert clip.joint_index(joint.name) == k
    want = np.array([[float(style.fmt(x)) for x in row] for row in skel.motion]).reshape(len(skel.motion), start)
    want[:, pos_cols] *= scale
    np.testing.assert_allclose(clip.motion, want, rtol=1e-15, atol=0)


@SETTINGS
@given(skel=skeletons(), style=styles, unit=st.sampled_from(["m", "cm"]))
def test_generated_skeleton_parses(skel, style, unit):
    lines, lay = serialize(skel, style)
    clip = parse_bvh(join(lines, style), path="gen.bvh", units=unit)
    check_matches(clip, skel, style, {"m": 1.0, "cm": 0.01}[unit])
    assert [j.line for j in clip.joints] == lay.joint


def _rest_size(skel: Skel) -> float:
    pos = [np.zeros(3)]
    for k in range(1, len(skel.names)):
        pos.append(pos[skel.parents[k]] + np.array(skel.offsets[k]))
    pts = pos + [pos[k] + np.array(e) for k, e in enumerate(skel.end_sites) if e is not None]
    pts = np.array(pts)
    return float(np.linalg.norm(pts.max(0) - pts.min(0)))


@SETTINGS
@given(skel=skeletons(), unit=st.sampled_from(["m", "cm", "mm"]), height=st.floats(0.8, 3.0))
def test_auto_units(skel, unit, height):
    size = _rest_size(skel)
    assume(size > 1e-3)
    scale = {"m": 1.0, "cm": 0.01, "mm": 0.001}[unit]
    factor = height / scale / size  # make the skeleton `height` metres tall in `unit`
    skel.offsets = [tuple(x * factor for x in o) for o in skel.offsets]
    skel.end_sites = [None if e is None else tuple(x * factor for x in e) for e in skel.end_sites]
    style = Style("\n", "\t", " ", "", 0, "own", "repr")
    lines, _ = serialize(skel, style)
    clip = parse_bvh(join(lines, style), units="auto")
    assert clip.length_scale == scale
    check_matches(clip, skel, style, scale)


@SETTINGS
@given(skel=skeletons(), style=styles, unit=st.sampled_from(["m", "cm", "mm", "in", 0.5]))
def test_generated_round_trip(skel, style, unit):
    lines, _ = serialize(skel, style)
    clip = parse_bvh(join(lines, style), units=unit)
    with tempfile.TemporaryDirectory() as tmp:
        out = os.path.join(tmp, "out.bvh")
        write_bvh(out, clip)
        again = read_bvh(out, units=clip.length_scale)
        assert os.listdir(tmp) == ["out.bvh"]
    _assert_clips_match(clip, again)
    rot = [c for j in clip.joints for c in j.rotation_columns]
    np.testing.assert_allclose(np.deg2rad(again.motion[:, rot]), np.deg2rad(clip.motion[:, rot]), rtol=0, atol=1e-9)


# ----------------------------------------------------------------------------------------------
# Generated damage: each must raise BvhError at a known line

DAMAGES = [
    "truncate_lines", "truncate_mid_line", "drop_value", "add_value", "non_numeric", "non_finite",
    "bogus_channel", "duplicate_axis", "channel_count", "frames_zero", "frames_invalid", "frame_time_bad",
    "second_root", "offset_count", "offset_text", "duplicate_name", "missing_brace",
    "no_motion",
]


def damage(data, skel: Skel, lines: list[str], lay: Layout, kind: str) -> tuple[list[str], int | None, str]:
    """Damage ``lines``; return the new lines, the line the error must name (None: unchecked) and a
    word the message must contain."""
    draw = data.draw
    lines = list(lines)
    n_frames, n_channels = len(lay.frame), len(skel.motion[0])

    def frame_tokens(t: int) -> list[str]:
        return lines[lay.frame[t] - 1].split()

    if kind == "truncate_lines":
        k = draw(st.integers(1, n_frames))
        del lines[lay.frame[-1] - k:]
        return lines, (lay.frame[n_frames - k - 1] if k < n_frames else lay.frame_time), "truncated"
    if kind == "truncate_mid_line":
        t = draw(st.integers(0, n_frames - 1))
        m = draw(st.integers(0, n_channels - 1))
        keep = frame_tokens(t)[:m]
        del lines[lay.frame[t] - 1:]
        if m == 0:
            return lines, (lay.frame[t - 1] if t else lay.frame_time), "truncated"
        lines.append(" ".join(keep))
        return lines, lay.frame[t], "truncated"
    if kind in ("drop_value", "add_value", "non_numeric", "non_finite"):
        t = draw(st.integers(0, n_frames - 1))
        toks = frame_tokens(t)
        if kind == "drop_value":
            del toks[draw(st.integers(0, len(toks) - 1))]
            word = str(n_channels)
        elif kind == "add_value":
            toks.insert(draw(st.integers(0, len(toks))), "1.5")
            word = "expected"
        elif kind == "non_numeric":
            toks[draw(st.integers(0, len(toks) - 1))] = draw(st.sampled_from(["abc", "1.2.3", "--5", "x", "1e", "0x1p", "#"]))
            word = "not a number"
        else:
            toks[draw(st.integers(0, len(toks) - 1))] = draw(st.sampled_from(["nan", "NaN", "inf", "-inf", "Infinity"]))
            word = "not finite"
        lines[lay.frame[t] - 1] = " ".join(toks)
        return lines, lay.frame[t], word
    if kind in ("bogus_channel", "duplicate_axis", "channel_count"):
        k = draw(st.sampled_from([i for i, c in enumerate(skel.channels) if c]))
        toks = lines[lay.channels[k] - 1].split()
        if kind == "bogus_channel":
            toks[2 + draw(st.integers(0, len(toks) - 3))] = draw(st.sampled_from(
                ["Wrotation", "Xrot", "Xposition2", "rotation", "Xscale", "X"]))
            word = "unknown channel"
        elif kind == "duplicate_axis":
            names = toks[2:]
            i, j = draw(st.permutations(range(len(names))))[:2]
            assume(names[i][1:].lower() == names[j][1:].lower())
            toks[2 + j] = names[i]
            word = "duplicate"
        else:
            toks[1] = str(int(toks[1]) + draw(st.sampled_from([-1, 1, 3])))
            word = "CHANNELS declares"
        lines[lay.channels[k] - 1] = " ".join(toks)
        return lines, lay.channels[k], word
    if kind == "frames_zero":
        lines[lay.frames - 1] = "Frames: 0"
        return lines, lay.frames, "at least one frame"
    if kind == "frames_invalid":
        lines[lay.frames - 1] = "Frames: " + draw(st.sampled_from(["-3", "abc", "", "2.5"]))
        return lines, lay.frames, "Frames"
    if kind == "frame_time_bad":
        lines[lay.frame_time - 1] = "Frame Time: " + draw(st.sampled_from(["0", "-0.033", "abc", "nan", "inf", ""]))
        return lines, lay.frame_time, "Frame Time"
    if kind == "second_root":
        extra = ["ROOT Extra", "{", "OFFSET 0 0 0", "CHANNELS 3 Zrotation Xrotation Yrotation", "}"]
        lines[lay.motion - 1:lay.motion - 1] = extra
        return lines, lay.motion, "several ROOTs"
    if kind in ("offset_count", "offset_text"):
        where = [lay.offset[k] for k in range(len(skel.names))] + list(lay.end_offset.values())
        line = draw(st.sampled_from(where))
        toks = lines[line - 1].split()
        if kind == "offset_count":
            if draw(st.booleans()):
                del toks[draw(st.integers(1, 3))]
            else:
                toks.append("0.5")
            word = "OFFSET needs 3"
        else:
            toks[draw(st.integers(1, 3))] = draw(st.sampled_from(["abc", "nan", "inf", "1..2"]))
            word = "OFFSET value"
        lines[line - 1] = " ".join(toks)
        return lines, line, word
    if kind == "duplicate_name":
        assume(len(skel.names) >= 2)
        j = draw(st.integers(1, len(skel.names) - 1))
        i = draw(st.integers(0, j - 1))
        head = lines[lay.joint[j] - 1]
        lines[lay.joint[j] - 1] = f"{head.split()[0]} {skel.names[i]}" + (" {" if head.endswith("{") else "")
        return lines, lay.joint[j], "duplicate joint name"
    if kind == "missing_brace":
        del lines[draw(st.sampled_from(lay.close)) - 1]
        return lines, None, ""
    if kind == "no_motion":
        del lines[lay.motion - 1:]
        return lines, len(lines), "MOTION"
    raise AssertionError(kind)


@pytest.mark.parametrize("kind", DAMAGES)
@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow, HealthCheck.filter_too_much])
@given(data=st.data(), skel=skeletons(max_joints=6), style=styles)
def test_generated_damage(kind, data, skel, style):
    lines, lay = serialize(skel, style)
    bad, line, word = damage(data, skel, lines, lay, kind)
    path = "dir/damaged file.bvh"
    with pytest.raises(BvhError) as info:
        parse_bvh(join(bad, style), path=path, units="cm")
    err = info.value
    assert isinstance(err, ValueError) and err.path == path
    assert str(err).startswith(f"{path}:{err.line}: ")
    assert err.line is not None and 1 <= err.line <= len(bad)
    if line is not None:
        assert err.line == line, str(err)
    assert word in err.message, str(err)


# ----------------------------------------------------------------------------------------------
# Hand-written cases

SMALL = """HIERARCHY
ROOT Pelvis
{
  OFFSET 0 90 0
  CHANNELS 6 Xposition Yposition Zposition Yrotation Xrotation Zrotation
  JOINT Spine
  {
    OFFSET 0 10 0
    CHANNELS 6 Zrotation Xrotation Yrotation Zposition Xposition Yposition
    End Site
    {
      OFFSET 0 50 0
    }
  }
  JOINT Leg
  {
    OFFSET 10 -5 0
    CHANNELS 3 Xrotation Zrotation Yrotation
    JOINT Shin
    {
      OFFSET 0 -45 0
      CHANNELS 0
      End Site
      {
        OFFSET 0 -40 0
      }
    }
  }
}
MOTION
Frames: 2
Frame Time: 0.0083333
1 90 2 10 20 30 1 2 3 4 5 6 7 8 9
1 91 2 11 21 31 1 2 3 4 5 6 7 8 9
"""


def test_extra_frame_lines_load_with_a_warning():
    # More frame lines than declared is common in exported files: all load, with a warning naming the line.
    lines = SMALL.rstrip("\n").split("\n")
    text = "\n".join(lines + [lines[-1], lines[-2]]) + "\n"
    clip = parse_bvh(text, path="extra.bvh")
    assert clip.n_frames == 4
    first_extra = len(lines) + 1
    assert clip.warnings == (f"extra.bvh:{first_extra}: 2 more frame lines than 'Frames: 2' declares; "
                             f"loaded all 4",)
    np.testing.assert_array_equal(clip.motion[2], clip.motion[1])
    assert parse_bvh(SMALL).warnings == ()
    with pytest.raises(BvhError, match="has 3 values"):  # a short extra line stays an error
        parse_bvh(text + "1 2 3\n", path="extra.bvh")


def test_small_file_conventions():
    clip = parse_bvh(SMALL, path="small.bvh")
    assert clip.length_scale == 0.01  # rest-pose box diagonal 150 units -> cm
    spine = clip.joints[1]
    assert spine.rotation_order == "ZXY" and spine.rotation_columns == (6, 7, 8)
    assert spine.translation_columns == (10, 11, 9)  # X, Y, Z whatever the file order
    np.testing.assert_allclose(clip.motion[0, [10, 11, 9]], [0.05, 0.06, 0.04])
    assert clip.joints[0].rotation_order == "YXZ"
    assert clip.joints[3].channels == () and clip.joints[3].rotation_order == ""
    assert clip.joints[3].translation_columns == () and clip.joints[3].rotation_columns == ()
    assert clip.joints[2].channel_start == 12
    assert clip.children(0) == (1, 2) and clip.children(3) == ()
    assert [j.line for j in clip.joints] == [2, 6, 15, 19]
    np.testing.assert_allclose(rest_pose_positions(clip), [[0, 0.9, 0], [0, 1.0, 0], [0.1, 0.85, 0], [0.1, 0.4, 0]])
    assert clip.duration == pytest.approx(0.0083333) and clip.n_frames == 2 and clip.n_channels == 15
    with pytest.raises(KeyError, match="Pelvis, Spine, Leg, Shin"):
        clip.joint_index("Arm")
    with pytest.raises(ValueError):
        clip.motion[0, 0] = 1.0  # read-only


def test_units_argument():
    assert parse_bvh(SMALL, units="mm").length_scale == 0.001
    assert parse_bvh(SMALL, units="M").length_scale == 1.0
    clip = parse_bvh(SMALL, units="in")
    assert clip.length_scale == 0.0254
    np.testing.assert_allclose(clip.joints[1].offset, [0, 0.254, 0])
    np.testing.assert_allclose(parse_bvh(SMALL, units=2).motion[0, :3], [2, 180, 4])
    for bad in ["km", "", -1.0, 0, float("nan"), float("inf"), True, None, [1.0]]:
        with pytest.raises(ValueError, match="units"):
            parse_bvh(SMALL, units=bad)
    with pytest.raises(ValueError, match="units"):
        read_bvh("/nonexistent/file.bvh", units="feet")


def test_error_format_and_pickle():
    err = BvhError("a/b.bvh", 12, "bad thing")
    assert str(err) == "a/b.bvh:12: bad thing" and err.line == 12 and err.message == "bad thing"
    assert str(BvhError("x.bvh", None, "m")) == "x.bvh: m"
    back = pickle.loads(pickle.dumps(err))
    assert (back.path, back.line, back.message, str(back)) == (err.path, err.line, err.message, str(err))


@pytest.mark.parametrize("text, line, word", [
    ("", 1, "empty file"),
    ("ROOT A\n", 1, "HIERARCHY"),
    ("HIERARCHY\nROOT A\n{\n  OFFSET 0 0 0\n  CHANNELS 3 Xrotation Yrotation Zrotation\n", 5, "not closed"),
    ("HIERARCHY\nROOT A\n{\n  OFFSET 0 0 0\n  CHANNELS 3 Xrotation Yrotation Zrotation\n}\n", 6, "missing MOTION"),
    ("HIERARCHY\nROOT A\n  OFFSET 0 0 0\n", 3, "expected '{'"),
    ("HIERARCHY\nROOT A\n{\n  CHANNELS 3 Xrotation Yrotation Zrotation\n}\nMOTION\n", 2, "no OFFSET"),
    ("HIERARCHY\nROOT A\n{\n  OFFSET 0 0 0\n  CHANNELS 2 Xrotation Yrotation\n}\n", 5, "0 or 3 rotation"),
    ("HIERARCHY\nROOT A\n{\n  OFFSET 0 0 0\n  CHANNELS 4 Xrotation Yrotation Zrotation Xposition\n}\n", 5,
     "0 or 3 position"),
    ("HIERARCHY\nROOT A\n{\n  OFFSET 0 0 0\n  CHANNELS 3 Xrotation Yrotation Zrotation\n}\n}\n", 7, "unmatched"),
    ("HIERARCHY\nJOINT A\n", 2, "before ROOT"),
    ("HIERARCHY\nROOT A\n{\n OFFSET 0 0 0\n End Site\n {\n  OFFSET 0 1 0\n }\n End Site\n", 9, "second End Site"),
    ("HIERARCHY\nROOT A\n{\n OFFSET 0 0 0\n CHANNELS 3 Xrotation Yrotation Zrotation\n}\nMOTION\n", 7, "Frames"),
    ("HIERARCHY\nROOT A\n{\n OFFSET 0 0 0\n CHANNELS 3 Xrotation Yrotation Zrotation\n}\nMOTION\nFrames: 1\n"
     "1 2 3\n", 9, "Frame Time"),
    ("HIERARCHY\nROOT A\n{\n OFFSET 0 0 0\n}\nMOTION\nFrames: 1\nFrame Time: 0.1\n\n", 8, "no channels"),
])
def test_handwritten_errors(text, line, word):
    with pytest.raises(BvhError) as info:
        parse_bvh(text, path="h.bvh")
    assert info.value.line == line, str(info.value)
    assert word in info.value.message, str(info.value)


def test_read_encodings_and_bom(tmp_path):
    text = SMALL.replace("Spine", "Épine")
    (tmp_path / "latin.bvh").write_bytes(text.encode("latin-1"))
    (tmp_path / "bom.bvh").write_bytes(b"\xef\xbb\xbf" + text.replace("\n", "\r\n").encode("utf-8"))
    assert read_bvh(tmp_path / "latin.bvh").joints[1].name == "Épine"
    clip = read_bvh(tmp_path / "bom.bvh")
    assert clip.joints[1].name == "Épine" and clip.path == str(tmp_path / "bom.bvh")
    with pytest.raises(BvhError) as info:
        (tmp_path / "bad.bvh").write_text(SMALL.replace("Frames: 2", "Frames: 3"))
        read_bvh(tmp_path / "bad.bvh")
    assert str(info.value).startswith(f"{tmp_path / 'bad.bvh'}:34: ")


# ----------------------------------------------------------------------------------------------
# Writer

def test_write_custom_motion_and_precision(tmp_path):
    clip = parse_bvh(SMALL, units="cm")
    motion = np.array(clip.motion)
    motion[:, 3:6] += 1e-7  # degrees: needs > 6 decimals
    motion[:, 0] = 0.123456789  # metres
    write_bvh(tmp_path / "m.bvh", clip, motion=motion)
    again = read_bvh(tmp_path / "m.bvh")
    np.testing.assert_allclose(again.motion, motion, rtol=1e-9, atol=1e-12)
    write_bvh(tmp_path / "p.bvh", clip, motion=motion, precision=2)
    coarse = read_bvh(tmp_path / "p.bvh")
    assert coarse.motion[0, 0] == pytest.approx(0.1235)  # 12.35 cm
    text = (tmp_path / "p.bvh").read_text()
    assert "Frame Time: 0.0083333" in text and "CHANNELS 6 Zrotation Xrotation Yrotation Zposition" in text
    assert "CHANNELS 0" in text and "\r" not in text


def test_write_rejects_bad_motion_without_writing(tmp_path):
    clip = parse_bvh(SMALL)
    target = tmp_path / "out.bvh"
    for bad in [np.zeros((2, 14)), np.zeros((0, 15)), np.zeros(15), np.full((2, 15), np.nan)]:
        with pytest.raises(ValueError):
            write_bvh(target, clip, motion=bad)
        assert os.listdir(tmp_path) == []
    with pytest.raises(ValueError, match="precision"):
        write_bvh(target, clip, precision=-1)
    assert os.listdir(tmp_path) == []
    # An existing file is left as it was.
    target.write_text("old")
    with pytest.raises(ValueError):
        write_bvh(target, clip, motion=np.zeros((3, 3)))
    assert target.read_text() == "old" and os.listdir(tmp_path) == ["out.bvh"]


def test_write_failure_leaves_no_temp_file(tmp_path, monkeypatch):
    clip = parse_bvh(SMALL)
    target = tmp_path / "out.bvh"
    target.write_text("old")

    def broken_replace(src, dst):
        raise OSError("disk on fire")

    monkeypatch.setattr(os, "replace", broken_replace)
    with pytest.raises(OSError, match="disk on fire"):
        write_bvh(target, clip)
    assert target.read_text() == "old" and os.listdir(tmp_path) == ["out.bvh"]
    monkeypatch.undo()
    write_bvh(target, clip)
    _assert_clips_match(clip, read_bvh(target))
    with pytest.raises(OSError):
        write_bvh(tmp_path / "missing_dir" / "x.bvh", clip)


def test_clip_validation():
    clip = parse_bvh(SMALL)
    with pytest.raises(ValueError, match="shape"):
        dataclasses.replace(clip, motion=np.zeros((2, 3)))
    swapped = (clip.joints[0], clip.joints[2], clip.joints[1], clip.joints[3])
    with pytest.raises(ValueError):
        dataclasses.replace(clip, joints=swapped)
    with pytest.raises(ValueError, match="channel"):
        BvhJoint("A", -1, np.zeros(3), ("Xrotation", "Xrotation", "Yrotation"), 0)
    j = BvhJoint("A", -1, [1, 2, 3], ["Zrotation", "Yrotation", "Xrotation"], 0)
    assert j.channels == ("Zrotation", "Yrotation", "Xrotation") and j.offset.dtype == np.float64
    made = BvhClip("made", (j,), 0.1, np.zeros((3, 3)), 1.0)
    assert made.n_frames == 3 and made.duration == pytest.approx(0.2) and math.isclose(made.fps, 10.0)
