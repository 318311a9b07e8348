"""neuromotor.model.anatomy (with labels, units and clip_edit): labels, sides, mirrors, up axis,
units and the virtual root, on the shipped clips (answers checked by eye and written out below)
and on random synthetic rigs."""

import dataclasses
import pathlib
import re

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from neuromotor.model.anatomy import SEGMENTS, UNIT_CHOICES, analyse, prepare_clip
from neuromotor.model.clip_edit import collapse_virtual_root, forward_kinematics, scale_clip
from neuromotor.model.bvh import parse_bvh, read_bvh

from synthetic_rigs import make_rig

MOCAP = pathlib.Path(__file__).resolve().parents[2].parent / "shared" / "mocap"
FILES = {
    "mocapbank": "mocapbank_19joint.bvh",
    "walk": "walk_22joint_zyx.bvh",
    "cmu": "cmu_01_01_jumps_31joint.bvh",
    "bandai": "bandai_kick_22joint_6ch.bvh",
}

# Expected segment of every joint, by name with the side marker written as '*' (both sides).
EXPECTED = {
    "mocapbank": {
        "Hips": "trunk", "Chest": "trunk", "Chest2": "trunk", "*Collar": "trunk", "*Shoulder": "upper_arm",
        "*Elbow": "forearm", "*Wrist": "hand", "Neck": "head", "Head": "head", "*Hip": "thigh",
        "*Knee": "shank", "*Ankle": "foot",
    },
    "walk": {
        "Hips": "trunk", "*UpLeg": "thigh", "*Leg": "shank", "*Foot": "foot", "*Toe": "toe", "Spine": "trunk",
        "Spine1": "trunk", "Spine2": "trunk", "Neck": "head", "Head": "head", "*Shoulder": "trunk",
        "*Arm": "upper_arm", "*ForeArm": "forearm", "*Hand": "hand",
    },
    "cmu": {
        "Hips": "trunk", "*HipJoint": "trunk", "*UpLeg": "thigh", "*Leg": "shank", "*Foot": "foot",
        "*ToeBase": "toe", "LowerBack": "trunk", "Spine": "trunk", "Spine1": "trunk", "Neck": "head",
        "Neck1": "head", "Head": "head", "*Shoulder": "trunk", "*Arm": "upper_arm", "*ForeArm": "forearm",
        "*Hand": "hand", "*FingerBase": "finger", "*Fingers": "finger", "*Thumb": "finger",
    },
    "bandai": {  # joint_Root (the ground marker) is removed
        "Hips": "trunk", "Spine": "trunk", "Chest": "trunk", "Neck": "head", "Head": "head",
        "Shoulder*": "trunk", "UpperArm*": "upper_arm", "LowerArm*": "forearm", "Hand*": "hand",
        "UpperLeg*": "thigh", "LowerLeg*": "shank", "Foot*": "foot", "Toes*": "toe",
    },
}
EXPECTED_UNITS = {"mocapbank": "cm", "walk": "cm", "cmu": "cmu", "bandai": "cm"}
SIDE_FORMS = [("Left", "Right"), ("L", "R"), ("_L", "_R")]


def _split_side(name: str) -> tuple[str, str]:
    """(name with its side marker replaced by '*', side)."""
    for pattern, side in ((r"^Left|^L(?=[A-Z])|_L$", "left"), (r"^Right|^R(?=[A-Z])|_R$", "right")):
        if re.search(pattern, name):
            return re.sub(pattern, "*", name).replace("_*", "*"), side
    return name, ""


def _path(key: str) -> pathlib.Path:
    path = MOCAP / FILES[key]
    if not path.exists():
        pytest.fail(f"shared mocap clip missing: {path}")
    return path


@pytest.fixture(scope="module")
def prepared():
    return {key: prepare_clip(_path(key)) for key in FILES}


