"""``[sim] driven_joints`` keywords (issue 37): ``trunk``, ``pelvis``, ``legs``, ``arms`` and
``head`` restrain the bodies ``neuromotor inspect`` labels so, on any rig; body names and the
single-body keywords keep working; a name or group that matches nothing is a one-line error
naming the field and index."""

from __future__ import annotations

import pytest

from conftest import ALL_CLIPS
from neuromotor.config import ConfigError
from neuromotor.model.load import load_character
from neuromotor.model.skeleton import GROUP_KEYWORDS, keyword_bodies, keyword_body
from neuromotor.studies.simulate import driven_bodies
from synthetic_rigs import chain_text, make_rig

LIMBS = {"legs": ("thigh", "shank", "foot"), "arms": ("upper_arm", "forearm", "hand")}


def _lr(*names: str) -> set[str]:
    """``{L}``/``{R}`` patterns on both sides."""
    return {n.format(L=s, R=s) for n in names for s in ("Left", "Right")}


def _ends(*names: str) -> set[str]:
    return {f"{n}_{s}" for n in names for s in "LR"}


# What `neuromotor inspect` prints for the shipped clips (segment column), written out by hand.
EXPECTED = {
    "mocapbank_19joint": dict(
        root="Hips",
        trunk={"Chest", "Chest2"} | _lr("{L}Collar"),
        head={"Neck", "Head"},
        arms=_lr("{L}Shoulder", "{L}Elbow", "{L}Wrist"),
        legs=_lr("{L}Hip", "{L}Knee", "{L}Ankle"),
    ),
    "walk_22joint_zyx": dict(
        root="Hips",
        trunk={"Spine", "Spine1", "Spine2"} | _lr("{L}Shoulder"),
        head={"Neck", "Head"},
        arms=_lr("{L}Arm", "{L}ForeArm", "{L}Hand"),
        legs=_lr("{L}UpLeg", "{L}Leg", "{L}Foot"),
    ),
    "cmu_01_01_jumps_31joint": dict(
        root="Hips",
        trunk={"LHipJoint", "RHipJoint", "LowerBack", "Spine", "Spine1"} | _lr("{L}Shoulder"),
        head={"Neck", "Neck1", "Head"},
        arms=_lr("{L}Arm", "{L}ForeArm", "{L}Hand"),
        legs=_lr("{L}UpLeg", "{L}Leg", "{L}Foot"),
    ),
    "bandai_kick_22joint_6ch": dict(
        root="Hips",
        trunk={"Spine", "Chest"} | _ends("Shoulder"),
        head={"Neck", "Head"},
        arms=_ends("UpperArm", "LowerArm", "Hand"),
        legs=_ends("UpperLeg", "LowerLeg", "Foot"),
    ),
}


def _names(character, bodies) -> set[str]:
    return {character.model.body_names[b] for b in bodies}


def _resolved(character, *entries) -> set[str]:
    return _names(character, driven_bodies(character, list(entries), "cfg.toml"))


@pytest.fixture(scope="module", params=sorted(ALL_CLIPS))
def shipped(request):
    return request.param, load_character(ALL_CLIPS[request.param])[0]


def test_every_shipped_clip_drives_the_bodies_inspect_labels(shipped):
    stem, character = shipped
    want = EXPECTED[stem]
    model, anat = character.model, character.anatomy
    assert model.body_names[0] == want["root"]
    for group in ("trunk", "head", "arms", "legs"):
        assert _resolved(character, group) == want[group], group  # the root is driven anyway: left out
        # ... and the anatomy's labels (inspect's segment column) say the same, body by body
        labels = GROUP_KEYWORDS[group]
        labelled = {model.joint_names[k] for k in anat.joints_of(*labels) if model.joint_body[k] >= 0}
        assert labelled == want[group] | ({want["root"]} if group == "trunk" else set())
    # The four groups and the root cover every simulated body once: a restraint misses nothing.
    groups = [want[g] for g in ("trunk", "head", "arms", "legs")] + [{want["root"]}]
    assert sum(len(g) for g in groups) == model.n_bodies == len(set().union(*groups))
    # A belted torso: trunk and pelvis, the pelvis being the root on every shipped clip.
    assert keyword_bodies(character, "pelvis") == (0,) and _resolved(character, "pelvis") == set()
    assert _resolved(character, "trunk", "pelvis") == want["trunk"]
    # Body names and single-body keywords still work, alone or with groups (no duplicates).
    hand = model.body_names[keyword_body(character, "left_hand")]
    assert _resolved(character, "left_hand") == {hand} and hand in want["arms"]
    chest = model.body_names[keyword_body(character, "chest")]
    assert _resolved(character, hand, "arms", "chest") == want["arms"] | {chest}
    assert _resolved(character, want["root"]) == set()  # naming the root is no error: it is driven anyway