@pytest.mark.parametrize("key", sorted(FILES))
def test_shipped_clip_labels_sides_mirrors(prepared, key):
    clip, anatomy, source = prepared[key]
    names = [j.name for j in clip.joints]
    assert len(anatomy.segment) == len(anatomy.side) == len(anatomy.mirror) == len(names)
    assert set(anatomy.segment) <= set(SEGMENTS)
    for k, name in enumerate(names):
        generic, side = _split_side(name)
        assert anatomy.segment[k] == EXPECTED[key][generic], (name, anatomy.segment[k])
        assert anatomy.side[k] == side, (name, anatomy.side[k])
        if side:
            partner = names[anatomy.mirror[k]]
            assert _split_side(partner) == (generic, "right" if side == "left" else "left"), (name, partner)
        else:
            assert anatomy.mirror[k] == -1, name
    assert np.array_equal(anatomy.up, [0.0, 1.0, 0.0]) and anatomy.up_axis == 1
    assert abs(np.linalg.norm(anatomy.forward) - 1) < 1e-12 and abs(anatomy.forward @ anatomy.up) < 1e-12
    assert anatomy.units == EXPECTED_UNITS[key]
    assert anatomy.length_scale == UNIT_CHOICES[EXPECTED_UNITS[key]]
    assert 1.4 <= anatomy.stature <= 2.0
    assert clip.length_scale == source.length_scale == anatomy.length_scale
    assert 0 <= anatomy.reference_frame < clip.n_frames
    chains = anatomy.limb_chains
    for limb, end in (("arm", "hand"), ("leg", "foot")):
        for side in ("left", "right"):
            chain = chains[f"{limb}_{side}"]
            assert anatomy.segment[chain[-1]] == end and all(anatomy.side[k] == side for k in chain)
    assert anatomy.segment[chains["head"][-1]] == "head"


def test_shipped_clip_facts(prepared):
    # Figures worth knowing: CMU's own unit, the walk's tall actor; forward faces +Z at the start of
    # the walk (it walks along +Z).
    assert prepared["cmu"][1].stature == pytest.approx(1.63, abs=0.03)
    assert prepared["walk"][1].stature == pytest.approx(1.78, abs=0.03)
    assert prepared["walk"][1].forward[2] > 0.9
    for key in ("mocapbank", "walk"):
        assert prepared[key][1].warnings == ()
    # CMU's conversion writes the bind pose as frame 1: skipped, and said so.
    (warning,) = prepared["cmu"][1].warnings
    assert "first 1 frame jumps" in warning and "bind pose" in warning
    assert prepared["cmu"][0].n_frames == read_bvh(_path("cmu"), units=1.0).n_frames - 1


def _rotate_file_root(raw, R: np.ndarray):
    """The same clip turned by R: the ROOT's position and rotation channels rotated."""
    root = raw.joints[0]
    motion = raw.motion.copy()
    cols = list(root.translation_columns)
    motion[:, cols] = motion[:, cols] @ R.T
    rcols = list(root.rotation_columns)
    order = root.rotation_order
    Rr = Rotation.from_euler(order, motion[:, rcols], degrees=True).as_matrix()
    motion[:, rcols] = Rotation.from_matrix(R @ Rr).as_euler(order, degrees=True)
    return dataclasses.replace(raw, motion=motion)


@pytest.mark.parametrize("key", sorted(FILES))
def test_z_up_copy_gives_the_same_anatomy(prepared, key):
    clip, anatomy, _ = prepared[key]
    raw = read_bvh(_path(key), units=1.0)
    R = Rotation.from_euler("x", 90, degrees=True).as_matrix()  # Y up -> Z up
    turned_clip, turned, _ = prepare_clip(_rotate_file_root(raw, R))
    assert [j.name for j in turned_clip.joints] == [j.name for j in clip.joints]
    assert turned.segment == anatomy.segment and turned.side == anatomy.side and turned.mirror == anatomy.mirror
    assert np.array_equal(turned.up, [0.0, 0.0, 1.0]) and turned.up_axis == 2
    assert turned.units == anatomy.units and turned.length_scale == anatomy.length_scale
    assert turned.stature == pytest.approx(anatomy.stature, rel=1e-9)
    assert turned.reference_frame == anatomy.reference_frame
    np.testing.assert_allclose(turned.forward, R @ anatomy.forward, atol=1e-6)


def test_bandai_virtual_root_is_collapsed_exactly():
    raw = read_bvh(_path("bandai"), units=1.0)
    new, removed, warnings = collapse_virtual_root(raw)
    assert removed == ("joint_Root",) and len(warnings) == 1 and "joint_Root" in warnings[0]
    assert new.joints[0].name == "Hips" and new.joints[0].parent == -1
    assert new.joints[0].channels[:3] == ("Xposition", "Yposition", "Zposition")
    assert new.joints[0].rotation_order == raw.joints[1].rotation_order
    assert [j.name for j in new.joints] == [j.name for j in raw.joints[1:]]
    assert new.n_channels == raw.n_channels - 6
    pos0, rot0, end0 = forward_kinematics(raw)
    pos1, rot1, end1 = forward_kinematics(new)
    np.testing.assert_allclose(pos1, pos0[:, 1:], rtol=0, atol=1e-9)
    np.testing.assert_allclose(rot1, rot0[:, 1:], rtol=0, atol=1e-9)
    np.testing.assert_allclose(end1, end0[:, 1:], rtol=0, atol=1e-9)
    # Continuous angles: no jumps of hundreds of degrees between frames.
    rot_cols = list(new.joints[0].rotation_columns)
    assert np.abs(np.diff(new.motion[:, rot_cols], axis=0)).max() < 90
    # A clip without a virtual root is left alone.
    plain = read_bvh(_path("walk"), units=1.0)
    same, removed, warnings = collapse_virtual_root(plain)
    assert same is plain and removed == () and warnings == ()


SEEDS = range(30)


@pytest.mark.parametrize("seed", SEEDS)
def test_synthetic_rigs(seed):
    rig = make_rig(seed)
    clip, anatomy, source = prepare_clip(parse_bvh(rig.text, units=1.0))
    assert [j.name for j in clip.joints] == rig.names
    assert list(anatomy.segment) == rig.segment
    assert list(anatomy.side) == rig.side
    assert list(anatomy.mirror) == rig.mirror
    np.testing.assert_array_equal(anatomy.up, rig.up)
    assert anatomy.units == rig.unit
    assert anatomy.stature == pytest.approx(rig.stature, rel=0.08)
    assert (rig.virtual_root is not None) == any("virtual root" in w for w in anatomy.warnings)
    assert source.joints[0].name == (rig.virtual_root or rig.names[0])


def test_synthetic_rigs_cover_the_options():
    seen = {k: set() for k in ("fingers", "toes", "face", "twist", "hip_link", "six_channels", "zero_end_sites",
                               "bent_zero_pose", "up", "virtual_root", "unit")}
    for seed in SEEDS:
        options = make_rig(seed, frames=2).options
        for k in seen:
            seen[k].add(options[k])
    assert all(len(v) >= 2 for v in seen.values()), seen
    assert seen["unit"] == {"m", "cm", "mm", "in", "cmu"}


def test_all_options_at_once():
    rig = make_rig(7, fingers=True, toes=True, face=True, props=2, twist=True, hip_link=True, six_channels=True,
                   zero_end_sites=True, bent_zero_pose=True, up="Z", virtual_root=True, unit="in")
    clip, anatomy, _ = prepare_clip(parse_bvh(rig.text, units=1.0))
    assert list(anatomy.segment) == rig.segment and list(anatomy.side) == rig.side
    assert list(anatomy.mirror) == rig.mirror and anatomy.units == "in"
    assert {"finger", "toe", "face", "detail"} <= set(anatomy.segment)


def test_giant_rig_is_scaled_with_a_warning():
    rig = make_rig(3, scale=2.2, unit="cm", stature=1.8)
    _, anatomy, _ = prepare_clip(parse_bvh(rig.text, units=1.0))
    assert anatomy.units == "scaled" and anatomy.stature == 1.75
    assert any("plausible stature" in w for w in anatomy.warnings)
    assert list(anatomy.segment) == rig.segment


def test_explicit_units_and_stature_win():
    raw = read_bvh(_path("walk"), units=1.0)
    auto = analyse(raw)
    height_raw = auto.stature / auto.length_scale
    mm = analyse(raw, units="mm")
    assert (mm.units, mm.length_scale) == ("mm", 0.001) and mm.stature == pytest.approx(height_raw * 0.001)
    given = analyse(raw, units="cm", stature=1.9)
    assert (given.units, given.length_scale, given.stature) == ("cm", 0.01, 1.9)
    free = analyse(raw, units=0.02)
    assert free.units == "given" and free.length_scale == 0.02
    tall = analyse(raw, stature=2.0)
    assert tall.units == "given" and tall.stature == 2.0
    assert tall.length_scale == pytest.approx(2.0 / height_raw)
    assert tall.segment == auto.segment
    clip, anatomy, source = prepare_clip(_path("walk"), units="in")
    assert clip.length_scale == source.length_scale == 0.0254 and anatomy.units == "in"
    np.testing.assert_allclose(clip.joints[2].offset, raw.joints[2].offset * 0.0254)
    with pytest.raises(ValueError, match="units"):
        analyse(raw, units="furlong")
    with pytest.raises(ValueError, match="stature"):
        analyse(raw, stature=-1.0)