@pytest.mark.parametrize("extremities", [False, True])
def test_synthetic_rig_groups_match_the_true_labels(tmp_path, extremities):
    """Random names and Euler orders, fingers, toes, face joints, props, twist joints: each group
    drives exactly the bodies whose true label (the rig's, not the anatomy's) is in it."""
    from neuromotor.model.skeleton import MassModelOptions

    rig = make_rig(7, fingers=True, toes=True, face=True, props=2, twist=True, hip_link=True, frames=30)
    path = tmp_path / "rig.bvh"
    path.write_text(rig.text)
    character, _ = load_character(path, options=MassModelOptions(simulate_extremities=extremities))
    model = character.model
    assert list(model.joint_names) == rig.names
    truth = dict(zip(rig.names, rig.segment))
    bodies = set(model.body_names[1:])
    for group, labels in {"trunk": ("trunk",), "head": ("head",), **LIMBS}.items():
        want = {n for n in bodies if truth[n] in labels}
        assert want, group
        assert _resolved(character, group) == want, group
    # Fingers and face joints are bodies only with simulate_extremities; no group takes them.
    detail = {n for n in bodies if truth[n] in ("finger", "toe", "face", "detail")}
    assert bool(detail) == extremities
    every = _resolved(character, "trunk", "head", "arms", "legs")
    assert every == bodies - detail


def _chain(tmp_path):
    path = tmp_path / "chain.bvh"
    path.write_text(chain_text())
    return path


def test_unmatched_names_and_groups_are_one_line_errors_naming_the_index(tmp_path):
    character, _ = load_character(ALL_CLIPS["mocapbank_19joint"])
    with pytest.raises(ConfigError) as e:
        driven_bodies(character, ["trunk", "Chest2", "tail"], "cfg.toml")
    msg = str(e.value)
    assert msg.startswith("cfg.toml: field 'sim.driven_joints[2]' = 'tail' matches no body; bodies are Hips, ")
    assert "keywords are trunk, pelvis, legs, arms, head, chest" in msg and "\n" not in msg
    chain, _ = load_character(_chain(tmp_path))
    assert _resolved(chain, "trunk") == {"Seg1", "Seg2", "Seg3"}  # everything is trunk on a chain
    for i, group in enumerate(("arms", "legs", "head", "pelvis", "left_hand")):
        with pytest.raises(ConfigError) as e:
            driven_bodies(chain, ["trunk"] * i + [group], "cfg.toml")
        msg = str(e.value)
        assert msg.startswith(f"cfg.toml: field 'sim.driven_joints[{i}]' = {group!r} matches no body on this rig")
        assert "\n" not in msg


def test_an_unknown_body_lists_only_the_keywords_this_rig_resolves(tmp_path):
    """A push's body that is no body and no resolvable keyword: the one-line error offers the
    bodies and only the segment keywords this rig's labels find (a chain has none, the shipped
    clip all fifteen), and says when the name is a keyword this rig does not find."""
    from neuromotor.model.skeleton import BODY_KEYWORDS
    from neuromotor.studies.simulate import body_lookup

    character, _ = load_character(ALL_CLIPS["mocapbank_19joint"])
    with pytest.raises(ConfigError) as e:
        body_lookup(character.model, "cfg.toml", character)("tail")
    assert str(e.value) == (f"cfg.toml: unknown body 'tail'; bodies are {', '.join(character.model.body_names)} "
                            f"(or one of {', '.join(BODY_KEYWORDS)})")
    chain, _ = load_character(_chain(tmp_path))
    with pytest.raises(ConfigError) as e:
        body_lookup(chain.model, "cfg.toml", chain)("pelvis")
    assert str(e.value) == (f"cfg.toml: 'pelvis' is a segment keyword this rig's labels do not find; bodies are "
                            f"{', '.join(chain.model.body_names)} (its labels find no segment keyword)")