def test_extra_frame_lines_load_with_a_warning(tmp_path):
    text = _path("mocapbank").read_text()
    lines = text.rstrip("\n").split("\n")
    path = tmp_path / "extra.bvh"
    path.write_text("\n".join(lines + lines[-3:]) + "\n")
    clip, anatomy, _ = prepare_clip(path)
    assert clip.n_frames == 455 + 3
    assert anatomy.warnings[0] == (f"{path}:{len(lines) + 1}: 3 more frame lines than 'Frames: 455' declares; "
                                   f"loaded all 458")
    # The character a command builds shows it once (the clip and its anatomy both carry it).
    from neuromotor.model.load import load_character

    warned = [w for w in load_character(path)[0].warnings if "more frame lines" in w]
    assert warned == [anatomy.warnings[0]]


def test_translation_channels_that_move_warn():
    rig = make_rig(11, six_channels=True, virtual_root=False, unit="cm", stature=1.7)
    raw = parse_bvh(rig.text, units=1.0)
    joint = raw.joints[3]
    motion = raw.motion.copy()
    motion[:, joint.translation_columns[0]] += np.linspace(0, 4.0, raw.n_frames)  # 4 cm drift
    anatomy = analyse(dataclasses.replace(raw, motion=motion))
    moved = [w for w in anatomy.warnings if "translation channels" in w]
    assert len(moved) == 1 and repr(joint.name) in moved[0]
    assert analyse(raw).warnings == ()


def test_scale_clip():
    raw = read_bvh(_path("cmu"), units=1.0)
    scaled = scale_clip(raw, 0.5)
    assert scaled.length_scale == 0.5
    np.testing.assert_allclose(scaled.joints[3].offset, raw.joints[3].offset * 0.5)
    np.testing.assert_allclose(scaled.joints[5].end_site, raw.joints[5].end_site * 0.5)
    cols = list(raw.joints[0].translation_columns)
    np.testing.assert_allclose(scaled.motion[:, cols], raw.motion[:, cols] * 0.5)
    rot = list(raw.joints[0].rotation_columns)
    np.testing.assert_array_equal(scaled.motion[:, rot], raw.motion[:, rot])


def test_inspect_shows_labels_units_stature_and_warnings(capsys):
    """`inspect` prints a segment column, the units, stature and up axis and every warning;
    `--json` gives `segment` and `side` per joint."""
    import json

    from neuromotor.cli import main

    path = str(_path("bandai"))
    assert main(["inspect", path, "--json"]) == 0
    data = json.loads(capsys.readouterr().out)
    assert data["units"] == "cm" and 1.4 < data["stature"] < 2.0 and data["up"] == [0.0, 1.0, 0.0]
    assert any("virtual root" in w for w in data["warnings"])
    by_name = {j["name"]: j for j in data["joints"]}
    assert "joint_Root" not in by_name  # removed: Hips is the driven root
    assert by_name["UpperLeg_L"]["segment"] == "thigh" and by_name["UpperLeg_L"]["side"] == "left"
    assert by_name["Toes_R"]["segment"] == "toe" and by_name["Toes_R"]["body"] is None
    assert by_name["Hand_R"]["segment"] == "hand" and by_name["Hand_R"]["body"]["mass"] > 0.2
    assert main(["inspect", path, "--stature", "1.80", "--body-mass", "80"]) == 0
    out = capsys.readouterr().out
    assert "stature   1.800 m" in out and "80.00 kg total" in out and "warning   joint 'joint_Root'" in out
    header = next(line for line in out.splitlines() if line.startswith("joint "))
    assert header.split()[:4] == ["joint", "parent", "segment", "mass"]
    assert re.search(r"^LowerLeg_R\s+UpperLeg_R\s+shank \(R\)", out, re.MULTILINE)
